"""Checkpoints: reading one as data (`read_checkpoint`; a run's best, `best_checkpoint`; and what
`ForceRegressor` keeps beside its weights: `band_from_checkpoint`, `reference_from_checkpoint`), and
`ResumableCheckpoint`, Lightning's ModelCheckpoint (the best checkpoint by the monitored metric) whose
`last.ckpt` is rewritten after every epoch.

Since Lightning 2.6, `save_last=True` writes `last.ckpt` only when a top-k checkpoint is saved, i.e.
when the validation loss improves. A run whose best epoch is early then keeps an early `last.ckpt`,
and resuming it repeats every epoch after that one (seen on `glove`: best epoch 4 of 60, so a resume
would have trained 55 epochs again). Here `last.ckpt` always holds the latest finished epoch, as
resuming needs; the best checkpoint is chosen exactly as before.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.callbacks import ModelCheckpoint

from vfdata.errors import InputError
from vfdata.weights import load_weights
from vfmodels.evaluation import band


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """A checkpoint's contents, read as data only (no code runs: `vfdata.weights.load_weights`); an
    InputError naming the file when it is missing, damaged or not a checkpoint."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "checkpoint not found")
    checkpoint = load_weights(path, "checkpoint")
    if not isinstance(checkpoint, dict):
        raise InputError(path, "not a checkpoint (its contents are not a dictionary)")
    return checkpoint


def best_checkpoint(dirpath: str | Path) -> Path:
    """The best checkpoint of a finished run: the one its ModelCheckpoint recorded in last.ckpt (by
    val/loss), else the only or lowest-loss *.ckpt other than last.ckpt in `dirpath`."""
    dirpath = Path(dirpath)
    last = dirpath / "last.ckpt"
    if last.is_file():
        for key, value in read_checkpoint(last).get("callbacks", {}).items():
            # "ModelCheckpoint{...}" in runs from before ResumableCheckpoint.
            if key.startswith(("ModelCheckpoint", "ResumableCheckpoint")) and value.get("best_model_path"):
                best = Path(value["best_model_path"])
                if best.is_file():
                    return best
                if (dirpath / best.name).is_file():  # the run folder was moved
                    return dirpath / best.name
    candidates = [p for p in dirpath.glob("*.ckpt") if p.name != "last.ckpt"]
    if not candidates:
        raise InputError(dirpath, "no checkpoint to use as 'best' (train first, or pass --ckpt_path FILE)")

    def val_loss(p: Path) -> float:
        try:
            return float(p.stem.rpartition("val_loss")[2])
        except ValueError:
            return float("inf")

    return min(candidates, key=val_loss)


def band_from_checkpoint(checkpoint: dict[str, Any], path: Path) -> band.BandCalibration | None:
    """The band calibration a checkpoint holds (`force_model.band`), None when it has none (no validation,
    or a checkpoint from before bands); an InputError naming the file when it is damaged."""
    spec = checkpoint.get("force_model")
    values = spec.get("band") if isinstance(spec, dict) else None
    if values is None:
        return None
    try:
        if not isinstance(values, dict):
            raise ValueError(f"band calibration {values!r} is not a mapping")
        return band.BandCalibration.from_dict(values)
    except ValueError as exc:
        raise InputError(path, str(exc)) from None


def reference_from_checkpoint(checkpoint: dict[str, Any], path: Path) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The embedding reference a checkpoint holds (`force_model.embedding_reference`: mean (D,), precision
    (D, D); `vfmodels.evaluation.familiarity`), None when it has none (a model without the causal interface,
    too few training frames, or a checkpoint from before it); an InputError naming the file when damaged."""
    spec = checkpoint.get("force_model")
    values = spec.get("embedding_reference") if isinstance(spec, dict) else None
    if values is None:
        return None
    mean = values.get("mean") if isinstance(values, dict) else None
    precision = values.get("precision") if isinstance(values, dict) else None
    if not (isinstance(mean, torch.Tensor) and isinstance(precision, torch.Tensor) and mean.ndim == 1
            and precision.shape == (len(mean), len(mean))):
        raise InputError(path, "embedding reference: not a mean (D,) and a precision (D, D)")
    return mean.double(), precision.double()


class ResumableCheckpoint(ModelCheckpoint):
    def on_train_epoch_end(self, trainer, pl_module) -> None:
        super().on_train_epoch_end(trainer, pl_module)
        if self._should_save_on_train_epoch_end(trainer):  # no validation this epoch
            self._save_last_every_epoch(trainer)

    def on_validation_end(self, trainer, pl_module) -> None:
        super().on_validation_end(trainer, pl_module)
        if not self._should_save_on_train_epoch_end(trainer):
            self._save_last_every_epoch(trainer)

    def _save_last_every_epoch(self, trainer) -> None:
        # Skipped when nothing new is there to save: sanity check, fast_dev_run, not fitting, or this
        # step already saved (the parent wrote a top-k checkpoint and last.ckpt with it).
        if self.save_last and not self._should_skip_saving_checkpoint(trainer):
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))
