"""Tracking quality without ground truth (real recordings): forward-backward consistency of the
geometry tracker over a stretch of frames. The points are tracked forward from the stretch's first
frame to its last, then a second tracker starts from where they ended and tracks them back; a point
that returns to where it started was followed consistently. Small errors do not prove the tracks
right (a tracker that never moves returns exactly), so read them with the coverage and NNI
(`vfdata.metrics`) and the tracks' displacement."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from vfdata.calibration import PinholeCamera
from vfdata.tracking.geometry import GeometryTracker


def _track(tracker: GeometryTracker, clouds: Sequence[np.ndarray], masks: Sequence[np.ndarray]) -> np.ndarray:
    for cloud, mask in zip(clouds, masks, strict=True):
        tracker.update(cloud, mask)
    return tracker.points


def forward_backward_error(clouds_mm: Sequence[np.ndarray], masks: Sequence[np.ndarray], camera: PinholeCamera,
                           num_points: int = 256, seed: int = 0, **options) -> dict[str, float]:
    """Forward from clouds_mm[0] to clouds_mm[-1] (camera frame, mm; masks (H, W) bool of the same
    frames), then back: the distances (mm) between where each point started and where it came back
    to (median, 95th percentile), and the median forward displacement over the stretch for scale."""
    if len(clouds_mm) < 2 or len(clouds_mm) != len(masks):
        raise ValueError("need at least two frames, a mask for each")
    forward = GeometryTracker(clouds_mm[0], camera, num_points, seed, **options)
    start = forward.points
    end = _track(forward, clouds_mm[1:], masks[1:])
    backward = GeometryTracker(end, camera, len(end), seed, **{**options, "isolation_factor": 0.0})
    # the backward tracker orders its points by its own sampling: map them back to the forward order
    order = cKDTree(end).query(backward.reference)[1]
    returned = np.empty_like(end)
    returned[order] = _track(backward, clouds_mm[-2::-1], masks[-2::-1])
    error = np.linalg.norm(returned - start, axis=1)
    moved = np.linalg.norm(end - start, axis=1)
    return {"median_mm": float(np.median(error)), "p95_mm": float(np.percentile(error, 95)),
            "forward_displacement_median_mm": float(np.median(moved)),
            "forward_displacement_p95_mm": float(np.percentile(moved, 95)), "frames": len(clouds_mm)}
