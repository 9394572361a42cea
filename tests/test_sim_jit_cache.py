"""The simulator's compiled kernels stay out of the way: the command line starts without them, and
their numba cache lives in the user's cache folder, never in the package; with neither writable,
`vfdata info` still works and nothing is written."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from rawfixtures import make_raw

import vfdata
from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder

PACKAGE = Path(vfdata.__file__).parent
# A one-line kernel call: compiles (or loads) one kernel of the renderer.
KERNEL_CALL = (
    "import numpy as np, vfdata.sim.kernels as k; "
    "print(k._JIT['cache'], k.unit_columns(np.ones((3, 2), np.float32))[0, 0])"
)


def _files(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def _environment(src: Path, home: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("XDG_CACHE_HOME", "NUMBA_CACHE_DIR", "PYTHONPATH")}
    return {**env, "PYTHONPATH": str(src), "HOME": str(home), "OMP_NUM_THREADS": "1", **extra}


def test_the_command_line_starts_without_the_simulator_kernels():
    code = ("import sys; from vfdata.cli import build_parser; build_parser(); "
            "print(sorted(m for m in ('numba', 'vfdata.sim.kernels', 'vfdata.sim.render') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.fixture
def sandbox(tmp_path):
    """A copy of the package, a home folder and a recording; the package's and the home's folders
    are made read-only (and left writable again for the clean-up)."""
    shutil.copytree(PACKAGE, tmp_path / "src" / "vfdata", ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / "home").mkdir()
    convert_raw_folder(make_raw(tmp_path / "raw", n=6), tmp_path / "rec.mcap", options=ConvertOptions(progress=False))
    folders = [tmp_path / "home", tmp_path / "src", *(p for p in (tmp_path / "src").rglob("*") if p.is_dir())]
    for folder in folders:
        folder.chmod(0o555)
    yield tmp_path
    for folder in folders:
        folder.chmod(0o755)


def _as_user() -> list[str]:
    """The command prefix under which permissions hold: none for a user; for root, who writes
    anywhere, root without the capabilities that override file permissions."""
    if os.geteuid() != 0:
        return []
    if shutil.which("setpriv") is None:
        pytest.skip("running as root without setpriv: cannot make a folder read-only to the command")
    return ["setpriv", "--bounding-set=-dac_override,-dac_read_search", "--"]


def test_info_with_a_read_only_package_and_home_writes_nothing(sandbox):
    src, home = sandbox / "src", sandbox / "home"
    prefix = _as_user()
    before = _files(sandbox)
    env = _environment(src, home)
    refused = subprocess.run([*prefix, sys.executable, "-c", f"open({str(home / 'x')!r}, 'w')"], env=env, cwd=sandbox,
                             capture_output=True, text=True)
    assert refused.returncode != 0 and "Permission denied" in refused.stderr  # the sandbox holds
    which = subprocess.run([*prefix, sys.executable, "-c", "import vfdata; print(vfdata.__file__)"], env=env,
                           cwd=sandbox, capture_output=True, text=True, check=True)
    assert which.stdout.strip() == str(src / "vfdata" / "__init__.py")
    info = subprocess.run([*prefix, sys.executable, "-m", "vfdata", "info", str(sandbox / "rec.mcap")], env=env,
                          cwd=sandbox, capture_output=True, text=True)
    assert info.returncode == 0, info.stderr
    assert "camera: 160x128" in info.stdout
    # The simulator itself still runs there, compiling in memory.
    kernel = subprocess.run([*prefix, sys.executable, "-c", KERNEL_CALL], env=env, cwd=sandbox,
                            capture_output=True, text=True)
    assert kernel.returncode == 0, kernel.stderr
    assert kernel.stdout.split()[0] == "False"
    assert _files(sandbox) == before


def test_the_kernel_cache_goes_to_the_users_cache_folder(tmp_path):
    src, home = tmp_path / "src", tmp_path / "home"
    shutil.copytree(PACKAGE, src / "vfdata", ignore=shutil.ignore_patterns("__pycache__"))
    home.mkdir()
    env = _environment(src, home, PYTHONDONTWRITEBYTECODE="1")
    before = _files(src)
    for _ in range(2):  # compile and store, then load
        out = subprocess.run([sys.executable, "-c", KERNEL_CALL], env=env, cwd=tmp_path, capture_output=True,
                             text=True)
        assert out.returncode == 0, out.stderr
        assert out.stdout.split()[0] == "True"
    assert _files(src) == before  # nothing written into the package
    cached = list((home / ".cache" / "vfdata" / "numba").rglob("*.nbi"))
    assert cached and (home / ".cache" / "vfdata" / "numba").stat().st_mode & 0o077 == 0
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
    subprocess.run([sys.executable, "-c", KERNEL_CALL], env=env, cwd=tmp_path, capture_output=True, text=True,
                   check=True)
    assert list((tmp_path / "xdg" / "vfdata" / "numba").rglob("*.nbi"))
