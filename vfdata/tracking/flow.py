"""Sparse 2D optical flow of tracked points between consecutive left images (pyramidal Lucas-Kanade),
shared by the `klt` baseline and the image term of the `geometry+` tracker."""

from __future__ import annotations

import cv2
import numpy as np

LK_WINDOW_PX = 21
LK_LEVELS = 3
LK_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) BGR image (OpenCV order), uint8 or uint16 or float in [0, 1] -> (H, W) uint8."""
    image = np.asarray(image)
    if image.ndim == 3:
        if image.shape[2] == 4:
            image = image[..., :3]
        image = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_BGR2GRAY)
    if image.dtype == np.uint8:
        return image
    if image.dtype == np.uint16:
        return (image >> 8).astype(np.uint8)
    return np.clip(np.asarray(image, dtype=np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)


def track_lk(
    previous: np.ndarray,
    current: np.ndarray,
    uv: np.ndarray,
    max_forward_backward_px: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Follow pixels `uv` (N, 2) from the gray image `previous` to `current`.

    Returns the new positions (N, 2) and an (N,) bool `ok`: LK converged both ways, tracking the new
    position back lands within `max_forward_backward_px` of the start (the forward-backward check that
    rejects occlusions, specular highlights and textureless drift) and the point stays in the image."""
    uv = np.asarray(uv, dtype=np.float32).reshape(-1, 1, 2)
    n = len(uv)
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    finite = np.isfinite(uv).all(axis=2)[:, 0]
    start = np.where(finite[:, None, None], uv, 0).astype(np.float32)
    params = dict(winSize=(LK_WINDOW_PX, LK_WINDOW_PX), maxLevel=LK_LEVELS, criteria=LK_CRITERIA)
    forward, st_f, _ = cv2.calcOpticalFlowPyrLK(previous, current, start, None, **params)
    backward, st_b, _ = cv2.calcOpticalFlowPyrLK(current, previous, forward, None, **params)
    fb_error = np.linalg.norm(backward - start, axis=2)[:, 0]
    h, w = current.shape[:2]
    new = forward[:, 0, :]
    inside = (new[:, 0] >= 0) & (new[:, 0] <= w - 1) & (new[:, 1] >= 0) & (new[:, 1] <= h - 1)
    ok = finite & (st_f[:, 0] == 1) & (st_b[:, 0] == 1) & (fb_error < max_forward_backward_px) & inside
    return new, ok


def refine_from_reference(
    reference: np.ndarray,
    current: np.ndarray,
    reference_uv: np.ndarray,
    guess_uv: np.ndarray,
    max_disagreement_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Follow pixels `reference_uv` (N, 2) of the gray `reference` image straight into `current`,
    starting Lucas-Kanade at `guess_uv` (N, 2), the frame-to-frame estimate of the same points.

    Frame-to-frame flow drifts: each step's sub-pixel error adds up over hundreds of frames. Matching
    the reference image's patch instead does not accumulate anything, but it can lock onto the wrong
    texture where the tissue looks different now (turned, stretched, under a highlight). The two
    estimates check each other: the reference match is kept (`ok`) only where it converged and lies
    within `max_disagreement_px` of the guess, which lets it correct the drift a little every frame
    and never jump away."""
    start = np.asarray(reference_uv, dtype=np.float32).reshape(-1, 1, 2)
    guess = np.asarray(guess_uv, dtype=np.float32).reshape(-1, 2)
    if len(start) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    params = dict(winSize=(LK_WINDOW_PX, LK_WINDOW_PX), maxLevel=LK_LEVELS, criteria=LK_CRITERIA,
                  flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    # OpenCV writes its answer into the initial-guess array: hand it a copy.
    found, status, _ = cv2.calcOpticalFlowPyrLK(reference, current, start, guess.reshape(-1, 1, 2).copy(), **params)
    found = found[:, 0, :]
    ok = (status[:, 0] == 1) & np.isfinite(found).all(axis=1)
    ok &= np.linalg.norm(found - guess, axis=1) < max_disagreement_px
    return found, ok
