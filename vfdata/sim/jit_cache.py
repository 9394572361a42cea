"""Where numba keeps the renderer's machine code: a folder of the user's own, never the source tree.

numba's default caches beside the source file (`__pycache__` of vfdata/sim), which writes into an
installed or shared checkout, and with neither that nor the home folder writable it refuses to
decorate the kernels at all. The cache is a set of pickles that numba loads and runs, so it must live
where only this user writes: `NUMBA_CACHE_DIR` if the user set one, else `<user cache>/vfdata/numba`
(`$XDG_CACHE_HOME` or `~/.cache`). Where that folder cannot be written the kernels are compiled in
every process instead (about 10 s of CPU for a synthesis), never cached somewhere shared like /tmp.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numba


def enable_cache() -> bool:
    """Point numba's cache at the user's folder; True if the kernels may be cached there, False
    (compile in memory only) where it cannot be written. Call before decorating any kernel."""
    folder = os.environ.get("NUMBA_CACHE_DIR") or _default_folder()
    if folder is None or not _writable(Path(folder)):
        return False
    os.environ["NUMBA_CACHE_DIR"] = str(folder)  # also for the synthesis' worker processes
    numba.core.config.reload_config()  # numba read its environment when it was first imported
    return True


def _default_folder() -> str | None:
    base = os.environ.get("XDG_CACHE_HOME")
    if not base:
        try:
            base = str(Path.home() / ".cache")
        except (RuntimeError, KeyError):  # no HOME and no password entry
            return None
    return str(Path(base) / "vfdata" / "numba")


def _writable(folder: Path) -> bool:
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True
