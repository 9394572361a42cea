"""The `vfdata` command line as a whole: every subcommand registers, and start-up stays light."""

from __future__ import annotations

import subprocess
import sys

from vfdata.cli import COMMANDS, build_parser
from vfdata.commands.experiment import EXTRA_VARIANT_NAMES, SIMULATOR_VARIANT_NAMES, VARIANT_NAMES


def test_every_command_registers():
    parser = build_parser()
    choices = parser._subparsers._group_actions[0].choices
    assert set(choices) == set(COMMANDS)


def test_experiment_help_lists_the_real_variants():
    from vfdata.experiment import EXTRA_VARIANTS, SIMULATOR_VARIANTS, VARIANTS

    assert tuple(VARIANTS) == VARIANT_NAMES
    assert tuple(SIMULATOR_VARIANTS) == SIMULATOR_VARIANT_NAMES
    assert tuple(EXTRA_VARIANTS) == EXTRA_VARIANT_NAMES


def test_startup_does_not_import_torch():
    code = "import sys; from vfdata.cli import build_parser; build_parser(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
