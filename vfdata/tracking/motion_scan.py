"""A quick look at how the tissue moves over a whole recording, before it is processed.

Which end of the tissue is clamped decides the object frame's +Z, and the plainest fact about it is
that the grasper moves the free end while the clamped end stays (`vfdata.recon.clamped_end.motion_cue`).
Processing fixes the object frame on the first frame, before any track exists, so this scan looks
ahead: it follows corners of the first frame's tissue with pyramidal Lucas-Kanade over every k-th left
image (a few hundred at most: about a second on one core for a 25 s recording) and lifts each to the
first frame's depth of its point. That keeps the motion across the view and drops the motion along
the line of sight, which is all the question needs.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from vfdata.calibration import PinholeCamera
from vfdata.tracking.flow import to_gray, track_lk

MAX_CORNERS = 300
SCAN_FRAMES = 120  # frames looked at, spread over the recording
FORWARD_BACKWARD_PX = 2.0  # looser than the trackers': frames far apart, and only the motion's size counts


def scan_stride(frames: int, looked_at: int = SCAN_FRAMES) -> int:
    """The step between the frames a scan of a `frames`-long recording looks at."""
    return max(1, int(np.ceil(frames / max(1, looked_at))))


@dataclass(frozen=True)
class LookAhead:
    """A recording's frames ahead of the first, for processing to look at before it starts: `frames` is
    how many will be processed, `left(i)` frame i's left rectified image, `pair(i)` its (left, right)."""

    frames: int
    left: Callable[[int], np.ndarray]
    pair: Callable[[int], tuple[np.ndarray, np.ndarray]]

    @property
    def scan_indices(self) -> range:
        """The frames a motion scan looks at: the first, then every k-th (`scan_stride`)."""
        return range(0, self.frames, scan_stride(self.frames))

    def scan_images(self) -> Iterator[np.ndarray]:
        """The left images of the scan's frames, in order."""
        return (self.left(i) for i in self.scan_indices)


def scan_motion(images: Iterable[np.ndarray], mask: np.ndarray, depth_mm: np.ndarray, camera: PinholeCamera
                ) -> tuple[np.ndarray, np.ndarray]:
    """Corners of the tissue (`mask`, (H, W) of the first image) followed through `images` (the first
    frame, then every k-th: BGR or grey), each lifted to 3D with the first frame's `depth_mm` (H, W, mm):
    (F, N, 3) camera-frame points (mm) and (F, N) visible (False once the point is lost)."""
    images = iter(images)
    first = to_gray(next(images))
    inner = cv2.erode(mask.astype(np.uint8), np.ones((7, 7), np.uint8))
    corners = cv2.goodFeaturesToTrack(first, MAX_CORNERS, 0.01, 7, mask=inner)
    if corners is None:
        return np.zeros((1, 0, 3)), np.zeros((1, 0), bool)
    uv = corners.reshape(-1, 2).astype(np.float64)
    z = depth_mm[np.clip(np.round(uv[:, 1]).astype(int), 0, camera.height - 1),
                 np.clip(np.round(uv[:, 0]).astype(int), 0, camera.width - 1)].astype(np.float64)
    keep = np.isfinite(z) & (z > 0)
    uv, z = uv[keep], z[keep]
    tracks, alive, previous = [uv.copy()], np.ones(len(uv), bool), first
    current = uv.copy()
    for image in images:
        gray = to_gray(image)
        idx = np.flatnonzero(alive)
        new, ok = track_lk(previous, gray, current[idx], FORWARD_BACKWARD_PX)
        current[idx] = new
        alive[idx[~ok]] = False
        tracks.append(np.where(alive[:, None], current, np.nan))
        previous = gray
    pixels = np.stack(tracks)  # (F, N, 2)
    points = np.stack([(pixels[..., 0] - camera.cx) * z / camera.fx, (pixels[..., 1] - camera.cy) * z / camera.fy,
                       np.broadcast_to(z, pixels.shape[:2])], axis=-1)
    return points, np.isfinite(pixels).all(axis=-1)
