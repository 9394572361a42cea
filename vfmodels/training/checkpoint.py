"""`ResumableCheckpoint`: Lightning's ModelCheckpoint (the best checkpoint by the monitored metric)
whose `last.ckpt` is rewritten after every epoch.

Since Lightning 2.6, `save_last=True` writes `last.ckpt` only when a top-k checkpoint is saved, i.e.
when the validation loss improves. A run whose best epoch is early then keeps an early `last.ckpt`,
and resuming it repeats every epoch after that one (seen on `glove`: best epoch 4 of 60, so a resume
would have trained 55 epochs again). Here `last.ckpt` always holds the latest finished epoch, as
resuming needs; the best checkpoint is chosen exactly as before.
"""

from __future__ import annotations

from lightning.pytorch.callbacks import ModelCheckpoint


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
