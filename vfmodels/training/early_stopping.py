"""`ValidationEarlyStopping`: stop training when the validation loss has not improved for `patience`
epochs; `patience: null` turns it off (the paper's protocol: every epoch of `max_epochs`, then the best
validation checkpoint).

On `mini` the proposed model's best validation epoch came at 3 of 60 (22 minutes of training for
nothing after the fourth). `train.py` monitors what its checkpoint monitors (`checkpoint.monitor`,
val/loss by default), so the kept checkpoint is always the best one seen; a config without a monitor
(`configs/visionforce.yaml`: the last averaged weights) runs every epoch. `vfdata experiment` runs
the paper's protocol (`--early_stopping.patience=null`) for Tables I-III.
"""

from __future__ import annotations

from lightning.pytorch.callbacks import EarlyStopping

DEFAULT_PATIENCE = 10  # epochs without a better validation loss


class ValidationEarlyStopping(EarlyStopping):
    def __init__(self, monitor: str | None = "val/loss", patience: int | None = DEFAULT_PATIENCE,
                 min_delta: float = 0.0, mode: str = "min") -> None:
        """
        Args:
            monitor: the metric (set from `checkpoint.monitor`; None: no early stopping).
            patience: epochs without a better `monitor` before training stops; None: every epoch
                (the paper's protocol).
            min_delta: the least change that counts as better.
            mode: min or max (set from `checkpoint.mode`).
        """
        super().__init__(monitor=monitor or "", patience=patience or 0, min_delta=min_delta, mode=mode,
                         strict=False)
        self.enabled = bool(monitor) and patience is not None

    def _run_early_stopping_check(self, trainer) -> None:
        if self.enabled:
            super()._run_early_stopping_check(trainer)
