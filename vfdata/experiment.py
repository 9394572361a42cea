"""The experiment grid of the paper: every model variant x seed on one dataset, then the reports.

    vfdata experiment datasets/glove.manifest.yaml --out results/glove [--seeds 3] [--epochs 60]

Steps (docs/experiments.md):
1. Prepare: every recording of the manifest is converted (raw folder -> `<id>.mcap`) and processed
   once per tracker the chosen variants need: `<id>.processed.mcap` with the geometry tracker (the
   proposed model and most ablations), `<id>.klt.mcap` with the KLT stand-in. Existing outputs are
   kept. A manifest per tracker is written to `OUT/manifests/`.
2. Train and test each variant x seed in-process through `train.py`'s LightningCLI with the
   variant's config from `configs/`: best checkpoint by validation loss, then the test recordings.
   Each run folder `OUT/runs/<variant>/seed<k>/` gets `predictions.npz` (test frames: recording,
   orientation_deg, frame_time_ns, pred (M, 3) N, true (M, 3) N) and `metrics.json`. A run with a
   metrics.json is finished and is not repeated, so an interrupted grid resumes where it stopped.
3. Report (`write_reports`): Tables I and II, Table III (tracking), the timing table and the plots
   into OUT/ (see vfdata.reports).
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import logging
import os
import sys
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from tqdm import tqdm

from vfdata import reports
from vfdata.datasets import load_manifest
from vfdata.errors import InputError, VisionForceError

REPO = Path(__file__).resolve().parents[1]


# ---- the grid ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Variant:
    """One row of the force tables: a training config, the tracker whose tracks it reads, and the
    table it belongs to (I: the proposed model against the image baselines; II: the ablations)."""

    name: str
    label: str
    config: str  # relative to configs/
    tracker: str = "geometry"
    table: str = "II"


VARIANTS: dict[str, Variant] = {v.name: v for v in (
    Variant("proposed", "Proposed (object frame, geometry tracking)", "proposed.yaml", table="I+II"),
    Variant("camera_frame", "Camera frame", "ablation_camera_frame.yaml"),
    Variant("klt", "KLT tracking (CoTracker stand-in)", "proposed.yaml", tracker="klt"),
    Variant("point_cloud", "Point cloud", "ablation_point_cloud.yaml"),
    Variant("position_only", "Position only", "ablation_position_only.yaml"),
    Variant("velocity_only", "Velocity only", "ablation_velocity_only.yaml"),
    Variant("top_bottom", "Top/bottom 20%", "ablation_top_bottom.yaml"),
    Variant("rgb", "RGB only (3D ResNet-18)", "baseline_rgb.yaml", table="I"),
    Variant("depth_vit", "Masked depth + ViT-Small", "baseline_depth_vit.yaml", table="I"),
)}

# Upper bounds that read the simulator's ground-truth tracks (tracker `groundtruth`: the true material
# positions of the same 256 points the geometry tracker starts from, visibility from the estimated
# mask, object frame estimated as for the proposed model). They separate the tracker's errors from the
# representation's: object frame vs camera frame with perfect tracks. Only on request (`--variants`):
# they need `ground_truth/` beside every raw folder, which real recordings do not have.
SIMULATOR_VARIANTS: dict[str, Variant] = {v.name: v for v in (
    Variant("groundtruth", "Ground-truth tracks (simulator upper bound)", "proposed.yaml", tracker="groundtruth"),
    Variant("camera_frame_groundtruth", "Camera frame, ground-truth tracks", "ablation_camera_frame.yaml",
            tracker="groundtruth"),
)}
# Beyond the paper, also only on request: the proposed model with every recording mirrored to the
# flank of the tissue its first frame shows (`ForceClipDataset(canonical_side=True)`), and the
# proposed model on the tracks of `geometry+` (the geometry tracker that also follows the image texture
# along the surface, docs/tracking.md).
EXTRA_VARIANTS: dict[str, Variant] = {v.name: v for v in (
    Variant("canonical_side", "Proposed, mirrored to the seen flank (beyond the paper)",
            "proposed_canonical_side.yaml"),
    Variant("geometry_plus", "Proposed on geometry+ tracks (beyond the paper)", "proposed.yaml",
            tracker="geometry+"),
)}
ALL_VARIANTS: dict[str, Variant] = {**VARIANTS, **SIMULATOR_VARIANTS, **EXTRA_VARIANTS}

# Derived file name per tracker (the manifest's `processed:` key points the datasets at it).
TRACKER_SUFFIX = {"geometry": ".processed.mcap", "klt": ".klt.mcap", "geometry+": ".geometry_plus.mcap",
                  "groundtruth": ".gt.mcap"}


@dataclass
class ExperimentOptions:
    seeds: int = 3
    epochs: int | None = None  # None: the config's (60)
    variants: list[str] | None = None  # None: the paper's grid (VARIANTS); the others only by name
    configs: Path = REPO / "configs"
    depth: str = "sgbm"
    segment: str = "colortrack"
    workers: int = 1  # recordings processed in parallel processes
    max_frames: int | None = None  # process only the first N frames of each recording (quick runs)
    train_args: list[str] = field(default_factory=list)  # extra LightningCLI arguments for every run
    progress: bool = True

    def chosen(self) -> list[Variant]:
        names = self.variants or list(VARIANTS)
        unknown = [n for n in names if n not in ALL_VARIANTS]
        if unknown:
            raise VisionForceError(f"unknown variant(s) {', '.join(unknown)} (known: {', '.join(ALL_VARIANTS)})")
        return [ALL_VARIANTS[n] for n in names]


# ---- manifests -----------------------------------------------------------------------------------


@dataclass
class Entry:
    id: str
    orientation_deg: float
    split: str
    raw: Path
    mcap: Path

    def processed(self, tracker: str) -> Path:
        return self.mcap.with_name(self.id + TRACKER_SUFFIX.get(tracker, f".{tracker}.mcap"))


def read_manifest(path: str | Path) -> tuple[dict, list[Entry]]:
    """The manifest's name and its recordings with absolute paths (parsed and checked by
    `vfdata.datasets.load_manifest`, the one reader of manifests)."""
    name, entries = load_manifest(path)
    return {"name": name}, [Entry(e.id, e.orientation_deg, e.split, e.raw, e.mcap) for e in entries]


def tracker_manifest(data: dict, entries: list[Entry], tracker: str, out: Path) -> Path:
    """A copy of the manifest whose `processed:` entries name the tracker's derived files (absolute
    paths, so it can live anywhere)."""
    copy = {k: v for k, v in data.items() if k not in ("root", "recordings")}
    copy["name"] = f"{data.get('name', 'dataset')}-{tracker}"
    copy["root"] = str(entries[0].mcap.parent)
    copy["recordings"] = [
        {"id": e.id, "orientation_deg": e.orientation_deg, "split": e.split, "raw": str(e.raw),
         "mcap": str(e.mcap), "processed": str(e.processed(tracker))} for e in entries
    ]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(yaml.safe_dump(copy, sort_keys=False))
    return out


# ---- step 1: convert and process -----------------------------------------------------------------


def _convert(entry: Entry, progress: bool) -> None:
    from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder

    if entry.mcap.is_file():
        return
    if not entry.raw.is_dir():
        raise InputError(entry.raw, f"recording {entry.id}: neither the raw folder nor {entry.mcap.name} exists "
                                    "(for simulated data run `vfdata synth --preset NAME DIR` first)")
    convert_raw_folder(entry.raw, entry.mcap, options=ConvertOptions(progress=progress))


def _process_one(job: tuple[str, str, str, str, str, int | None]) -> str:
    from vfdata.processing import ProcessOptions, process_recording

    src, out, tracker, depth, segment, max_frames = job
    # One BLAS/torch thread per process: several recordings run side by side instead.
    import torch

    torch.set_num_threads(1)
    process_recording(src, out, ProcessOptions(depth=depth, segment=segment, tracker=tracker,
                                               max_frames=max_frames, progress=False))
    return out


def prepare(entries: list[Entry], trackers: list[str], options: ExperimentOptions) -> dict[str, float]:
    """Convert what is missing, then process every recording for each tracker (skipping outputs that
    exist). Returns wall seconds per step."""
    seconds = {}
    started = time.perf_counter()
    for entry in tqdm(entries, desc="convert", unit="recording", disable=not options.progress):
        _convert(entry, progress=False)
    seconds["convert"] = time.perf_counter() - started
    jobs = [(str(e.mcap), str(e.processed(t)), t, options.depth, options.segment, options.max_frames)
            for t in trackers for e in entries if not e.processed(t).is_file()]
    started = time.perf_counter()
    if jobs:
        bar = tqdm(total=len(jobs), desc="process", unit="recording", disable=not options.progress)
        if options.workers > 1:
            with ProcessPoolExecutor(options.workers) as pool:
                for _ in pool.map(_process_one, jobs):
                    bar.update()
        else:
            for job in jobs:
                _process_one(job)
                bar.update()
        bar.close()
    seconds["process"] = time.perf_counter() - started
    return seconds


# ---- step 2: train and test ----------------------------------------------------------------------


def _train_module():
    """train.py (the LightningCLI entry point at the repository root)."""
    path = REPO / "train.py"
    if not path.is_file():
        raise VisionForceError(f"{path}: train.py not found (the experiment runner needs the repository checkout)")
    spec = importlib.util.spec_from_file_location("visionforce_train", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@contextlib.contextmanager
def _quiet_lightning():
    """Lightning's start-up chatter (accelerator lines, tips) off, and no command line for the CLI to
    read besides the arguments it is given."""
    loggers = [logging.getLogger(name) for name in ("lightning.pytorch", "lightning.fabric", "lightning")]
    levels = [lg.level for lg in loggers]
    argv = sys.argv
    try:
        for lg in loggers:
            lg.setLevel(logging.WARNING)
        sys.argv = argv[:1]
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*(LeafSpec|log_every_n_steps|num_workers).*")
            yield
    finally:
        sys.argv = argv
        for lg, level in zip(loggers, levels, strict=True):
            lg.setLevel(level)


def clip_frames(parts: list[dict]) -> dict[str, np.ndarray]:
    """Per-frame test results from overlapping clips: each frame once, from the clip in which it had
    the most history (the latest position), as an online causal estimator would give it. `parts`
    are per-batch dicts of flat arrays: recording, orientation_deg, frame_time_ns, position, pred, true."""
    frames = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    rec = frames["recording"].astype(str)
    order = np.lexsort((-frames["position"], frames["frame_time_ns"], rec))
    rec_o, time_o = rec[order], frames["frame_time_ns"][order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = (rec_o[1:] != rec_o[:-1]) | (time_o[1:] != time_o[:-1])
    keep = order[first]
    out = {k: v[keep] for k, v in frames.items() if k != "position"}
    out["recording"] = out["recording"].astype(str)
    return out


def test_predictions(regressor, loader) -> tuple[dict[str, np.ndarray], float]:
    """Run a trained regressor over a test loader -> (per-frame predictions, model frames/s)."""
    import torch

    from vfmodels.regressor import ForceRegressor

    parts, model_seconds, model_frames = [], 0.0, 0
    regressor.eval()
    with torch.no_grad():
        for batch in loader:
            started = time.perf_counter()
            pred = ForceRegressor.unmirror(regressor.predict_forces(batch), batch).numpy()
            model_seconds += time.perf_counter() - started
            true = ForceRegressor.unmirror(batch["force"], batch).numpy()
            b, t = pred.shape[:2]
            model_frames += b * t
            parts.append(dict(
                recording=np.repeat(np.asarray(batch["recording"], dtype=object), t),
                orientation_deg=np.repeat(torch.as_tensor(batch["orientation_deg"]).float().numpy(), t),
                frame_time_ns=batch["frame_time_ns"].numpy().reshape(-1).astype(np.int64),
                position=np.tile(np.arange(t), b),
                pred=pred.reshape(-1, 3).astype(np.float64),
                true=true.reshape(-1, 3).astype(np.float64),
            ))
    if not parts:
        raise VisionForceError("the test split gave no clips")
    return clip_frames(parts), model_frames / max(model_seconds, 1e-9)


def run_one(variant: Variant, seed: int, manifest: Path, run_dir: Path, options: ExperimentOptions) -> dict:
    """Train (best checkpoint by validation loss) and test one variant with one seed; writes
    predictions.npz and, last, metrics.json (the marker of a finished run)."""
    import lightning.pytorch as L
    import torch

    from vfmodels.regressor import ForceRegressor

    config = options.configs / variant.config
    if not config.is_file():
        raise InputError(config, f"config of variant '{variant.name}' not found")
    train = _train_module()
    run_dir.mkdir(parents=True, exist_ok=True)
    args = [f"--config={config}", f"--data.manifest={manifest}", f"--seed_everything={seed}",
            f"--trainer.default_root_dir={run_dir}", "--trainer.enable_progress_bar=false",
            "--trainer.enable_model_summary=false", "--data.progress=false",
            # Decoded arrays are cached per results folder (keyed by the source files and options).
            f"--data.cache_dir={run_dir.parent.parent.parent / 'cache'}", *options.train_args]
    if options.epochs is not None:
        args.append(f"--trainer.max_epochs={options.epochs}")
    started = time.perf_counter()
    with _quiet_lightning():
        cli = train.ForceCLI(ForceRegressor, L.LightningDataModule, subclass_mode_data=True,
                             save_config_kwargs={"overwrite": True}, run=False, args=args)
        # Reuse the last checkpoint of an interrupted run of this variant and seed.
        last = run_dir / "checkpoints" / "last.ckpt"
        cli.datamodule.setup("fit")  # decoding (or the cache) apart from the training time
        setup_seconds = time.perf_counter() - started
        cli.trainer.fit(cli.model, datamodule=cli.datamodule, ckpt_path=str(last) if last.is_file() else None)
    train_seconds = time.perf_counter() - started - setup_seconds
    best = cli.trainer.checkpoint_callback.best_model_path or str(train.best_checkpoint(run_dir / "checkpoints"))

    regressor = ForceRegressor.load(best)
    datamodule = cli.datamodule
    datamodule.setup("test")
    threads = torch.get_num_threads()
    predictions, force_fps = test_predictions(regressor, datamodule.test_dataloader())
    np.savez_compressed(run_dir / "predictions.npz", **predictions)
    metrics = reports.run_metrics(predictions)
    summary = {
        "variant": variant.name, "seed": seed, "tracker": variant.tracker, "config": str(config),
        "checkpoint": str(Path(best).resolve()), "epochs": cli.trainer.current_epoch,
        "setup_seconds": round(setup_seconds, 1), "train_seconds": round(train_seconds, 1),
        "test_frames": int(len(predictions["true"])),
        "force_fps": force_fps, "torch_threads": threads,
        "pooled": metrics["pooled"], "mean": metrics["mean"], "std": metrics["std"],
        "groups": {str(k): v for k, v in metrics["groups"].items()},
    }
    tmp = run_dir / "metrics.json.partial"
    tmp.write_text(json.dumps(summary, indent=2))
    tmp.replace(run_dir / "metrics.json")
    return summary


def run_folder(out: Path, variant: Variant, seed: int) -> Path:
    return out / "runs" / variant.name / f"seed{seed}"


def pending_runs(out: Path, grid: list[tuple[Variant, int]]) -> list[tuple[Variant, int]]:
    """The runs of the grid without a metrics.json (written last by a finished run)."""
    return [(v, s) for v, s in grid if not (run_folder(out, v, s) / "metrics.json").is_file()]


@dataclass
class ExperimentResult:
    out: Path
    runs: dict[str, list[Path]]  # variant -> run folders with metrics
    reports: dict[str, Path]
    seconds: dict[str, float]


def run_experiment(manifest: str | Path, out: str | Path, options: ExperimentOptions | None = None
                   ) -> ExperimentResult:
    """The whole grid (see the module docstring); resumable."""
    options = options or ExperimentOptions()
    manifest, out = Path(manifest), Path(out)
    data, entries = read_manifest(manifest)
    variants = options.chosen()
    trackers = sorted({v.tracker for v in variants}, key=lambda t: t != "geometry")
    out.mkdir(parents=True, exist_ok=True)
    seconds = prepare(entries, trackers, options)
    manifests = {t: tracker_manifest(data, entries, t, out / "manifests" / f"{t}.manifest.yaml") for t in trackers}
    (out / "experiment.json").write_text(json.dumps({
        "manifest": str(manifest.resolve()), "variants": [v.name for v in variants], "seeds": options.seeds,
        "epochs": options.epochs, "depth": options.depth, "segment": options.segment,
        "max_frames": options.max_frames, "cpu_count": os.cpu_count(),
    }, indent=2))

    grid = [(v, s) for v in variants for s in range(options.seeds)]
    todo = pending_runs(out, grid)
    runs: dict[str, list[Path]] = {v.name: [] for v in variants}
    started = time.perf_counter()
    bar = tqdm(total=len(grid), initial=len(grid) - len(todo), desc="experiment", unit="run",
               disable=not options.progress)
    for variant, seed in grid:
        run_dir = run_folder(out, variant, seed)
        if (variant, seed) in todo:
            bar.set_postfix_str(f"{variant.name} seed {seed}")
            run_one(variant, seed, manifests[variant.tracker], run_dir, options)
            bar.update()
        runs[variant.name].append(run_dir)
    bar.close()
    seconds["train_test"] = time.perf_counter() - started
    started = time.perf_counter()
    paths = write_reports(out, manifest)
    seconds["reports"] = time.perf_counter() - started
    (out / "timing_wall.json").write_text(json.dumps(seconds, indent=2))
    return ExperimentResult(out, runs, paths, seconds)


# ---- step 3: reports -----------------------------------------------------------------------------


def load_runs(out: Path) -> dict[str, list[dict]]:
    """{variant: [run_metrics result per finished seed]} from OUT/runs/*/seed*/predictions.npz, in
    the order of VARIANTS (unknown folders last); each with "training" (`reports.training_summary`)
    where the run's CSV logs are there."""
    found: dict[str, list[dict]] = {}
    for metrics_path in sorted((out / "runs").glob("*/seed*/metrics.json")):
        predictions = np.load(metrics_path.parent / "predictions.npz", allow_pickle=False)
        run = reports.run_metrics(dict(predictions))
        curves = reports.read_epoch_curves(metrics_path.parent)
        if len(curves["epoch"]):
            run["training"] = reports.training_summary(curves)
        found.setdefault(metrics_path.parent.parent.name, []).append(run)
    order = [n for n in ALL_VARIANTS if n in found] + sorted(set(found) - set(ALL_VARIANTS))
    return {name: found[name] for name in order}


def _force_tables(out: Path, runs: dict[str, list[dict]], dataset: str) -> dict[str, Path]:
    labels = {n: v.label for n, v in ALL_VARIANTS.items()}
    aggregated = {name: reports.aggregate_seeds(r) for name, r in runs.items()}
    table1 = {n: a for n, a in aggregated.items() if "I" in ALL_VARIANTS.get(n, Variant(n, n, "")).table.split("+")}
    table2 = {n: a for n, a in aggregated.items() if "II" in ALL_VARIANTS.get(n, Variant(n, n, "")).table.split("+")}
    paths = {}
    if table1:
        for suffix, path in reports.write_force_table(out, "table1_force", table1, labels,
                                                      f"Table I: force estimation on {dataset}, proposed model "
                                                      "and image baselines").items():
            paths[f"table1.{suffix}"] = path
    if table2:
        for suffix, path in reports.write_force_table(out, "table2_ablations", table2, labels,
                                                      f"Table II: ablations on {dataset}").items():
            paths[f"table2.{suffix}"] = path
    checked = claims(aggregated)
    if checked:
        (out / "claims.json").write_text(json.dumps(checked, indent=2))
        paths["claims"] = out / "claims.json"
    return paths


def claims(aggregated: dict[str, dict]) -> dict[str, dict]:
    """The paper's claims checked on the average RMSE (N): each with the two values and whether it holds."""
    rmse = {name: agg["value"]["rmse"] for name, agg in aggregated.items()}
    result = {}

    def compare(key: str, better: str, worse: str, factor: float = 1.0, text: str = "") -> None:
        if better in rmse and worse in rmse:
            result[key] = {"text": text, better: rmse[better], worse: rmse[worse],
                           "holds": bool(rmse[better] <= factor * rmse[worse])}

    def halves(key: str, obj: str, cam: str, text: str) -> None:
        if obj in rmse and cam in rmse:
            result[key] = {"text": text, obj: rmse[obj], cam: rmse[cam],
                           "reduction": -reports.relative_change(rmse[obj], rmse[cam]),
                           "holds": bool(rmse[obj] <= 0.5 * rmse[cam])}

    halves("object_frame_halves_rmse", "proposed", "camera_frame",
           "object frame lowers the average RMSE by >= 50% vs the camera frame")
    # The same claim with the simulator's true tracks: the representation without tracking errors.
    halves("object_frame_halves_rmse_groundtruth", "groundtruth", "camera_frame_groundtruth",
           "with ground-truth tracks, the object frame lowers the average RMSE by >= 50% vs the camera frame")
    # Beyond the paper: the object frame once every recording shows the same flank of the tissue.
    halves("object_frame_halves_rmse_canonical_side", "canonical_side", "camera_frame",
           "mirrored to the seen flank (beyond the paper), the object frame lowers the average RMSE by >= 50% "
           "vs the camera frame")
    compare("geometry_beats_klt", "proposed", "klt", text="geometry tracking beats KLT")
    compare("geometry_plus_beats_klt", "geometry_plus", "klt", text="geometry+ tracking (beyond the paper) beats KLT")
    compare("beats_position_only", "proposed", "position_only", text="position + velocity beats position only")
    compare("beats_velocity_only", "proposed", "velocity_only", text="position + velocity beats velocity only")
    compare("beats_rgb", "proposed", "rgb", text="proposed beats RGB only")
    compare("beats_depth_vit", "proposed", "depth_vit", text="proposed beats masked depth + ViT")
    return result


def tracking_quality(processed: Path, recording: Path, ground_truth: Path | None) -> dict:
    """Coverage and NNI at the force peaks of one recording and, with simulator ground truth, the
    tracking error over all frames: {"coverage": [...], "nni": [...], "error": TrackingError dict}."""
    import cv2

    from vfdata import metrics
    from vfdata.predict import read_tracks
    from vfdata.recording import Recording, layout
    from vfdata.tracking import ground_truth_tracks

    tracks = read_tracks(processed)
    points_cam = tracks.points_object_mm @ tracks.rotation.T + tracks.origin_mm
    with Recording.open(recording) as rec:
        force = rec.force_at(tracks.times_ns)[:, :3]
        camera = rec.camera
    peaks = metrics.force_peaks(np.nan_to_num(force))
    coverage, nni = [], []
    with Recording.open(processed) as derived:
        for peak in peaks:
            msg = derived.message(layout.TISSUE_MASK, int(peak))
            mask = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_GRAYSCALE) > 127
            uv = camera.project(points_cam[peak])
            coverage.append(metrics.coverage(uv, mask, tracks.visible[peak]))
            nni.append(metrics.nearest_neighbour_index(points_cam[peak], points_cam[0], tracks.visible[peak],
                                                       tracks.visible[0]))
    result = {"coverage": coverage, "nni": nni, "peaks": [int(p) for p in peaks]}
    if ground_truth is not None and (ground_truth / "points.npy").is_file():
        material = np.load(ground_truth / "points.npy", mmap_mode="r")
        normals = np.load(ground_truth / "normals.npy", mmap_mode="r")
        frames = min(len(points_cam), len(material))
        truth, truth_normals = ground_truth_tracks(points_cam[0], material[:frames], normals[:frames])
        result["error"] = metrics.tracking_error(points_cam[:frames], truth, truth_normals,
                                                 tracks.visible[:frames]).as_dict()
    return result


def _tracking_table(out: Path, entries: list[Entry], trackers: list[str]) -> tuple[dict, dict]:
    rows, per_recording = {}, {}
    tests = [e for e in entries if e.split == "test"]
    for tracker in trackers:
        results = []
        for entry in tests:
            if entry.processed(tracker).is_file() and entry.mcap.is_file():
                gt = entry.raw / "ground_truth"
                results.append(tracking_quality(entry.processed(tracker), entry.mcap, gt if gt.is_dir() else None))
                per_recording.setdefault(tracker, {})[entry.id] = results[-1]
        if not results:
            continue
        coverage = np.concatenate([r["coverage"] for r in results]) if results else np.zeros(0)
        nni = np.concatenate([r["nni"] for r in results]) if results else np.zeros(0)
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


def _stage_fps(entries: list[Entry], tracker: str) -> dict[str, float]:
    from vfdata.recording import Recording, layout

    per, frames = [], []
    for entry in entries:
        path = entry.processed(tracker)
        if path.is_file():
            with Recording.open(path) as rec:
                meta = rec.metadata_records.get(layout.DERIVED_METADATA, {})
            if "stage_fps" in meta:
                per.append(json.loads(meta["stage_fps"]))
                frames.append(int(meta.get("frames", 1)))
    return reports.combine_stage_fps(per, frames) if per else {}


def _figures(out: Path, entries: list[Entry], trackers: list[str], dataset: str) -> dict[str, Path]:
    from vfdata.predict import read_tracks
    from vfdata.recording import Recording

    paths = {}
    proposed = sorted((out / "runs" / "proposed").glob("seed*/predictions.npz"))
    if proposed:
        predictions = dict(np.load(proposed[0], allow_pickle=False))
        paths["fig7"] = reports.plot_force_curves(predictions, out / "fig7_force_curves.png",
                                                  title=f"{dataset}: proposed model, test orientations")
    curves = {f"{run.parent.name} {run.name}": reports.read_epoch_curves(run)
              for run in sorted((out / "runs").glob("*/seed*"))}
    curves = {label: c for label, c in curves.items() if len(c["epoch"])}  # runs without logs yet
    if curves:
        paths["training"] = reports.plot_training_curves(curves, out / "fig_training_curves.png",
                                                         title=f"{dataset}: loss per epoch")
    forces = {"train": [], "test": []}
    for entry in entries:
        if entry.split in forces and entry.mcap.is_file():
            with Recording.open(entry.mcap) as rec:
                forces[entry.split].append(rec.force_at(rec.frame_times_ns)[:, :3])
    if forces["train"] and forces["test"]:
        paths["fig5"] = reports.plot_force_distributions(np.concatenate(forces["train"]),
                                                         np.concatenate(forces["test"]),
                                                         out / "fig5_force_kde.png", title=f"{dataset}: force")
    test = next((e for e in entries if e.split == "test" and e.processed(trackers[0]).is_file()), None)
    if test is not None:
        import cv2

        from vfdata import metrics
        from vfdata.recording import layout

        with Recording.open(test.mcap) as rec:
            force = rec.force_at(rec.frame_times_ns)[:, :3]
            peaks = metrics.force_peaks(np.nan_to_num(force))
            limit = len(read_tracks(test.processed(trackers[0])).times_ns)
            peaks = peaks[peaks < limit]
            peak = int(peaks[np.argmax(np.linalg.norm(force[peaks], axis=1))]) if len(peaks) else limit - 1
            image = rec.rectified_frame(peak).left
            camera = rec.camera
        shown = {}
        mask = None
        for tracker in trackers:
            if test.processed(tracker).is_file():
                tracks = read_tracks(test.processed(tracker))
                cam = tracks.points_object_mm[peak] @ tracks.rotation.T + tracks.origin_mm
                shown[tracker] = (camera.project(cam), tracks.visible[peak])
                if mask is None:
                    with Recording.open(test.processed(tracker)) as derived:
                        msg = derived.message(layout.TISSUE_MASK, peak)
                    mask = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_GRAYSCALE) > 127
        paths["fig6"] = reports.plot_tracked_points(image, shown, out / "fig6_tracked_points.png", mask,
                                                    title=f"{test.id}, frame {peak} (force peak)")
    firsts = {f"{e.id} ({e.orientation_deg:g} deg)": _first_frame(e, trackers[0])
              for e in entries if e.split == "test" and e.processed(trackers[0]).is_file()}
    if firsts:
        paths["first_frames"] = reports.plot_first_frames(
            firsts, out / "fig_first_frames.png",
            title=f"{dataset}: first frame of each test recording (mask, object frame, tracked points)")
    return paths


def _first_frame(entry: Entry, tracker: str) -> np.ndarray:
    """`first_frame_preview` of a processed recording, drawn from its files."""
    import cv2

    from vfdata.recon.object_frame import ObjectFrame
    from vfdata.recon.preview import first_frame_preview
    from vfdata.recording import Recording, layout

    with Recording.open(entry.mcap) as rec:
        image, camera = rec.rectified_frame(0).left, rec.camera
    with Recording.open(entry.processed(tracker)) as derived:
        mask_msg = derived.message(layout.TISSUE_MASK, 0)
        points = derived.message(layout.TRACKING_POINTS, 0).points
        frame = ObjectFrame.from_dict(json.loads(derived.metadata_records[layout.DERIVED_METADATA]["object_frame"]))
    mask = cv2.imdecode(np.frombuffer(mask_msg.data, np.uint8), cv2.IMREAD_GRAYSCALE) > 127
    tracked = frame.to_camera(np.stack([points["x"], points["y"], points["z"]], axis=1))
    return first_frame_preview(image, mask, camera, frame, tracked)


def write_reports(out: str | Path, manifest: str | Path | None = None) -> dict[str, Path]:
    """All tables and plots of a results folder (also on a partial grid: what has run is shown)."""
    out = Path(out)
    if manifest is None:
        manifest = json.loads((out / "experiment.json").read_text())["manifest"]
    data, entries = read_manifest(manifest)
    dataset = str(data.get("name", Path(manifest).stem))
    runs = load_runs(out)
    paths = _force_tables(out, runs, dataset) if runs else {}
    trackers = [t for t in TRACKER_SUFFIX if any(e.processed(t).is_file() for e in entries)]

    rows, per_recording = _tracking_table(out, entries, trackers)
    if rows:
        labels = {"geometry": "Geometry-constrained (proposed)", "klt": "KLT (CoTracker stand-in)",
                  "geometry+": "Geometry+ (with image flow)", "groundtruth": "Ground truth"}
        (out / "table3_tracking.md").write_text(reports.tracking_table_markdown(rows, labels))
        (out / "table3_tracking.csv").write_text(reports.tracking_table_csv(rows))
        (out / "tracking_per_recording.json").write_text(json.dumps(per_recording, indent=2))
        paths["table3.md"] = out / "table3_tracking.md"

    stage_fps = _stage_fps(entries, "geometry")
    runs_of_proposed = (out / "runs" / "proposed").glob("seed*/metrics.json")
    force_fps = [f for f in (json.loads(p.read_text()).get("force_fps") for p in runs_of_proposed) if f]
    if force_fps:
        stage_fps["force"] = float(np.mean(force_fps))
    if stage_fps:
        (out / "timing.md").write_text(reports.timing_table_markdown(stage_fps))
        (out / "timing.json").write_text(json.dumps(stage_fps, indent=2))
        paths["timing.md"] = out / "timing.md"
    paths.update(_figures(out, entries, trackers or ["geometry"], dataset))
    return paths


def summary_text(out: Path, paths: dict[str, Path]) -> str:
    """What the command prints at the end: Table I (or II) and where everything is."""
    lines = []
    for key in ("table1.md", "table2.md"):
        if key in paths:
            lines.append(paths[key].read_text())
    if "claims" in paths:
        for claim in json.loads(paths["claims"].read_text()).values():
            lines.append(f"- {claim['text']}: {'yes' if claim['holds'] else 'NO'}")
    lines.append("")
    for key, path in sorted(paths.items()):
        lines.append(f"{key:>10}: {path}")
    return "\n".join(lines)


__all__ = ["ALL_VARIANTS", "EXTRA_VARIANTS", "SIMULATOR_VARIANTS", "VARIANTS", "ExperimentOptions", "Variant",
           "read_manifest", "run_experiment", "write_reports"]
