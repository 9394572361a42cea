"""The point trackers behind one interface and one registry, for `vfdata process`, the live
estimator and the tracking evaluation alike.

The trackers' own classes take different inputs: the geometry tracker tissue clouds (and images for
`geometry+`), KLT images and depth maps, the ground truth frame indices, CoTracker a whole clip. Each
adapter here takes a `FrameInputs` per frame and reads what its tracker needs (`Tracker.inputs`):

    tracker = make_tracker("geometry", first, num_points=256, seed=0)
    points, visible = tracker.points, tracker.visible      # frame 0: the reference points
    for frame in later_frames:
        points, visible = tracker.update(frame)             # (n, 3) mm left camera frame, (n,) bool

An offline tracker (`tracker.offline`, CoTracker) sees the whole clip at once: `collect(frame)` for
every later frame, then `finish()` gives the tracks of all frames, the first included.

Every tracker picks the same reference points for a seed (`select_reference_points` on the first
frame's cloud), so their tracks compare point by point.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from vfdata.calibration import PinholeCamera
from vfdata.errors import BackendError, InputError
from vfdata.tracker_kinds import TRACKER_KINDS
from vfdata.tracking.cotracker import CoTrackerTracker
from vfdata.tracking.geometry import GeometryTracker
from vfdata.tracking.groundtruth import GroundTruthTracker
from vfdata.tracking.klt import DEFAULT_LIFT, KLTTracker
from vfdata.tracking.sampling import select_reference_points

# The simulator's material points and normals, (F, P, 3) each: its ground_truth/ folder, or the arrays.
GroundTruth = Path | tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True, kw_only=True)
class FrameInputs:
    """What a tracker may use of one frame. Give what the tracker reads (`Tracker.inputs`); the
    rest may stay None."""

    index: int  # frame number in the recording; 0 is the reference frame
    camera: PinholeCamera  # the left rectified camera
    image_bgr: np.ndarray | None = None  # (H, W, 3) uint8 left rectified image, OpenCV order
    depth_mm: np.ndarray | None = None  # (H, W) z-depth in mm of the left camera; NaN or 0 = none
    mask: np.ndarray | None = None  # (H, W) bool tissue mask
    cloud_mm: np.ndarray | None = None  # (M, 3) tissue cloud, mm, left camera frame
    right_bgr: np.ndarray | None = None  # (H, W, 3) uint8 right rectified image (None: an RGB-D recording)
    baseline_mm: float | None = None  # the rectified pair's baseline (None: no right view)
    working_range_mm: tuple[float, float] | None = None  # nearest and farthest surface expected, mm


class Tracker(Protocol):
    """A point tracker over a video, started on its first frame by `make_tracker`."""

    name: str
    offline: bool  # True: `collect` each later frame, then `finish`; False: `update` each frame
    inputs: frozenset[str]  # the FrameInputs fields `update` / `collect` read

    @property
    def reference(self) -> np.ndarray:
        """(n, 3) the tracked points on the first frame, mm, left camera frame."""

    @property
    def points(self) -> np.ndarray:
        """(n, 3) the latest positions, mm (NaN: lost): the reference until the first update."""

    @property
    def visible(self) -> np.ndarray:
        """(n,) bool: which of `points` the latest frame shows (inside its tissue mask)."""

    def start(self, frame: FrameInputs) -> tuple[np.ndarray, np.ndarray]:
        """First frame -> (reference points (n, 3) mm, visible (n,)); picks the points."""

    def update(self, frame: FrameInputs) -> tuple[np.ndarray, np.ndarray]:
        """Next frame -> (points (n, 3) mm, visible (n,)). Online trackers only."""

    def collect(self, frame: FrameInputs) -> None:
        """Keep the next frame for `finish`. Offline trackers only."""

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        """Tracks of every frame seen, the first included: ((F, n, 3) mm, (F, n)). Offline only."""


class _Adapter:
    """What the adapters share: the latest result, the checks of the inputs, the refusals of the
    calls that the tracker's kind (online or offline) does not take."""

    name = ""
    offline = False
    inputs: frozenset[str] = frozenset()
    first_inputs: frozenset[str] = frozenset({"cloud_mm", "mask"})

    def __init__(self, num_points: int, seed: int):
        self.num_points, self.seed = int(num_points), int(seed)
        self._points: np.ndarray | None = None
        self._visible: np.ndarray | None = None

    @property
    def reference(self) -> np.ndarray:
        return self._tracker.reference

    @property
    def points(self) -> np.ndarray:
        return self._points.copy()

    @property
    def visible(self) -> np.ndarray:
        return self._visible.copy()

    def start(self, frame: FrameInputs) -> tuple[np.ndarray, np.ndarray]:
        _require(self.name, frame, self.first_inputs)
        self._build(frame)
        reference = self.reference
        return self._keep(reference, frame.camera.in_mask(reference, frame.mask))

    def update(self, frame: FrameInputs) -> tuple[np.ndarray, np.ndarray]:
        if self.offline:
            raise BackendError(f"tracker '{self.name}' is offline (it tracks the whole clip at once): "
                               "collect the frames, then finish(); it cannot stream")
        _require(self.name, frame, self.inputs)
        return self._keep(*self._update(frame))

    def collect(self, frame: FrameInputs) -> None:
        raise BackendError(f"tracker '{self.name}' is online: update() it frame by frame")

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        raise BackendError(f"tracker '{self.name}' is online: update() it frame by frame")

    def _keep(self, points: np.ndarray, visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        self._points, self._visible = points, visible
        return points.copy(), visible.copy()

    def _build(self, frame: FrameInputs) -> None:
        raise NotImplementedError

    def _update(self, frame: FrameInputs) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError


class _Geometry(_Adapter):
    """`geometry` and `geometry+` (vfdata.tracking.geometry); options are TrackerOptions fields."""

    def __init__(self, name: str, num_points: int, seed: int, **options):
        super().__init__(num_points, seed)
        if "mode" in options:
            raise BackendError(f"{name}: no 'mode' option: the tracker's name is its mode (geometry, geometry+)")
        self.name, self.options = name, options
        self.inputs = frozenset({"cloud_mm", "mask", "image_bgr"} if name == "geometry+" else {"cloud_mm", "mask"})
        self.first_inputs = self.inputs

    def _build(self, frame: FrameInputs) -> None:
        options = dict(self.options)
        if self.name == "geometry+":
            options.setdefault("reference_image", frame.image_bgr)
        self._tracker = GeometryTracker(frame.cloud_mm, camera=frame.camera, num_points=self.num_points,
                                        seed=self.seed, mode=self.name, **options)

    def _update(self, frame: FrameInputs) -> tuple[np.ndarray, np.ndarray]:
        return self._tracker.update(frame.cloud_mm, frame.mask, frame.image_bgr if self.name == "geometry+" else None)


class _KLT(_Adapter):
    """`klt` (vfdata.tracking.klt): Lucas-Kanade in the left images, lifted with the depth maps or, with
    `lift="stereo"`, by each point's match in the right image (options: KLTTracker's)."""

    name = "klt"

    def __init__(self, num_points: int, seed: int, **options):
        super().__init__(num_points, seed)
        self.options = options
        self.lift = options.get("lift", DEFAULT_LIFT)
        stereo = frozenset({"right_bgr", "baseline_mm"}) if self.lift == "stereo" else frozenset()
        self.inputs = frozenset({"image_bgr", "depth_mm", "mask"}) | stereo
        self.first_inputs = frozenset({"cloud_mm", "image_bgr", "mask"}) | stereo

    def _build(self, frame: FrameInputs) -> None:
        stereo = {"reference_right": frame.right_bgr, "baseline_mm": frame.baseline_mm,
                  "working_range_mm": frame.working_range_mm} if self.lift == "stereo" else {}
        self._tracker = KLTTracker(frame.cloud_mm, frame.camera, frame.image_bgr, num_points=self.num_points,
                                   seed=self.seed, **stereo, **self.options)

    def _update(self, frame: FrameInputs) -> tuple[np.ndarray, np.ndarray]:
        return self._tracker.update(frame.image_bgr, frame.depth_mm, frame.mask, frame.right_bgr)


class _CoTracker(_Adapter):
    """`cotracker` (vfdata.tracking.cotracker), offline; options: checkpoint (required), device,
    window_len. The checkpoint is loaded when the tracker is made."""

    name = "cotracker"
    offline = True
    inputs = frozenset({"image_bgr", "depth_mm", "mask"})
    first_inputs = frozenset({"cloud_mm", "image_bgr", "depth_mm", "mask"})

    def __init__(self, num_points: int, seed: int, checkpoint: str | Path | None = None, **options):
        super().__init__(num_points, seed)
        self._make = lambda cloud, camera: CoTrackerTracker(cloud, camera, checkpoint, num_points=self.num_points,
                                                            seed=self.seed, **options)
        self._clip: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def _build(self, frame: FrameInputs) -> None:
        self._tracker = self._make(frame.cloud_mm, frame.camera)
        self._clip = []
        self._collect(frame)

    def collect(self, frame: FrameInputs) -> None:
        _require(self.name, frame, self.inputs)
        self._collect(frame)

    def _collect(self, frame: FrameInputs) -> None:
        self._clip.append((frame.image_bgr[..., ::-1].copy(), frame.depth_mm, frame.mask))  # CoTracker takes RGB

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        images, depths, masks = (np.stack(parts) for parts in zip(*self._clip, strict=True))
        points, visible = self._tracker.track(images, depths, masks)
        self._keep(points[-1], visible[-1])
        return points, visible


class _GroundTruth(_Adapter):
    """`groundtruth` (vfdata.tracking.groundtruth): the simulator's material points, carried to the
    reference points; needs `ground_truth` (the ground_truth/ folder, or its points and normals)."""

    name = "groundtruth"
    inputs = frozenset({"mask"})

    def __init__(self, num_points: int, seed: int, ground_truth: GroundTruth | None = None):
        super().__init__(num_points, seed)
        if ground_truth is None:
            raise InputError(Path("ground_truth"), "tracker 'groundtruth' needs the simulator's ground_truth/ "
                             "folder (--ground-truth DIR, or beside the raw folder)")
        if isinstance(ground_truth, tuple):
            self._material = ground_truth
        else:
            folder = Path(ground_truth)
            for name in ("points.npy", "normals.npy"):
                if not (folder / name).is_file():
                    raise InputError(folder / name, "missing: not a simulator ground_truth/ folder")
            self._material = (np.load(folder / "points.npy", mmap_mode="r"),
                              np.load(folder / "normals.npy", mmap_mode="r"))

    def _build(self, frame: FrameInputs) -> None:
        points, normals = self._material
        self._tracker = GroundTruthTracker(frame.cloud_mm, points, normals, camera=frame.camera,
                                           num_points=self.num_points, seed=self.seed)

    def _update(self, frame: FrameInputs) -> tuple[np.ndarray, np.ndarray]:
        if not 0 <= frame.index < len(self._tracker.tracks):
            raise InputError(Path("ground_truth"), f"has {len(self._tracker.tracks)} frames, no frame {frame.index}")
        return self._tracker.update(frame.index, frame.mask)


class _Static(_Adapter):
    """`static`: the reference points standing still, the lower bound of the evaluation."""

    name = "static"
    inputs = frozenset({"mask"})

    def _build(self, frame: FrameInputs) -> None:
        cloud = np.asarray(frame.cloud_mm, dtype=np.float64)
        cloud = cloud[np.isfinite(cloud).all(axis=1)]
        if len(cloud) == 0:
            raise InputError("cloud", "the first frame's tissue cloud has no points")
        self._reference = cloud[select_reference_points(cloud, self.num_points, self.seed)]

    @property
    def reference(self) -> np.ndarray:
        return self._reference.copy()

    def _update(self, frame: FrameInputs) -> tuple[np.ndarray, np.ndarray]:
        return self._reference.copy(), frame.camera.in_mask(self._reference, frame.mask)


def _geometry(name: str) -> Callable[..., _Adapter]:
    def make(num_points: int, seed: int, **options) -> _Adapter:
        return _Geometry(name, num_points, seed, **options)

    return make


# name -> maker(num_points, seed, **options); `groundtruth` alone takes ground_truth=.
_MAKERS: dict[str, Callable[..., _Adapter]] = {
    "geometry": _geometry("geometry"),
    "geometry+": _geometry("geometry+"),
    "klt": _KLT,
    "cotracker": _CoTracker,
    "groundtruth": _GroundTruth,
    "static": _Static,
}
TRACKERS: tuple[str, ...] = tuple(TRACKER_KINDS)
assert set(_MAKERS) == set(TRACKER_KINDS), "every tracker kind (vfdata.tracker_kinds) has a maker here"


def make_tracker(name: str, first_frame: FrameInputs, num_points: int = 256, seed: int = 0,
                 ground_truth: GroundTruth | None = None, **options) -> Tracker:
    """The tracker `name` (one of TRACKERS), started on `first_frame` (which needs `cloud_mm` and
    `mask`, and `image_bgr` for the image-based trackers): its `points` are then the reference
    points, `visible` those inside the first mask. `options` go to the tracker's class (see each)."""
    if name not in _MAKERS:
        raise BackendError(f"unknown tracker '{name}' (known: {', '.join(TRACKERS)})")
    if ground_truth is not None and name == "groundtruth":
        options["ground_truth"] = ground_truth
    try:
        tracker = _MAKERS[name](num_points, seed, **options)
        tracker.start(first_frame)
    except TypeError as exc:  # unknown or misspelt options
        raise BackendError(f"{name}: bad options {sorted(options)}: {exc}") from exc
    except ValueError as exc:  # a reference cloud too small, a bad option value
        raise InputError("tracker", f"{name}: {exc}") from exc
    return tracker


def _require(name: str, frame: FrameInputs, needed: frozenset[str]) -> None:
    missing = sorted(field for field in needed if getattr(frame, field) is None)
    if missing:
        raise BackendError(f"tracker '{name}' needs {', '.join(missing)} of frame {frame.index}")

