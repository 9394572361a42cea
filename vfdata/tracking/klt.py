"""The `klt` baseline: a 2D tracker lifted to 3D, the stand-in for the paper's CoTracker ablation.

The same 256 reference points as the geometry tracker are projected into the reference left image and
followed frame to frame with OpenCV's pyramidal Lucas-Kanade; each frame's 2D position is lifted to 3D
with that frame's depth map. A point is lost for good, as a 2D tracker would lose it, when LK fails,
the forward-backward check fails (occlusion by the instrument, specular highlights, weak texture) or
it leaves the image; lost points are NaN and never visible again.
"""

from __future__ import annotations

import numpy as np

from vfdata.calibration import PinholeCamera
from vfdata.tracking.flow import to_gray, track_lk
from vfdata.tracking.lifting import lift_pixels
from vfdata.tracking.sampling import select_reference_points


class KLTTracker:
    """reference_points: (N, 3) reference tissue cloud (mm, camera frame); reference_image: the left
    image of that frame. `.update(image, depth_mm, mask)` -> (points (n, 3) mm, NaN when lost or
    without depth; visible (n,) bool)."""

    def __init__(
        self,
        reference_points: np.ndarray,
        camera: PinholeCamera,
        reference_image: np.ndarray,
        num_points: int = 256,
        seed: int = 0,
        max_forward_backward_px: float = 1.0,
    ):
        reference_points = np.asarray(reference_points, dtype=np.float64)
        reference_points = reference_points[np.isfinite(reference_points).all(axis=1)]
        self.camera = camera
        self.reference = reference_points[select_reference_points(reference_points, num_points, seed=seed)]
        self.max_forward_backward_px = max_forward_backward_px
        self.uv = camera.project(self.reference)  # (n, 2) current pixels, NaN once lost
        self.alive = np.isfinite(self.uv).all(axis=1)
        self._points = self.reference.copy()
        self._image = to_gray(reference_image)

    @property
    def points(self) -> np.ndarray:
        return self._points.copy()

    def update(
        self, image: np.ndarray, depth_mm: np.ndarray, mask: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        gray = to_gray(image)
        idx = np.flatnonzero(self.alive)
        new_uv, ok = track_lk(self._image, gray, self.uv[idx], self.max_forward_backward_px)
        self.uv[idx] = new_uv
        lost = idx[~ok]
        self.alive[lost] = False
        self.uv[lost] = np.nan
        self._image = gray
        self._points = lift_pixels(self.uv, depth_mm, self.camera)
        visible = np.isfinite(self._points).all(axis=1)
        if mask is not None:
            visible &= self.camera.in_mask(self._points, np.asarray(mask))  # NaN points project nowhere
        return self._points.copy(), visible
