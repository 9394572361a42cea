"""Live sources for `vfdata live`: rectified stereo pairs (or an RGB-D camera's depth frames), one
at a time, each with the moment it arrived, produced by a thread of their own as a camera driver would.

- `RecordingReplay`: a recording MCAP (stereo or RGB-D) replayed at its own rate (`speed` 1.0; 0 = as
  fast as the consumer takes them). By default no frame is dropped: a consumer slower than the rate falls behind,
  and each frame's `arrival_s` is the moment the camera would have delivered it, so that lag shows in
  the latency instead of being hidden. `like_camera=True` keeps only the newest frame instead, as a
  camera does: a slower consumer skips frames (`dropped`) and its latency stays that of one frame.
- `VideoStereo`: two OpenCV video sources (device indices, files or stream URLs) or one side-by-side
  source, rectified with a calibration file (`StereoCalibration`). Like a camera, it keeps only the
  newest pair: a consumer slower than the camera skips frames (`dropped` counts them). Files are
  paced at their own frame rate.

Both iterate `LiveFrame`s (`for frame in source: ...`) and stop with `close()` or at the end of the
input; an error in the producer thread is raised in the consumer's. Each has its rig (`vfdata.rig`:
`source.rig`), which knows its camera, prompt, stage defaults and live view."""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vfdata.calibration import StereoCalibration
from vfdata.errors import InputError
from vfdata.recording import Recording
from vfdata.rig import Frame, StereoRig, rig_for
from vfdata.video_log import quiet_ffmpeg_log

_END = object()


@dataclass
class LiveFrame:
    index: int  # in the source's order (skipped frames of a camera leave gaps)
    stamp_ns: int
    left: np.ndarray  # rectified BGR (RGB-D: the depth drawn as grey, vfdata.rig.depth_view)
    right: np.ndarray | None  # None for RGB-D
    arrival_s: float  # time.perf_counter() when the camera delivered it (a replay: when it was due)
    depth_mm: np.ndarray | None = None  # RGB-D: the sensor's depth (H, W) mm, NaN unknown


class _Producer:
    """A thread filling a queue with frames; `keep_latest` replaces an unread frame (a camera)."""

    def __init__(self, produce, keep_latest: bool, name: str):
        self._queue: queue.Queue = queue.Queue(maxsize=1 if keep_latest else 4)
        self._keep_latest = keep_latest
        self._stop = threading.Event()
        self.dropped = 0
        self._produce = produce
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._started = False

    def _put(self, item) -> bool:
        """False once stopped."""
        while not self._stop.is_set():
            if self._keep_latest and item is not _END:
                try:
                    self._queue.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass
            try:
                self._queue.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _run(self) -> None:
        try:
            for item in self._produce(self._stop):
                if not self._put(item):
                    return
            self._put(_END)
        except BaseException as exc:  # handed to the consumer, raised there
            self._put(exc)

    def __iter__(self) -> Iterator[LiveFrame]:
        if not self._started:
            self._started = True
            self._thread.start()
        while True:
            item = self._queue.get()
            if item is _END:
                return
            if isinstance(item, BaseException):
                raise item
            yield item

    def close(self) -> None:
        self._stop.set()
        if self._started:
            self._thread.join(timeout=5)


class RecordingReplay:
    """A recording replayed as a live source (see the module docstring)."""

    def __init__(self, path: str | Path, speed: float = 1.0, max_frames: int | None = None,
                 like_camera: bool = False):
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(self.path, "recording not found")
        if speed < 0:
            raise InputError(self.path, f"replay speed must be >= 0 (0: as fast as possible), not {speed}")
        self.recording = Recording.open(self.path)
        self.rig = rig_for(self.recording, self.path)
        try:
            self.rig.check()
        except InputError:
            self.recording.close()
            raise
        self.speed = float(speed)
        self.frames = self.recording.num_frames if max_frames is None else min(max_frames, self.recording.num_frames)
        if like_camera and self.speed == 0:
            raise InputError(self.path, "a replay like a camera needs a rate: --speed > 0")
        self._producer = _Producer(self._produce, keep_latest=like_camera, name="vf-replay")

    @property
    def dropped(self) -> int:
        return self._producer.dropped

    def decoded(self) -> Iterator[Frame]:
        """Each frame as processing sees it (`vfdata.rig.Frame`), decoded in the caller's thread and without
        pacing (iterating the replay itself runs the camera-like thread)."""
        return self.rig.frames(self.frames)

    def _produce(self, stop: threading.Event):
        times = self.recording.frame_times_ns
        started = time.perf_counter()
        for i, (stamp_ns, left, right, depth_mm) in enumerate(self.decoded()):
            if stop.is_set():
                return
            if self.speed > 0:
                due = started + (int(times[i]) - int(times[0])) / 1e9 / self.speed
                wait = due - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
            else:
                due = time.perf_counter()
            yield LiveFrame(i, stamp_ns, left, right, due, depth_mm)

    def __iter__(self) -> Iterator[LiveFrame]:
        return iter(self._producer)

    def close(self) -> None:
        self._producer.close()
        self.recording.close()


def _capture_target(source: str) -> int | str:
    """A device index ('0') or a file path / stream URL, as cv2.VideoCapture takes them."""
    return int(source) if source.isdigit() else source


def _open_capture(source: str) -> cv2.VideoCapture:
    quiet_ffmpeg_log()  # our line names the source; FFmpeg's own would come first
    capture = cv2.VideoCapture(_capture_target(source))
    if not capture.isOpened():
        raise InputError(Path(source), "video source cannot be opened (device index, video file or stream URL)")
    return capture


class VideoStereo:
    """Two OpenCV sources (left, right) or one side-by-side source, rectified with `calibration`."""

    def __init__(self, left: str, right: str | None, calibration: str | Path, side_by_side: bool = False,
                 max_frames: int | None = None):
        if (right is None) != side_by_side:
            raise InputError(Path(left), "give a right source, or --side-by-side for one source holding both views")
        self.calibration = StereoCalibration.load(calibration)
        rect = self.calibration.rectified
        self.rig = StereoRig(left, camera=rect.left, baseline_mm=rect.baseline_mm)
        self.sources = (left,) if right is None else (left, right)
        self.captures = [_open_capture(s) for s in self.sources]
        self.max_frames = max_frames
        # Files are paced at their own rate, as a camera would deliver them; devices and streams block.
        self.is_file = all(Path(s).is_file() for s in self.sources)
        fps = self.captures[0].get(cv2.CAP_PROP_FPS)
        self.period_s = 1.0 / fps if self.is_file and fps and fps > 0 else 0.0
        self._producer = _Producer(self._produce, keep_latest=True, name="vf-capture")

    @property
    def dropped(self) -> int:
        return self._producer.dropped

    def _read(self, index: int) -> tuple[np.ndarray, np.ndarray] | None:
        if len(self.captures) == 1:
            ok, frame = self.captures[0].read()
            if not ok:
                return None
            if frame.shape[1] % 2:
                raise InputError(Path(self.sources[0]), f"frame {index}: side-by-side width {frame.shape[1]} is odd")
            half = frame.shape[1] // 2
            left, right = frame[:, :half], frame[:, half:]
        else:
            # grab both first, then decode: the two exposures as close in time as OpenCV allows
            if not (self.captures[0].grab() and self.captures[1].grab()):
                return None
            ok_left, left = self.captures[0].retrieve()
            ok_right, right = self.captures[1].retrieve()
            if not (ok_left and ok_right):
                return None
        expected = (self.calibration.height, self.calibration.width)
        if left.shape[:2] != expected or right.shape[:2] != expected:
            raise InputError(Path(self.sources[0]), f"frame {index}: images are {left.shape[1]}x{left.shape[0]}, "
                                                    f"the calibration's {expected[1]}x{expected[0]}")
        return self.calibration.rectify_pair(np.ascontiguousarray(left), np.ascontiguousarray(right))

    def _produce(self, stop: threading.Event):
        started = time.perf_counter()
        index = 0
        while not stop.is_set() and (self.max_frames is None or index < self.max_frames):
            pair = self._read(index)
            if pair is None:
                return
            if self.period_s:
                wait = started + index * self.period_s - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
            yield LiveFrame(index, time.time_ns(), pair[0], pair[1], time.perf_counter())
            index += 1

    def __iter__(self) -> Iterator[LiveFrame]:
        return iter(self._producer)

    def close(self) -> None:
        self._producer.close()
        for capture in self.captures:
            capture.release()
