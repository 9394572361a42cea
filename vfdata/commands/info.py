"""`vfdata info FILE`: topics, types, counts, rates, duration, gaps and force-to-frame sync."""

from __future__ import annotations

import argparse
from pathlib import Path

from vfdata.errors import InputError
from vfdata.recording.inspect import info_text


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="describe a recording or derived MCAP",
                       description="Print what an MCAP file holds: each topic's type, message count, rate and "
                                   "gaps, the duration, the camera, the force-to-frame sync and the metadata. "
                                   "Reads the file only; for its integrity use `vfdata check`.")
    p.add_argument("file", type=Path, help="recording, derived (.processed.mcap) or force (.force.mcap) MCAP")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.file.suffix == ".ckpt" or (args.file / "checkpoints").is_dir():
        raise InputError(args.file, "a trained model, not an MCAP file: `vfdata model-info` describes models")
    print(info_text(args.file))
    return 0
