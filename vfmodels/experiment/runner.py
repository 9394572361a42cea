"""The experiment grid of the paper: every model variant x seed on one dataset, then the reports.

    vfdata experiment datasets/glove.manifest.yaml --out results/glove [--seeds 3] [--epochs 60]

Steps (docs/experiments.md):
1. Prepare (`prepare`): convert and process every recording, once per tracker the variants need; a
   manifest per tracker is written to `OUT/manifests/`.
2. Train and test each variant x seed through the project's LightningCLI (`vfmodels.training.train`) with the
   variant's config from the package's configs (`vfmodels.training.config_files`; the tree's `configs/`): best
   checkpoint by validation loss, then `trainer.predict` over the test split. Each run folder
   `OUT/runs/<variant>/seed<k>/` gets `predictions.npz` (test frames: recording, orientation_deg,
   frame_time_ns, pred (M, 3) N, true (M, 3) N) and `metrics.json`. A run with a metrics.json is
   finished and is not repeated, so an interrupted grid resumes.
3. Report (`vfmodels.experiment.report`): Tables I-III, the timing table and the figures into OUT/.
"""

from __future__ import annotations

import json
import logging
import os
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

import lightning.pytorch as L
import numpy as np
import torch
from tqdm import tqdm

from vfdata.device import lightning_accelerator, resolve_device
from vfdata.errors import InputError, VisionForceError
from vfdata.executor import run_jobs
from vfdata.manifest import Manifest, load_manifest, write_manifest
from vfdata.recording.derived import read_confidence
from vfdata.split_forces import manifest_forces, split_warnings, summarise, write_split_report
from vfdata.threads import set_threads
from vfmodels.experiment.prepare import any_depth_only, convert_all, derived_path, prepare
from vfmodels.experiment.report import write_doubtful, write_reports
from vfmodels.experiment.ridge_run import run_ridge
from vfmodels.experiment.runs import run_folder, write_run
from vfmodels.experiment.variants import ALL_VARIANTS, DEFAULT_VARIANTS, LADDER, Variant, for_depth_only
from vfmodels.training.checkpoint import best_checkpoint
from vfmodels.training.config_files import CONFIGS
from vfmodels.training.prediction_writer import PredictionCollector
from vfmodels.training.regressor import ForceRegressor
from vfmodels.training.train import adopt_normalisation, make_cli

# Tables I-III follow the paper's protocol: every epoch of the config, then the best validation checkpoint.
PAPER_PROTOCOL = ("--early_stopping.patience=null",)
log = logging.getLogger(__name__)


@dataclass
class ExperimentOptions:
    seeds: int = 3
    epochs: int | None = None  # None: the config's
    variants: list[str] | None = None  # None: DEFAULT_VARIANTS; the others only by name
    ladder: bool = False  # also the attribution ladder (LADDER: simulator recordings only)
    configs: Path = CONFIGS
    depth: str = "sgbm"
    segment: str = "colortrack"
    prompt: str | None = None  # first-frame prompt for recordings whose metadata and manifest entry have none
    workers: int = 1  # recordings processed in parallel processes (executor local)
    executor: str = "local"  # where processing jobs and training runs go: local, or ray (docs/cluster.md)
    ray_address: str | None = None  # the Ray cluster (None: the running one, or a new local instance)
    device: str = "cpu"  # cpu, cuda, auto: the geometry tracker's and the training's (vfdata.device: auto)
    max_frames: int | None = None  # process only the first N frames of each recording (quick runs)
    keep_doubtful: bool = False  # train and validate on recordings `vfdata process` judged doubtful too
    train_args: list[str] = field(default_factory=list)  # extra LightningCLI arguments for every run
    progress: bool = True

    def chosen(self) -> list[Variant]:
        names = list(self.variants or DEFAULT_VARIANTS)
        if self.ladder:
            names += [n for n in LADDER if n not in names]
        unknown = [n for n in names if n not in ALL_VARIANTS]
        if unknown:
            raise VisionForceError(f"unknown variant(s) {', '.join(unknown)} (known: {', '.join(ALL_VARIANTS)})")
        return [ALL_VARIANTS[n] for n in names]


def tracker_manifest(manifest: Manifest, tracker: str, out: Path, keep_doubtful: bool = False
                     ) -> tuple[Path, list[dict]]:
    """A copy of the manifest whose `processed:` entries name the tracker's derived files, and the
    recordings `vfdata process` judged doubtful (`vfdata.confidence`: id, split, reasons). Doubtful training
    and validation recordings are left out unless `keep_doubtful`: a reversed object frame turns every label
    of a recording (on a fresh colon dataset one such recording took validation from 2.35 to 3.06 N)."""
    entries, doubtful = [], []
    for entry in manifest.entries:
        entry = entry.with_processed(derived_path(entry, tracker))
        verdict = read_confidence(entry.processed) if entry.processed.is_file() else None
        left_out = False
        if verdict is not None and verdict.doubtful:
            left_out = entry.split in ("train", "val") and not keep_doubtful
            doubtful.append({"id": entry.id, "split": entry.split, "tracker": tracker, "reasons": verdict.reasons,
                             "left_out": left_out, "figures": verdict.figures})
        if not left_out:
            entries.append(entry)
    if not any(e.split == "train" for e in entries) and any(e.split == "train" for e in manifest.entries):
        raise InputError(manifest.path, f"every training recording was judged doubtful ({tracker} tracks): see "
                                        "their .processed.png, or keep them with --keep-doubtful")
    return write_manifest(out, f"{manifest.name}-{tracker}", entries), doubtful


@contextmanager
def _quiet_lightning():
    """Lightning's start-up chatter (accelerator lines, tips, advice on workers) off in grid runs."""
    loggers = [logging.getLogger(name) for name in ("lightning.pytorch", "lightning.fabric", "lightning")]
    levels = [lg.level for lg in loggers]
    try:
        for lg in loggers:
            lg.setLevel(logging.WARNING)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*(LeafSpec|log_every_n_steps|num_workers|_pytree).*")
            yield
    finally:
        for lg, level in zip(loggers, levels, strict=True):
            lg.setLevel(level)


def test_predictions(regressor: ForceRegressor, loader) -> tuple[dict[str, np.ndarray], float]:
    """`trainer.predict` over a test loader -> (per-frame predictions, model frames/s)."""
    collector = PredictionCollector()
    trainer = L.Trainer(accelerator="cpu", devices=1, logger=False, enable_progress_bar=False,
                        enable_model_summary=False, callbacks=[collector])
    started = time.perf_counter()
    with _quiet_lightning():
        trainer.predict(regressor, dataloaders=loader, return_predictions=False)
    seconds = time.perf_counter() - started
    frames = collector.frames
    if frames is None or not len(frames["true"]):
        raise VisionForceError("the test split gave no clips")
    clips = len(loader.dataset)
    return frames, clips * loader.dataset.spec.clip_frames / max(seconds, 1e-9)


def run_one(variant: Variant, seed: int, manifest: Path, run_dir: Path, options: ExperimentOptions,
            cache_dir: Path) -> dict:
    """Train (best checkpoint by validation loss) and test one variant with one seed; writes
    predictions.npz and, last, metrics.json (the marker of a finished run)."""
    config = options.configs / variant.config
    if not config.is_file():
        raise InputError(config, f"config of variant '{variant.name}' not found")
    if variant.kind == "ridge":
        return run_ridge(variant, seed, config, manifest, run_dir, cache_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    args = [f"--config={config}", f"--data.manifest={manifest}", f"--seed_everything={seed}",
            f"--trainer.default_root_dir={run_dir}", "--trainer.enable_progress_bar=false",
            "--trainer.enable_model_summary=false", "--data.progress=false",
            f"--data.cache_dir={cache_dir}", *PAPER_PROTOCOL, *variant.overrides, *options.train_args]
    if options.epochs is not None:
        args.append(f"--trainer.max_epochs={options.epochs}")
    started = time.perf_counter()
    with _quiet_lightning():
        cli = make_cli(args, run=False)
        adopt_normalisation(cli.model, cli.datamodule)  # decoding (or the cache) apart from the training time
        setup_seconds = time.perf_counter() - started
        last = run_dir / "checkpoints" / "last.ckpt"  # resume an interrupted run of this variant and seed
        cli.trainer.fit(cli.model, datamodule=cli.datamodule, ckpt_path=str(last) if last.is_file() else None)
    train_seconds = time.perf_counter() - started - setup_seconds
    best = cli.trainer.checkpoint_callback.best_model_path or str(best_checkpoint(run_dir / "checkpoints"))
    regressor = ForceRegressor.load(best)
    cli.datamodule.setup("test")
    predictions, force_fps = test_predictions(regressor, cli.datamodule.test_dataloader())
    validation, _ = test_predictions(regressor, cli.datamodule.val_dataloader())
    summary = {
        "variant": variant.name, "seed": seed, "tracker": variant.tracker, "config": str(config),
        "checkpoint": str(Path(best).resolve()), "epochs": cli.trainer.current_epoch,
        "setup_seconds": round(setup_seconds, 1), "train_seconds": round(train_seconds, 1),
        "force_fps": force_fps, "torch_threads": torch.get_num_threads(),
    }
    return write_run(run_dir, predictions, summary, validation)


def run_job(job: tuple) -> Path:
    """One training run of the grid as a job (module level: it crosses to a Ray task); one torch
    thread, as the local grid trains."""
    variant, seed, manifest, run_dir, options, cache_dir = job
    set_threads(1)
    run_one(variant, seed, manifest, run_dir, options, cache_dir)
    return run_dir


@dataclass
class ExperimentResult:
    out: Path
    runs: dict[str, list[Path]]  # variant -> run folders with metrics
    reports: dict[str, Path]
    seconds: dict[str, float]


def run_experiment(manifest_path: str | Path, out: str | Path, options: ExperimentOptions | None = None
                   ) -> ExperimentResult:
    """The whole grid (see the module docstring); resumable."""
    options = options or ExperimentOptions()
    out = Path(out)
    manifest = load_manifest(manifest_path)
    convert_seconds = convert_all(list(manifest.entries), options.progress)
    # what the splits' labels allow, said before the long part (vfdata.split_forces)
    splits = summarise(manifest_forces(manifest))
    write_split_report(out, splits)
    for line in split_warnings(splits):
        log.warning(f"warning: {manifest.path}: {line}")
    variants = options.chosen()
    flat_tissue = any_depth_only(list(manifest.entries))
    if flat_tissue:
        variants = for_depth_only(variants)
    trackers = sorted({v.tracker for v in variants}, key=lambda t: t != "geometry")
    out.mkdir(parents=True, exist_ok=True)
    set_threads(1)  # training on small batches: one thread is the fastest on a few cores
    training = resolve_device(options.device, "training")
    if training != "cpu":
        options = replace(options, train_args=[f"--trainer.accelerator={lightning_accelerator(training)}",
                                               *options.train_args])
    seconds = prepare(list(manifest.entries), trackers, options.depth, options.segment, options.prompt,
                      options.max_frames, options.workers, options.progress, options.executor, options.ray_address,
                      resolve_device(options.device, "frames"))
    seconds["convert"] += convert_seconds
    manifests, doubtful = {}, []
    for t in trackers:
        manifests[t], flagged = tracker_manifest(manifest, t, out / "manifests" / f"{t}.manifest.yaml",
                                                 options.keep_doubtful)
        doubtful += flagged
    for d in doubtful:
        log.warning(f"warning: {d['id']} ({d['split']}, {d['tracker']} tracks) is doubtful: "
                    f"{', '.join(d['reasons'])}" + ("; left out of training" if d["left_out"] else ""))
    write_doubtful(out, doubtful)
    (out / "experiment.json").write_text(json.dumps({
        "manifest": str(manifest.path), "variants": [v.name for v in variants], "seeds": options.seeds,
        "epochs": options.epochs, "depth": options.depth, "segment": options.segment,
        "max_frames": options.max_frames, "cpu_count": os.cpu_count(), "flat_tissue": flat_tissue,
        "keep_doubtful": options.keep_doubtful,
    }, indent=2))
    grid = [(v, s) for v in variants for s in range(options.seeds)]
    todo = [(v, s) for v, s in grid if not (run_folder(out, v, s) / "metrics.json").is_file()]
    runs: dict[str, list[Path]] = {v.name: [] for v in variants}
    started = time.perf_counter()
    with tqdm(total=len(grid), initial=len(grid) - len(todo), desc="experiment", unit="run",
              disable=not options.progress) as bar:
        if options.executor == "local":
            for variant, seed in todo:
                bar.set_postfix_str(f"{variant.name} seed {seed}")
                run_one(variant, seed, manifests[variant.tracker], run_folder(out, variant, seed), options,
                        out / "cache")
                bar.update()
        else:  # every run a task of its own; each writes its folder on the shared file system
            jobs = [(v, s, manifests[v.tracker], run_folder(out, v, s), replace(options, progress=False),
                     out / "cache") for v, s in todo]
            for _ in run_jobs(run_job, jobs, options.executor, ray_address=options.ray_address):
                bar.update()
        for variant, seed in grid:
            runs[variant.name].append(run_folder(out, variant, seed))
    seconds["train_test"] = time.perf_counter() - started
    started = time.perf_counter()
    paths = write_reports(out, manifest.path)
    seconds["reports"] = time.perf_counter() - started
    (out / "timing_wall.json").write_text(json.dumps(seconds, indent=2))
    return ExperimentResult(out, runs, paths, seconds)
