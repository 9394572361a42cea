"""The `vfdata` command line. Each subcommand lives in `vfdata/commands/<name>.py` and defines
`register(subparsers)`; errors derived from VisionForceError become one line and exit code 1."""

from __future__ import annotations

import argparse
import importlib
import sys

from vfdata.errors import VisionForceError

# Order is the order shown in --help.
COMMANDS = [
    "convert",
    "info",
    "check",
    "process",
    "inspect-bag",
    "synth",
    "experiment",
    "predict",
    "quickstart",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vfdata", description="VisionForce recordings and pipeline.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        module = importlib.import_module(f"vfdata.commands.{name.replace('-', '_')}")
        module.register(sub)
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
