"""Stage 2: the tissue mask of every frame, from a first-frame prompt.

A segmenter (`vfdata.recon.segmenter.Segmenter`) is a small state machine over a video:
`start(first_image, prompt)` returns the first mask, then `track(image)` the next one per frame
(`segment_video` runs both over a sequence). Backends by name (`make_segmenter`):

- `colortrack` (default, runs anywhere without weights; `vfdata.recon.colortrack`): GrabCut from the
  prompt, then a colour model, a flow-carried prior and a depth cue per frame.
- `sam2` (`vfdata.recon.sam2_segmenter`): Meta's SAM2 video predictor from the user's local config
  and checkpoint.
- `plane` (`vfdata.recon.plane`): for a depth camera over a flat board, what stands above the board.
- `recorded`: masks supplied with the recording (the simulator's true masks), passed through; for
  measuring what the segmentation costs (the attribution ladder, docs/results.md).

Prompts (`vfdata.recon.prompt.Prompt`): a box and/or positive and negative points, from the command
line (`Prompt.parse`), the recording's metadata (`prompt_box`) or a detector
(`vfdata.recon.detector.DetectorPrompt`, the paper's fine-tuned Faster R-CNN).

Images are (H, W, 3) uint8 BGR; masks (H, W) bool.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from vfdata.errors import BackendError, InputError
from vfdata.recon.colortrack import ColorTrackSegmenter, ColorTrackSettings
from vfdata.recon.detector import DetectorPrompt
from vfdata.recon.plane import PlaneSegmenter
from vfdata.recon.prompt import Prompt
from vfdata.recon.sam2_segmenter import Sam2Segmenter
from vfdata.recon.segmenter import Segmenter

# Names other modules import from here since before the split.
__all__ = [
    "SEGMENT_BACKENDS",
    "ColorTrackSegmenter",
    "ColorTrackSettings",
    "DetectorPrompt",
    "Prompt",
    "Sam2Segmenter",
    "Segmenter",
    "make_segmenter",
    "mask_iou",
    "segment_video",
]

class RecordedMasks(Segmenter):
    """Masks given in frame order (`masks=`, an iterable of (H, W) bool arrays, read lazily), one per
    `start`/`track` call; the prompt is not used."""

    name = "recorded"

    def __init__(self, masks: Iterable[np.ndarray]):
        self._masks = iter(masks)
        self._consumed = 0

    def _next(self, image: np.ndarray) -> np.ndarray:
        mask = next(self._masks, None)
        if mask is None:
            raise BackendError(f"recorded: no mask supplied for frame {self._consumed}")
        self._consumed += 1
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != image.shape[:2]:
            raise InputError("recorded mask", f"frame {self._consumed - 1}: mask {mask.shape} but image "
                                              f"{image.shape[:2]}")
        return mask

    def start(self, image: np.ndarray, prompt: Prompt, depth_mm: np.ndarray | None = None) -> np.ndarray:
        return self._next(image)

    def track(self, image: np.ndarray, depth_mm: np.ndarray | None = None) -> np.ndarray:
        return self._next(image)


SEGMENT_BACKENDS = {"colortrack": ColorTrackSegmenter, "sam2": Sam2Segmenter, "recorded": RecordedMasks,
                    "plane": PlaneSegmenter}


def make_segmenter(name: str = "colortrack", **options) -> Segmenter:
    """The segmenter `name` with its options (see each backend's class)."""
    try:
        cls = SEGMENT_BACKENDS[name]
    except KeyError:
        raise BackendError(
            f"unknown segmentation backend '{name}'; known: {', '.join(SEGMENT_BACKENDS)}"
        ) from None
    try:
        return cls(**options)
    except TypeError as exc:
        raise BackendError(f"{name}: bad options {sorted(options)}: {exc}") from exc


def segment_video(
    frames: Iterable[np.ndarray],
    prompt: Prompt | str,
    *,
    backend: str = "colortrack",
    depths: Iterable[np.ndarray] | None = None,
    **options,
) -> list[np.ndarray]:
    """Convenience: masks of a whole video from a prompt (a Prompt or its CLI string)."""
    if isinstance(prompt, str):
        prompt = Prompt.parse(prompt)
    return make_segmenter(backend, **options).segment_video(frames, prompt, depths)


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks (1.0 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0
