"""Can a few physical features of the depth carry force from the training stretch of a real recording
to its test stretch where the learned models cannot? (docs/results.md, "Real recording: Gao et al.
2018"). Per frame, over the first frame's tissue mask, the depth change since frame 0 (mm) is fitted
by a plane: its offset and its tilts along the image's u and v (a pull tilts the organ), and what
sinks below that plane (a press dents it) as a volume (mm x px / 1000). Each set of features gets a
least-squares line fitted on the training frames and is scored on the test frames; the correlations
say whether a feature goes with a force component the same way in both stretches.

    python bench/study_depth_plane.py datasets/gao2018.manifest.yaml     # after vfdata process (README)
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from vfdata.manifest import load_manifest
from vfdata.recording import Recording
from vfdata.recording.derived import DerivedRecording
from vfmodels.experiment.force_maps import depth_change
from vfmodels.experiment.frame_baselines import per_component_metrics
from vfmodels.experiment.prepare import derived_path

FEATURES = ("offset_mm", "tilt_u_mm", "tilt_v_mm", "dent_volume")
SETS = {"tilt": [1, 2], "plane": [0, 1, 2], "dent": [3], "plane + dent": [0, 1, 2, 3]}
MIN_PIXELS = 50


def plane_features(change_mm: np.ndarray, region: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(T, 4): per frame the plane fitted to the depth change over `region` (offset mm at the image
    centre, tilt mm across the image along u and v) and the volume that sinks below it; NaN for frames
    not `valid` (T,) (the mask rejected them: glitches) or with fewer than MIN_PIXELS of the region known."""
    height, width = region.shape
    v, u = np.mgrid[0:height, 0:width]
    out = np.full((len(change_mm), len(FEATURES)), np.nan)
    for t, change in enumerate(change_mm):
        known = region & np.isfinite(change)
        if not valid[t] or known.sum() < MIN_PIXELS:
            continue
        design = np.stack([np.ones(known.sum()), u[known] / width - 0.5, v[known] / height - 0.5], axis=1)
        coef, *_ = np.linalg.lstsq(design, change[known], rcond=None)
        below = np.clip(change[known] - design @ coef, 0.0, None)  # depth grows away from the camera
        out[t] = [*coef, below.sum() / 1e3]
    return out


def held(features: np.ndarray) -> np.ndarray:
    """Frames without features (the mask rejected them) hold the last known ones, as the tracks do."""
    out = features.copy()
    for t in range(1, len(out)):
        if np.isnan(out[t, 0]):
            out[t] = out[t - 1]
    return np.nan_to_num(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("manifest", help="a manifest that splits one recording in time (frames: per entry)")
    args = parser.parse_args(argv)
    manifest = load_manifest(args.manifest)
    splits = {e.split: np.arange(*e.frames) for e in manifest.entries}
    entry = manifest.entries[0]
    rec = Recording.open(entry.mcap)
    count = rec.num_frames
    force = rec.force_at(rec.frame_times_ns)[:, :3]
    depths = np.stack([rec.depth_mm(i) for i in range(count)])
    with DerivedRecording.open(derived_path(entry, "geometry")) as derived:
        masks = np.stack([derived.mask(i) for i in range(count)])
    valid = masks.reshape(count, -1).any(axis=1)
    region = masks[int(np.argmax(valid))]
    features = held(plane_features(depth_change(depths), region, valid))
    train, test = splits["train"], splits["test"]
    print("correlation with the force, train / test:")
    for k, name in enumerate(FEATURES):
        pairs = [f"{comp} {np.corrcoef(features[train, k], force[train, c])[0, 1]:+.2f} / "
                 f"{np.corrcoef(features[test, k], force[test, c])[0, 1]:+.2f}"
                 for c, comp in enumerate(("Fx", "Fy", "Fz"))]
        print(f"  {name:12s} " + "   ".join(pairs))
    print("\nleast squares on the training frames, test frames:")
    print(f"  {'features':14s} {'RMSE Fx':>8s} {'RMSE Fy':>8s} {'RMSE Fz':>8s} {'R² Fx':>6s} {'R² Fy':>6s} "
          f"{'R² Fz':>6s} {'R² mean':>7s}")
    for name, columns in SETS.items():
        design = np.c_[features[:, columns], np.ones(count)]
        weights, *_ = np.linalg.lstsq(design[train], force[train], rcond=None)
        m = per_component_metrics(design[test] @ weights, force[test])
        print(f"  {name:14s} {m['rmse_fx']:8.2f} {m['rmse_fy']:8.2f} {m['rmse_fz']:8.2f} {m['r2_fx']:6.2f} "
              f"{m['r2_fy']:6.2f} {m['r2_fz']:6.2f} {m['r2']:7.2f}")
    # The dent without the pulls: what of its volume the tilts do not explain (fitted on training).
    tilts = np.c_[features[:, 1:3], np.ones(count)]
    weights, *_ = np.linalg.lstsq(tilts[train], features[train, 3], rcond=None)
    dent_alone = features[:, 3] - tilts @ weights
    line = np.c_[dent_alone, np.ones(count)]
    weights, *_ = np.linalg.lstsq(line[train], force[train, 2], rcond=None)
    r2 = per_component_metrics(np.c_[np.zeros((len(test), 2)), line[test] @ weights], force[test])["r2_fz"]
    corr = [np.corrcoef(dent_alone[idx], force[idx, 2])[0, 1] for idx in (train, test)]
    print(f"\nthe dent less what the tilts explain: correlation with Fz {corr[0]:+.2f} / {corr[1]:+.2f} "
          f"(train / test), Fz R² {r2:.2f} from it")
    return 0


if __name__ == "__main__":
    sys.exit(main())
