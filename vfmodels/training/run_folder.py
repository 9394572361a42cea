"""A training run's folder as the user meets it: what a finished fit says it kept (the closing line),
and what a fit that failed before its first step leaves (nothing it created)."""

from __future__ import annotations

import shutil
from pathlib import Path

from vfmodels.training.checkpoint import read_checkpoint


def run_entries(root: Path) -> set[Path]:
    """What a run folder holds before a run: its entries and those of its log folders."""
    if not root.is_dir():
        return set()
    entries = set(root.iterdir())
    for logs in ("csv", "tb", "lightning_logs"):
        if (root / logs).is_dir():
            entries |= set((root / logs).iterdir())
    return entries


def remove_new_entries(root: Path, existed: set[Path] | None) -> None:
    """After a fit that failed before its first training step: remove what it created in the run folder
    (empty log versions, the saved config, an empty checkpoints/), and the folder if it made it."""
    if existed is None or not root.is_dir():
        return
    new = sorted(run_entries(root) - existed, key=lambda p: len(p.parts), reverse=True)
    for path in new:
        if path.is_dir():
            if any(f.suffix == ".ckpt" for f in path.rglob("*")):
                continue  # never a checkpoint
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
    for logs in ("csv", "tb", "lightning_logs"):
        if (root / logs).is_dir() and (root / logs) not in existed and not any((root / logs).iterdir()):
            (root / logs).rmdir()
    if not existed and not any(root.iterdir()):
        root.rmdir()


def closing_line(trainer, argv: list[str]) -> str:
    """Which checkpoint a finished fit keeps, its epoch and validation loss, and how to test it."""
    callback = trainer.checkpoint_callback
    path = Path(callback.best_model_path) if callback is not None and callback.best_model_path else None
    epoch, loss = None, None
    if path is not None and path.is_file():
        state = read_checkpoint(path)
        epoch = state.get("epoch")
        for key, value in state.get("callbacks", {}).items():
            if key.startswith("ResumableCheckpoint") and value.get("current_score") is not None:
                loss = float(value["current_score"])
    if loss is None and callback is not None and callback.best_model_score is not None:
        loss = float(callback.best_model_score)
    if loss is None and "val/loss" in trainer.callback_metrics:
        loss = float(trainer.callback_metrics["val/loss"])
    monitored = callback is not None and callback.monitor is not None
    what = "best checkpoint (lowest val/loss)" if monitored else "last checkpoint (no monitor)"
    stopper = next((c for c in trainer.early_stopping_callbacks if c.stopped_epoch), None)
    stopped = (f"; stopped after epoch {stopper.stopped_epoch}: no better {stopper.monitor} in {stopper.patience} "
               "epochs" if stopper is not None else "")
    fit_only = ("--trainer.max_epochs", "--ckpt_path", "--early_stopping")
    args = [a for a in argv if a != "fit" and not a.startswith(fit_only)]
    command = " ".join(["python train.py test", *args, "--ckpt_path best"])
    return (f"{what}: {path if path else 'none saved'} (epoch {epoch if epoch is not None else '?'}, val/loss "
            f"{f'{loss:.5f}' if loss is not None else 'n/a'}{stopped})\ntest it: {command}")
