"""The `probe` tracker: points that stay on their pixel while the surface under them moves.

A fixed depth camera over an organ that lies on a board and is pressed: the organ dents and hardly
slides, so the force shows in how far the surface under each place sinks, not in where its texture
goes. Each reference point keeps the pixel it projects to on the first frame; every later frame
re-reads the depth there (the median over a small window of valid, in-mask pixels: one Kinect pixel
is quantised to 1-2 mm at 0.7 m, about the size of a dent) and lifts the point along its viewing ray.
This is the Eulerian view of the surface, a height field sampled at fixed places. It needs no image
and nothing to drift: a point is where the surface is, at its own place, in every frame.

It suits a static camera over a tissue that stays in place (RGB-D recordings of a flat organ, the
Gao et al. 2018 set-up); a moving endoscope or a tube that swings needs a tracker that follows
material points (geometry, klt).
"""

from __future__ import annotations

import numpy as np

from vfdata.calibration import PinholeCamera
from vfdata.tracking.sampling import select_reference_points


class ProbeTracker:
    """reference_points: (N, 3) reference tissue cloud (mm, camera frame). `.update(depth_mm, mask)`
    -> (points (n, 3) mm, visible (n,) bool); a point without enough depth under it in a frame is
    held where it was last seen and marked not visible.

    radius_px: the window is (2 r + 1) pixels square; min_valid: the share of its pixels that must
    have depth (and lie inside the mask) for the point to be read in that frame."""

    def __init__(self, reference_points: np.ndarray, camera: PinholeCamera, num_points: int = 256, seed: int = 0,
                 radius_px: int = 2, min_valid: float = 0.25):
        if radius_px < 0:
            raise ValueError(f"radius_px must be >= 0, got {radius_px}")
        if not 0.0 < min_valid <= 1.0:
            raise ValueError(f"min_valid must be in (0, 1], got {min_valid}")
        reference_points = np.asarray(reference_points, dtype=np.float64)
        reference_points = reference_points[np.isfinite(reference_points).all(axis=1)]
        self.camera = camera
        self.reference = reference_points[select_reference_points(reference_points, num_points, seed=seed)]
        self.uv = camera.project(self.reference)  # (n, 2) fixed pixels
        self.rays = np.column_stack([(self.uv[:, 0] - camera.cx) / camera.fx,
                                     (self.uv[:, 1] - camera.cy) / camera.fy,
                                     np.ones(len(self.uv))])  # (n, 3): a point is ray * z
        offsets = np.arange(-radius_px, radius_px + 1)
        du, dv = np.meshgrid(offsets, offsets)
        self._du, self._dv = du.ravel(), dv.ravel()
        self._min_count = max(1, int(np.ceil(min_valid * len(self._du))))
        self._points = self.reference.copy()

    @property
    def points(self) -> np.ndarray:
        return self._points.copy()

    def update(self, depth_mm: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        z = self.depth_under(depth_mm, mask)
        visible = np.isfinite(z)
        self._points[visible] = self.rays[visible] * z[visible, None]
        return self._points.copy(), visible

    def depth_under(self, depth_mm: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """(n,) the median z-depth (mm) of the valid pixels in each point's window; NaN where fewer
        than the window's `min_valid` share have depth (and lie inside `mask`)."""
        depth_mm = np.asarray(depth_mm, dtype=np.float64)
        h, w = depth_mm.shape
        u = np.floor(self.uv[:, 0] + 0.5).astype(np.int64)[:, None] + self._du[None]
        v = np.floor(self.uv[:, 1] + 0.5).astype(np.int64)[:, None] + self._dv[None]
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        uc, vc = np.clip(u, 0, w - 1), np.clip(v, 0, h - 1)
        z = np.where(inside, depth_mm[vc, uc], np.nan)
        z[~(np.isfinite(z) & (z > 0))] = np.nan
        if mask is not None:
            z[~np.asarray(mask, dtype=bool)[vc, uc]] = np.nan
        enough = np.sum(np.isfinite(z), axis=1) >= self._min_count
        out = np.full(len(z), np.nan)
        out[enough] = np.nanmedian(z[enough], axis=1)
        return out
