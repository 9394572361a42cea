"""Network weights from files the user gives: tensors only, never pickled code.

`torch.load` unpickles; a checkpoint can name any callable to be called while it loads (a crafted
file runs a command). With `weights_only=True` torch's unpickler accepts tensors, containers and plain
values only, whatever torch's default is in the installed version (it changed in 2.6; pyproject asks
for torch>=2.4). Every loader of third-party weights (Stereo Any Video, SAM2, the tissue detector,
CoTracker) goes through `load_state_dict`, and hands the packages a state dict, never the file.
"""

from __future__ import annotations

import pickle
import re
import warnings
from pathlib import Path
from typing import Any

from vfdata.errors import InputError


def load_weights(path: str | Path, what: str) -> Any:
    """The object saved in `path` by `torch.save` (a state dict, or dicts of them), on the CPU.

    `what` names the file's role in the messages ("Stereo Any Video checkpoint"). A file that needs
    pickled code to load is refused with an InputError naming it, before any of that code runs; an
    unreadable one (truncated, not a torch file) too."""
    import torch  # heavy, and only the optional network backends need it

    path = Path(path)
    try:
        with warnings.catch_warnings():  # torch's notes on foreign pickles would add lines to the one-line error
            warnings.simplefilter("ignore")
            return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        # torch's restricted unpickler names the callable it refused to import ("GLOBAL os.system").
        named = re.search(r"GLOBAL\s+([\w.]+)", str(exc))
        if named is None:  # not a pickle torch writes: a damaged or foreign file
            raise InputError(path, f"not a readable {what} (not a file torch.save wrote)") from None
        raise InputError(
            path,
            f"{what} holds pickled code ({named.group(1)}), not only tensors, and was refused without "
            "running it; load it where you trust it and save its state_dict() instead",
        ) from None
    except OSError:
        raise
    except Exception as exc:  # torch reports damaged files as RuntimeError, KeyError, EOFError, ...
        raise InputError(path, f"not a readable {what} ({_first_line(exc)})") from None


def load_state_dict(path: str | Path, what: str) -> dict:
    """A model's state dict from `path` (`load_weights`): bare, or under "model" and/or "state_dict",
    with the "module." prefix of a DataParallel model removed; InputError for anything else."""
    state = load_weights(path, what)
    for key in ("model", "state_dict"):
        if isinstance(state, dict) and key in state:
            state = state[key]
    if not isinstance(state, dict):
        raise InputError(Path(path), f"a {what} holds a state dict, not a {type(state).__name__}")
    # Checkpoints saved from DataParallel prefix every key with "module."; the bare model has none.
    return {str(k).removeprefix("module."): v for k, v in state.items()}


def _first_line(exc: BaseException) -> str:
    """The exception's class and the first sentence of its message."""
    text = str(exc).strip().split("\n")[0].split(". ")[0]
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
