"""Would the silhouette give a tissue radius that a view from behind does not inflate? (issue 32)

r0, each point's distance from the object's Z axis, grows with the axis's offset from the tube's centre,
which a view from behind sets a few mm off; `ClipSpec.radius: tissue` divides it by the median r0 of the
first frame, which loses the tissue's absolute size. This probe measures a view-independent candidate,
the width of the silhouette across the axis: per slice along Z (`--slice-mm`), the spread of the first
frame's tracked points along their widest direction in XY (10th to 90th percentile, over 0.8 for points
spread evenly across the silhouette), keeping points within 1.5 median r0 of the axis (off the tissue:
bed, fixture), the median over slices. It is held against the simulator's radius (the mean of the
clamped and free ends') and against the median r0, per recording.

Reads an experiment's token cache (`polar_z_disp_vel` tokens with r0 in mm, as the sweep's `visionforce`
runs before 2026-12-08 wrote them) and the raw folders' `ground_truth/params.json`:

    python bench/study_silhouette_radius.py /data/sweep17/colon_125 /data/sweep17/colon_131 ...
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))

from study_radius import cached_tokens  # noqa: E402

from vfdata.errors import InputError  # noqa: E402

R0, Z_FROM_TIP = 2, 5  # polar_z_disp_vel: (cos, sin, r0), (0, 0, z - z_tip), displacement, velocity


def silhouette_radius(xy_mm: np.ndarray, z_mm: np.ndarray, slice_mm: float = 15.0, low: float = 10.0) -> float:
    """Half the silhouette's width, mm: per slice along Z the spread of the points (K, 2) along their
    widest direction, percentile `low` to 100 - `low` scaled to the whole width; the median over slices."""
    widths = []
    for start in np.arange(z_mm.min(), z_mm.max(), slice_mm):
        inside = (z_mm >= start) & (z_mm < start + slice_mm)
        if inside.sum() < 8:
            continue
        points = xy_mm[inside] - xy_mm[inside].mean(axis=0)
        widest = np.linalg.eigh(np.cov(points.T))[1][:, -1]
        across = points @ widest
        spread = np.percentile(across, 100 - low) - np.percentile(across, low)
        widths.append(spread / (1 - 2 * low / 100))
    return float(np.median(widths)) / 2 if widths else float("nan")


def first_frame_points(cache: Path, recording: str) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(xy mm, z mm from the tip, r0 mm) of the first frame's valid points of a cached recording (None: no
    cache of its r0-in-mm tokens; `study_radius.cached_tokens` finds and checks it)."""
    try:
        arrays = cached_tokens(cache, recording)
    except InputError:
        return None
    first = arrays["inputs"][0][arrays["valid"][0]].astype(np.float64)
    r0 = first[:, R0]
    return np.stack([r0 * first[:, 0], r0 * first[:, 1]], axis=1), first[:, Z_FROM_TIP], r0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("seeds", nargs="+", type=Path, help="sweep seed folders (data/ and results/cache/)")
    parser.add_argument("--slice-mm", type=float, default=15.0)
    args = parser.parse_args()
    rows = []
    for folder in args.seeds:
        manifest = yaml.safe_load(next((folder / "data").glob("*.manifest.yaml")).read_text())
        views = {r["id"]: r for r in manifest["recordings"]}
        for recording in views:
            points = first_frame_points(folder / "results" / "cache", recording)
            if points is None:
                continue
            xy, z, r0 = points
            tissue = r0 < 1.5 * np.median(r0)
            tube = json.loads((folder / "data" / recording / "ground_truth" / "params.json").read_text())["tube"]
            true_mm = (tube["base_radius_mm"] + tube["tip_radius_mm"]) / 2
            rows.append((folder.name, recording, views[recording]["split"], views[recording]["orientation_deg"],
                         true_mm, float(np.median(r0)), silhouette_radius(xy[tissue], z[tissue], args.slice_mm)))
    print("seed       recording  split  view  true mm  median r0  silhouette")
    for seed, recording, split, view, true_mm, median_mm, silhouette_mm in rows:
        print(f"{seed:<10} {recording:<10} {split:<6} {view:4d}  {true_mm:7.1f}  {median_mm:9.1f}  "
              f"{silhouette_mm:10.1f}")
    table = np.array([r[4:] for r in rows], dtype=float)
    truth, median_r0, silhouette = table.T
    for name, values in (("median r0", median_r0), ("silhouette", silhouette)):
        ratio = values / truth
        print(f"{name}: correlation with the true radius {np.corrcoef(truth, values)[0, 1]:.2f}; "
              f"over the true radius median {np.median(ratio):.2f}, 90th percentile {np.percentile(ratio, 90):.2f}, "
              f"largest {ratio.max():.2f} ({len(rows)} recordings)")


if __name__ == "__main__":
    main()
