"""The frames of a recording at which the tissue rests again, where its axis may be seen a second time.

The object frame is decided on the first frame, and one frame is one view of an occluder: an instrument
lying along the tube, or across its clamped end, hides part of it and bleeds its depth into the rest, and
the axis fitted there is turned (fresh sweep: glove 213's `glove_014` 12.0 degrees, colon 121's 227
degree view 13.3). Later in the recording the grasper lets the tissue go back to where it was, with the
instrument elsewhere. At those frames the tissue has the first frame's shape, so its axis is the same
line, seen past another occlusion: averaging the fits of the first frame and of the resting ones is
closer to the truth than the first alone (docs/reconstruction.md, "The axis, seen again at rest").

A frame rests when the points of the motion scan (`vfdata.tracking.motion_scan`: corners of the first
mask followed over the recording, lifted at the first frame's depth) sit within `REST_MM` of where they
were, at the median. Frames in the first `REST_AFTER_FRAMES` are passed over: the instrument has not
moved yet, so they would see the first frame's occlusion again.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

REST_MM = 1.5  # median displacement of the scan's points from the first frame under which the tissue rests
REST_AFTER_FRAMES = 30  # about a second at 30 frames/s: earlier frames see the first frame's occlusion
MAX_REST_FRAMES = 4  # spread over the resting frames: enough to outvote one occluded view (each fit ~0.7 s)
MIN_POINTS = 10  # scan points followed to a frame, under which its rest cannot be told
TRIM_DEG = 7.0  # a fit this far from the mean of all is left out of it
CONFIRM_FITS = 2  # resting frames' fits within TRIM_DEG of the axis that lift the first frame's doubt on it
_TRIM_COS = float(np.cos(np.radians(TRIM_DEG)))


def _agree(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two unit line directions (sign arbitrary) lie within TRIM_DEG of each other."""
    return abs(float(a @ b)) >= _TRIM_COS


def rest_frames(points_mm: np.ndarray, visible: np.ndarray, indices: Sequence[int]) -> list[int]:
    """The frames (of `indices`, those of the scan's (F, N, 3) `points_mm` and (F, N) `visible`, the first
    frame first) at which the tissue rests, at most MAX_REST_FRAMES spread evenly over them."""
    points, seen = np.asarray(points_mm, dtype=np.float64), np.asarray(visible, dtype=bool)
    resting = []
    for j in range(1, len(points)):
        if indices[j] < REST_AFTER_FRAMES:
            continue
        both = seen[j] & seen[0]
        if both.sum() < MIN_POINTS:
            continue
        if np.median(np.linalg.norm(points[j, both] - points[0, both], axis=1)) < REST_MM:
            resting.append(int(indices[j]))
    if len(resting) <= MAX_REST_FRAMES:
        return resting
    return [resting[k] for k in np.linspace(0, len(resting) - 1, MAX_REST_FRAMES).round().astype(int)]


def mean_direction(first: np.ndarray, others: Sequence[np.ndarray]) -> np.ndarray:
    """The unit mean of the line directions `first` and `others` (each (3,), sign arbitrary), each turned
    to `first`'s side."""
    first = np.asarray(first, dtype=np.float64) / np.linalg.norm(first)
    total = first.copy()
    for d in others:
        d = np.asarray(d, dtype=np.float64) / np.linalg.norm(d)
        total += d if d @ first >= 0 else -d
    return total / np.linalg.norm(total)


def trimmed_direction(first: np.ndarray, others: Sequence[np.ndarray]) -> np.ndarray:
    """The axis of the first frame's fit `first` and the resting frames' `others` ((3,) directions, sign
    arbitrary): their mean, taken again over the fits within TRIM_DEG of it until that keeps the same
    fits, on `first`'s side; when no fit lies within TRIM_DEG of the first mean, it starts from the largest
    group of two or more that agree within TRIM_DEG. A resting frame can be seen badly too (a pull along
    the line of sight that the scan cannot see, an instrument over the tissue), and so can the first:
    neither pulls the mean alone (glove 216's `glove_001`: three fits within 4 degrees and one 42 degrees
    off, whose mean of all four was 11.1 degrees from the truth; the group's is 2.8)."""
    fits = [np.asarray(d, dtype=np.float64) / np.linalg.norm(d) for d in (first, *others)]
    fits = [d if d @ fits[0] >= 0 else -d for d in fits]
    mean, kept = mean_direction(fits[0], fits[1:]), None
    for _ in range(len(fits)):
        now = [k for k, d in enumerate(fits) if _agree(d, mean)]
        if not now and kept is None:  # a far stray among few fits drags the mean away from all of them:
            # start again from the largest group that agrees, if two fits or more do (the first's on a tie)
            group = max(([j for j, e in enumerate(fits) if _agree(d, e)] for d in fits), key=len)
            now = group if len(group) > 1 else now
        if not now or now == kept:
            break
        kept = now
        mean = mean_direction(fits[kept[0]], [fits[k] for k in kept[1:]])
    return mean if mean @ fits[0] >= 0 else -mean


def confirming_fits(axis: np.ndarray, others: Sequence[np.ndarray]) -> int:
    """How many of the resting frames' fits `others` ((3,) directions, sign arbitrary) lie within TRIM_DEG
    of the chosen `axis`. Each was fitted on its own frame and kept only where that frame did not doubt it,
    so CONFIRM_FITS of them agreeing is an axis seen twice more past other occlusions: the first frame's
    doubt about its own fit no longer holds for the axis taken."""
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    return sum(_agree(np.asarray(d, dtype=np.float64) / np.linalg.norm(d), axis) for d in others)
