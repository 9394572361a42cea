"""Where the depth moves with each force component, stretch by stretch: a check that a recording's
training stretch teaches what its test stretch asks (docs/results.md, "Real recording").

A model learns, from the training frames, which surface motion goes with which force. If in the test
stretch the same force comes with another motion (a press at another place, a pull no longer coupled
to the press), no model of the video can carry it over. The response map of a component over a set
of frames is the per-pixel correlation between the depth change and that force component; two
stretches agree as far as their maps correlate over the tissue (how the components couple in each:
`vfdata.split_forces.component_coupling`). Pure functions on arrays: depths
(T, H, W) mm with NaN unknown, forces (T, 3) N.
"""

from __future__ import annotations

import cv2
import numpy as np

SMOOTH_PX = 5  # spatial box filter (pixels): one Kinect pixel is quantised to 1-2 mm at 0.7 m


def depth_change(depths_mm: np.ndarray, reference: int = 0, smooth_px: int = SMOOTH_PX) -> np.ndarray:
    """(T, H, W) each frame's depth less the reference frame's (mm; 0 where either is unknown),
    box-filtered over `smooth_px` pixels."""
    change = np.nan_to_num(np.asarray(depths_mm, np.float64) - np.asarray(depths_mm[reference], np.float64), nan=0.0)
    if smooth_px <= 1:
        return change
    return np.stack([cv2.blur(frame, (smooth_px, smooth_px)) for frame in change])


def response_maps(change_mm: np.ndarray, force_n: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """(3, H, W): per pixel, the correlation over `frames` between the depth change (T, H, W) and each
    force component (T, 3); 0 where the depth does not change."""
    x = change_mm[frames] - change_mm[frames].mean(axis=0)
    y = force_n[frames] - force_n[frames].mean(axis=0)
    cov = np.einsum("thw,tc->chw", x, y)
    norm = np.sqrt((x ** 2).sum(axis=0))[None] * np.sqrt((y ** 2).sum(axis=0))[:, None, None]
    return np.divide(cov, norm, out=np.zeros_like(cov), where=norm > 1e-9)


def map_agreement(maps_a: np.ndarray, maps_b: np.ndarray, region: np.ndarray) -> list[float]:
    """Per component, the correlation of two stretches' response maps (3, H, W) over `region` (H, W)
    bool: 1 = the force moves the same places the same way in both."""
    return [float(np.corrcoef(a[region], b[region])[0, 1]) for a, b in zip(maps_a, maps_b, strict=True)]
