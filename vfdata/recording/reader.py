"""`Recording`: the reader other projects import.

It reads any MCAP whose channels use the layout's ROS 2 schemas (CDR), whoever wrote it. Frame times
are the left image's MCAP log times, which the layout requires to equal `header.stamp`; force and
pose times are their messages' `header.stamp` (acquisition time).

Damage is never served silently: a chunk that fails its checks (`vfdata.mcap_io.file`) raises a
`CorruptChunkError` when its messages are read, unless the file is opened with `damaged="skip"` or
`damaged="serve"`; a payload that is not what its topic's type says raises a `FormatError` naming the
file, the topic and the message."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from vfdata.calibration import PinholeCamera, RectifiedStereo
from vfdata.errors import FormatError
from vfdata.mcap_io.cdr import CdrError
from vfdata.mcap_io.file import McapFile
from vfdata.recording import layout
from vfdata.recording.messages import (
    CameraInfo,
    CompressedImage,
    PoseStamped,
    WrenchStamped,
    decode,
    decode_pose_batch,
    decode_wrench_batch,
)

# What a decoder raises on a payload that is not its type: CdrError, a bad UTF-8 string
# (UnicodeDecodeError), a PointCloud2 whose fields make no numpy dtype (ValueError, TypeError).
_DECODE_ERRORS = (CdrError, ValueError, TypeError, IndexError)

# Largest gap (ns) between force samples across which `force_at` interpolates; beyond it the
# result is NaN. 50 ms: a 30 Hz frame and a half, far above the 1 ms of a 1 kHz ATI stream.
FORCE_GAP_TOLERANCE_NS = 50_000_000
POSE_GAP_TOLERANCE_NS = 200_000_000


@dataclass(frozen=True)
class TopicInfo:
    topic: str
    msgtype: str
    count: int
    first_ns: int
    last_ns: int

    @property
    def rate_hz(self) -> float:
        span = (self.last_ns - self.first_ns) / 1e9
        return (self.count - 1) / span if self.count > 1 and span > 0 else 0.0


@dataclass(frozen=True)
class StereoFrame:
    index: int
    stamp_ns: int
    left: np.ndarray  # (H, W, 3) BGR uint8, rectified
    right: np.ndarray


@dataclass(frozen=True)
class ForceSeries:
    times_ns: np.ndarray  # (N,) int64, header stamps, sorted
    wrench: np.ndarray  # (N, 6) float64: fx fy fz (N), tx ty tz (N*m), sensor frame
    frame_id: str = layout.SENSOR_FRAME


@dataclass(frozen=True)
class PoseSeries:
    times_ns: np.ndarray  # (N,) int64
    position_m: np.ndarray  # (N, 3)
    quaternion_xyzw: np.ndarray  # (N, 4)


class Recording:
    """A recording (or derived) MCAP file. `Recording.open(path)` reads only the summary; frames,
    force and pose are read when asked, each chunk checked on its first read. `damaged`: "error"
    (default) refuses the messages of a damaged chunk with a `CorruptChunkError`; "skip" checks every
    chunk on opening and leaves the damaged ones out (`problems` lists them); "serve" does the same but
    serves the chunks that fail only their CRC as they are. Safe to hand to DataLoader workers (the
    file is reopened after a fork)."""

    def __init__(self, path: str | Path, damaged: str = "error"):
        self.path = Path(path)
        self._mcap = McapFile(self.path, damaged=damaged)
        self._by_topic = {c.topic: c for c in self._mcap.index.channels.values()}

    @classmethod
    def open(cls, path: str | Path, damaged: str = "error") -> Recording:
        return cls(path, damaged)

    def close(self) -> None:
        self._mcap.close()

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- summary ---------------------------------------------------------------------------------
    @property
    def problems(self) -> list[str]:
        """Damage found so far: on opening, and in the chunks read since (all of them with
        damaged="skip" or "serve"). Empty for a sound file."""
        return list(dict.fromkeys(self._mcap.index.problems))

    @cached_property
    def topics(self) -> dict[str, TopicInfo]:
        result = {}
        for channel in sorted(self._mcap.index.channels.values(), key=lambda c: c.topic):
            loc = self._mcap.index.messages[channel.id]
            first = int(loc.log_time_ns[0]) if len(loc) else 0
            last = int(loc.log_time_ns[-1]) if len(loc) else 0
            result[channel.topic] = TopicInfo(channel.topic, channel.msgtype, len(loc), first, last)
        return result

    @property
    def time_range_ns(self) -> tuple[int, int]:
        infos = [t for t in self.topics.values() if t.count and t.topic != layout.TF_STATIC]
        if not infos:
            return (0, 0)
        return min(t.first_ns for t in infos), max(t.last_ns for t in infos)

    @cached_property
    def metadata_records(self) -> dict[str, dict[str, str]]:
        return dict(self._mcap.index.metadata)

    @cached_property
    def metadata(self) -> layout.RecordingMeta:
        return layout.RecordingMeta.from_record(self.metadata_records.get(layout.RECORDING_METADATA, {}))

    def has(self, topic: str) -> bool:
        return topic in self.topics and self.topics[topic].count > 0

    def _channel(self, topic: str, msgtype: str | None = None):
        """The channel of `topic`, which must have messages, be CDR, and have the type the layout (or
        `msgtype`) gives it."""
        channel = self._by_topic.get(topic)
        if channel is None or self.topics[topic].count == 0:
            raise FormatError(self.path, f"no messages on {topic}")
        expected = msgtype or layout.RECORDING_TOPICS.get(topic) or layout.DERIVED_TOPICS.get(topic)
        if expected and channel.msgtype != expected:
            raise FormatError(self.path, f"{topic} has type '{channel.msgtype}', expected {expected}")
        if channel.message_encoding != layout.MESSAGE_ENCODING:
            raise FormatError(self.path, f"{topic} has message encoding '{channel.message_encoding}', expected "
                                         f"{layout.MESSAGE_ENCODING}")
        return channel

    def _decode(self, channel, payload, i: int):
        try:
            return decode(channel.msgtype, payload)
        except _DECODE_ERRORS as exc:
            raise FormatError(self.path, f"{channel.topic}: message {i} is not a valid {channel.msgtype} "
                                         f"({exc})") from None

    def messages(self, topic: str, start: int = 0, stop: int | None = None):
        """Decoded messages of a topic, in log-time order: yields (log_time_ns, message)."""
        channel = self._channel(topic)
        for i, (log_time, payload) in enumerate(self._mcap.iter_payloads(channel.id, start, stop), start):
            yield log_time, self._decode(channel, payload, i)

    def message(self, topic: str, i: int):
        channel = self._channel(topic)
        return self._decode(channel, self._mcap.payload(channel.id, i), i)

    def payloads(self, topic: str, start: int = 0, stop: int | None = None):
        """Undecoded messages of a topic (any encoding), in log-time order: yields (log_time_ns, payload
        bytes or a view into the chunk)."""
        channel = self._by_topic.get(topic)
        if channel is None:
            raise FormatError(self.path, f"no topic {topic}")
        yield from self._mcap.iter_payloads(channel.id, start, stop)

    def log_times_ns(self, topic: str) -> np.ndarray:
        return self._mcap.index.messages[self._channel(topic).id].log_time_ns

    # -- camera ----------------------------------------------------------------------------------
    @cached_property
    def camera_infos(self) -> tuple[CameraInfo, CameraInfo]:
        return self.message(layout.LEFT_INFO, 0), self.message(layout.RIGHT_INFO, 0)

    @cached_property
    def stereo(self) -> RectifiedStereo:
        """The rectified stereo model from the camera_info topics (P of each view)."""
        left, right = self.camera_infos
        p1, p2 = np.asarray(left.p).reshape(3, 4), np.asarray(right.p).reshape(3, 4)
        if p1[0, 0] <= 0 or p2[0, 0] <= 0:
            raise FormatError(self.path, "camera_info P has no focal length")
        camera = PinholeCamera(p1[0, 0], p1[1, 1], p1[0, 2], p1[1, 2], int(left.width), int(left.height))
        baseline_mm = float(-p2[0, 3] / p2[0, 0]) * 1000.0
        return RectifiedStereo(camera, baseline_mm, np.asarray(left.r).reshape(3, 3), np.asarray(right.r).reshape(3, 3))

    @property
    def camera(self) -> PinholeCamera:
        """The camera the frames' depth and clouds are in: the left rectified view, or an RGB-D
        recording's depth camera."""
        return self.depth_camera if self.is_rgbd else self.stereo.left

    # -- RGB-D -----------------------------------------------------------------------------------
    @cached_property
    def is_rgbd(self) -> bool:
        """An RGB-D recording: a depth image topic and no stereo pair (docs/format.md)."""
        return self.has(layout.DEPTH_IMAGE) and not self.has(layout.LEFT_IMAGE)

    @property
    def camera_frame_id(self) -> str:
        """The frame of the camera processing sees through: the left view's, or the depth camera's."""
        return layout.DEPTH_FRAME if self.is_rgbd else layout.LEFT_FRAME

    def _info_camera(self, topic: str) -> PinholeCamera:
        info = self.message(topic, 0)
        p = np.asarray(info.p).reshape(3, 4)
        if p[0, 0] <= 0 or p[1, 1] <= 0:
            raise FormatError(self.path, f"{topic}: P has no focal length")
        return PinholeCamera(p[0, 0], p[1, 1], p[0, 2], p[1, 2], int(info.width), int(info.height))

    @cached_property
    def depth_camera(self) -> PinholeCamera:
        """The depth camera of an RGB-D recording (its CameraInfo's P)."""
        return self._info_camera(layout.DEPTH_INFO)

    @cached_property
    def color_camera(self) -> PinholeCamera:
        return self._info_camera(layout.COLOR_INFO)

    def depth_mm(self, i: int) -> np.ndarray:
        """Depth frame i of an RGB-D recording: (H, W) float32 mm, NaN where unknown."""
        if not 0 <= i < self.num_frames:
            raise IndexError(f"frame {i} out of range 0..{self.num_frames - 1}")
        image = self.message(layout.DEPTH_IMAGE, i)
        if image.encoding not in ("16UC1", "mono16") or image.step < 2 * image.width \
                or len(image.data) < image.step * image.height:
            raise FormatError(self.path, f"{layout.DEPTH_IMAGE}: message {i} is not a 16UC1 depth image "
                                         f"({image.encoding}, {image.width}x{image.height}, step {image.step})")
        data = np.frombuffer(image.data, dtype=">u2" if image.is_bigendian else "<u2", count=image.step // 2
                             * image.height).reshape(image.height, image.step // 2)[:, :image.width]
        depth = data.astype(np.float32)
        depth[data == 0] = np.nan
        return depth

    def color_image(self, i: int) -> np.ndarray:
        """Colour frame i of an RGB-D recording (BGR uint8), the one stamped like depth frame i."""
        times = self.log_times_ns(layout.COLOR_IMAGE)
        pos = int(np.searchsorted(times, self.frame_times_ns[i]))
        if pos >= len(times) or times[pos] != self.frame_times_ns[i]:
            raise FormatError(self.path, f"frame {i}: no colour image stamped like its depth image")
        return self._decode_image(self.message(layout.COLOR_IMAGE, pos), i)

    @cached_property
    def is_rectified(self) -> bool:
        """True when the stored images are already rectified (no distortion, identity R, P = [K|t])."""
        rectified = True
        for info in self.camera_infos:
            rectified &= bool(
                np.allclose(info.d, 0) and np.allclose(np.asarray(info.r).reshape(3, 3), np.eye(3))
                and np.allclose(np.asarray(info.k).reshape(3, 3), np.asarray(info.p).reshape(3, 4)[:, :3])
            )
        return rectified

    @cached_property
    def _rectify_maps(self):
        maps = []
        for info in self.camera_infos:
            k, p = np.asarray(info.k).reshape(3, 3), np.asarray(info.p).reshape(3, 4)
            maps.append(cv2.initUndistortRectifyMap(
                k, np.asarray(info.d), np.asarray(info.r).reshape(3, 3), p[:, :3], (int(info.width), int(info.height)),
                cv2.CV_16SC2,
            ))
        return maps

    def rectified_frame(self, i: int) -> StereoFrame:
        """Stereo frame i, rectified with the camera_info (unchanged when already rectified)."""
        frame = self.frame(i)
        if self.is_rectified:
            return frame
        (l1, l2), (r1, r2) = self._rectify_maps
        return StereoFrame(i, frame.stamp_ns, cv2.remap(frame.left, l1, l2, cv2.INTER_LINEAR),
                           cv2.remap(frame.right, r1, r2, cv2.INTER_LINEAR))

    def rectified_left(self, i: int) -> np.ndarray:
        """The left image of frame i, rectified, without decoding the right one."""
        left = self.left_image(i)
        if self.is_rectified:
            return left
        (l1, l2), _ = self._rectify_maps
        return cv2.remap(left, l1, l2, cv2.INTER_LINEAR)

    # -- frames ----------------------------------------------------------------------------------
    @property
    def frame_topic(self) -> str:
        """The topic whose messages are the frames: the left image, or an RGB-D recording's depth."""
        return layout.DEPTH_IMAGE if self.is_rgbd else layout.LEFT_IMAGE

    @cached_property
    def frame_times_ns(self) -> np.ndarray:
        return self.log_times_ns(self.frame_topic)

    @property
    def num_frames(self) -> int:
        return len(self.frame_times_ns) if self.has(self.frame_topic) else 0

    @cached_property
    def _right_index(self) -> np.ndarray:
        """For each left frame, the index of the right frame with the same stamp."""
        left, right = self.frame_times_ns, self.log_times_ns(layout.RIGHT_IMAGE)
        if len(left) == len(right) and np.array_equal(left, right):
            return np.arange(len(left))
        pos = np.clip(np.searchsorted(right, left), 0, len(right) - 1)
        if not np.array_equal(right[pos], left):
            raise FormatError(self.path, "left and right image stamps do not pair")
        return pos

    def frame_images(self, i: int) -> tuple[CompressedImage, CompressedImage]:
        """The compressed left and right images of frame i (no decoding)."""
        if not 0 <= i < self.num_frames:
            raise IndexError(f"frame {i} out of range 0..{self.num_frames - 1}")
        left = self.message(layout.LEFT_IMAGE, i)
        right = self.message(layout.RIGHT_IMAGE, int(self._right_index[i]))
        return left, right

    def frame(self, i: int) -> StereoFrame:
        """Stereo frame i decoded to BGR uint8 arrays."""
        left, right = self.frame_images(i)
        return StereoFrame(i, int(self.frame_times_ns[i]), self._decode_image(left, i), self._decode_image(right, i))

    def left_image(self, i: int) -> np.ndarray:
        if not 0 <= i < self.num_frames:
            raise IndexError(f"frame {i} out of range 0..{self.num_frames - 1}")
        return self._decode_image(self.message(layout.LEFT_IMAGE, i), i)

    def frames(self, indices=None):
        """Iterate decoded stereo frames (all by default)."""
        for i in range(self.num_frames) if indices is None else indices:
            yield self.frame(int(i))

    def frame_index_at(self, time_ns: int, tolerance_ns: int | None = None) -> int:
        """Index of the frame nearest to `time_ns`; KeyError if farther than `tolerance_ns`
        (default half a frame period)."""
        times = self.frame_times_ns
        if len(times) == 0:
            raise KeyError("recording has no frames")
        pos = int(np.clip(np.searchsorted(times, time_ns), 1, len(times) - 1)) if len(times) > 1 else 0
        if pos > 0 and abs(times[pos - 1] - time_ns) <= abs(times[pos] - time_ns):
            pos -= 1
        if tolerance_ns is None:
            tolerance_ns = int(np.median(np.diff(times)) // 2) if len(times) > 1 else 0
        if abs(int(times[pos]) - time_ns) > tolerance_ns:
            raise KeyError(f"no frame within {tolerance_ns} ns of {time_ns}")
        return pos

    def _decode_image(self, image: CompressedImage, i: int) -> np.ndarray:
        array = cv2.imdecode(np.frombuffer(image.data, dtype=np.uint8), cv2.IMREAD_COLOR)
        if array is None:
            raise FormatError(self.path, f"frame {i}: {image.format} image on {image.frame_id} cannot be decoded")
        return array

    # -- force and pose --------------------------------------------------------------------------
    @cached_property
    def force(self) -> ForceSeries:
        """The whole force/torque series, sorted by header stamp."""
        times, values = self._fixed_series(layout.WRENCH, WrenchStamped.msgtype, decode_wrench_batch, 6)
        return ForceSeries(times, values, self.message(layout.WRENCH, 0).frame_id)

    def _fixed_series(self, topic: str, msgtype: str, decode_batch, width: int) -> tuple[np.ndarray, np.ndarray]:
        """Header stamps (N,) and values (N, width) of a fixed-size stamped topic, decoded chunk by
        chunk into preallocated arrays (a 30-minute 1 kHz series costs its 100 MB, not three times
        that), sorted by stamp."""
        channel = self._channel(topic, msgtype)
        count = len(self._mcap.index.messages[channel.id])
        times = np.empty(count, dtype=np.int64)
        values = np.empty((count, width))
        filled = 0
        for matrix in self._mcap.iter_payload_matrices(channel.id):
            try:
                t, v = decode_batch(matrix)
            except _DECODE_ERRORS as exc:
                raise FormatError(self.path, f"{topic}: messages are not valid {msgtype} ({exc})") from None
            times[filled:filled + len(t)] = t
            values[filled:filled + len(t)] = v
            filled += len(t)
        if (np.diff(times) < 0).any():
            order = np.argsort(times, kind="stable")
            times, values = times[order], values[order]
        return times, values

    def force_at(self, times_ns, max_gap_ns: int = FORCE_GAP_TOLERANCE_NS) -> np.ndarray:
        """Wrench (N, 6) linearly interpolated at `times_ns`. NaN where a time falls outside the
        series or inside a gap between samples longer than `max_gap_ns`."""
        series = self.force
        return _interpolate(series.times_ns, series.wrench, np.asarray(times_ns, dtype=np.int64), max_gap_ns)

    @cached_property
    def ecm_pose(self) -> PoseSeries:
        times, values = self._fixed_series(layout.ECM_POSE, PoseStamped.msgtype, decode_pose_batch, 7)
        return PoseSeries(times, values[:, :3], values[:, 3:])

    def ecm_pose_at(self, times_ns, max_gap_ns: int = POSE_GAP_TOLERANCE_NS) -> tuple[np.ndarray, np.ndarray]:
        """(positions (N, 3) m, quaternions (N, 4) xyzw) at `times_ns`: linear in position, slerp in
        rotation; NaN outside the series or across gaps longer than `max_gap_ns`."""
        series = self.ecm_pose
        times = np.asarray(times_ns, dtype=np.int64)
        position = _interpolate(series.times_ns, series.position_m, times, max_gap_ns)
        quat = np.full((len(times), 4), np.nan)
        if len(series.times_ns) == 1:
            same = times == series.times_ns[0]
            quat[same] = series.quaternion_xyzw[0]
            return position, quat
        ok = np.isfinite(position[:, 0])
        if ok.any():
            t0 = series.times_ns[0]
            slerp = Slerp((series.times_ns - t0).astype(np.float64), Rotation.from_quat(series.quaternion_xyzw))
            quat[ok] = slerp((times[ok] - t0).astype(np.float64)).as_quat()
        return position, quat


def _interpolate(t: np.ndarray, values: np.ndarray, at: np.ndarray, max_gap_ns: int) -> np.ndarray:
    out = np.full((len(at), values.shape[1]), np.nan)
    if len(t) == 0:
        return out
    right = np.searchsorted(t, at, side="left")
    exact = (right < len(t)) & (t[np.minimum(right, len(t) - 1)] == at)
    inside = (right > 0) & (right < len(t))
    left = np.maximum(right - 1, 0)
    r = np.minimum(right, len(t) - 1)
    gap = t[r] - t[left]
    ok = inside & (gap <= max_gap_ns)
    w = np.zeros(len(at))
    w[ok] = (at[ok] - t[left[ok]]) / gap[ok]
    out[ok] = values[left[ok]] * (1 - w[ok, None]) + values[r[ok]] * w[ok, None]
    out[exact] = values[r[exact]]
    return out
