"""Step 3 of an experiment: from a results folder's runs and processed recordings to Tables I-III,
the timing table, the paper's claims checked (`claims.json`) and the figures. Also on a partial grid:
what has run is shown."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from vfdata import metrics as tracking_metrics
from vfdata.errors import InputError
from vfdata.manifest import ManifestEntry, load_manifest
from vfdata.recon.preview import first_frame_preview
from vfdata.recording import Recording
from vfdata.recording.derived import DerivedRecording
from vfdata.rig import rig_for
from vfdata.tissue_lean import lean_markdown, lean_report, read_lean
from vfdata.tracker_kinds import tracker_label
from vfdata.tracking import ground_truth_tracks
from vfmodels.experiment.prepare import derived_path
from vfmodels.experiment.variants import (
    ALL_VARIANTS,
    LADDER_MODELS,
    LADDER_RUNGS,
    TRACKER_SUFFIX,
    Variant,
    for_depth_only,
)
from vfmodels.reports import figures, tables
from vfmodels.reports.tables import run_metrics


def load_runs(out: Path) -> dict[str, list[dict]]:
    """{variant: [run_metrics result per finished seed]} from OUT/runs/*/seed*/, in the order of the
    variant registry (unknown folders last); each with "training" where the run's CSV logs are."""
    found: dict[str, list[dict]] = {}
    for metrics_path in sorted((out / "runs").glob("*/seed*/metrics.json")):
        with np.load(metrics_path.parent / "predictions.npz", allow_pickle=False) as predictions:
            run = run_metrics(dict(predictions))
        summary = json.loads(metrics_path.read_text())
        if "val" in summary:
            run["val"] = summary["val"]
        curves = tables.read_epoch_curves(metrics_path.parent)
        if len(curves["epoch"]):
            run["training"] = tables.training_summary(curves)
            # a config that keeps the last weights (no monitor) is tested at its last epoch, not the best
            tested = re.search(r"epoch(\d+)", Path(summary.get("checkpoint", "")).name)
            if tested:
                run["training"]["best_epoch"] = int(tested.group(1))
        found.setdefault(metrics_path.parent.parent.name, []).append(run)
    order = [n for n in ALL_VARIANTS if n in found] + sorted(set(found) - set(ALL_VARIANTS))
    return {name: found[name] for name in order}


def _in_table(name: str, table: str) -> bool:
    return table in ALL_VARIANTS.get(name, Variant(name, name, "")).table.split("+")


def force_tables(out: Path, runs: dict[str, list[dict]], dataset: str, labels: dict[str, str],
                 val_recordings: int | None = None) -> dict[str, Path]:
    aggregated = {name: tables.aggregate_seeds(r) for name, r in runs.items()}
    paths = {}
    for key, number, stem, title in (
            ("I", 1, "table1_force", f"Table I: force estimation on {dataset}, the models and the image baselines"),
            ("II", 2, "table2_ablations", f"Table II: ablations on {dataset}")):
        chosen = {n: a for n, a in aggregated.items() if _in_table(n, key)}
        if chosen:
            for suffix, path in tables.write_force_table(out, stem, chosen, labels, title).items():
                paths[f"table{number}.{suffix}"] = path
    if any("@" in name for name in aggregated):
        (out / "ladder.md").write_text(ladder_markdown(aggregated, dataset))
        paths["ladder.md"] = out / "ladder.md"
    transfer = tables.transfer_markdown(runs, labels, dataset)
    if transfer:
        (out / "transfer.md").write_text(transfer)
        paths["transfer.md"] = out / "transfer.md"
    sure = tables.band_markdown(runs, labels, dataset, val_recordings)
    if sure:
        (out / "band.md").write_text(sure)
        paths["band.md"] = out / "band.md"
    checked = claims(aggregated)
    if checked:
        (out / "claims.json").write_text(json.dumps(checked, indent=2))
        paths["claims"] = out / "claims.json"
    return paths


def ladder_markdown(aggregated: dict[str, dict], dataset: str) -> str:
    """The attribution ladder: per model, the test RMSE (N) and R² with each stage's output replaced by
    the simulator's truth, from all-surface true points down to the real pipeline."""
    rungs = [*LADDER_RUNGS, "pipeline"]
    labels = [LADDER_RUNGS[r][2] for r in LADDER_RUNGS] + ["the pipeline (our depth, mask, frame, tracker)"]
    lines = [f"**Attribution ladder on {dataset}: test avg RMSE (N) / R² as each stage is replaced by the truth**", "",
             "| model | " + " | ".join(labels) + " |", "| --- |" + " ---: |" * len(rungs)]
    for model in LADDER_MODELS:
        cells = []
        for rung in rungs:
            agg = aggregated.get(model if rung == "pipeline" else f"{model}@{rung}")
            cells.append("–" if agg is None else f"{agg['value']['rmse']:.3f} / {agg['value']['r2']:.2f}")
        if any(c != "–" for c in cells):
            lines.append(f"| {model} | " + " | ".join(cells) + " |")
    lines += ["", "Each step to the right replaces one more of the simulator's truths by the pipeline's estimate; "
                  "the drop between two columns is what that stage costs. Means over seeds."]
    return "\n".join(lines) + "\n"


def claims(aggregated: dict[str, dict]) -> dict[str, dict]:
    """The paper's claims checked on the average RMSE (N): each with the two values and whether it holds."""
    rmse = {name: agg["value"]["rmse"] for name, agg in aggregated.items()}
    result = {}

    def compare(key: str, better: str, worse: str, text: str) -> None:
        if better in rmse and worse in rmse:
            result[key] = {"text": text, better: rmse[better], worse: rmse[worse],
                           "holds": bool(rmse[better] <= rmse[worse])}

    def halves(key: str, obj: str, cam: str, text: str) -> None:
        if obj in rmse and cam in rmse:
            result[key] = {"text": text, obj: rmse[obj], cam: rmse[cam],
                           "reduction": -tables.relative_change(rmse[obj], rmse[cam]),
                           "holds": bool(rmse[obj] <= 0.5 * rmse[cam])}

    halves("object_frame_halves_rmse", "proposed", "camera_frame",
           "object frame lowers the average RMSE by >= 50% vs the camera frame")
    halves("object_frame_halves_rmse_groundtruth", "groundtruth", "camera_frame_groundtruth",
           "with ground-truth tracks, the object frame lowers the average RMSE by >= 50% vs the camera frame")
    halves("object_frame_halves_rmse_canonical_side", "canonical_side", "camera_frame",
           "mirrored to the seen flank (beyond the paper), the object frame lowers the average RMSE by >= 50% "
           "vs the camera frame")
    halves("visionforce_object_frame_halves_rmse", "visionforce", "visionforce_camera_frame",
           "visionforce: the object frame lowers the average RMSE by >= 50% vs the camera frame")
    compare("visionforce_beats_proposed", "visionforce", "proposed", "visionforce beats the paper's proposed model")
    compare("visionforce_geometry_beats_klt", "visionforce@geometry", "visionforce",
            "visionforce: geometry tracking beats KLT (visionforce reads KLT tracks)")
    compare("visionforce_beats_displacement_only", "visionforce", "visionforce_displacement_only",
            "visionforce: displacement + velocity beats displacement only")
    compare("visionforce_beats_velocity_only", "visionforce", "visionforce_velocity_only",
            "visionforce: displacement + velocity beats velocity only")
    compare("visionforce_beats_rgb", "visionforce", "rgb", "visionforce beats RGB only")
    compare("visionforce_beats_depth_vit", "visionforce", "depth_vit", "visionforce beats masked depth + ViT")
    compare("geometry_beats_klt", "proposed", "klt", "geometry tracking beats KLT")
    compare("geometry_plus_beats_klt", "geometry_plus", "klt", "geometry+ tracking (beyond the paper) beats KLT")
    compare("beats_position_only", "proposed", "position_only", "position + velocity beats position only")
    compare("beats_velocity_only", "proposed", "velocity_only", "position + velocity beats velocity only")
    compare("beats_rgb", "proposed", "rgb", "proposed beats RGB only")
    compare("beats_depth_vit", "proposed", "depth_vit", "proposed beats masked depth + ViT")
    return result


def tracking_quality(processed: Path, recording: Path, ground_truth: Path | None) -> dict:
    """Coverage and NNI at the force peaks of one recording and, with simulator ground truth, the
    tracking error over all frames: {"coverage": [...], "nni": [...], "error": TrackingError dict}."""
    with DerivedRecording.open(processed) as derived:
        tracks = derived.tracks()
        points_cam = np.stack([tracks.points_camera_mm(i) for i in range(len(tracks.times_ns))])
        with Recording.open(recording) as rec:
            force = rec.force_at(tracks.times_ns)[:, :3]
            camera = rec.camera
        peaks = tracking_metrics.force_peaks(np.nan_to_num(force))
        coverage, nni = [], []
        for peak in peaks:
            coverage.append(tracking_metrics.coverage(camera.project(points_cam[peak]), derived.mask(int(peak)),
                                                      tracks.visible[peak]))
            nni.append(tracking_metrics.nearest_neighbour_index(points_cam[peak], points_cam[0], tracks.visible[peak],
                                                                tracks.visible[0]))
    result = {"coverage": coverage, "nni": nni, "peaks": [int(p) for p in peaks]}
    if ground_truth is not None and (ground_truth / "points.npy").is_file():
        material = np.load(ground_truth / "points.npy", mmap_mode="r")
        normals = np.load(ground_truth / "normals.npy", mmap_mode="r")
        frames = min(len(points_cam), len(material))
        truth, truth_normals = ground_truth_tracks(points_cam[0], material[:frames], normals[:frames])
        result["error"] = tracking_metrics.tracking_error(points_cam[:frames], truth, truth_normals,
                                                          tracks.visible[:frames]).as_dict()
    return result


def tracking_table(entries: list[ManifestEntry], trackers: list[str]) -> tuple[dict, dict]:
    """Table III rows per tracker over the test recordings, and the per-recording results."""
    rows, per_recording = {}, {}
    tests = [e for e in entries if e.split == "test"]
    for tracker in trackers:
        results = []
        for entry in tests:
            if derived_path(entry, tracker).is_file() and entry.mcap.is_file():
                gt = entry.ground_truth
                results.append(tracking_quality(derived_path(entry, tracker), entry.mcap, gt if gt.is_dir() else None))
                per_recording.setdefault(tracker, {})[entry.id] = results[-1]
        if not results:
            continue
        coverage = np.concatenate([r["coverage"] for r in results])
        nni = np.concatenate([r["nni"] for r in results])
        row = {"peaks": int(len(coverage)), "coverage_mean": float(np.mean(coverage)) if len(coverage) else np.nan,
               "coverage_std": float(np.std(coverage)) if len(coverage) else np.nan,
               "nni_mean": float(np.nanmean(nni)) if len(nni) else np.nan,
               "nni_std": float(np.nanstd(nni)) if len(nni) else np.nan}
        errors = [r["error"] for r in results if "error" in r]
        if errors:
            # Pooled over recordings by the number of compared pairs (medians are not additive, so
            # this is a weighted mean of per-recording medians and percentiles; stated in the docs).
            weights = np.array([e["count"] for e in errors], dtype=np.float64)
            for key in errors[0]:
                if key != "count":
                    row[key] = float(np.average([e[key] for e in errors], weights=weights))
        rows[tracker] = row
    return rows, per_recording


def stage_rates(entries: list[ManifestEntry], tracker: str) -> dict[str, float]:
    per, frames = [], []
    for entry in entries:
        if derived_path(entry, tracker).is_file():
            with DerivedRecording.open(derived_path(entry, tracker)) as derived:
                if derived.meta.get("stage_fps"):
                    per.append(derived.meta.json("stage_fps"))
                    frames.append(int(derived.meta.get("frames", "1")))
    return tables.combine_stage_fps(per, frames) if per else {}


def rate_conditions(entries: list[ManifestEntry], tracker: str) -> str:
    """How the stage rates were measured (threads, cores, load: `vfdata process` records them), one line;
    empty for files from before it did."""
    seen = []
    for entry in entries:
        if derived_path(entry, tracker).is_file():
            with DerivedRecording.open(derived_path(entry, tracker)) as derived:
                if derived.meta.get("stage_cores"):
                    seen.append((derived.meta.get("stage_threads", "?"), int(derived.meta.number("stage_cores")),
                                 float(derived.meta.number("stage_load_1min"))))
    if not seen:
        return ""
    threads = ", ".join(sorted({t for t, _, _ in seen}))
    cores, load = max(c for _, c, _ in seen), max(v for _, _, v in seen)
    shared = " (the machine was shared: load above the cores, so these rates are below the method's)" \
        if load > cores else ""
    return (f"\nMeasured by `vfdata process` with {threads} torch thread(s) per process on {cores} core(s), "
            f"1-minute load average up to {load:.1f}{shared}.\n")


def first_frame(entry: ManifestEntry, tracker: str) -> np.ndarray:
    """`first_frame_preview` of a processed recording, drawn from its files."""
    with Recording.open(entry.mcap) as rec:
        image, camera = rig_for(rec).image(0), rec.camera
    with DerivedRecording.open(derived_path(entry, tracker)) as derived:
        tracks = derived.tracks()
        return first_frame_preview(image, derived.mask(0), camera, tracks.frame, tracks.points_camera_mm(0))


def write_figures(out: Path, entries: list[ManifestEntry], trackers: list[str], dataset: str) -> dict[str, Path]:
    paths = {}
    for variant in ("visionforce", "proposed"):  # Fig. 7 of the default model, else the paper's
        runs = sorted((out / "runs" / variant).glob("seed*/predictions.npz"))
        if runs:
            with np.load(runs[0], allow_pickle=False) as predictions:
                paths["fig7"] = figures.plot_force_curves(dict(predictions), out / "fig7_force_curves.png",
                                                          title=f"{dataset}: {variant} model, test orientations")
            break
    curves = {f"{run.parent.name} {run.name}": tables.read_epoch_curves(run)
              for run in sorted((out / "runs").glob("*/seed*"))}
    curves = {label: c for label, c in curves.items() if len(c["epoch"])}  # runs without logs yet
    if curves:
        paths["training"] = figures.plot_training_curves(curves, out / "fig_training_curves.png",
                                                         title=f"{dataset}: loss per epoch")
    forces: dict[str, list[np.ndarray]] = {"train": [], "test": []}
    for entry in entries:
        if entry.split in forces and entry.mcap.is_file():
            with Recording.open(entry.mcap) as rec:
                forces[entry.split].append(rec.force_at(rec.frame_times_ns)[:, :3])
    if forces["train"] and forces["test"]:
        paths["fig5"] = figures.plot_force_distributions(np.concatenate(forces["train"]),
                                                         np.concatenate(forces["test"]),
                                                         out / "fig5_force_kde.png", title=f"{dataset}: force")
    test = next((e for e in entries if e.split == "test" and derived_path(e, trackers[0]).is_file()), None)
    if test is not None:
        paths["fig6"] = _tracked_points_figure(out, test, trackers)
    firsts = {f"{e.id} ({e.orientation_deg:g} deg)": first_frame(e, trackers[0])
              for e in entries if e.split == "test" and derived_path(e, trackers[0]).is_file()}
    if firsts:
        paths["first_frames"] = figures.plot_first_frames(
            firsts, out / "fig_first_frames.png",
            title=f"{dataset}: first frame of each test recording (mask, object frame, tracked points)")
    return paths


def _tracked_points_figure(out: Path, test: ManifestEntry, trackers: list[str]) -> Path:
    """Fig. 6: each tracker's points on the test recording's largest force peak."""
    with DerivedRecording.open(derived_path(test, trackers[0])) as derived, Recording.open(test.mcap) as rec:
        limit = derived.num_frames
        force = rec.force_at(rec.frame_times_ns)[:, :3]
        peaks = tracking_metrics.force_peaks(np.nan_to_num(force))
        peaks = peaks[peaks < limit]
        peak = int(peaks[np.argmax(np.linalg.norm(force[peaks], axis=1))]) if len(peaks) else limit - 1
        image, camera, mask = rig_for(rec).image(peak), rec.camera, derived.mask(peak)
    shown = {}
    for tracker in trackers:
        if derived_path(test, tracker).is_file():
            with DerivedRecording.open(derived_path(test, tracker)) as derived:
                tracks = derived.tracks()
            shown[tracker] = (camera.project(tracks.points_camera_mm(peak)), tracks.visible[peak])
    return figures.plot_tracked_points(image, shown, out / "fig6_tracked_points.png", mask,
                                       title=f"{test.id}, frame {peak} (force peak)")


def write_reports(out: str | Path, manifest: str | Path | None = None) -> dict[str, Path]:
    """All tables and plots of a results folder (also on a partial grid)."""
    out = Path(out)
    ran = json.loads((out / "experiment.json").read_text()) if (out / "experiment.json").is_file() else {}
    if manifest is None:
        manifest = ran["manifest"]
    data = load_manifest(manifest)
    entries = list(data.entries)
    runs = load_runs(out)
    # on RGB-D recordings the variants ran as flat tissue (variants.for_depth_only): the labels say so
    variants = list(ALL_VARIANTS.values())
    labels = {v.name: v.label for v in (for_depth_only(variants) if ran.get("flat_tissue") else variants)}
    doubtful = read_doubtful(out)
    paths = force_tables(out, runs, data.name, labels, validation_recordings(entries, doubtful)) if runs else {}
    trackers = [t for t in TRACKER_SUFFIX if any(derived_path(e, t).is_file() for e in entries)]
    rows, per_recording = tracking_table(entries, trackers)
    if rows:
        labels = {tracker: tracker_label(tracker) for tracker in rows}
        (out / "table3_tracking.md").write_text(tables.tracking_table_markdown(rows, labels))
        (out / "table3_tracking.csv").write_text(tables.tracking_table_csv(rows))
        (out / "tracking_per_recording.json").write_text(json.dumps(per_recording, indent=2))
        paths["table3.md"] = out / "table3_tracking.md"
    rates = stage_rates(entries, "geometry")
    model_fps = [json.loads(p.read_text()).get("force_fps") for p in (out / "runs").glob("*/seed*/metrics.json")]
    model_fps = [f for f in model_fps if f]
    if model_fps:
        rates["force"] = float(np.mean(model_fps))
    if rates:
        (out / "timing.md").write_text(tables.timing_table_markdown(rates) + rate_conditions(entries, "geometry"))
        (out / "timing.json").write_text(json.dumps(rates, indent=2))
        paths["timing.md"] = out / "timing.md"
    paths.update(write_figures(out, entries, trackers or ["geometry"], data.name))
    if doubtful:
        (out / "doubtful.md").write_text(doubtful_markdown(doubtful))
        paths["doubtful.md"] = out / "doubtful.md"
    paths.update(write_lean(out, entries, trackers, doubtful))
    return paths


def write_doubtful(out: Path, doubtful: list[dict]) -> Path:
    """OUT/doubtful.json: the recordings `vfdata process` judged doubtful (`runner.tracker_manifest`: id, split,
    tracker, reasons, whether left out, figures)."""
    (out / "doubtful.json").write_text(json.dumps(doubtful, indent=2))
    return out / "doubtful.json"


def read_doubtful(out: Path) -> list[dict]:
    """OUT/doubtful.json as `write_doubtful` wrote it ([] when there is none); an InputError naming the file
    when it is not that list."""
    path = out / "doubtful.json"
    if not path.is_file():
        return []
    try:
        entries = json.loads(path.read_text())
        if not (isinstance(entries, list) and all(isinstance(d, dict) and {"id", "split", "reasons"} <= d.keys()
                                                  for d in entries)):
            raise ValueError
    except ValueError:
        raise InputError(path, "not the doubtful report `vfdata experiment` writes") from None
    return entries


def write_lean(out: Path, entries: list[ManifestEntry], trackers: list[str], doubtful: list[dict]) -> dict[str, Path]:
    """`lean.json` and `lean.md`: how each tissue hangs against the training tissues (`vfdata.tissue_lean`), where
    gravity is known; nothing otherwise."""
    leans = {}
    for entry in entries:
        derived = next((derived_path(entry, t) for t in trackers if derived_path(entry, t).is_file()), None)
        if derived is not None and entry.id not in leans:
            leans[entry.id] = (entry.split, read_lean(derived, entry.mcap))
    report = lean_report(leans, {d["id"] for d in doubtful})
    if not report["training_deg"] or not report["recordings"]:
        return {}
    (out / "lean.json").write_text(json.dumps(report, indent=1))
    (out / "lean.md").write_text(lean_markdown(report))
    return {"lean.md": out / "lean.md"}


def validation_recordings(entries: list[ManifestEntry], doubtful: list[dict]) -> int:
    """How many recordings the runs validated on: the manifest's validation entries less those the grid left
    out as doubtful, frame ranges of one recording counted once."""
    left_out = {d["id"] for d in doubtful if d.get("left_out")}
    return len({e.mcap for e in entries if e.split == "val" and e.id not in left_out})


def doubtful_markdown(doubtful: list[dict]) -> str:
    """The recordings `vfdata process` judged doubtful (`vfdata.confidence`), and what the grid did with them."""
    lines = ["# Doubtful recordings", "",
             "Judged by `vfdata process` (reasons: docs/reconstruction.md, \"How sure\"). Training and validation "
             "recordings among them were left out unless the experiment ran with `--keep-doubtful`; test "
             "recordings stay in the tables.", "",
             "| recording | split | tracks | reasons | left out |", "| --- | --- | --- | --- | --- |"]
    lines += [f"| {d['id']} | {d['split']} | {d['tracker']} | {', '.join(d['reasons'])} | "
              f"{'yes' if d['left_out'] else 'no'} |" for d in doubtful]
    return "\n".join(lines) + "\n"


def summary_text(paths: dict[str, Path]) -> str:
    """What the command prints at the end: Table I (or II), how sure (the band per view), the claims and where
    everything is."""
    lines = [paths[key].read_text() for key in ("table1.md", "table2.md", "band.md", "doubtful.md", "lean.md")
             if key in paths]
    if "claims" in paths:
        for claim in json.loads(paths["claims"].read_text()).values():
            lines.append(f"- {claim['text']}: {'yes' if claim['holds'] else 'NO'}")
    lines.append("")
    lines += [f"{key:>10}: {path}" for key, path in sorted(paths.items())]
    return "\n".join(lines)
