"""Where a prompt box's depth can be the tissue's: a ramp grown from the box's middle.

A tissue that runs into depth (a tube seen along its length) spans a wide range of depths across the
prompt box, while the bed beside its near end can sit at the depth of its middle. A constant band around
the middle's depth then keeps the bed and drops the far half of the tissue (the simulator's colon at
270 degrees: 51% of the tissue's pixels outside the band, mask IoU 0.54). The tissue's visible surface
is close to a plane, and a plane's inverse depth is affine in the pixel coordinates, so the gate here
is a plane in inverse depth fitted to the seed's pixels and refitted as it grows: each round accepts
the box's pixels within the tolerance of the plane that are connected to the seed, over a window that
widens from the seed to the whole box.
"""

from __future__ import annotations

import cv2
import numpy as np

ROUNDS = 6  # the window grows from the seed's neighbourhood to the whole box in this many rounds
TRIM = 0.1  # the fit drops this share of its worst residuals (the tube's rims, stray matches)


def ramp_gate(depth_mm: np.ndarray, usable: np.ndarray, seed: np.ndarray, tolerance_mm: float,
              bridge: np.ndarray | None = None) -> np.ndarray:
    """(H, W) bool: the pixels of a box whose depth lies within `tolerance_mm` of the tissue's ramp and
    that connect to `seed` through such pixels. `depth_mm` (H, W), <= 0 where unknown; `usable` (H, W)
    the pixels that may be tissue (known depth, not metal); `seed` (H, W) pixels known to be on the
    tissue (the box's middle or the prompt's points), whose median depth starts the ramp. `bridge` (H, W):
    pixels the tissue may pass behind (an instrument lying across it), through which the tissue on either
    side stays connected; they are never accepted themselves."""
    depth = np.asarray(depth_mm, dtype=np.float64)
    usable = usable & (depth > 0)
    start = seed & usable
    if start.sum() < 3:
        return usable.copy()
    median = float(np.median(depth[start]))
    accepted = start & (np.abs(depth - median) <= tolerance_mm)
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    u, v = u / max(w, 1), v / max(h, 1)  # unit box coordinates: a well-conditioned fit
    ys, xs = np.nonzero(start)
    centre = np.array([ys.mean() / max(h, 1), xs.mean() / max(w, 1)])
    for k in range(1, ROUNDS + 1):
        along = _long_axis(u[accepted], v[accepted])
        s_all = u * along[0] + v * along[1]
        ramp = _fit_inverse_ramp(s_all[accepted], depth[accepted])
        if ramp is None:
            break
        predicted = 1.0 / np.maximum(ramp[0] + ramp[1] * s_all, 1e-9)
        reach = k / ROUNDS
        window = (np.abs(v - centre[0]) <= reach) & (np.abs(u - centre[1]) <= reach)
        near = usable & window & (np.abs(depth - predicted) <= tolerance_mm)
        grown = _connected_to(near, start, bridge)
        if (grown == accepted).all() and reach >= 1:
            break
        accepted = grown
    return accepted


def _long_axis(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The unit direction (du, dv) along which the pixels spread most (their principal axis)."""
    if len(u) < 3:
        return np.array([1.0, 0.0])
    _vals, vecs = np.linalg.eigh(np.cov(np.stack([u, v])))
    return vecs[:, -1]


def _fit_inverse_ramp(s: np.ndarray, depth: np.ndarray) -> np.ndarray | None:
    """Least-squares 1/depth = a + b s, refitted without the worst `TRIM` of the residuals."""
    if len(depth) < 3:
        return None
    design = np.stack([np.ones_like(s), s], axis=1)
    target = 1.0 / depth
    coef, *_ = np.linalg.lstsq(design, target, rcond=None)
    residual = np.abs(design @ coef - target)
    keep = residual <= np.quantile(residual, 1 - TRIM)
    if keep.sum() >= 3:
        coef, *_ = np.linalg.lstsq(design[keep], target[keep], rcond=None)
    return coef


def _connected_to(region: np.ndarray, seed: np.ndarray, bridge: np.ndarray | None = None) -> np.ndarray:
    """The pixels of `region` whose components (8-connected, through `bridge` pixels too) touch `seed`."""
    linked = region if bridge is None else region | bridge
    n, labels = cv2.connectedComponents(linked.astype(np.uint8), connectivity=8)
    if n <= 1:
        return region & seed
    touched = np.unique(labels[seed & region])
    touched = touched[touched > 0]
    return np.isin(labels, touched) & region
