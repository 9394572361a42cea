"""The `vfdata` command line. Each subcommand is a module that defines `register(subparsers)`: the data
commands live in `vfdata/commands/<name>.py`; commands of packages built on vfdata (the model commands
of `vfmodels`: experiment, predict, quickstart) are found through the `visionforce.commands` entry
points, so vfdata never imports them. Every failure ends in one line on stderr and a non-zero exit:
errors derived from VisionForceError (the file and the problem) and OSError exit 1, anything unexpected
exits 1 with a line saying so; `--debug` shows the traceback instead. Ctrl-C, SIGTERM and SIGHUP run
the cleanup (no temporary file is left) and exit 130, 143 and 129; a closed stdout (`vfdata info |
head`) ends the command quietly."""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
from collections.abc import Callable
from importlib.metadata import entry_points

from vfdata import __version__
from vfdata.errors import Terminated, VisionForceError

# Order is the order shown in --help; the entry-point commands follow.
COMMANDS = [
    "convert",
    "export",
    "info",
    "check",
    "sync",
    "process",
    "inspect-bag",
    "synth",
]
ENTRY_POINT_GROUP = "visionforce.commands"
_SIGPIPE_EXIT = 128 + 13


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vfdata", description="VisionForce recordings and pipeline.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    parser.add_argument("--version", action="version", version=f"vfdata {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"vfdata.commands.{name.replace('-', '_')}").register(sub)
    for point in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda p: p.name):
        point.load().register(sub)
    return parser


def _raise_terminated(signum: int, _frame) -> None:
    raise Terminated(signum)


def _termination_handlers() -> dict[int, Callable | int | None]:
    """Install the handler that turns SIGTERM and SIGHUP into `Terminated`, where they still have
    their default action (not under `nohup`, not in a thread); returns the handlers it replaced."""
    replaced = {}
    for signum in (signal.SIGTERM, signal.SIGHUP):
        try:
            if signal.getsignal(signum) is signal.SIG_DFL:
                replaced[signum] = signal.signal(signum, _raise_terminated)
        except ValueError:  # not the main thread of the main interpreter
            pass
    return replaced


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    replaced = _termination_handlers()
    try:
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # here, so that a closed pipe is seen below, not at interpreter exit
        return code
    except BrokenPipeError:
        # The reader of our stdout has gone (`vfdata info | head`): nothing left to say to anyone.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return _SIGPIPE_EXIT
    except Terminated as exc:
        print(f"vfdata {args.command}: terminated (signal {exc.signum})", file=sys.stderr)
        return 128 + exc.signum
    except KeyboardInterrupt:
        print(f"vfdata {args.command}: interrupted", file=sys.stderr)
        return 130
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
    except Exception as exc:  # a bug, not bad input: still one line, with the way to learn more
        if args.debug:
            raise
        text = (str(exc).strip().splitlines() or [""])[0]
        print(f"vfdata {args.command}: internal error: {type(exc).__name__}: {text} (a bug in vfdata: run "
              f"`vfdata --debug {args.command} ...` for the traceback and report it)", file=sys.stderr)
        return 1
    finally:
        for signum, handler in replaced.items():
            signal.signal(signum, handler)


if __name__ == "__main__":
    sys.exit(main())
