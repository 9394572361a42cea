"""The interface every tissue segmentation backend implements (`vfdata.recon.segment` picks one).

A segmenter is a small state machine over a video: `start(first_image, prompt)` returns the first
mask, then `track(image)` the next one per frame. Images are (H, W, 3) uint8 BGR; masks (H, W) bool.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable

import numpy as np

from vfdata.errors import InputError
from vfdata.recon.prompt import Prompt


class Segmenter(ABC):
    """A video tissue segmenter: `start` on the first frame with a prompt, then `track` per frame."""

    name: str = ""
    # Whether `start` may run on any frame of a recording with the first frame's prompt, cheaply, beside the
    # running video (the object frame's look at resting frames, `vfdata.recon.rest_frames`).
    any_frame: bool = False

    @abstractmethod
    def start(self, image: np.ndarray, prompt: Prompt, depth_mm: np.ndarray | None = None) -> np.ndarray:
        """First frame + prompt -> (H, W) bool mask. Resets any previous video."""

    @abstractmethod
    def track(self, image: np.ndarray, depth_mm: np.ndarray | None = None) -> np.ndarray:
        """Next frame -> (H, W) bool mask."""

    def segment_video(
        self, frames: Iterable[np.ndarray], prompt: Prompt, depths: Iterable[np.ndarray] | None = None
    ) -> list[np.ndarray]:
        """Masks of a whole video (optionally with per-frame depth in mm)."""
        depth_iter = iter(depths) if depths is not None else None
        masks = []
        for i, frame in enumerate(frames):
            depth = next(depth_iter) if depth_iter is not None else None
            masks.append(self.start(frame, prompt, depth) if i == 0 else self.track(frame, depth))
        return masks

    def parameters(self) -> dict:
        return {"backend": self.name}


def check_image(image: np.ndarray) -> None:
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise InputError("image", f"expected an (H, W, 3) uint8 BGR image, got {image.shape} {image.dtype}")
