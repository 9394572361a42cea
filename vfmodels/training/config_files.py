"""The model configs (`train.py --config`, the experiment grid's variants) as package data.

The YAML files live in the package, `vfmodels/configs/`, so that an installed wheel has them (`vfdata
experiment`, `vfdata quickstart` from any folder); the source tree's `configs/` is a link to that folder,
so `python train.py fit --config configs/visionforce.yaml` reads the same files (one copy, nothing to
keep in step). Where an installed package keeps them:

    python -m vfmodels.training.config_files              # the folder
    python -m vfmodels.training.config_files visionforce  # one config's path
"""

from __future__ import annotations

import sys
from importlib.resources import files
from pathlib import Path

from vfdata.errors import InputError

# pip installs a wheel as files on disk, never zipped, so the package's resources are a folder that
# Lightning's CLI can be given paths into (it reads `--config` from a path).
CONFIGS = Path(str(files("vfmodels") / "configs"))


def config_path(name: str) -> Path:
    """The packaged config `name` ('visionforce' or 'visionforce.yaml'); InputError naming the folder
    and the configs it has when there is none of that name."""
    path = CONFIGS / (name if name.endswith(".yaml") else f"{name}.yaml")
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in CONFIGS.glob("*.yaml")))
        raise InputError(path, f"no config of that name (the package has: {known})")
    return path


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    try:
        print(config_path(args[0]) if args else CONFIGS)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
