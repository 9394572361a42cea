"""A trained force model as inference needs it, read from its checkpoint once.

`TrainedModel.load(ckpt)` gives the regressor (eval mode, on its device), the `ClipSpec` it was trained
with, the tracker whose tracks it was trained on and how low its training tissues hang: everything
`vfdata predict`, `--stream` and `vfdata live` ask of a checkpoint. Each of them once read the file
again for each fact (six reads of 70 ms for a `visionforce` checkpoint); now the command loads it once
and hands the object down. Only point models with the causal interface load: the others cannot run
frame by frame (`vfmodels/training/regressor.py` says what a model implements).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from vfdata.clips.datamodule import spec_from_checkpoint_hparams
from vfdata.clips.spec import ClipSpec
from vfdata.device import shared_device_options
from vfdata.engine import EngineOptions
from vfdata.errors import InputError, VisionForceError
from vfdata.tracking.registry import TRACKERS
from vfmodels.training.checkpoint import best_checkpoint, read_checkpoint
from vfmodels.training.regressor import ForceRegressor

DEFAULT_TRACKER = EngineOptions.tracker  # the engine's, for a checkpoint that does not say which tracks it had


@dataclass(frozen=True)
class TrainedModel:
    path: Path
    regressor: ForceRegressor
    spec: ClipSpec
    tracker: str | None  # the tracker of the training recordings (None: an older checkpoint does not say)
    lean_deg: list[float] | None  # [low, high] deg below level of the training tissues (vfdata.tissue_lean)

    @classmethod
    def load(cls, ckpt: str | Path, device: str = "cpu", checkpoint: dict[str, Any] | None = None) -> TrainedModel:
        """The model of a .ckpt file, or of a run folder's best checkpoint (in its checkpoints/), on `device`
        (`vfdata.device.resolve_device`), from the file's contents when already read (`checkpoint`); an
        InputError naming the file when it is not a point model that runs frame by frame."""
        path = Path(ckpt)
        if path.is_dir():
            path = best_checkpoint(path / "checkpoints" if (path / "checkpoints").is_dir() else path)
        checkpoint = read_checkpoint(path) if checkpoint is None else checkpoint
        regressor = ForceRegressor.load(path, checkpoint=checkpoint)
        if regressor.model.input_key != "tokens":
            raise InputError(path, f"{type(regressor.model).__name__} takes {regressor.model.input_key}, not tracked "
                                   "points: prediction runs the point-based models (visionforce, proposed, ablations)")
        spec = spec_from_checkpoint_hparams(checkpoint.get("datamodule_hyper_parameters") or {}, path)
        if spec.input != "tracks":
            raise InputError(path, f"the model was trained on '{spec.input}' inputs, not tracked points")
        if not regressor.causal:
            raise InputError(path, f"{type(regressor.model).__name__} does not run frame by frame (no encode_frames/"
                                   "decode_frames: vfmodels/training/regressor.py says what a model implements)")
        if regressor.model.config.get("in_features", spec.channels) != spec.channels:
            raise InputError(path, f"model takes {regressor.model.config['in_features']} features per point, its "
                                   f"clip spec gives {spec.channels} ({spec.features})")
        state = checkpoint.get("ForceDataModule") or {}
        state = state if isinstance(state, dict) else {}
        return cls(path, regressor.to(device), spec, _tracker(state, path), _lean(state, path))

    @classmethod
    def of(cls, model: TrainedModel | str | Path, device: str = "cpu") -> TrainedModel:
        """`model` as given, or loaded from a checkpoint path (the library's callers may pass either)."""
        return model if isinstance(model, TrainedModel) else cls.load(model, device)

    def tracker_settings(self, device: str, tracker: str | None = None) -> tuple[str, dict]:
        """The tracker to process with (`tracker`, else the training recordings', else geometry) and its
        options on a resolved `device`: a tracker without a GPU path (KLT) stays on the CPU."""
        tracker = tracker or self.tracker or DEFAULT_TRACKER
        return tracker, shared_device_options(tracker, device)


def history(spec: ClipSpec, window: int | None) -> int:
    """Frames of history a force is estimated from: `window`, or the clip length the model was trained on
    (`spec.clip_frames`, for None); 0 carries the temporal state over the whole recording."""
    if window is not None and window < 0:
        raise VisionForceError(f"window {window}: a number of frames >= 0 (0: the whole recording)")
    return spec.clip_frames if window is None else int(window)


def model_device(regressor: ForceRegressor) -> torch.device:
    return next(regressor.parameters()).device


def _tracker(state: dict[str, Any], path: Path) -> str | None:
    tracker = state.get("tracker")
    if tracker is not None and tracker not in TRACKERS:
        raise InputError(path, f"the checkpoint names an unknown tracker {tracker!r} (known: {', '.join(TRACKERS)})")
    return tracker


def _lean(state: dict[str, Any], path: Path) -> list[float] | None:
    lean = state.get("tissue_lean_deg")
    if lean is None:
        return None
    if not (isinstance(lean, (list, tuple)) and len(lean) == 2 and all(isinstance(v, (int, float)) for v in lean)):
        raise InputError(path, f"the checkpoint's tissue_lean_deg {lean!r} is not a range of two angles")
    return [float(v) for v in lean]
