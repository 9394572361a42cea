"""The study of one real recording split in time (docs/results.md, "Real recording: Gao et al. 2018"):
after `vfdata experiment MANIFEST --out OUT` has trained and tested the networks, this adds the
per-frame reference models (constant, ridge on the depth change, ridge on the masked depth) on the
manifest's temporal split and on the original code's random 80/20 frame split, the networks' test
metrics with MAE, tracking quality without ground truth (forward-backward consistency, coverage and
NNI at the force peaks) and two figures, into OUT/study.json, OUT/study.md, OUT/force_time.png and
OUT/tracks_peak.png.

    python -m vfmodels.experiment.real_study datasets/gao2018.manifest.yaml --out results/gao2018
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from vfdata.errors import InputError
from vfdata.manifest import load_manifest
from vfdata.metrics import coverage, force_magnitude, force_peaks, nearest_neighbour_index
from vfdata.recording import Recording
from vfdata.recording.derived import DerivedRecording
from vfdata.rig import rig_for
from vfdata.split_forces import beyond_training, component_coupling
from vfdata.tracking.consistency import forward_backward_error
from vfmodels.experiment.force_maps import depth_change, map_agreement, response_maps
from vfmodels.experiment.frame_baselines import (
    depth_change_features,
    masked_depth_features,
    per_component_metrics,
    random_indices,
    run_baselines,
    temporal_indices,
)
from vfmodels.experiment.prepare import derived_path

FB_HALF_WINDOW = 15  # frames before and after a peak for forward-backward (1 s in all at 30 Hz)
MAX_PEAKS = 6


def _one_recording(manifest) -> tuple[Path, Path, dict[str, tuple[int, int]]]:
    mcaps = {e.mcap for e in manifest.entries}
    if len(mcaps) != 1 or any(e.frames is None for e in manifest.entries):
        raise InputError(manifest.path, "the real-recording study needs one recording split in time (frames: on "
                                        "every entry of one mcap)")
    splits = {e.split: e.frames for e in manifest.entries}
    entry = manifest.entries[0]
    return entry.mcap, derived_path(entry, "geometry"), splits


def network_metrics(out: Path) -> tuple[dict, dict]:
    """Test metrics (with MAE) and predictions of every network run under OUT/runs (seed 0)."""
    metrics, predictions = {}, {}
    for path in sorted(out.glob("runs/*/seed0/predictions.npz")):
        data = np.load(path)
        name = path.parent.parent.name
        metrics[name] = per_component_metrics(data["pred"], data["true"])
        predictions[name] = (np.asarray(data["frame_time_ns"], np.int64), np.asarray(data["pred"]))
    return metrics, predictions


def tracking_quality(derived: DerivedRecording, camera, force_n: np.ndarray, test: tuple[int, int],
                     tracker_options: dict) -> dict:
    """Coverage and NNI at the force peaks of the test stretch, forward-backward error around them."""
    tracks = derived.tracks()
    start, stop = test
    peaks = [int(p) + start for p in force_peaks(force_n[start:stop])]
    peaks = sorted(peaks, key=lambda p: -force_magnitude(force_n[p:p + 1])[0])[:MAX_PEAKS]
    first_uv = camera.project(tracks.points_camera_mm(0))
    rows = []
    for peak in sorted(peaks):
        uv = camera.project(tracks.points_camera_mm(peak))
        mask = derived.mask(peak)
        window = range(max(0, peak - FB_HALF_WINDOW), min(derived.num_frames, peak + FB_HALF_WINDOW + 1))
        clouds = [tracks.frame.to_camera(derived.cloud_mm(i)) for i in window]
        masks = [derived.mask(i) for i in window]
        fb = forward_backward_error(clouds, masks, camera, len(tracks.visible[0]), **tracker_options)
        rows.append({"frame": peak, "force_n": force_n[peak].round(2).tolist(),
                     "coverage": coverage(uv, mask, tracks.visible[peak]),
                     "nni": nearest_neighbour_index(uv, first_uv, tracks.visible[peak], tracks.visible[0]),
                     "visible": float(tracks.visible[peak].mean()), "forward_backward": fb,
                     # how far the points moved from frame 0 (object frame; Z: height above the board)
                     "deepest_sink_mm": float(-(tracks.points_object_mm[peak, :, 2]
                                                - tracks.points_object_mm[0, :, 2]).min()),
                     "displacement_p95_mm": float(np.percentile(np.linalg.norm(
                         tracks.points_object_mm[peak] - tracks.points_object_mm[0], axis=1), 95))})
    return {"peaks": rows, "mean_coverage": float(np.mean([r["coverage"] for r in rows])),
            "mean_nni": float(np.mean([r["nni"] for r in rows])),
            "fb_median_mm": float(np.median([r["forward_backward"]["median_mm"] for r in rows])),
            "fb_forward_displacement_median_mm": float(np.median(
                [r["forward_backward"]["forward_displacement_median_mm"] for r in rows]))}


def stretch_responses(depths: np.ndarray, masks: np.ndarray, force: np.ndarray,
                      splits: dict[str, tuple[int, int]], out: Path) -> dict:
    """Training against test stretch: the response maps (force_maps), how far they agree over the
    organ, how the components couple in each; the figure `force_maps.png`."""
    # matplotlib only for the figure, on the file-only backend that vfmodels.reports.figures sets
    import matplotlib.pyplot as plt

    from vfmodels.reports.figures import save_figure

    seen = masks.any(axis=(1, 2))  # frames the mask rejected (glitches: empty) are left out
    change = depth_change(depths, reference=int(np.argmax(seen)))
    region = masks[seen].mean(axis=0) > 0.5
    frames = {name: np.flatnonzero(seen[slice(*splits[name])]) + splits[name][0] for name in ("train", "test")}
    maps = {name: response_maps(change, force, idx) for name, idx in frames.items()}
    fig, axes = plt.subplots(2, 3, figsize=(11, 7.2))
    for row, name in enumerate(("train", "test")):
        for col, comp in enumerate(("Fx", "Fy", "Fz")):
            ax = axes[row, col]
            image = ax.imshow(maps[name][col], vmin=-0.8, vmax=0.8, cmap="RdBu_r")
            ax.contour(region, levels=[0.5], colors="black", linewidths=0.6)
            ax.set_title(f"{comp}, {name} frames {splits[name][0]}-{splits[name][1] - 1}", fontsize=9)
            ax.set_xticks([])
            ax.set_yticks([])
            if col == 2:
                fig.colorbar(image, ax=ax, fraction=0.046, label="correlation")
    fig.suptitle("Where the depth moves with each force component (correlation per pixel; black: the organ)",
                 fontsize=10)
    save_figure(fig, out / "force_maps.png")
    agreement = map_agreement(maps["train"], maps["test"], region)
    return {"map_agreement": dict(zip(("fx", "fy", "fz"), agreement, strict=True)),
            "coupling": {name: component_coupling(force[idx]) for name, idx in frames.items()}}


def _table(results: dict[str, dict[str, float]]) -> str:
    head = "| model | RMSE Fx | RMSE Fy | RMSE Fz | MAE Fx | MAE Fy | MAE Fz | MAE | R² Fx | R² Fy | R² Fz | R² mean |"
    lines = [head, "|" + " --- |" * 12]
    for name, m in results.items():
        values = [m[f"rmse_{c}"] for c in ("fx", "fy", "fz")] + [m[f"mae_{c}"] for c in ("fx", "fy", "fz")]
        values += [m["mae"]] + [m[f"r2_{c}"] for c in ("fx", "fy", "fz")] + [m["r2"]]
        lines.append(f"| {name} | " + " | ".join(f"{v:.2f}" for v in values) + " |")
    return "\n".join(lines)


def run_study(manifest_path: str | Path, out: str | Path, tracker_options: dict | None = None) -> dict:
    # figures puts matplotlib on its file-only backend before pyplot loads
    from vfmodels.reports.figures import plot_tracked_points, save_figure

    manifest = load_manifest(manifest_path)
    out = Path(out)
    mcap, derived_file, splits = _one_recording(manifest)
    rec = Recording.open(mcap)
    count = rec.num_frames
    force = rec.force_at(rec.frame_times_ns)[:, :3]
    depths = np.stack([rec.depth_mm(i) for i in range(count)])
    with DerivedRecording.open(derived_file) as derived:
        masks = np.stack([derived.mask(i) for i in range(count)])
        quality = tracking_quality(derived, rec.camera, force, splits["test"], tracker_options or {})
        peak = max(quality["peaks"], key=lambda r: abs(r["force_n"][2]))["frame"]
        tracks = derived.tracks()
        uv = rec.camera.project(tracks.points_camera_mm(peak))
        plot_tracked_points(rig_for(rec).image(peak), {f"geometry, frame {peak}": (uv, tracks.visible[peak])},
                            out / "tracks_peak.png", mask=masks[peak],
                            title=f"Largest test press (Fz {force[peak, 2]:.0f} N), depth view")
    responses = stretch_responses(depths, masks, force, splits, out)
    features = {"ridge_depth_change": depth_change_features(depths),
                "ridge_masked_depth": masked_depth_features(depths, masks)}
    temporal, temporal_pred = run_baselines(features, force, temporal_indices(splits))
    randomly, _ = run_baselines(features, force, random_indices(count))
    time_to_frame = {int(t): i for i, t in enumerate(rec.frame_times_ns)}
    networks, network_pred = network_metrics(out)
    test = np.arange(*splits["test"])
    temporal = {**networks, **temporal}
    # What the unseen peak costs: the same test frames less those whose force lies outside every
    # training value (per component, beyond the training minimum or maximum).
    train_force = force[slice(*splits["train"])]
    inside = ~beyond_training(force, train_force, margin=0.0).any(axis=1)
    in_range = {}
    for name, (times, pred) in network_pred.items():
        frames = np.array([time_to_frame[int(t)] for t in times])
        keep = inside[frames]
        in_range[name] = per_component_metrics(pred[keep], force[frames[keep]])
    for name, pred in temporal_pred.items():
        in_range[name] = per_component_metrics(pred[inside[test]], force[test][inside[test]])

    import matplotlib.pyplot as plt  # on the file-only backend that run_study's import of figures set

    fig, axes = plt.subplots(3, 1, figsize=(10, 7), sharex=True)
    seconds = (rec.frame_times_ns - rec.frame_times_ns[0]) / 1e9
    for row, comp in enumerate(("Fx", "Fy", "Fz")):
        ax = axes[row]
        ax.plot(seconds, force[:, row], color="black", lw=1.0, label="measured")
        for name, (times, pred) in network_pred.items():
            frames = [time_to_frame[int(t)] for t in times]
            ax.plot(seconds[frames], pred[:, row], lw=1.0, label=name)
        ax.plot(seconds[test], temporal_pred["ridge_depth_change"][:, row], lw=1.0, ls="--",
                label="ridge, depth change")
        for split, (a, b) in splits.items():
            ax.axvspan(seconds[a], seconds[b - 1], alpha=0.08, color={"train": "tab:blue", "val": "tab:orange",
                                                                       "test": "tab:green"}[split])
        ax.set_ylabel(f"{comp} (N)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, ncol=4, loc="upper left")
    axes[-1].set_xlabel("time (s); shaded: train, validation, test")
    save_figure(fig, out / "force_time.png")

    result = {"splits": {k: list(v) for k, v in splits.items()}, "temporal": temporal, "random_80_20": randomly,
              "temporal_within_training_range": in_range,
              "test_frames_within_training_range": int(inside[test].sum()),
              "tracking": quality, "peak_frame": peak, "stretch_responses": responses,
              "train_force_range_n": [force[slice(*splits["train"])].min(axis=0).round(1).tolist(),
                                      force[slice(*splits["train"])].max(axis=0).round(1).tolist()],
              "test_force_range_n": [force[test].min(axis=0).round(1).tolist(),
                                     force[test].max(axis=0).round(1).tolist()]}
    (out / "study.json").write_text(json.dumps(result, indent=1))
    sections = [(f"Temporal split (test {splits['test']})", temporal),
                (f"Temporal split, the {int(inside[test].sum())} test frames inside the training range", in_range),
                ("Random 80/20 frame split", randomly)]
    agree, coupling = responses["map_agreement"], responses["coupling"]
    stretches = ("## Training against test stretch\n\n| | Fx | Fy | Fz |\n| --- | --- | --- | --- |\n"
                 "| response maps agree (correlation over the organ) | "
                 + " | ".join(f"{agree[c]:.2f}" for c in ("fx", "fy", "fz")) + " |\n\n"
                 + "\n".join(f"- {name}: components correlate Fx-Fy {c['fx_fy']:.2f}, Fx-Fz {c['fx_fz']:.2f}, "
                             f"Fy-Fz {c['fy_fz']:.2f}" for name, c in coupling.items()))
    (out / "study.md").write_text("\n\n".join(f"## {title}\n\n{_table(rows)}" for title, rows in sections)
                                  + "\n\n" + stretches + "\n")
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("manifest", type=Path)
    parser.add_argument("--out", type=Path, required=True, help="the experiment's results folder")
    parser.add_argument("--tracker-options", default="{}", help="JSON options of the geometry tracker, as processed")
    args = parser.parse_args(argv)
    result = run_study(args.manifest, args.out, json.loads(args.tracker_options))
    print((args.out / "study.md").read_text())
    print(json.dumps(result["tracking"], indent=1)[:2000])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
