"""Lifting 2D tracks to 3D with a depth map (shared by the 2D-tracker baselines)."""

from __future__ import annotations

import numpy as np

from vfdata.calibration import PinholeCamera


def lift_pixels(uv: np.ndarray, depth_mm: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """(N, 2) pixels + (H, W) z-depth (mm; 0 or NaN = none) -> (N, 3) camera-frame points (mm), NaN
    where the pixel is outside the image, NaN itself, or has no depth. The depth is read at the
    nearest pixel: interpolating across a tissue/instrument edge would invent a surface in between."""
    uv = np.asarray(uv, dtype=np.float64)
    depth_mm = np.asarray(depth_mm, dtype=np.float64)
    out = np.full((len(uv), 3), np.nan)
    ok = np.isfinite(uv).all(axis=1)
    u = np.full(len(uv), -1, dtype=np.int64)
    v = np.full(len(uv), -1, dtype=np.int64)
    u[ok] = np.floor(uv[ok, 0] + 0.5).astype(np.int64)
    v[ok] = np.floor(uv[ok, 1] + 0.5).astype(np.int64)
    h, w = depth_mm.shape
    ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    z = np.full(len(uv), np.nan)
    z[ok] = depth_mm[v[ok], u[ok]]
    ok &= np.isfinite(z) & (z > 0)
    out[ok, 0] = (uv[ok, 0] - camera.cx) * z[ok] / camera.fx
    out[ok, 1] = (uv[ok, 1] - camera.cy) * z[ok] / camera.fy
    out[ok, 2] = z[ok]
    return out
