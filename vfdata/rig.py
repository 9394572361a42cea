"""The rig: a recording or a camera as the engine's input. What kind of input it is (a stereo pair, an
RGB-D camera) is known here and in the recording layer only; everything that runs the engine asks its rig.

A rig owns its camera model (the left rectified view, or the depth camera), the stereo baseline (0 for
a camera that brings its depth), gravity-up in the camera frame (from a recording's ECM pose), the
first frame's tissue prompt (given, else a recording's metadata), the stage defaults of its kind
(`stage_options`), the engine built on all of these (`engine`), a recording's frames as the engine runs
them (`frames`: `Frame`s), the image a person is shown of a frame (`image`, the live view's messages
`view_messages`) and the image whose motion the clock offset follows (`motion_image`).

    rig = rig_for(rec, path)                      # a recording: StereoRig or RgbdRig
    engine = rig.engine(rig.stage_options(options), rig.prompt(None), look_ahead=rec.num_frames)
    for result in engine.run(rig.frames()):
        ...
    rig = StereoRig(path, camera=camera, baseline_mm=baseline_mm)   # a live stereo camera

A new kind of input (say, a monocular camera with a depth model) is one more subclass here, made by
`rig_for` from what its recording holds (`Recording.is_rgbd` and its kin, vfdata/recording/reader.py)."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Iterator
from dataclasses import replace
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar, NamedTuple

import cv2
import numpy as np

from vfdata.calibration import PinholeCamera
from vfdata.errors import InputError
from vfdata.object_frames import TUBE_FRAMES
from vfdata.recon.depth import SENSOR_DEPTH
from vfdata.recon.object_frame import up_in_camera
from vfdata.recon.prompt import Prompt
from vfdata.recording import Recording, layout
from vfdata.recording.derived import depth_message
from vfdata.recording.messages import CameraInfo, CompressedImage
from vfdata.tracker_kinds import IMAGE_TRACKERS, TRACKER_KINDS

if TYPE_CHECKING:  # the engine pulls in torch (the trackers): imported where an engine is built
    from vfdata.engine import EngineOptions, FrameEngine
    from vfdata.tracking.motion_scan import LookAhead

log = logging.getLogger(__name__)

JPEG_QUALITY = 85  # the live view's left image


class Frame(NamedTuple):
    """One frame as the engine takes it (`FrameEngine.run`, `FrameEngine.step`)."""

    stamp_ns: int
    left: np.ndarray  # BGR: the left rectified view, or an RGB-D frame's depth drawn as grey (`depth_view`)
    right: np.ndarray | None = None  # the right rectified view (None: a camera that brings its depth)
    depth_mm: np.ndarray | None = None  # the sensor's depth (H, W) mm, NaN unknown (None: to be matched)


def camera_up(rec: Recording) -> np.ndarray | None:
    """Gravity-up in the camera frame at the first frame, from the ECM pose (None without one, or
    when the converter had to assume the up direction of the pose's frame: a bag without gravity_up)."""
    if not rec.has(layout.ECM_POSE) or rec.metadata.extra.get("gravity_up_assumed") == "true":
        return None
    _, quat = rec.ecm_pose_at(rec.frame_times_ns[:1])
    if not np.isfinite(quat).all():
        return None
    return up_in_camera(quat[0], rec.metadata.gravity_up_world)


def recording_prompt(rec: Recording, src: Path, given: str | None) -> Prompt:
    """The first frame's tissue prompt: given, else the recording metadata's `prompt` or `prompt_box`."""
    if given:
        return Prompt.parse(given)
    if rec.metadata.extra.get("prompt"):
        return Prompt.parse(rec.metadata.extra["prompt"])
    box = rec.metadata.extra.get("prompt_box")
    if not box:
        raise InputError(src, "no tissue prompt: give --prompt box:x0,y0,x1,y1 (or points:x,y;...) or a "
                              "prompt_box in the recording's metadata")
    try:
        values = json.loads(box) if box.strip().startswith("[") else [float(v) for v in box.split(",")]
        return Prompt.from_box([float(v) for v in values])
    except (ValueError, TypeError) as exc:
        raise InputError(src, f"prompt_box {box!r} in the metadata is not x0,y0,x1,y1 ({exc})") from None


def find_ground_truth(rec: Recording, given: Path | None) -> Path | None:
    """The simulator's ground_truth/ folder: given, or beside the raw folder the recording came from."""
    if given is not None:
        if not Path(given).is_dir():
            raise InputError(given, "ground-truth folder not found")
        return Path(given)
    source = Path(rec.metadata.source) if rec.metadata.source else None
    if source is not None and (source / "ground_truth").is_dir():
        return source / "ground_truth"
    return None


def rectified_camera_info(camera: PinholeCamera, stamp_ns: int, baseline_mm: float = 0.0,
                          frame_id: str = layout.LEFT_FRAME) -> CameraInfo:
    """CameraInfo of a rectified view (no distortion, identity R; P[0, 3] = -fx * baseline in m)."""
    p = np.hstack([camera.K, np.zeros((3, 1))])
    p[0, 3] = -camera.fx * baseline_mm / 1000.0
    return CameraInfo(int(stamp_ns), frame_id, camera.height, camera.width, "plumb_bob", np.zeros(5), camera.K,
                      np.eye(3), p)


def depth_view(depth_mm: np.ndarray, near_mm: float, far_mm: float) -> np.ndarray:
    """A depth image drawn as grey BGR (near bright, unknown black): the image the segmenter, the
    image-based trackers and the preview see when the colour view is not registered to the depth."""
    scaled = np.nan_to_num((far_mm - depth_mm) / max(far_mm - near_mm, 1e-6), nan=0.0)
    grey = np.clip(scaled * 255.0, 0, 255).astype(np.uint8)
    return cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)


class Rig:
    """A recording (`rec`) or a camera (its `camera` and `baseline_mm` given) as the engine's input; `path`
    names it in errors. The kinds below fill in what differs (see the module docstring)."""

    kind: ClassVar[str]  # "stereo", "rgbd"
    label: ClassVar[str]  # in messages: "a stereo", "an RGB-D"
    camera_frame_id: ClassVar[str]  # the frame of the camera processing sees through
    topics: ClassVar[tuple[str, ...]]  # what a recording of this kind holds
    # Its image is its depth drawn as grey: the image trackers see no texture, and a flat organ on a board
    # has none of a tube's symmetries (vfmodels.experiment).
    depth_only: ClassVar[bool] = False

    def __init__(self, path: str | Path, rec: Recording | None = None, *, camera: PinholeCamera | None = None,
                 baseline_mm: float = 0.0, up: np.ndarray | None = None):
        self.path, self.rec = Path(path), rec
        if rec is None:  # a camera: its model given, no metadata, no ECM pose (these replace the cached reads)
            if camera is None:
                raise InputError(self.path, "a camera rig needs its camera model")
            self.camera, self.baseline_mm, self.up = camera, float(baseline_mm), up

    @cached_property
    def camera(self) -> PinholeCamera:
        return self.rec.camera

    @cached_property
    def baseline_mm(self) -> float:
        return 0.0

    @cached_property
    def up(self) -> np.ndarray | None:
        """Gravity-up in the camera frame (`camera_up`; None: unknown)."""
        return camera_up(self.rec)

    def check(self) -> None:
        """InputError unless the recording holds what a recording of this kind needs."""
        for topic in self.topics if self.rec is not None else ():
            if not self.rec.has(topic):
                raise InputError(self.path, f"source has no {topic}: not {self.label} recording")

    def prompt(self, given: str | None) -> Prompt:
        """The first frame's tissue prompt: given, else the recording's (`recording_prompt`)."""
        if self.rec is None:
            if not given:
                raise InputError(self.path, "a camera needs --prompt box:x0,y0,x1,y1 (the tissue in the first frame)")
            return Prompt.parse(given)
        return recording_prompt(self.rec, self.path, given)

    def stage_options(self, options: EngineOptions) -> EngineOptions:
        """`options` with the defaults of this kind of input (InputError for stages it cannot run)."""
        raise NotImplementedError

    def ground_truth(self, given: Path | None) -> Path | None:
        """The simulator's ground truth for the `recorded` stages (None: none applies)."""
        return None

    def engine(self, options: EngineOptions, prompt: Prompt, ground_truth: Path | None = None,
               look_ahead: int = 0) -> FrameEngine:
        """The engine on this input, with `options` as `stage_options` gave them. `look_ahead`: frames of
        the recording the tube's frame may look at ahead of the first (`FrameEngine`; 0: none, as a stream)."""
        # here, not at the top: the engine pulls in torch (the trackers); a source or `vfdata sync` does not
        from vfdata.engine import FrameEngine

        self.check()
        return FrameEngine(self.camera, self.baseline_mm, prompt, options, up=self.up, ground_truth=ground_truth,
                           look_ahead=self._look_ahead(look_ahead) if look_ahead and self.rec is not None else None)

    def _look_ahead(self, frames: int) -> LookAhead | None:
        return None

    def frames(self, count: int | None = None) -> Iterator[Frame]:
        """The recording's first `count` frames (default all) as the engine takes them."""
        raise NotImplementedError

    def image(self, i: int) -> np.ndarray:
        """The BGR image processing saw of frame i (the preview's, the overlay's)."""
        raise NotImplementedError

    def motion_image(self, i: int) -> np.ndarray:
        """The image of frame i whose motion the clock offset follows (`vfdata.clock_offset`)."""
        raise NotImplementedError

    def view_messages(self, stamp_ns: int, left: np.ndarray, depth_mm: np.ndarray | None,
                      wants: Callable[[str], bool]) -> list[tuple[str, object]]:
        """(topic, message) of the live view of a frame: its image (only where `wants(topic)`: it costs an
        encoding) and the camera it was seen through."""
        raise NotImplementedError

    def _count(self, count: int | None) -> int:
        return self.rec.num_frames if count is None else min(count, self.rec.num_frames)


class StereoRig(Rig):
    """A rectified stereo pair: depth by matching, the tube's object frame by default."""

    kind, label, camera_frame_id = "stereo", "a stereo", layout.LEFT_FRAME
    topics = (layout.LEFT_IMAGE, layout.RIGHT_IMAGE, layout.LEFT_INFO, layout.RIGHT_INFO)

    @cached_property
    def baseline_mm(self) -> float:
        return self.rec.stereo.baseline_mm

    def stage_options(self, options: EngineOptions) -> EngineOptions:
        """The tube's frame for `auto`; a stereo pair has no sensor depth to take."""
        if options.depth == SENSOR_DEPTH:
            raise InputError(self.path, f"depth '{SENSOR_DEPTH}' is an RGB-D camera's own; a stereo recording's depth "
                                        "comes from its pair (leave --depth out, or name a stereo backend)")
        return replace(options, object_frame="tissue") if options.object_frame == "auto" else options

    def ground_truth(self, given: Path | None) -> Path | None:
        """Given, or the simulator's beside the raw folder (`find_ground_truth`); a camera: given."""
        return given if self.rec is None else find_ground_truth(self.rec, given)

    def _look_ahead(self, frames: int) -> LookAhead:
        # here, not at the top: the motion scan's module pulls in torch (vfdata.tracking)
        from vfdata.tracking.motion_scan import LookAhead

        rec = self.rec

        def pair(i: int) -> tuple[np.ndarray, np.ndarray]:
            frame = rec.rectified_frame(i)
            return frame.left, frame.right

        return LookAhead(self._count(frames), rec.rectified_left, pair)

    def frames(self, count: int | None = None) -> Iterator[Frame]:
        for k in range(self._count(count)):
            frame = self.rec.rectified_frame(k)
            yield Frame(frame.stamp_ns, frame.left, frame.right)

    def image(self, i: int) -> np.ndarray:
        """The left rectified view."""
        return self.rec.rectified_left(i)

    def motion_image(self, i: int) -> np.ndarray:
        """The left view as recorded."""
        return self.rec.left_image(i)

    def view_messages(self, stamp_ns: int, left: np.ndarray, depth_mm: np.ndarray | None,
                      wants: Callable[[str], bool]) -> list[tuple[str, object]]:
        """The left view as JPEG, and its rectified camera."""
        messages = []
        if wants(layout.LEFT_IMAGE):
            _, jpeg = cv2.imencode(".jpg", left, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            messages.append((layout.LEFT_IMAGE, CompressedImage(stamp_ns, layout.LEFT_FRAME, "jpeg", jpeg.tobytes())))
        return [*messages, (layout.LEFT_INFO, rectified_camera_info(self.camera, stamp_ns))]


class RgbdRig(Rig):
    """A depth camera: its recorded depth (no matching), drawn as grey for the image stages, and the
    board's plane and frame by default."""

    kind, label, camera_frame_id = "rgbd", "an RGB-D", layout.DEPTH_FRAME
    topics = (layout.DEPTH_IMAGE, layout.DEPTH_INFO)
    depth_only = True

    def stage_options(self, options: EngineOptions) -> EngineOptions:
        """Its recorded depth (no matching), the `plane` mask unless another is asked for (the stereo
        default, colortrack, needs a colour view registered to the depth), and the board frame unless the
        camera frame is asked for. The tracker gets its kind's RGB-D defaults (`TrackerKind.rgbd_options`:
        the geometry trackers' weak anchor: an organ on a board stays in place and only dents); `klt`
        lifts with the recorded depth (`lift=depth`): there is no right image to match in."""
        src = self.path
        if options.depth not in ("sgbm", SENSOR_DEPTH):
            raise InputError(src, f"an RGB-D recording brings its depth: depth '{options.depth}' does not apply "
                                  f"(leave --depth out, or --depth {SENSOR_DEPTH})")
        if options.object_frame in TUBE_FRAMES:
            raise InputError(src, "the tube's object frame does not apply to an RGB-D recording of a flat organ: "
                                  "--object-frame board (default) or camera")
        if options.tracker in IMAGE_TRACKERS:
            log.warning(f"warning: {src}: tracker '{options.tracker}' follows the image, and an RGB-D recording's "
                        "image here is its depth drawn as grey, whose brightness a press changes: --tracker "
                        "geometry needs only the depth (docs/tracking.md)")
        tracker_options = dict(options.tracker_options)
        kind = TRACKER_KINDS.get(options.tracker)
        for key, value in (kind.rgbd_options if kind is not None else {}).items():
            tracker_options.setdefault(key, value)
        if tracker_options.get("lift", "depth") != "depth":
            raise InputError(src, f"an RGB-D recording has no right image: {options.tracker}'s lift "
                                  f"'{tracker_options['lift']}' does not apply (lift=depth)")
        return replace(options, depth=SENSOR_DEPTH,
                       segment="plane" if options.segment == "colortrack" else options.segment,
                       object_frame="board" if options.object_frame == "auto" else options.object_frame,
                       tracker_options=tracker_options)

    @cached_property
    def _grey_range_mm(self) -> tuple[float, float]:
        """The depth view's grey range: the first frame's 1st-99th depth percentiles."""
        first = self.rec.depth_mm(0)
        valid = first[np.isfinite(first)]
        if valid.size == 0:
            raise InputError(self.rec.path, "the first depth frame has no depth")
        near, far = (float(v) for v in np.percentile(valid, [1, 99]))
        return near, far

    def frames(self, count: int | None = None) -> Iterator[Frame]:
        """Each frame's depth, and its view (`image`) as `left`."""
        for k in range(self._count(count)):
            depth = self.rec.depth_mm(k)
            yield Frame(int(self.rec.frame_times_ns[k]), depth_view(depth, *self._grey_range_mm), None, depth)

    def image(self, i: int) -> np.ndarray:
        """The depth drawn as grey (`depth_view`, the first frame's range)."""
        return depth_view(self.rec.depth_mm(i), *self._grey_range_mm)

    def motion_image(self, i: int) -> np.ndarray:
        """The colour view, or without one the depth drawn as grey (each frame's own range)."""
        if self.rec.has(layout.COLOR_IMAGE):
            return self.rec.color_image(i)
        depth = self.rec.depth_mm(i)
        finite = depth[np.isfinite(depth)]
        near, far = (np.percentile(finite, [1, 99]) if len(finite) else (0.0, 1.0))
        return np.clip(np.nan_to_num((far - depth) / max(far - near, 1e-6)) * 255, 0, 255).astype(np.uint8)

    def view_messages(self, stamp_ns: int, left: np.ndarray, depth_mm: np.ndarray | None,
                      wants: Callable[[str], bool]) -> list[tuple[str, object]]:
        """The sensor's depth as the drivers publish it (16UC1 mm, REP 118), and the depth camera."""
        messages = []
        if wants(layout.DEPTH_IMAGE):
            messages.append((layout.DEPTH_IMAGE, depth_message(depth_mm, stamp_ns, self.camera_frame_id)))
        return [*messages, (layout.DEPTH_INFO, rectified_camera_info(self.camera, stamp_ns,
                                                                    frame_id=self.camera_frame_id))]


def rig_for(rec: Recording, path: str | Path | None = None) -> Rig:
    """The rig of a recording (`path` names it in errors; default the recording's own)."""
    return (RgbdRig if rec.is_rgbd else StereoRig)(rec.path if path is None else path, rec)
