"""The `vfdata` command line. Each subcommand is a module that defines `register(subparsers)`: the data
commands live in `vfdata/commands/<name>.py`; commands of packages built on vfdata (the model commands
of `vfmodels`: experiment, predict, quickstart) are found through the `visionforce.commands` entry
points, so vfdata never imports them. Errors derived from VisionForceError become one line and exit
code 1."""

from __future__ import annotations

import argparse
import importlib
import sys
from importlib.metadata import entry_points

from vfdata.errors import VisionForceError

# Order is the order shown in --help; the entry-point commands follow.
COMMANDS = [
    "convert",
    "info",
    "check",
    "process",
    "inspect-bag",
    "synth",
]
ENTRY_POINT_GROUP = "visionforce.commands"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vfdata", description="VisionForce recordings and pipeline.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"vfdata.commands.{name.replace('-', '_')}").register(sub)
    for point in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda p: p.name):
        point.load().register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except VisionForceError as exc:
        if args.debug:
            raise
        print(f"vfdata {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        if args.debug:
            raise
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"vfdata {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"vfdata {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
