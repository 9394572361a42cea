"""A ridge variant's run (`Variant.kind == "ridge"`): the clip spec of its config, `vfmodels.networks.ridge` fitted
on the training split (strengths chosen on validation), the test frames written like a network's run."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import yaml

from vfdata.clips.dataset import ForceClipDataset
from vfdata.clips.spec import ClipSpec
from vfdata.errors import InputError
from vfdata.manifest import load_manifest
from vfmodels.experiment.runs import write_run
from vfmodels.experiment.variants import Variant
from vfmodels.networks.ridge import RidgeForceModel


def config_spec(config: Path, overrides: tuple[str, ...] = ()) -> ClipSpec:
    """The ClipSpec of a training config, with `--data.spec.<field>=<value>` overrides applied."""
    try:
        values = dict(yaml.safe_load(config.read_text())["data"]["init_args"].get("spec", {}))
    except (KeyError, TypeError, yaml.YAMLError) as exc:
        raise InputError(config, f"no data.init_args.spec in the config ({exc})") from None
    for item in overrides:
        key, _, value = item.removeprefix("--data.spec.").partition("=")
        if item.startswith("--data.spec."):
            values[key] = yaml.safe_load(value)
    return ClipSpec(**values)


def run_ridge(variant: Variant, seed: int, config: Path, manifest_path: Path, run_dir: Path, cache_dir: Path) -> dict:
    spec = config_spec(config, variant.overrides)
    manifest = load_manifest(manifest_path)
    started = time.perf_counter()
    splits = {s: ForceClipDataset(manifest.split(s), spec, cache_dir, progress=False) for s in ("train", "val", "test")}
    setup_seconds = time.perf_counter() - started
    model = RidgeForceModel(mirror=spec.mirror_augment, rotate=spec.rotate_augment)
    model.fit(splits["train"].recordings, splits["val"].recordings)
    train_seconds = time.perf_counter() - started - setup_seconds
    run_dir.mkdir(parents=True, exist_ok=True)
    return write_run(run_dir, _predictions(model, splits["test"]), {
        "variant": variant.name, "seed": seed, "tracker": variant.tracker, "config": str(config), "kind": "ridge",
        "alphas": model.chosen_alphas, "setup_seconds": round(setup_seconds, 1),
        "train_seconds": round(train_seconds, 1)}, _predictions(model, splits["val"]))


def _predictions(model: RidgeForceModel, split: ForceClipDataset) -> dict[str, np.ndarray]:
    """Every frame of a split's recordings: the arrays of a run's predictions.npz."""
    parts = {k: [] for k in ("recording", "orientation_deg", "frame_time_ns", "pred", "true")}
    unmirror = np.array([1.0, -1.0, 1.0])
    for entry, decoded in zip(split.entries, split.recordings, strict=True):
        flip = unmirror if decoded.side < 0 else 1.0
        parts["recording"].append(np.full(len(decoded.times_ns), entry.id))
        parts["orientation_deg"].append(np.full(len(decoded.times_ns), entry.orientation_deg))
        parts["frame_time_ns"].append(decoded.times_ns)
        parts["pred"].append(model.predict(decoded) * flip)
        parts["true"].append(decoded.force_n.astype(np.float64) * flip)
    return {k: np.concatenate(v) for k, v in parts.items()}
