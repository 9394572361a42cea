"""`klt`: a 2D tracker lifted to 3D, the tracker of `visionforce` and the stand-in for the paper's CoTracker
ablation.

The same 256 reference points as the geometry tracker are projected into the reference left image and
followed frame to frame with OpenCV's pyramidal Lucas-Kanade. A point is lost when LK fails, the
forward-backward check fails (occlusion by the instrument, specular highlights, weak texture) or it leaves
the image; a lost point is NaN and not visible from then on, unless `recover` finds it again (below).

Each frame's 2D positions are lifted to 3D (`lift`) with that frame's depth map (`"depth"`), or by each
point's own stereo match in the right image of the same pair, triangulated, with the depth map where
the match is rejected (`"stereo"`, vfdata.tracking.stereo_lift; docs/tracking.md has the figures).

With `recover` (off by default) a lost point is looked for again every 4th frame: its reference patch (the
first image's) is matched into the current image by Lucas-Kanade, started where its tracked neighbours'
motion says it should be, and taken back only where the match lands near that guess and tracks back onto
the reference pixel. A recovered point keeps its identity, so its displacement is still from where it was
first seen. It keeps many more points on long recordings (on 742-frame `colon` recordings 106-191 of 256 at
the end against 4-175), but the points that come back are lifted less exactly, and `visionforce` trained on
them erred more at the views it never saw on two of three fresh datasets (docs/tracking.md, "Lost and
found"), so it is an option, not the default.
"""

from __future__ import annotations

import numpy as np

from vfdata.calibration import PinholeCamera
from vfdata.tracking.flow import refine_from_reference, to_gray, track_lk
from vfdata.tracking.lifting import lift_pixels
from vfdata.tracking.sampling import select_reference_points
from vfdata.tracking.stereo_lift import StereoLift

LIFTS = ("depth", "stereo")
DEFAULT_LIFT = "depth"
RECOVER_NEIGHBOURS = 6  # tracked points whose motion places a lost one
RECOVER_RADIUS_PX = 80.0  # ... found this near it in the reference image
RECOVER_GUESS_PX = 4.0  # the reference match must land this near the neighbours' guess ...
RECOVER_LAST_PX = 30.0  # ... or this near where the point was last seen, where too few neighbours are tracked
# Lost points are looked for every this many frames: each look builds two image pyramids, most of its
# cost, so looking every 4th frame keeps the tracker a small part of a live frame's time (docs/tracking.md).
RECOVER_EVERY = 4


class KLTTracker:
    """reference_points: (N, 3) reference tissue cloud (mm, camera frame); reference_image: the left
    image of that frame. `.update(image, depth_mm, mask, right_image)` -> (points (n, 3) mm, NaN when
    lost or without depth; visible (n,) bool).

    `lift="stereo"` needs `reference_right` (the right rectified image of the reference frame),
    `baseline_mm` and a `right_image` at every update; `working_range_mm` (near, far) bounds the
    disparities it accepts (`StereoLift`). The reference points are then lifted by their stereo match
    too, so that the displacements compare positions lifted the same way.

    `smoothing` in [0, 1), for either lift, filters each point's depth along its ray over time: the
    weight of its previous depth in the new one (an exponential filter, restarted where a point has
    no depth; 0: none). `recover` looks for lost points again (the module's docstring)."""

    def __init__(
        self,
        reference_points: np.ndarray,
        camera: PinholeCamera,
        reference_image: np.ndarray,
        num_points: int = 256,
        seed: int = 0,
        max_forward_backward_px: float = 1.0,
        lift: str = DEFAULT_LIFT,
        reference_right: np.ndarray | None = None,
        baseline_mm: float | None = None,
        working_range_mm: tuple[float, float] | None = None,
        smoothing: float = 0.0,
        recover: bool = False,
    ):
        if lift not in LIFTS:
            raise ValueError(f"lift '{lift}' is not one of {', '.join(LIFTS)}")
        if not 0.0 <= smoothing < 1.0:
            raise ValueError(f"smoothing {smoothing} is not in [0, 1)")
        if not isinstance(recover, bool):
            raise ValueError(f"recover {recover!r} is not true or false")
        reference_points = np.asarray(reference_points, dtype=np.float64)
        reference_points = reference_points[np.isfinite(reference_points).all(axis=1)]
        self.camera, self.lift, self.smoothing = camera, lift, float(smoothing)
        self.reference = reference_points[select_reference_points(reference_points, num_points, seed=seed)]
        self.max_forward_backward_px = max_forward_backward_px
        self.recover = recover
        self.uv = camera.project(self.reference)  # (n, 2) current pixels, NaN while lost
        self.alive = np.isfinite(self.uv).all(axis=1)
        self._image = to_gray(reference_image)
        self._reference_image = self._image
        self._reference_uv = self.uv.copy()
        self._last_uv = self.uv.copy()  # where each point was last tracked
        self._frame = 0
        self.stereo: StereoLift | None = None
        self.from_stereo = np.zeros(len(self.reference), bool)  # which points the latest frame lifted by stereo
        if lift == "stereo":
            if reference_right is None or baseline_mm is None:
                raise ValueError("lift 'stereo' needs the right image and the baseline (a stereo recording)")
            self.stereo = StereoLift(camera, baseline_mm, working_range_mm, len(self.reference))
            # Where the reference match is rejected the point stays the cloud's (the depth map's) own.
            lifted, self.from_stereo = self.stereo.lift(self.uv, self._image, to_gray(reference_right), self.reference)
            self.reference[self.from_stereo] = lifted[self.from_stereo]
        self._points = self.reference.copy()

    @property
    def points(self) -> np.ndarray:
        return self._points.copy()

    def _smooth(self, lifted: np.ndarray) -> np.ndarray:
        """`lifted` (n, 3) with each depth filtered against the latest frame's, along the point's ray."""
        previous = self._points[:, 2]
        z = lifted[:, 2]
        blend = np.isfinite(previous) & np.isfinite(z)
        scale = np.ones(len(z))
        scale[blend] = (self.smoothing * previous[blend] + (1.0 - self.smoothing) * z[blend]) / z[blend]
        return lifted * scale[:, None]  # the same ray, the filtered depth

    def update(
        self, image: np.ndarray, depth_mm: np.ndarray, mask: np.ndarray | None = None,
        right_image: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        gray = to_gray(image)
        idx = np.flatnonzero(self.alive)
        new_uv, ok = track_lk(self._image, gray, self.uv[idx], self.max_forward_backward_px)
        self.uv[idx] = new_uv
        lost = idx[~ok]
        self.alive[lost] = False
        self.uv[lost] = np.nan
        if self.recover:
            self._recover(gray)
            self._last_uv[self.alive] = self.uv[self.alive]
        self._image = gray
        points = lift_pixels(self.uv, depth_mm, self.camera)
        if self.stereo is not None:
            if right_image is None:
                raise ValueError("lift 'stereo' needs the right image of every frame")
            points, self.from_stereo = self.stereo.lift(self.uv, gray, to_gray(right_image), points)
        self._points = self._smooth(points) if self.smoothing > 0 else points
        visible = np.isfinite(self._points).all(axis=1)
        if mask is not None:
            visible &= self.camera.in_mask(self._points, np.asarray(mask))  # NaN points project nowhere
        return self._points.copy(), visible

    def _recover(self, gray: np.ndarray) -> None:
        """Look for the lost points in `gray`. Each is guessed at its reference pixel moved as its tracked
        neighbours (in the reference image) moved, or, without enough close neighbours, where it was last
        seen; then matched from the reference image, and kept where the match lands near the guess and
        tracks back onto the reference pixel."""
        self._frame += 1
        ref = self._reference_uv
        if self._frame % RECOVER_EVERY:
            return
        lost = np.flatnonzero(~self.alive & np.isfinite(ref).all(axis=1))
        if len(lost) == 0:
            return
        guess = self._last_uv[lost].copy()
        reach = np.full(len(lost), RECOVER_LAST_PX)
        alive = np.flatnonzero(self.alive)
        if len(alive) >= RECOVER_NEIGHBOURS:
            dist = np.linalg.norm(ref[lost, None, :] - ref[None, alive, :], axis=2)
            near = np.argsort(dist, axis=1)[:, :RECOVER_NEIGHBOURS]
            placed = (np.take_along_axis(dist, near, axis=1) < RECOVER_RADIUS_PX).all(axis=1)
            moved = (self.uv[alive[near[placed]]] - ref[alive[near[placed]]]).mean(axis=1)
            guess[placed] = ref[lost[placed]] + moved
            reach[placed] = RECOVER_GUESS_PX
        found, ok = refine_from_reference(self._reference_image, gray, ref[lost], guess, RECOVER_LAST_PX)
        ok &= np.linalg.norm(found - guess, axis=1) < reach
        back, ok_back = track_lk(gray, self._reference_image, found, self.max_forward_backward_px)
        ok &= ok_back & (np.linalg.norm(back - ref[lost], axis=1) < self.max_forward_backward_px)
        self.uv[lost[ok]] = found[ok]
        self.alive[lost[ok]] = True
