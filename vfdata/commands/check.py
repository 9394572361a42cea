"""`vfdata check FILE`: CRCs, layout, stamps and sync; exit 1 listing every problem."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from vfdata.recording.inspect import check_file


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("check", help="validate a recording or derived MCAP")
    p.add_argument("file", type=Path)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    problems = check_file(args.file)
    if problems:
        for problem in problems:
            print(f"{args.file}: {problem}", file=sys.stderr)
        return 1
    print(f"{args.file}: ok")
    return 0
