"""`EpochTimer`: logs how long each training epoch took, so that a run's wall time can be read from
its own logs even after it was interrupted and resumed (the resumed process only sees its part).

Logged once per epoch (CSV and TensorBoard, against the global step like every epoch-level metric;
the CSV also has the epoch):
- `time/epoch_s`: wall seconds from the start of the epoch's training to the end of its validation;
- `time/epoch_cpu_s`: this process's CPU seconds over the same span (user + system, all threads).
  CPU seconds over the thread count is what the epoch would take on an otherwise idle machine; a
  wall figure well above it means other work shared the cores. DataLoader worker processes
  (`num_workers > 0`) are not counted.
Not in any epoch: start-up, the sanity check, testing, and an epoch that a resume re-entered in the
middle (Lightning skips its start hook); so summed epoch times are a lower bound of a run's wall time.
With several processes (DDP) rank 0's times are logged.
"""

from __future__ import annotations

import time

from lightning.pytorch.callbacks import Callback


class EpochTimer(Callback):
    def __init__(self) -> None:
        self._wall_start: float | None = None
        self._cpu_start: float | None = None

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        self._wall_start = time.perf_counter()
        self._cpu_start = time.process_time()

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        # Lightning runs the epoch's validation before this hook, so both spans include it.
        if self._wall_start is None or trainer.sanity_checking:
            return
        wall = time.perf_counter() - self._wall_start
        cpu = time.process_time() - self._cpu_start
        pl_module.log_dict({"time/epoch_s": wall, "time/epoch_cpu_s": cpu}, on_step=False, on_epoch=True,
                          rank_zero_only=True)
        self._wall_start = None
