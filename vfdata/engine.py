"""The per-frame engine of the method: stereo pair (or a depth camera's frame) -> depth -> tissue mask
-> tissue cloud -> (first frame: object frame, reference points) -> tracked points. `vfdata process`
(offline, into a derived MCAP), `vfmodels.inference.predict` (offline, in memory) and the live estimator
(`vfmodels.inference.live`, one frame at a time) all drive this one engine. Its input, a recording or a camera,
is a rig (`vfdata.rig`): the rig builds the engine and gives the frames.

    engine = rig.engine(rig.stage_options(EngineOptions()), rig.prompt(None))
    for result in engine.run(rig.frames()):        # offline: the depth backend may overlap frames
        ...  result.mask, result.cloud_mm, result.points_mm, result.visible
    result = engine.step(index, stamp_ns, left, right, depth_mm)   # live: one frame

Each stage's wall time and the CPU time of the thread that ran it accumulate in `engine.clock`, so
stage rates can be reported as the method runs (`StageClock.fps`), with the thread count beside them.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from vfdata.calibration import PinholeCamera
from vfdata.errors import InputError
from vfdata.object_frames import OBJECT_FRAMES, TUBE_FRAMES
from vfdata.recon import Prompt, make_depth_estimator, make_segmenter, tissue_cloud
from vfdata.recon.depth import SENSOR_DEPTH
from vfdata.recon.object_frame import ObjectFrame, estimate_object_frame, origin_cut_by_view
from vfdata.recon.plane import board_frame, camera_frame, fit_board_plane
from vfdata.recon.rest_frames import rest_frames
from vfdata.recon.tissue_frame import fitted_axis, tissue_frame
from vfdata.recon.tube_axis import TubeAxis
from vfdata.tracking.motion_scan import LookAhead, scan_motion
from vfdata.tracking.registry import FrameInputs, Tracker, make_tracker

log = logging.getLogger(__name__)

MIN_FIRST_CLOUD = 50  # points: fewer on the first frame means the prompt missed the tissue
SIM_DEPTH_UNIT_MM = 0.1  # the simulator's ground_truth/depth/*.png


@dataclass
class EngineOptions:
    """The stages and their settings (`vfdata process` options without the file handling)."""

    depth: str = "sgbm"
    depth_options: dict = field(default_factory=dict)
    segment: str = "colortrack"
    segment_options: dict = field(default_factory=dict)
    tracker: str = "geometry"  # a name of vfdata.tracking.registry.TRACKERS, or "none"
    tracker_options: dict = field(default_factory=dict)
    num_points: int = 256
    seed: int = 0
    # Nearest and farthest surface expected in front of the scope, mm: sets the stereo matcher's
    # disparity range unless depth_options give one. Without a floor, dark textureless background
    # matches at near-zero disparity (depth near infinity) and leaks into the tissue's edges.
    working_range_mm: tuple[float, float] = (40.0, 300.0)
    # The frame tracks and clouds are written in: a key of vfdata.object_frames.OBJECT_FRAMES.
    object_frame: str = "auto"
    # Depth only where the tissue can be: the box of the previous frame's mask grown by this many
    # pixels each way (0: the whole image, always for the first frame). Depth elsewhere is NaN. A
    # live option: its rate and accuracy against the whole image are in docs/live.md.
    depth_roi_margin_px: int = 0



@dataclass
class StageClock:
    """Wall and thread-CPU seconds per stage."""

    seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    cpu_seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))

    @staticmethod
    def now() -> tuple[float, float]:
        return time.perf_counter(), time.thread_time()

    def add(self, stage: str, started: tuple[float, float]) -> tuple[float, float]:
        now = self.now()
        self.seconds[stage] += now[0] - started[0]
        self.cpu_seconds[stage] += now[1] - started[1]
        return now

    def fps(self, frames: int) -> dict[str, float]:
        return {stage: (frames / s if s > 0 else float("inf")) for stage, s in self.seconds.items()}


@dataclass
class ImageStages:
    """Depth, mask and cloud of one frame (the stages that need only its images)."""

    depth_mm: np.ndarray  # (H, W) float32, NaN unknown
    mask: np.ndarray  # (H, W) bool
    cloud_mm: np.ndarray  # (M, 3) left camera frame
    right: np.ndarray | None = None  # the right rectified image (None: an RGB-D frame), for the stereo lift


@dataclass
class FrameResult:
    """Everything the engine knows of one frame; points in the left camera frame, mm."""

    index: int
    stamp_ns: int
    left: np.ndarray
    depth_mm: np.ndarray
    mask: np.ndarray
    cloud_mm: np.ndarray
    points_mm: np.ndarray | None  # (N, 3) tracked points (None: no tracker, or an offline one)
    visible: np.ndarray | None  # (N,) bool


def recorded_masks(ground_truth: Path) -> Iterator[np.ndarray]:
    """The simulator's true tissue masks, frame by frame."""
    for path in sorted((Path(ground_truth) / "mask").glob("*.png")):
        data = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if data is None:
            raise InputError(path, "not a readable mask PNG")
        yield data > 127


def recorded_depths(ground_truth: Path) -> Iterator[np.ndarray]:
    """The simulator's true depth maps (mm, NaN unknown), frame by frame."""
    for path in sorted((Path(ground_truth) / "depth").glob("*.png")):
        data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if data is None:
            raise InputError(path, "not a readable 16-bit depth PNG")
        depth = data.astype(np.float32) * np.float32(SIM_DEPTH_UNIT_MM)
        depth[data == 0] = np.nan
        yield depth


def depth_roi(mask: np.ndarray, margin_px: int, max_disparity_px: int | None) -> tuple[int, int, int, int, int]:
    """The region whose depth is needed next: the box of `mask` (H, W) grown by `margin_px`, as
    (y0, y1, x0, x1, xc): rows y0:y1, columns x0:x1, and xc <= x0 where the matched crop starts (a
    left pixel x matches the right image at x - d, d <= `max_disparity_px`; None: from column 0).
    Even offsets, so that a half-resolution matcher sees the same pixel grid. The whole image when
    the mask is empty."""
    h, w = mask.shape
    rows, cols = np.any(mask, axis=1), np.any(mask, axis=0)
    if not rows.any():
        return 0, h, 0, w, 0
    y0, y1 = np.flatnonzero(rows)[[0, -1]]
    x0, x1 = np.flatnonzero(cols)[[0, -1]]
    y0, x0 = max(0, int(y0) - margin_px) // 2 * 2, max(0, int(x0) - margin_px) // 2 * 2
    y1, x1 = min(h, int(y1) + 1 + margin_px), min(w, int(x1) + 1 + margin_px)
    xc = 0 if max_disparity_px is None else max(0, x0 - int(max_disparity_px)) // 2 * 2
    return y0, y1, x0, x1, xc


class FrameEngine:
    """Runs the stages frame after frame (see the module docstring). The first frame fixes the object
    frame (`self.frame`) and starts the tracker; `up` is gravity-up in the left camera frame (from the
    ECM pose; None: X from the image's up). `ground_truth` is the simulator's ground_truth/ folder,
    for the `recorded` depth and the `groundtruth` tracker. `look_ahead`, when the input is a recording,
    gives its frames ahead of the first (`vfdata.tracking.motion_scan.LookAhead`): the tube's frame then
    also hears how each end moves over the recording, and sees its axis again at the frames where the
    tissue rests (`vfdata.recon.tissue_frame`, `vfdata.recon.rest_frames`)."""

    def __init__(self, camera: PinholeCamera, baseline_mm: float, prompt: Prompt, options: EngineOptions | None = None,
                 up: np.ndarray | None = None, ground_truth: Path | None = None,
                 look_ahead: LookAhead | None = None):
        self.options = options or EngineOptions()
        self.camera, self.baseline_mm, self.prompt = camera, float(baseline_mm), prompt
        self.prompt.check_inside(camera.width, camera.height)
        self.up, self.ground_truth, self.look_ahead = up, ground_truth, look_ahead
        if self.options.object_frame not in OBJECT_FRAMES:
            raise InputError("object frame", f"'{self.options.object_frame}' is not one of {', '.join(OBJECT_FRAMES)}")
        self.depth = None if self.options.depth == SENSOR_DEPTH else make_depth_estimator(
            self.options.depth, **self._depth_options())
        self.segmenter = make_segmenter(self.options.segment, **self._segment_options())
        self.clock = StageClock()
        self.frame: ObjectFrame | None = None
        self.origin_cut = False
        self.tracker: Tracker | None = None
        self.frames = 0
        self._last_mask: np.ndarray | None = None  # the previous image_stages' mask (the depth's region)

    def _depth_options(self) -> dict:
        options = dict(self.options.depth_options)
        if self.options.depth == "sgbm" and not {"min_disparity", "max_disparity"} & set(options):
            near, far = self.options.working_range_mm
            options["min_disparity"] = int(np.floor(self.camera.fx * self.baseline_mm / far))
            options["max_disparity"] = int(np.ceil(self.camera.fx * self.baseline_mm / near))
        if self.options.depth == "recorded":
            if self.ground_truth is None:
                raise InputError(Path("ground_truth"), "depth 'recorded' needs the simulator's ground_truth/ "
                                                       "(--ground-truth DIR, or beside the raw folder)")
            options.setdefault("depths", recorded_depths(self.ground_truth))
        return options

    def _segment_options(self) -> dict:
        options = dict(self.options.segment_options)
        if self.options.segment == "recorded":
            if self.ground_truth is None:
                raise InputError(Path("ground_truth"), "segment 'recorded' needs the simulator's ground_truth/ "
                                                       "(--ground-truth DIR, or beside the raw folder)")
            options.setdefault("masks", recorded_masks(self.ground_truth))
        return options

    @property
    def parameters(self) -> dict:
        """The stages' names and settings, for provenance."""
        depth = {"backend": SENSOR_DEPTH} if self.depth is None else self.depth.parameters()
        return {"depth": depth, "object_frame": self.options.object_frame,
                "segment": getattr(self.segmenter, "parameters", dict)(),
                "tracker": {"name": self.options.tracker, "num_points": self.options.num_points,
                            "seed": self.options.seed, **self.options.tracker_options}}

    @property
    def offline_tracker(self) -> bool:
        return self.tracker is not None and self.tracker.offline

    # ---- the stages ------------------------------------------------------------------------------

    def image_stages(self, left: np.ndarray, right: np.ndarray | None, first: bool,
                     depth_mm: np.ndarray | None = None) -> ImageStages:
        """Depth (unless given), mask and cloud of one frame. Thread-safe apart from the segmenter's
        state, so the live estimator may run it for frame t+1 while frame t is tracked."""
        t = self.clock.now()
        if depth_mm is None:
            margin = self.options.depth_roi_margin_px
            roi = None if first or margin <= 0 or self._last_mask is None else \
                depth_roi(self._last_mask, margin, self._max_disparity_px())
            depth_mm = self._depth_in(left, right, roi)
            t = self.clock.add("depth", t)
        mask = self.segmenter.start(left, self.prompt, depth_mm) if first else self.segmenter.track(left, depth_mm)
        self._last_mask = mask
        t = self.clock.add("mask", t)
        cloud = tissue_cloud(depth_mm, mask, self.camera)
        self.clock.add("cloud", t)
        return ImageStages(depth_mm, mask, cloud, right)

    def _max_disparity_px(self) -> int | None:
        return self._depth_options().get("max_disparity") if self.options.depth == "sgbm" else None

    def _depth_in(self, left: np.ndarray, right: np.ndarray, roi: tuple[int, int, int, int, int] | None
                  ) -> np.ndarray:
        """Depth (mm) of the whole pair, or of `roi` (`depth_roi`) only: NaN elsewhere."""
        if roi is None:
            return self.depth.depth_mm(left, right, self.camera, self.baseline_mm)
        y0, y1, x0, x1, xc = roi
        crop = PinholeCamera(self.camera.fx, self.camera.fy, self.camera.cx - xc, self.camera.cy - y0, x1 - xc, y1 - y0)
        inside = self.depth.depth_mm(np.ascontiguousarray(left[y0:y1, xc:x1]),
                                     np.ascontiguousarray(right[y0:y1, xc:x1]), crop, self.baseline_mm)
        depth = np.full(left.shape[:2], np.nan, np.float32)
        depth[y0:y1, x0:x1] = inside[:, x0 - xc:]
        return depth

    def track(self, index: int, stamp_ns: int, left: np.ndarray, images: ImageStages) -> FrameResult:
        """The frame's tracked points; the first frame also fixes the object frame and the tracker."""
        t = self.clock.now()
        stereo = images.right is not None and self.baseline_mm > 0
        inputs = FrameInputs(index=index, camera=self.camera, image_bgr=left, depth_mm=images.depth_mm,
                             mask=images.mask, cloud_mm=images.cloud_mm, right_bgr=images.right if stereo else None,
                             baseline_mm=self.baseline_mm if stereo else None,
                             working_range_mm=self.options.working_range_mm)
        points = visible = None
        if self.frames == 0:
            self._start(inputs)
            t = self.clock.add("object_frame", t)
            if self.tracker is not None:
                points, visible = self.tracker.points, self.tracker.visible
        elif self.tracker is not None and self.tracker.offline:
            self.tracker.collect(inputs)
        elif self.tracker is not None:
            points, visible = self.tracker.update(inputs)
        self.clock.add("tracking", t)
        self.frames += 1
        return FrameResult(index, int(stamp_ns), left, images.depth_mm, images.mask, images.cloud_mm, points, visible)

    def _start(self, first: FrameInputs) -> None:
        if not first.mask.any() or len(first.cloud_mm) < MIN_FIRST_CLOUD:
            raise InputError("prompt", f"the tissue mask of the first frame is empty ({int(first.mask.sum())} "
                                       f"pixels, {len(first.cloud_mm)} points): check the prompt")
        if self.options.object_frame == "board":
            plane = getattr(self.segmenter, "plane", None) or fit_board_plane(first.depth_mm, first.mask)
            self.frame = board_frame(plane, self.camera, first.cloud_mm)
        elif self.options.object_frame == "camera":
            self.frame = camera_frame()
        elif self.options.object_frame == "paper":
            self.frame = estimate_object_frame(first.cloud_mm, self.up)
        else:
            # A look ahead at the recording, when the caller can give one: the motion of each end (clamped_end),
            # and the axis again where the tissue rests (rest_frames).
            motion = rest_axes = None
            if self.look_ahead is not None:
                motion = scan_motion(self.look_ahead.scan_images(), first.mask, first.depth_mm, self.camera)
                rest_axes = self._rest_axes(rest_frames(*motion, self.look_ahead.scan_indices))
            self.frame = tissue_frame(first.image_bgr, first.mask, first.depth_mm, first.cloud_mm, self.camera,
                                      self.up, motion, rest_axes)
        self.origin_cut = self.options.object_frame in ("auto", *TUBE_FRAMES) and bool(
            origin_cut_by_view(first.cloud_mm, self.frame, self.camera))
        if self.origin_cut:
            log.warning("warning: the tissue runs out of the image at its wide end: the object frame's origin "
                        "(2nd percentile along Z) may be where the view cuts it, not at the clamp")
        if self.options.tracker != "none":
            self.tracker = make_tracker(self.options.tracker, first, self.options.num_points, self.options.seed,
                                        ground_truth=self.ground_truth, **self.options.tracker_options)

    def _rest_axes(self, frames: list[int]) -> dict[int, TubeAxis]:
        """The axis fitted at each of `frames` (where the tissue rests) as on the first frame, from its own
        depth and a mask started anew from the prompt; frames whose fit is doubtful or impossible are left
        out. None are fitted when the depth or mask backend cannot run on a frame alone (`any_frame`)."""
        if not frames or self.depth is None or not (self.depth.any_frame and self.segmenter.any_frame):
            return {}
        # their own instances: the running depth stream may be matching the next pair in its thread
        depth = make_depth_estimator(self.options.depth, **self._depth_options())
        segmenter = make_segmenter(self.options.segment, **self._segment_options())
        axes = {}
        for i in frames:
            left, right = self.look_ahead.pair(i)
            depth_mm = depth.depth_mm(left, right, self.camera, self.baseline_mm)
            try:
                mask = segmenter.start(left, self.prompt, depth_mm)
                axis, diagnostics = fitted_axis(left, mask, depth_mm, tissue_cloud(depth_mm, mask, self.camera),
                                                self.camera)
            except InputError:  # no tissue, or too little, in the prompt there: the other frames stand
                continue
            if not diagnostics["axis_doubtful"]:
                axes[i] = axis
        return axes

    def step(self, index: int, stamp_ns: int, left: np.ndarray, right: np.ndarray | None = None,
             depth_mm: np.ndarray | None = None) -> FrameResult:
        """One frame through every stage (live use): a stereo pair, or a depth camera's `depth_mm` with
        its view as `left` and no `right` (`vfdata.rig.Frame`)."""
        return self.track(index, stamp_ns, left, self.image_stages(left, right, self.frames == 0, depth_mm))

    def run(self, frames: Iterable[tuple[int, np.ndarray, np.ndarray | None, np.ndarray | None]]
            ) -> Iterator[FrameResult]:
        """(stamp_ns, left, right, depth_mm) frames (`vfdata.rig.Frame`) -> one FrameResult each, in order.
        A depth backend sees the pairs as a stream, so it can overlap consecutive frames (sgbm matches the
        next pair in a second thread while this one is refined); with the sensor's depth (`depth`
        'sensor') each frame's `depth_mm` is taken as it is. Time spent producing the frames counts as
        "decode"."""
        if self.depth is None:
            yield from self._run_given_depth(frames)
            return
        pending: list[tuple[int, np.ndarray, np.ndarray]] = []

        def feed():
            started = self.clock.now()
            for stamp_ns, left, right, _ in frames:
                started = self.clock.add("decode", started)
                pending.append((stamp_ns, left, right))
                yield left, right
                started = self.clock.now()

        depths = self.depth.depth_stream(feed(), self.camera, self.baseline_mm)
        index = 0
        while True:
            t = self.clock.now()
            decode_before = self.clock.seconds["decode"]
            try:
                depth = next(depths)
            except StopIteration:
                return
            # Waiting for the depth includes producing the pairs it pulled: that counts as decode.
            self.clock.add("depth", t)
            self.clock.seconds["depth"] -= self.clock.seconds["decode"] - decode_before
            stamp_ns, left, right = pending.pop(0)
            # The depth is given, so the right image only travels on to the tracker (the stereo lift).
            yield self.track(index, stamp_ns, left, self.image_stages(left, right, index == 0, depth))
            index += 1

    def _run_given_depth(self, frames: Iterable[tuple[int, np.ndarray, np.ndarray | None, np.ndarray | None]]
                         ) -> Iterator[FrameResult]:
        """The frames of a depth camera: the recorded depth replaces stereo matching; `left` (H, W, 3) BGR
        in the depth camera's pixels feeds the segmenter and the image-based trackers."""
        started = self.clock.now()
        for index, (stamp_ns, left, right, depth_mm) in enumerate(frames):
            self.clock.add("decode", started)
            yield self.track(index, stamp_ns, left, self.image_stages(left, right, index == 0, depth_mm))
            started = self.clock.now()

    def finish(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The tracks of an offline tracker over every frame seen ((F, N, 3) mm, (F, N)); None else."""
        if not self.offline_tracker:
            return None
        t = self.clock.now()
        tracks = self.tracker.finish()
        self.clock.add("tracking", t)
        return tracks
