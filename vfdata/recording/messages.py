"""Typed ROS 2 messages of the VisionForce layout, with their CDR encoding and decoding.

Stamps are integer nanoseconds (`stamp_ns`); `header.stamp` is split into sec/nanosec on the wire.
Quaternions are (x, y, z, w) as in ROS. `decode(msgtype, payload)` handles every supported type;
`decode_wrench_batch` is the vectorised path for long force series."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vfdata.recording.cdr import CdrError, CdrReader, CdrWriter

NS_PER_S = 1_000_000_000  # ROS time is (sec, nanosec); vfdata's stamps are int ns


def _write_header(w: CdrWriter, stamp_ns: int, frame_id: str) -> None:
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    w.int32(sec)
    w.uint32(nanosec)
    w.string(frame_id)


def _read_header(r: CdrReader) -> tuple[int, str]:
    sec = r.int32()
    nanosec = r.uint32()
    return sec * NS_PER_S + nanosec, r.string()


@dataclass
class CompressedImage:
    msgtype = "sensor_msgs/msg/CompressedImage"
    stamp_ns: int
    frame_id: str
    format: str  # "jpeg" or "png"
    data: bytes

    def encode(self) -> bytes:
        w = CdrWriter()
        _write_header(w, self.stamp_ns, self.frame_id)
        w.string(self.format)
        w.bytes_sequence(self.data)
        return w.getvalue()

    @classmethod
    def decode(cls, payload: bytes | memoryview) -> CompressedImage:
        r = CdrReader(payload)
        stamp, frame = _read_header(r)
        return cls(stamp, frame, r.string(), r.bytes_sequence())


@dataclass
class Image:
    msgtype = "sensor_msgs/msg/Image"
    stamp_ns: int
    frame_id: str
    height: int
    width: int
    encoding: str  # e.g. "bgr8", "rgb8", "mono8", "16UC1", "32FC1"
    is_bigendian: int
    step: int
    data: bytes

    def encode(self) -> bytes:
        w = CdrWriter()
        _write_header(w, self.stamp_ns, self.frame_id)
        w.uint32(self.height)
        w.uint32(self.width)
        w.string(self.encoding)
        w.uint8(self.is_bigendian)
        w.uint32(self.step)
        w.bytes_sequence(self.data)
        return w.getvalue()

    @classmethod
    def decode(cls, payload: bytes | memoryview) -> Image:
        r = CdrReader(payload)
        stamp, frame = _read_header(r)
        return cls(stamp, frame, r.uint32(), r.uint32(), r.string(), r.uint8(), r.uint32(), r.bytes_sequence())


@dataclass
class CameraInfo:
    msgtype = "sensor_msgs/msg/CameraInfo"
    stamp_ns: int
    frame_id: str
    height: int
    width: int
    distortion_model: str
    d: np.ndarray
    k: np.ndarray  # (3, 3)
    r: np.ndarray  # (3, 3)
    p: np.ndarray  # (3, 4); p[0, 3] = -fx * baseline in metres for the right camera
    binning_x: int = 0
    binning_y: int = 0
    roi: tuple[int, int, int, int, bool] = (0, 0, 0, 0, False)

    def encode(self) -> bytes:
        w = CdrWriter()
        _write_header(w, self.stamp_ns, self.frame_id)
        w.uint32(self.height)
        w.uint32(self.width)
        w.string(self.distortion_model)
        w.float64s(self.d, sequence=True)
        w.float64s(self.k, sequence=False)
        w.float64s(self.r, sequence=False)
        w.float64s(self.p, sequence=False)
        w.uint32(self.binning_x)
        w.uint32(self.binning_y)
        x_offset, y_offset, height, width, do_rectify = self.roi
        for value in (x_offset, y_offset, height, width):
            w.uint32(value)
        w.bool(do_rectify)
        return w.getvalue()

    @classmethod
    def decode(cls, payload: bytes | memoryview) -> CameraInfo:
        r = CdrReader(payload)
        stamp, frame = _read_header(r)
        height, width = r.uint32(), r.uint32()
        model = r.string()
        d = r.float64s()
        k = r.float64s(9).reshape(3, 3)
        rr = r.float64s(9).reshape(3, 3)
        p = r.float64s(12).reshape(3, 4)
        bx, by = r.uint32(), r.uint32()
        roi = (r.uint32(), r.uint32(), r.uint32(), r.uint32(), r.bool())
        return cls(stamp, frame, height, width, model, d, k, rr, p, bx, by, roi)


@dataclass
class WrenchStamped:
    msgtype = "geometry_msgs/msg/WrenchStamped"
    stamp_ns: int
    frame_id: str
    force: tuple[float, float, float]  # N
    torque: tuple[float, float, float]  # N·m

    def encode(self) -> bytes:
        w = CdrWriter()
        _write_header(w, self.stamp_ns, self.frame_id)
        for value in (*self.force, *self.torque):
            w.float64(value)
        return w.getvalue()

    @classmethod
    def decode(cls, payload: bytes | memoryview) -> WrenchStamped:
        r = CdrReader(payload)
        stamp, frame = _read_header(r)
        values = [r.float64() for _ in range(6)]
        return cls(stamp, frame, tuple(values[:3]), tuple(values[3:]))


@dataclass
class PoseStamped:
    msgtype = "geometry_msgs/msg/PoseStamped"
    stamp_ns: int
    frame_id: str
    position: tuple[float, float, float]  # m
    orientation: tuple[float, float, float, float]  # x, y, z, w

    def encode(self) -> bytes:
        w = CdrWriter()
        _write_header(w, self.stamp_ns, self.frame_id)
        for value in (*self.position, *self.orientation):
            w.float64(value)
        return w.getvalue()

    @classmethod
    def decode(cls, payload: bytes | memoryview) -> PoseStamped:
        r = CdrReader(payload)
        stamp, frame = _read_header(r)
        values = [r.float64() for _ in range(7)]
        return cls(stamp, frame, tuple(values[:3]), tuple(values[3:]))


@dataclass
class TransformStamped:
    msgtype = "geometry_msgs/msg/TransformStamped"
    stamp_ns: int
    frame_id: str
    child_frame_id: str
    translation: tuple[float, float, float]  # m
    rotation: tuple[float, float, float, float]  # x, y, z, w

    def write(self, w: CdrWriter) -> None:
        _write_header(w, self.stamp_ns, self.frame_id)
        w.string(self.child_frame_id)
        for value in (*self.translation, *self.rotation):
            w.float64(value)

    @classmethod
    def read(cls, r: CdrReader) -> TransformStamped:
        stamp, frame = _read_header(r)
        child = r.string()
        values = [r.float64() for _ in range(7)]
        return cls(stamp, frame, child, tuple(values[:3]), tuple(values[3:]))

    def encode(self) -> bytes:
        w = CdrWriter()
        self.write(w)
        return w.getvalue()

    @classmethod
    def decode(cls, payload: bytes | memoryview) -> TransformStamped:
        return cls.read(CdrReader(payload))


@dataclass
class TFMessage:
    msgtype = "tf2_msgs/msg/TFMessage"
    transforms: list[TransformStamped] = field(default_factory=list)

    @property
    def stamp_ns(self) -> int:
        return self.transforms[0].stamp_ns if self.transforms else 0

    def encode(self) -> bytes:
        w = CdrWriter()
        w.uint32(len(self.transforms))
        for transform in self.transforms:
            transform.write(w)
        return w.getvalue()

    @classmethod
    def decode(cls, payload: bytes | memoryview) -> TFMessage:
        r = CdrReader(payload)
        return cls([TransformStamped.read(r) for _ in range(r.uint32())])


# sensor_msgs/PointField datatypes -> numpy
POINT_FIELD_DTYPES = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}
_DTYPE_TO_POINT_FIELD = {np.dtype(v).str.lstrip("|"): k for k, v in POINT_FIELD_DTYPES.items()}


@dataclass
class PointCloud2:
    """An unorganised (height 1) little-endian cloud. `points` is a numpy structured array."""

    msgtype = "sensor_msgs/msg/PointCloud2"
    stamp_ns: int
    frame_id: str
    points: np.ndarray

    def encode(self) -> bytes:
        points = np.ascontiguousarray(self.points)
        dtype = points.dtype
        w = CdrWriter()
        _write_header(w, self.stamp_ns, self.frame_id)
        w.uint32(1)
        w.uint32(len(points))
        w.uint32(len(dtype.names))
        for name in dtype.names:
            sub, offset = dtype.fields[name][:2]
            w.string(name)
            w.uint32(offset)
            w.uint8(_DTYPE_TO_POINT_FIELD[sub.str.lstrip("|").replace("=", "<")])
            w.uint32(1)
        w.bool(False)
        w.uint32(dtype.itemsize)
        w.uint32(dtype.itemsize * len(points))
        w.bytes_sequence(points.tobytes())
        w.bool(bool(all(np.isfinite(points[n]).all() for n in dtype.names)))
        return w.getvalue()

    @classmethod
    def decode(cls, payload: bytes | memoryview) -> PointCloud2:
        r = CdrReader(payload)
        stamp, frame = _read_header(r)
        height, width = r.uint32(), r.uint32()
        names, formats, offsets = [], [], []
        for _ in range(r.uint32()):
            name, offset, datatype, count = r.string(), r.uint32(), r.uint8(), r.uint32()
            if datatype not in POINT_FIELD_DTYPES:
                raise CdrError(f"PointField '{name}' has unknown datatype {datatype}")
            names.append(name)
            formats.append((POINT_FIELD_DTYPES[datatype], (count,)) if count > 1 else POINT_FIELD_DTYPES[datatype])
            offsets.append(offset)
        if r.bool():
            raise CdrError("big-endian PointCloud2 is not supported")
        point_step = r.uint32()
        r.uint32()  # row_step
        data = r.bytes_sequence()
        dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})
        points = np.frombuffer(data, dtype=dtype, count=height * width).copy()
        return cls(stamp, frame, points)


MESSAGE_TYPES = {
    cls.msgtype: cls
    for cls in (
        CompressedImage, Image, CameraInfo, WrenchStamped, PoseStamped, TransformStamped, TFMessage,
        PointCloud2,
    )
}


def decode(msgtype: str, payload: bytes | memoryview):
    """Decode a CDR payload of one of the supported types."""
    try:
        cls = MESSAGE_TYPES[msgtype]
    except KeyError:
        raise CdrError(f"unsupported message type {msgtype}") from None
    return cls.decode(payload)


def _batch_fixed_tail(payloads: np.ndarray, n_doubles: int) -> tuple[np.ndarray, np.ndarray]:
    """Stamped messages whose body after the header is `n_doubles` float64, all with the same
    payload length (so the same frame_id length): (N, L) uint8 -> stamps_ns (N,), values (N, n)."""
    count, length = payloads.shape
    if count == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, n_doubles))
    if not (payloads[:, 1] == 1).all():
        raise CdrError("not a little-endian CDR payload (encapsulation header is not 00 01)")
    sec = payloads[:, 4:8].copy().view("<i4").ravel().astype(np.int64)
    nanosec = payloads[:, 8:12].copy().view("<u4").ravel().astype(np.int64)
    str_len = int(payloads[0, 12:16].copy().view("<u4")[0])
    body = 4 + 12 + str_len
    body += (-(body - 4)) % 8
    if body + 8 * n_doubles != length:
        raise CdrError(f"payload of {length} bytes does not match its frame_id length {str_len}")
    values = payloads[:, body:].copy().view("<f8").reshape(count, n_doubles)
    return sec * NS_PER_S + nanosec, values


def decode_wrench_batch(payloads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, L) uint8 WrenchStamped payloads of equal length -> header stamps (N,) ns, (N, 6) wrench."""
    return _batch_fixed_tail(payloads, 6)


def decode_pose_batch(payloads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, L) uint8 PoseStamped payloads of equal length -> stamps (N,) ns, (N, 7) x y z qx qy qz qw."""
    return _batch_fixed_tail(payloads, 7)
