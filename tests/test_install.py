"""An installed package (a wheel, not `pip install -e`) runs the main job from any folder: everything the
commands read ships inside the packages (the model configs: `vfmodels.training.config_files`).

The slow test builds a wheel from the tree, installs it into a fresh virtual environment (which borrows
the big dependencies, torch and the rest, from this one through a .pth file instead of installing them
again) and runs `vfdata quickstart` from a folder outside the tree."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import time
from pathlib import Path

import pytest

from vfdata.errors import InputError
from vfmodels.experiment.variants import ALL_VARIANTS
from vfmodels.training.config_files import CONFIGS, config_path

ROOT = Path(__file__).resolve().parents[1]


def test_the_source_trees_configs_are_the_packages():
    """`configs/` (the path users type) is the package's folder itself: one copy of each config."""
    assert (ROOT / "configs").resolve() == CONFIGS.resolve()
    assert CONFIGS.resolve().is_relative_to((ROOT / "vfmodels").resolve())
    for variant in ALL_VARIANTS.values():
        assert config_path(variant.config).is_file(), variant.config
    with pytest.raises(InputError, match="no config of that name"):
        config_path("nonesuch")


def _tree_files(root: Path) -> list[str]:
    """What a clone of the tree holds (tracked, and new files not ignored), as relative paths."""
    listed = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"], cwd=root,
                            capture_output=True, check=True).stdout.decode()
    return [p for p in listed.split("\0") if p and os.path.lexists(root / p)]


def _copy_tree(root: Path, dest: Path) -> None:
    for rel in _tree_files(root):
        target = dest / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        source = root / rel
        if source.is_symlink():
            os.symlink(os.readlink(source), target)
        else:
            shutil.copy2(source, target)


# Nothing of the tree on the path (PYTHONPATH), as on a machine that never saw it.
CLEAN_ENV = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}


def _run(argv: list[str], cwd: Path, timeout: float = 1800) -> subprocess.CompletedProcess:
    done = subprocess.run(argv, cwd=cwd, env=CLEAN_ENV, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"{' '.join(map(str, argv))}: exit {done.returncode}\n{done.stdout[-3000:]}\n" \
                                 f"{done.stderr[-3000:]}"
    return done


@pytest.mark.slow
def test_a_wheel_installed_into_a_fresh_environment_runs_the_quickstart_from_another_folder(tmp_path):
    started = time.perf_counter()
    src = tmp_path / "src"
    _copy_tree(ROOT, src)  # build from a copy: the build's own folders stay out of the tree
    no_isolation = ["--no-build-isolation"] if _has("setuptools") else []  # the build backend without the network
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", *no_isolation, "-q", "-w", str(tmp_path / "dist"),
          str(src)], cwd=tmp_path)
    wheel = next((tmp_path / "dist").glob("visionforce-*.whl"))

    env_dir = tmp_path / "env"
    _run([sys.executable, "-m", "venv", str(env_dir)], cwd=tmp_path)
    python = env_dir / "bin" / "python"
    site = Path(_run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                     cwd=tmp_path).stdout.strip())
    _run([str(python), "-m", "pip", "install", "--no-deps", "--no-index", "-q", str(wheel)], cwd=tmp_path)
    # Then the dependencies from this environment: its site-packages after the new one's (after the
    # install: pip would take this environment's editable install of the tree for the wheel). A path in a
    # .pth file is only appended to sys.path (its own .pth files, such as that editable install's finder,
    # are not run), so the wheel's packages are the ones imported.
    shared = dict.fromkeys([sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]])
    (site / "zz_shared_dependencies.pth").write_text("".join(f"{p}\n" for p in shared))
    built_s = time.perf_counter() - started

    work = tmp_path / "elsewhere"  # no source tree here or above
    work.mkdir()
    where = _run([str(python), "-c", "import vfdata, vfmodels.training.config_files as c; print(vfdata.__file__); "
                                     "print(c.config_path('visionforce'))"], cwd=work).stdout.split()
    assert all(Path(p).is_relative_to(site) for p in where), where
    quick = _run([str(env_dir / "bin" / "vfdata"), "quickstart", "qs"], cwd=work)
    assert "Table I" in quick.stdout and "visionforce" in quick.stdout and "proposed" in quick.stdout, quick.stdout
    assert list((work / "qs" / "results").glob("table1*.md")), sorted((work / "qs" / "results").iterdir())
    print(f"\nwheel built and installed in {built_s:.0f} s; quickstart {time.perf_counter() - started - built_s:.0f} s")


def _has(module: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(module) is not None
