"""The `vfdata` command line as a whole: every subcommand registers, and start-up stays light."""

from __future__ import annotations

import subprocess
import sys

from vfdata.cli import COMMANDS, build_parser


def test_every_command_registers():
    """The data commands of vfdata and the model commands vfmodels adds through its entry points."""
    parser = build_parser()
    choices = parser._subparsers._group_actions[0].choices
    assert set(choices) == {*COMMANDS, "experiment", "predict", "quickstart"}


def test_vfdata_imports_nothing_of_vfmodels():
    code = ("import sys, pkgutil, importlib, vfdata\n"
            "for m in pkgutil.walk_packages(vfdata.__path__, 'vfdata.'):\n"
            "    if not m.name.endswith('__main__'): importlib.import_module(m.name)\n"
            "print(sorted(n for n in sys.modules if n.startswith('vfmodels')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_startup_does_not_import_torch():
    code = "import sys; from vfdata.cli import build_parser; build_parser(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_process_help_names_every_registered_tracker():
    from vfdata.commands.process import TRACKER_HELP
    from vfdata.tracking.registry import TRACKERS

    assert all(name in TRACKER_HELP for name in TRACKERS)
