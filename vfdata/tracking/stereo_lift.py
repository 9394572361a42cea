"""Lifting tracked left-image points to 3D by their own stereo match: the `klt` tracker's `lift="stereo"`.

Reading the depth map at a tracked pixel takes the stereo matcher's depth there, and the matcher's depth
is noisiest along the line of sight: where the tissue runs into depth, the axial displacement that
carries Fz lies along it (issue 32). Each point is instead followed from the left image into the right
image of the same rectified pair with pyramidal Lucas-Kanade, sub-pixel, and triangulated:
z = fx * baseline / disparity. A match is kept only where it stays on the point's row (rectified: the
true match lies on the same row), tracking it back from the right image lands where it started, and its
disparity puts the surface inside the working range; elsewhere the depth map lifts the point.
"""

from __future__ import annotations

import cv2
import numpy as np

from vfdata.calibration import PinholeCamera
from vfdata.tracking.flow import LK_CRITERIA

# The two views of the tissue differ in their shading (the light sits between the cameras, and specular
# highlights move with the view), and where its texture is faint a smooth brightness difference pulls
# Lucas-Kanade off the match by tenths of a pixel. Matching the images less their local mean (a
# high-pass, as SGBM's prefilter matches gradients) removes it: on tuning seed 301 the median disparity
# error against the simulator's depth fell from 0.39 to 0.17 px on a frontal view, 0.25 to 0.12 at 45 degrees.
HIGHPASS_SIGMA_PX = 4.0
HIGHPASS_GAIN = 3.0  # the high-passed image, times this, around grey 128 (LK takes 8-bit images)
STEREO_WINDOW_PX = 15
# The search starts at a guess (the point's disparity in the previous frame, else the depth map's), so
# two pyramid levels (+-4x the window's reach) are plenty, and fewer levels leave fewer wrong minima.
STEREO_LEVELS = 2
MAX_ROW_OFFSET_PX = 1.0  # a match further off the point's row is not the same surface point
MAX_FORWARD_BACKWARD_PX = 0.5  # right -> left must land this close to the left pixel
# LK's minimum is also where the left and right patches merely look least unlike, and a self-consistent
# wrong match (another surface in the right view: the instrument, a fold) passes the two checks above.
MIN_CORRELATION = 0.8  # zero-mean normalised cross-correlation of the matched windows
CORRELATION_WINDOW_PX = 11
# Near the tissue's silhouette and the instrument a window straddles two surfaces and may settle on a
# consistent but wrong match, several pixels off (tens of mm in depth). The depth map is rarely off by
# this much: a match that disagrees with it by more is not trusted, and neither is one without it.
MAX_DEPTH_DISAGREEMENT_PX = 1.0


def disparity_range_px(camera: PinholeCamera, baseline_mm: float,
                       working_range_mm: tuple[float, float] | None) -> tuple[float, float]:
    """The disparities (px) of surfaces between the nearest and farthest of `working_range_mm`; without
    a range, any positive disparity up to the image's width."""
    if working_range_mm is None:
        return 0.0, float(camera.width)
    near, far = working_range_mm
    return camera.fx * baseline_mm / far, camera.fx * baseline_mm / near


def stereo_image(gray: np.ndarray) -> np.ndarray:
    """(H, W) uint8 gray view -> the uint8 image the stereo match runs on: less its local mean
    (Gaussian, `HIGHPASS_SIGMA_PX`), times `HIGHPASS_GAIN`, around 128."""
    g = np.asarray(gray, dtype=np.float32)
    high = g - cv2.GaussianBlur(g, (0, 0), HIGHPASS_SIGMA_PX)
    return np.clip(128.0 + HIGHPASS_GAIN * high + 0.5, 0, 255).astype(np.uint8)


def match_right(
    left: np.ndarray,
    right: np.ndarray,
    uv: np.ndarray,
    guess_px: np.ndarray,
    disparity_px: tuple[float, float],
    max_row_offset_px: float = MAX_ROW_OFFSET_PX,
    max_forward_backward_px: float = MAX_FORWARD_BACKWARD_PX,
    min_correlation: float = MIN_CORRELATION,
) -> tuple[np.ndarray, np.ndarray]:
    """Follow left pixels `uv` (N, 2) into the right image of the same rectified pair (uint8, as
    `stereo_image` makes them), each search starting at its disparity guess `guess_px` (N,) (the match
    at u - d on the same row).

    Returns the disparities (N,) px (u_left - u_right, sub-pixel) and an (N,) bool `ok`: LK converged
    both ways, the match lies within `max_row_offset_px` of the point's row, tracking it back lands within
    `max_forward_backward_px` of `uv`, the match is inside the image, its disparity inside
    `disparity_px` (lo, hi), and the two windows correlate at `min_correlation` or more."""
    uv = np.asarray(uv, dtype=np.float32).reshape(-1, 2)
    n = len(uv)
    if n == 0:
        return np.zeros(0), np.zeros(0, bool)
    guess = np.asarray(guess_px, dtype=np.float32).reshape(-1)
    finite = np.isfinite(uv).all(axis=1) & np.isfinite(guess)
    start = np.where(finite[:, None], uv, 0).astype(np.float32)
    initial = start.copy()
    initial[:, 0] -= np.where(finite, guess, 0)
    params = dict(winSize=(STEREO_WINDOW_PX, STEREO_WINDOW_PX), maxLevel=STEREO_LEVELS, criteria=LK_CRITERIA,
                  flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    # OpenCV writes its answer into the initial-guess array: hand it copies.
    found, st_f, _ = cv2.calcOpticalFlowPyrLK(left, right, start.reshape(-1, 1, 2), initial.reshape(-1, 1, 2).copy(),
                                              **params)
    back, st_b, _ = cv2.calcOpticalFlowPyrLK(right, left, found.copy(), start.reshape(-1, 1, 2).copy(), **params)
    found, back = found[:, 0, :].astype(np.float64), back[:, 0, :].astype(np.float64)
    disparity = start[:, 0] - found[:, 0]
    h, w = right.shape[:2]
    ok = finite & (st_f[:, 0] == 1) & (st_b[:, 0] == 1) & np.isfinite(found).all(axis=1)
    ok &= np.abs(found[:, 1] - start[:, 1]) <= max_row_offset_px
    ok &= np.linalg.norm(back - start, axis=1) <= max_forward_backward_px
    ok &= (found[:, 0] >= 0) & (found[:, 0] <= w - 1)
    ok &= (disparity >= disparity_px[0]) & (disparity <= disparity_px[1])
    for i in np.flatnonzero(ok):
        ok[i] = window_correlation(left, right, start[i], found[i]) >= min_correlation
    disparity[~ok] = np.nan
    return disparity, ok


def window_correlation(left: np.ndarray, right: np.ndarray, left_uv: np.ndarray, right_uv: np.ndarray,
                       size: int = CORRELATION_WINDOW_PX) -> float:
    """Zero-mean normalised cross-correlation of the `size` x `size` windows around the sub-pixel
    positions `left_uv` in `left` and `right_uv` in `right` (gray); 0 for a flat window."""
    a = cv2.getRectSubPix(left, (size, size), (float(left_uv[0]), float(left_uv[1])), patchType=cv2.CV_32F)
    b = cv2.getRectSubPix(right, (size, size), (float(right_uv[0]), float(right_uv[1])), patchType=cv2.CV_32F)
    a, b = a - a.mean(), b - b.mean()
    norm = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum()) / norm if norm > 0 else 0.0


def triangulate(uv: np.ndarray, disparity_px: np.ndarray, camera: PinholeCamera, baseline_mm: float) -> np.ndarray:
    """(N, 2) left pixels and their (N,) rectified disparities (px) -> (N, 3) left-camera points (mm);
    NaN where the disparity is not positive."""
    uv = np.asarray(uv, dtype=np.float64)
    d = np.asarray(disparity_px, dtype=np.float64)
    out = np.full((len(uv), 3), np.nan)
    ok = np.isfinite(uv).all(axis=1) & (d > 0)
    z = camera.fx * baseline_mm / d[ok]
    out[ok, 0] = (uv[ok, 0] - camera.cx) * z / camera.fx
    out[ok, 1] = (uv[ok, 1] - camera.cy) * z / camera.fy
    out[ok, 2] = z
    return out


class StereoLift:
    """Lifts the same N tracked points frame after frame: `lift(uv, left, right, fallback_mm)` -> ((N, 3)
    mm, (N,) bool: lifted by its stereo match, not by the depth map's `fallback_mm`).

    Each point's search starts at its own disparity of the previous frame (the tissue moves little
    between frames), else at the depth map's, else at the median of the others'."""

    def __init__(self, camera: PinholeCamera, baseline_mm: float, working_range_mm: tuple[float, float] | None,
                 count: int):
        if not baseline_mm > 0:
            raise ValueError(f"stereo lift: the baseline must be positive, not {baseline_mm} mm")
        self.camera, self.baseline_mm = camera, float(baseline_mm)
        self.range_px = disparity_range_px(camera, self.baseline_mm, working_range_mm)
        self._guess = np.full(count, np.nan)  # the latest disparity each point had, px

    def lift(self, uv: np.ndarray, left: np.ndarray, right: np.ndarray, fallback_mm: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
        """`uv` (N, 2) left pixels (NaN: lost), the gray left and right images, and `fallback_mm` (N, 3)
        the points as the depth map lifts them (NaN: no depth) -> ((N, 3) mm left camera frame: the
        stereo match's, else the fallback's; (N,) bool: lifted by the stereo match). A match is kept
        only within `MAX_DEPTH_DISAGREEMENT_PX` of the fallback's disparity."""
        uv = np.asarray(uv, dtype=np.float64)
        fallback = np.array(fallback_mm, dtype=np.float64).reshape(len(uv), 3)
        alive = np.flatnonzero(np.isfinite(uv).all(axis=1))
        with np.errstate(divide="ignore", invalid="ignore"):
            from_depth = self.camera.fx * self.baseline_mm / fallback[alive, 2]
        guess = np.where(np.isfinite(self._guess[alive]), self._guess[alive], from_depth)
        known = np.isfinite(guess)
        guess[~known] = np.median(guess[known]) if known.any() else 0.5 * sum(self.range_px)
        disparity, ok = match_right(stereo_image(left), stereo_image(right), uv[alive], guess, self.range_px)
        with np.errstate(invalid="ignore"):
            ok &= np.abs(disparity - from_depth) <= MAX_DEPTH_DISAGREEMENT_PX  # NaN (no depth): rejected
        # A rejected match (a highlight, the instrument over the point) keeps its last disparity as the next guess.
        kept = np.where(np.isfinite(self._guess[alive]), self._guess[alive], from_depth)
        self._guess[alive] = np.where(ok, disparity, kept)
        points = fallback
        stereo = np.zeros(len(uv), bool)
        stereo[alive[ok]] = True
        points[alive[ok]] = triangulate(uv[alive[ok]], disparity[ok], self.camera, self.baseline_mm)
        return points, stereo
