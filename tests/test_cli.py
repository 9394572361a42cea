"""The `vfdata` command line as a whole: every subcommand registers, and start-up stays light."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from vfdata.cli import COMMANDS, build_parser, main

ROOT = Path(__file__).resolve().parents[1]


def test_every_command_registers():
    """The data commands of vfdata and the model commands vfmodels adds through its entry points."""
    parser = build_parser()
    choices = parser._subparsers._group_actions[0].choices
    assert set(choices) == {*COMMANDS, "experiment", "live", "model-info", "predict", "quickstart"}


def test_vfdata_imports_nothing_of_vfmodels():
    # A module that needs an extra's package (the LeRobot formats' pyarrow and PyAV, say) is passed over
    # where that extra is not installed; any other failed import fails the test.
    code = ("import sys, pkgutil, importlib, vfdata\n"
            f"optional = {sorted(OPTIONAL_PACKAGES)}\n"
            "for m in pkgutil.walk_packages(vfdata.__path__, 'vfdata.'):\n"
            "    if m.name.endswith('__main__'): continue\n"
            "    try: importlib.import_module(m.name)\n"
            "    except ModuleNotFoundError as e:\n"
            "        if (e.name or '').split('.')[0] not in optional: raise\n"
            "print(sorted(n for n in sys.modules if n.startswith('vfmodels')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


# The import names of the packages that pyproject.toml's extras add (torchvision, foxglove-sdk, Ray,
# pyarrow and PyAV, open3d).
OPTIONAL_PACKAGES = {"torchvision", "foxglove", "ray", "pyarrow", "av", "open3d"}


def test_startup_does_not_import_torch():
    code = "import sys; from vfdata.cli import build_parser; build_parser(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_process_help_names_every_registered_tracker():
    from vfdata.cli import build_parser
    from vfdata.tracking.registry import TRACKERS

    process = build_parser()._subparsers._group_actions[0].choices["process"]
    tracker_help = next(a.help for a in process._actions if "--tracker" in a.option_strings)
    assert all(name in tracker_help for name in TRACKERS)


def test_a_trackers_facts_come_from_its_kind():
    """What the device policy, RGB-D processing and the reports say of a tracker is its entry in
    vfdata.tracker_kinds, and every entry can be made."""
    from vfdata.calibration import PinholeCamera
    from vfdata.device import shared_device_options, tracker_device_options
    from vfdata.engine import EngineOptions
    from vfdata.errors import VisionForceError
    from vfdata.rig import RgbdRig
    from vfdata.tracker_kinds import TRACKER_KINDS, tracker_label
    from vfdata.tracking.registry import TRACKERS

    assert set(TRACKERS) == set(TRACKER_KINDS)
    for name, kind in TRACKER_KINDS.items():
        assert tracker_label(name) == kind.label
        assert (shared_device_options(name, "cuda") == {"device": "cuda"}) == kind.gpu
        if not kind.gpu:
            with pytest.raises(VisionForceError, match="CPU only"):
                tracker_device_options(name, "cuda")
        rig = RgbdRig(Path("rec.mcap"), camera=PinholeCamera(100.0, 100.0, 32.0, 24.0, 64, 48))
        options = rig.stage_options(EngineOptions(tracker=name)).tracker_options
        assert all(options[key] == value for key, value in kind.rgbd_options.items())


def test_process_predict_and_live_take_the_same_pipeline_flags_to_the_same_options():
    """One definition of the engine's flags (vfdata/commands/engine_flags.py): each command that runs the
    engine accepts every one of them, and the same words give the same EngineOptions fields."""
    from vfdata.cli import build_parser
    from vfdata.commands.engine_flags import engine_settings

    flags = ["--depth", "sgbm", "--depth-options", "scale=0.5", "--working-range-mm", "50", "250",
             "--segment", "colortrack", "--object-frame", "paper", "--tracker", "klt", "--tracker-options",
             "smoothing=0.5", "--points", "128", "--seed", "3", "--device", "cpu", "--threads", "2"]
    parser = build_parser()
    commands = {"process": ["process", "rec.mcap"], "predict": ["predict", "rec.mcap", "--ckpt", "m.ckpt"],
                "live": ["live", "rec.mcap", "--ckpt", "m.ckpt"]}
    settings = {name: engine_settings(parser.parse_args(argv + flags)) for name, argv in commands.items()}
    assert settings["process"] == settings["predict"] == settings["live"]
    assert settings["live"] == {"depth": "sgbm", "depth_options": {"scale": 0.5}, "segment": "colortrack",
                                "segment_options": {}, "tracker": "klt", "tracker_options": {"smoothing": 0.5},
                                "num_points": 128, "seed": 3, "working_range_mm": (50.0, 250.0),
                                "object_frame": "paper"}
    assert parser.parse_args(commands["predict"]).tracker is None  # the checkpoint's, unless given


def _vfdata(*args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.Popen([sys.executable, "-m", "vfdata", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env)


def test_closed_stdout_ends_quietly(tmp_path):
    """`vfdata info X | head`: the reader has gone before we write; no 'error: Broken pipe'."""
    from rawfixtures import make_raw

    from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder

    out = convert_raw_folder(make_raw(tmp_path / "rec", n=3), tmp_path / "rec.mcap",
                             options=ConvertOptions(progress=False))
    run = _vfdata("info", str(out))
    run.stdout.close()
    assert run.wait(timeout=60) == 141
    assert run.stderr.read() == ""


def test_debug_shows_the_traceback_and_errors_are_one_line(tmp_path):
    plain = _vfdata("convert", "--quiet", str(tmp_path / "missing"), str(tmp_path / "out.mcap"))
    debug = _vfdata("--debug", "convert", "--quiet", str(tmp_path / "missing"), str(tmp_path / "out.mcap"))
    assert plain.wait(timeout=60) == 1 and debug.wait(timeout=60) == 1
    assert plain.stderr.read().strip() == f"vfdata convert: error: {tmp_path / 'missing'}: recording folder not found"
    trace = debug.stderr.read()
    assert "Traceback" in trace and "InputError" in trace


def test_an_unexpected_exception_is_one_line_too(monkeypatch, capsys):
    from vfdata.commands import info

    def broken(args):
        raise ZeroDivisionError("division by zero\nsecond line")

    monkeypatch.setattr(info, "run", broken)
    assert main(["info", "x.mcap"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == ("vfdata info: internal error: ZeroDivisionError: division by zero (a bug in vfdata: run "
                   "`vfdata --debug info ...` for the traceback and report it)")


def test_version(capsys):
    from vfdata import __version__

    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0 and __version__ in capsys.readouterr().out


def test_data_commands_describe_themselves_and_every_option():
    choices = build_parser()._subparsers._group_actions[0].choices
    for name in ("convert", "info", "check", "process"):
        parser = choices[name]
        assert parser.description, name
        undocumented = [a.dest for a in parser._actions if not a.help and a.dest != "help"]
        assert undocumented == [], (name, undocumented)


@pytest.mark.slow  # 30-45 s here: simulating, converting and processing a recording
def test_the_readme_loop_runs_twice(tmp_path, capsys):
    """`convert --skip-existing && process --skip-existing` over a dataset: the second pass keeps every
    output as it is and succeeds; without the flag an existing output is refused."""
    from vfdata.manifest import load_manifest
    from vfdata.sim import synthesize

    manifest = synthesize("mini", tmp_path / "mini", frames=4, progress=False)
    entries = list(load_manifest(manifest))[:1]

    def loop() -> None:
        for e in entries:
            assert main(["convert", str(e.raw), str(e.mcap), "--quiet", "--skip-existing"]) == 0
            assert main(["process", str(e.mcap), "--quiet", "--skip-existing"]) == 0

    loop()
    outputs = [p for e in entries for p in (e.mcap, e.processed, e.processed.with_suffix(".png"))]
    stamps = [p.stat().st_mtime_ns for p in outputs]
    loop()
    assert [p.stat().st_mtime_ns for p in outputs] == stamps
    assert main(["convert", str(entries[0].raw), str(entries[0].mcap), "--quiet"]) == 1
    assert main(["process", str(entries[0].mcap), "--quiet", "--skip-existing", "--overwrite"]) == 1
