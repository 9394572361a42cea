"""Output options shared by the data commands."""

from __future__ import annotations

import argparse
from pathlib import Path

from vfdata.errors import VisionForceError


def skip_existing(args: argparse.Namespace, *outputs: Path) -> bool:
    """--skip-existing: True (and a line saying so) when every output is there. Outputs are written
    beside the target and renamed at the end, so an existing one is a finished one."""
    if not getattr(args, "skip_existing", False):
        return False
    if args.overwrite:
        raise VisionForceError("--skip-existing and --overwrite contradict each other: choose one")
    if all(Path(p).is_file() or Path(p).is_dir() for p in outputs):
        print(f"kept {outputs[0]} (exists; --skip-existing)")
        return True
    return False
