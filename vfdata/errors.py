"""Named exceptions. Every user-facing failure is one of these, rendered by the CLI as one line."""

from __future__ import annotations

from pathlib import Path


class VisionForceError(Exception):
    """Base class: a problem the user can fix, reported as one line without a traceback."""

    def __reduce__(self):
        # Pickled as its message and attributes, whatever the subclass's __init__ takes: an error
        # crosses back whole from a worker process or a Ray task (the default calls __init__(*args)).
        return _rebuild, (type(self), self.args, self.__dict__)


def _rebuild(cls: type, args: tuple, state: dict) -> VisionForceError:
    error = cls.__new__(cls)
    error.args = args
    error.__dict__.update(state)
    return error


class InputError(VisionForceError):
    """A bad input file or folder: names the path and the problem."""

    def __init__(self, path: str | Path, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


class FormatError(InputError):
    """An MCAP file that does not follow the VisionForce layout, or is damaged."""


class BackendError(VisionForceError):
    """An unknown backend, or a backend whose model, code or checkpoint is not available."""


class OutputExistsError(VisionForceError):
    def __init__(self, path: str | Path):
        self.path = Path(path)
        super().__init__(f"{path}: output exists (pass --overwrite to replace it)")


class OutputError(VisionForceError):
    """An output that cannot be written (a full disk, ...): names the path and the problem."""

    def __init__(self, path: str | Path, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


class Terminated(BaseException):
    """SIGTERM or SIGHUP arrived (timeout, systemd, docker, SLURM, a closed terminal): raised by the
    CLI's handler so that cleanup (`finally`, context managers) runs as for Ctrl-C. A BaseException,
    like KeyboardInterrupt, so that no `except Exception` swallows it."""

    def __init__(self, signum: int):
        self.signum = signum
        super().__init__(f"terminated by signal {signum}")
