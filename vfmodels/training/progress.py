"""`RunProgressBar`: Lightning's progress bar with the whole run's remaining time beside the epoch's.

`run_eta` is the mean wall time of the finished epochs times the epochs left (plus what is left of
this one); with early stopping on it is an upper bound, marked `<=`.
"""

from __future__ import annotations

import time

from lightning.pytorch.callbacks import TQDMProgressBar


def format_seconds(seconds: float) -> str:
    """3725 -> '1h02m', 125 -> '2m05s', 7.4 -> '7s'."""
    seconds = max(0, int(round(seconds)))
    if seconds >= 3600:
        return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m"
    if seconds >= 60:
        return f"{seconds // 60}m{seconds % 60:02d}s"
    return f"{seconds}s"


def run_eta(elapsed_s: float, epochs_done: int, epoch_fraction: float, max_epochs: int) -> float | None:
    """Seconds left in a run of `max_epochs` after `epochs_done` whole epochs and `epoch_fraction` of the
    next took `elapsed_s`; None before anything can be said."""
    done = epochs_done + epoch_fraction
    if done <= 0 or max_epochs <= 0:
        return None
    return elapsed_s / done * max(0.0, max_epochs - done)


class RunProgressBar(TQDMProgressBar):
    def __init__(self) -> None:
        super().__init__()
        self._fit_started: float | None = None
        self._first_epoch = 0

    def on_train_start(self, trainer, pl_module) -> None:
        super().on_train_start(trainer, pl_module)
        self._fit_started = time.perf_counter()
        self._first_epoch = trainer.current_epoch  # a resumed run times only its own epochs

    def get_metrics(self, trainer, pl_module) -> dict:
        items = super().get_metrics(trainer, pl_module)
        items.pop("v_num", None)
        max_epochs = trainer.max_epochs or -1
        if self._fit_started is None or max_epochs < 0 or trainer.sanity_checking or not trainer.training:
            return items
        batches = trainer.num_training_batches
        fraction = trainer.fit_loop.epoch_loop.batch_progress.current.completed / batches if batches else 0.0
        left = run_eta(time.perf_counter() - self._fit_started, trainer.current_epoch - self._first_epoch,
                       min(fraction, 1.0), max_epochs - self._first_epoch)
        if left is not None:
            stops_early = any(getattr(c, "enabled", False) for c in trainer.early_stopping_callbacks)
            items["run_eta"] = ("<=" if stops_early else "") + format_seconds(left)
        return items
