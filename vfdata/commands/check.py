"""`vfdata check FILE`: CRCs, layout, stamps and sync; exit 1 listing every problem."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from vfdata.recording.inspect import check_file, file_verdict


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("check", help="validate a recording or derived MCAP",
                       description="Validate an MCAP file: every chunk's CRC and index, the data-section CRC, the "
                                   "layout (topics, schemas, metadata), stamps in order and the force-to-frame "
                                   "sync. Prints 'FILE: ok' and exits 0, or one line per problem and exits 1. A "
                                   "derived file whose recording `vfdata process` judged doubtful says so "
                                   "after the ok.")
    p.add_argument("file", type=Path, help="recording, derived (.processed.mcap) or force (.force.mcap) MCAP")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    problems = check_file(args.file)
    if problems:
        for problem in problems:
            print(f"{args.file}: {problem}", file=sys.stderr)
        return 1
    # A doubtful recording is a sound file: said beside the ok, not as a problem.
    verdict = file_verdict(args.file)
    print(f"{args.file}: ok" + (f" ({verdict})" if verdict and verdict != "ok" else ""))
    return 0
