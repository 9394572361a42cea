"""`vfdata check FILE`: CRCs, layout, stamps and sync; exit 1 listing every problem."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from vfdata.recording.inspect import check_file


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("check", help="validate a recording or derived MCAP",
                       description="Validate an MCAP file: every chunk's CRC and index, the data-section CRC, the "
                                   "layout (topics, schemas, metadata), stamps in order and the force-to-frame "
                                   "sync. Prints 'FILE: ok' and exits 0, or one line per problem and exits 1.")
    p.add_argument("file", type=Path, help="recording, derived (.processed.mcap) or force (.force.mcap) MCAP")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    problems = check_file(args.file)
    if problems:
        for problem in problems:
            print(f"{args.file}: {problem}", file=sys.stderr)
        return 1
    print(f"{args.file}: ok")
    return 0
