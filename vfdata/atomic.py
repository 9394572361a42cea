"""Atomic outputs: write to a hidden temporary path beside the target, publish it under its name at the
end, and leave nothing behind when anything fails (or the user interrupts, or SIGTERM arrives: the
CLI turns it into an exception, so the `finally` here runs).

- An output that is one of the inputs (the same path after resolving links, a hard link to it, a
  file inside an input folder, or a folder holding an input) is refused before anything is written;
  so is a device, FIFO or socket (`/dev/null`: publishing would replace the special file itself).
- Without `overwrite`, publishing never replaces a file that appeared meanwhile (another run writing
  the same output): `renameat2(RENAME_NOREPLACE)` where the kernel and file system have it, else a
  hard link (`link` fails if the name exists) and the temporary name removed. Of two runs racing for
  one output exactly one succeeds; the other gets OutputExistsError.
- A temporary `.NAME.tmp-<pid>` left by a run that was killed (its process is gone) is removed by the
  next run writing NAME. Process ids are those of this machine: one output name written at once from
  two machines sharing the folder is not supported.
- A full disk (ENOSPC, EDQUOT) becomes an OutputError naming the output."""

from __future__ import annotations

import ctypes
import errno
import os
import re
import shutil
from collections.abc import Iterable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

from vfdata.errors import InputError, OutputError, OutputExistsError

_DISK_FULL = (errno.ENOSPC, errno.EDQUOT)
_AT_FDCWD = -100
_RENAME_NOREPLACE = 1
_TEMPORARY = re.compile(r"\.(?P<name>.+)\.tmp-\d+")  # `_tmp_prefix` and a process id


@contextmanager
def atomic_output(path: str | Path, overwrite: bool = False, inputs: Iterable[str | Path] = ()) -> Iterator[Path]:
    """Yield a temporary path (file or folder, as the caller creates it) that becomes `path` when the
    block succeeds. Refuses an existing `path` unless `overwrite`, and a `path` that is one of
    `inputs` (files or folders the output is made from) always."""
    path = Path(path)
    check_output(path, overwrite, inputs)
    remove_stale_temporaries(path)
    tmp = path.with_name(f"{_tmp_prefix(path)}{os.getpid()}")
    _remove(tmp)
    try:
        yield tmp
        _publish(tmp, path, overwrite)
    except OSError as exc:
        named = output_os_error(path, exc)
        if named is None:
            raise
        raise named from exc
    finally:
        _remove(tmp)


@contextmanager
def atomic_outputs(paths: Iterable[str | Path], overwrite: bool | Iterable[bool] = False,
                   inputs: Iterable[str | Path] = ()) -> Iterator[list[Path]]:
    """`atomic_output` for outputs that belong together (a file and its preview): one temporary path
    each, all published when the block succeeds (the last first), none left when it fails, and the
    ones already published removed again if publishing a later one fails. `overwrite`: for all, or
    one per path."""
    paths, inputs = [Path(p) for p in paths], list(inputs)
    replace = [overwrite] * len(paths) if isinstance(overwrite, bool) else list(overwrite)
    published: list[Path] = []
    try:
        with ExitStack() as stack:
            temporaries = [stack.enter_context(_Member(p, o, inputs, published))
                           for p, o in zip(paths, replace, strict=True)]
            yield temporaries
    except BaseException:
        for path in published:
            _remove(path)
        raise


class _Member:
    """One output of `atomic_outputs`: an `atomic_output` that notes when it has published."""

    def __init__(self, path: Path, overwrite: bool, inputs: list, published: list[Path]):
        self._manager = atomic_output(path, overwrite, inputs)
        self.path, self.published = path, published

    def __enter__(self) -> Path:
        return self._manager.__enter__()

    def __exit__(self, *exc_info) -> bool:
        done = self._manager.__exit__(*exc_info)
        if exc_info[0] is None:
            self.published.append(self.path)
        return done


def check_output(path: str | Path, overwrite: bool = False, inputs: Iterable[str | Path] = ()) -> None:
    """What `atomic_output` checks before it starts, for a caller that wants to fail before its own
    long preparation (a bag scan): `path` is not an input, does not exist unless `overwrite`, and its
    folder exists."""
    path = Path(path)
    refuse_inputs(path, inputs)
    if path.exists() and not (path.is_file() or path.is_dir()):
        # A device, FIFO or socket (or a link to one: /dev/null, /dev/stdout): publishing would replace
        # the special file itself, not write into it.
        raise InputError(path, "is not a regular file (a device, FIFO or socket): write the output to a file")
    if path.exists() and not overwrite:
        raise OutputExistsError(path)
    if not path.parent.is_dir():
        raise InputError(path.parent, "output folder does not exist")


def refuse_inputs(path: str | Path, inputs: Iterable[str | Path]) -> None:
    """InputError when writing `path` would replace or remove one of `inputs`: the same path once links
    are resolved, the same file under another name (a hard link), an existing file inside an input
    folder, or a folder that holds an input."""
    path = Path(path)
    out = path.resolve()
    exists = path.exists()
    for given in inputs:
        given = Path(given)
        source = given.resolve()
        if out == source or source.is_relative_to(out):
            raise InputError(path, f"is the input {given} (or holds it): write the output elsewhere")
        if not exists or not given.exists():
            continue
        if given.is_dir():
            if out.is_relative_to(source):
                raise InputError(path, f"is inside the input folder {given}: write the output elsewhere")
            if path.is_file() and _has_same_file(given, path):
                raise InputError(path, f"is a hard link to a file of the input folder {given}: write the output "
                                       "elsewhere")
        elif os.path.samefile(given, path):
            raise InputError(path, f"is the same file as the input {given} (a hard link): write the output elsewhere")


def _has_same_file(folder: Path, path: Path) -> bool:
    target = os.stat(path)
    for root, _dirs, files in os.walk(folder):
        for name in files:
            try:
                st = os.stat(os.path.join(root, name))
            except OSError:
                continue
            if (st.st_ino, st.st_dev) == (target.st_ino, target.st_dev):
                return True
    return False


def _tmp_prefix(path: Path) -> str:
    return f".{path.name}.tmp-"


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Remove the temporaries `.NAME.tmp-<pid>` of `path` whose process is gone (a run killed before
    it could clean up); returns what was removed."""
    path = Path(path)
    prefix = _tmp_prefix(path)
    removed = []
    try:
        entries = [e.name for e in os.scandir(path.parent) if e.name.startswith(prefix)]
    except OSError:
        return removed
    for name in entries:
        pid = name[len(prefix):]
        if pid.isascii() and pid.isdigit() and int(pid) != os.getpid() and not _alive(int(pid)):
            _remove(path.parent / name)
            removed.append(path.parent / name)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True  # another user's process (or not a pid we can ask about): leave its files alone
    return True


def output_os_error(path: str | Path, exc: OSError) -> OutputError | None:
    """An OSError met while writing `path` as the OutputError that names `path` (not its temporary):
    a full disk or quota, or a failure on the temporary or on `path` itself (permissions, a read-only
    file system); None for other errors (an input that cannot be read names itself)."""
    path, named = Path(path), _published_name(Path(path))
    if exc.errno in _DISK_FULL:
        return OutputError(named, "no space left on the device (or quota exceeded); nothing was written: free some "
                                 "space or write the output elsewhere")
    names = {str(exc.filename or ""), str(getattr(exc, "filename2", None) or "")}
    if any(Path(name).name.startswith(_tmp_prefix(path)) or name == str(path) for name in names if name):
        return OutputError(named, f"cannot be written ({exc.strerror or exc}); nothing was written: check the folder's "
                                  "permissions or write the output elsewhere")
    return None


def _published_name(path: Path) -> Path:
    """The output a temporary will be published as (a writer given the temporary of an `atomic_outputs`
    member writes through a temporary of its own): errors name what the user asked for."""
    while (match := _TEMPORARY.fullmatch(path.name)) is not None:
        path = path.with_name(match["name"])
    return path


def _publish(tmp: Path, path: Path, overwrite: bool) -> None:
    if overwrite:
        if path.is_dir() and not path.is_symlink() and tmp.is_dir():
            _remove(path)
        os.replace(tmp, path)
        return
    if _rename_noreplace(tmp, path):
        return
    if tmp.is_dir():  # folders cannot be hard-linked: a check and a rename, with a short window
        if os.path.lexists(path):
            raise OutputExistsError(path)
        os.rename(tmp, path)
        return
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise OutputExistsError(path) from None
    # `tmp` is unlinked by the caller's `finally`


def _libc_renameat2():
    try:
        function = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):  # not glibc >= 2.28, or not Linux
        return None
    function.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    function.restype = ctypes.c_int
    return function


_RENAMEAT2 = _libc_renameat2()


def _rename_noreplace(tmp: Path, path: Path) -> bool:
    """rename(tmp, path) failing if `path` exists; False where the system cannot do it (the caller
    falls back to a hard link)."""
    if _RENAMEAT2 is None:
        return False
    if _RENAMEAT2(_AT_FDCWD, os.fsencode(tmp), _AT_FDCWD, os.fsencode(path), _RENAME_NOREPLACE) == 0:
        return True
    code = ctypes.get_errno()
    if code == errno.EEXIST:
        raise OutputExistsError(path)
    if code in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EPERM):  # file system without the flag
        return False
    raise OSError(code, os.strerror(code), str(path))


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists() or path.is_symlink():
        path.unlink()
