"""The interface every stereo depth backend implements (`vfdata.recon.depth` picks one).

Images are (H, W, 3) uint8 BGR (OpenCV order) or (H, W) uint8 grey, already rectified. Disparities are
float32 pixels of the left image (x_right = x_left - d); depths are float32 mm along the left camera's
optical axis; NaN marks a pixel without a value.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator

import cv2
import numpy as np

from vfdata.calibration import PinholeCamera
from vfdata.errors import InputError


class DepthEstimator(ABC):
    """A stereo depth backend. Subclasses implement `disparity`; `depth_mm` converts it."""

    name: str = ""
    # Whether any one frame's depth comes from its pair alone, cheaply, beside the running stream (the
    # object frame's look at resting frames, `vfdata.recon.rest_frames`): not a recorded sequence, nor a
    # video model that would be loaded twice.
    any_frame: bool = False

    @abstractmethod
    def disparity(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """Rectified pair -> (H, W) float32 disparity of the left image in pixels (NaN: none)."""

    def depth_mm(
        self, left: np.ndarray, right: np.ndarray, camera: PinholeCamera, baseline_mm: float
    ) -> np.ndarray:
        """Rectified pair -> (H, W) float32 z-depth in mm of the left camera (NaN: none)."""
        return camera.depth_from_disparity(self.disparity(left, right), baseline_mm)

    def depth_stream(
        self, pairs: Iterable[tuple[np.ndarray, np.ndarray]], camera: PinholeCamera, baseline_mm: float
    ) -> Iterator[np.ndarray]:
        """Depth maps (mm) of a stream of rectified pairs, in order. Backends may overlap the work of
        consecutive frames; the results are those of `depth_mm` frame by frame."""
        for left, right in pairs:
            yield self.depth_mm(left, right, camera, baseline_mm)

    def parameters(self) -> dict:
        """The backend's name and settings, for provenance records."""
        return {"backend": self.name}


def check_pair(left: np.ndarray, right: np.ndarray) -> None:
    if left.shape != right.shape:
        raise InputError(
            "stereo pair", f"left image {left.shape} and right image {right.shape} differ in size"
        )
    if left.ndim not in (2, 3) or left.shape[0] < 16 or left.shape[1] < 16:
        raise InputError("stereo pair", f"expected (H, W) or (H, W, 3) images, got {left.shape}")


def grey(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.dtype != np.uint8:
        image = cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return image
