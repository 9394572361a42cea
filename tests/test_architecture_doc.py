"""docs/architecture.md names every module of vfdata and vfmodels: a newcomer's map stays true to the tree."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_module_is_on_the_map():
    text = (ROOT / "docs" / "architecture.md").read_text()
    names = set(re.findall(r"`([\w./-]+)`", text))
    missing = []
    for package in ("vfdata", "vfmodels"):
        for path in sorted((ROOT / package).rglob("*.py")):
            if path.name in ("__init__.py", "__main__.py"):
                continue
            relative = path.relative_to(ROOT / package).as_posix()
            # a table row names a module by its path in its package, its file name, or (inside a folder's row)
            # its bare name
            if not {relative, path.name, path.stem, relative.removesuffix(".py")} & names:
                missing.append(f"{package}/{relative}")
    assert not missing, f"docs/architecture.md does not name: {', '.join(missing)}"
