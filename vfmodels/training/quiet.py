"""Lightning's chatter that says nothing about the run, off: the cloud tips, the `_pytree` deprecation,
the `log_every_n_steps` advice on small datasets and the DataLoader-worker advice (one process per
worker is the project's thread policy, vfdata/threads.py, and clips decode once into memory) and the
advice against passing `args` to LightningCLI from a program with its own command line (the grid does)."""

from __future__ import annotations

import logging
import warnings

NOISE = r".*(LeafSpec|_pytree|log_every_n_steps|does not have many workers|num_workers|args parameter is intended).*"


class _DropTips(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("💡")


_TIPS = _DropTips()


def quiet_lightning() -> None:
    """Install the filters for the rest of the process (idempotent)."""
    warnings.filterwarnings("ignore", message=NOISE)
    # rank_zero_info logs on this logger; a filter on the logger itself sees its records.
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero"):
        logger = logging.getLogger(name)
        if _TIPS not in logger.filters:
            logger.addFilter(_TIPS)
