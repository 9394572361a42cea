"""Typed ROS 2 messages of the VisionForce layout, with their CDR encoding and decoding.

Stamps are integer nanoseconds (`stamp_ns`); `header.stamp` is split into sec/nanosec on the wire.
Quaternions are (x, y, z, w) as in ROS. `decode(msgtype, payload)` handles every supported type;
`encode_stamped_batch` / `decode_stamped_batch` are the vectorised paths for long force and pose
series (the converters and the reader)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vfdata.mcap_io.cdr import CdrError, CdrReader, CdrWriter

NS_PER_S = 1_000_000_000  # ROS time is (sec, nanosec); vfdata's stamps are int ns
# The last stamp a ROS 2 header holds (int32 seconds); stamps of the layout lie in 0 .. MAX_STAMP_NS.
MAX_STAMP_NS = (2**31 - 1) * NS_PER_S + NS_PER_S - 1


def _write_header(w: CdrWriter, stamp_ns: int, frame_id: str) -> None:
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    w.int32(sec)
    w.uint32(nanosec)
    w.string(frame_id)


def _read_header(r: CdrReader) -> tuple[int, str]:
    sec = r.int32()
    nanosec = r.uint32()
    return sec * NS_PER_S + nanosec, r.string()


def _encode_stamped_doubles(stamp_ns: int, frame_id: str, values) -> bytes:
    """A message that is a header and float64 values only (WrenchStamped, PoseStamped)."""
    w = CdrWriter()
    _write_header(w, stamp_ns, frame_id)
    for value in values:
        w.float64(value)
    return w.getvalue()


def _decode_stamped_doubles(payload: bytes | memoryview, count: int) -> tuple[int, str, list[float]]:
    r = CdrReader(payload)
    stamp, frame = _read_header(r)
    return stamp, frame, [r.float64() for _ in range(count)]


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
class Float64:
    """A bare number, no header: its time is the MCAP message's log time (`/force/estimate/unlike`)."""

    msgtype = "std_msgs/msg/Float64"
    data: float

    def encode(self) -> bytes:
        w = CdrWriter()
        w.float64(self.data)
        return w.getvalue()

    @classmethod
    def decode(cls, payload: bytes | memoryview) -> Float64:
        return cls(CdrReader(payload).float64())


@dataclass
class WrenchStamped:
    msgtype = "geometry_msgs/msg/WrenchStamped"
    stamp_ns: int
    frame_id: str
    force: tuple[float, float, float]  # N
    torque: tuple[float, float, float]  # N·m

    def encode(self) -> bytes:
        return _encode_stamped_doubles(self.stamp_ns, self.frame_id, (*self.force, *self.torque))

    @classmethod
    def decode(cls, payload: bytes | memoryview) -> WrenchStamped:
        stamp, frame, values = _decode_stamped_doubles(payload, 6)
        return cls(stamp, frame, tuple(values[:3]), tuple(values[3:]))


@dataclass
class PoseStamped:
    msgtype = "geometry_msgs/msg/PoseStamped"
    stamp_ns: int
    frame_id: str
    position: tuple[float, float, float]  # m
    orientation: tuple[float, float, float, float]  # x, y, z, w

    def encode(self) -> bytes:
        return _encode_stamped_doubles(self.stamp_ns, self.frame_id, (*self.position, *self.orientation))

    @classmethod
    def decode(cls, payload: bytes | memoryview) -> PoseStamped:
        stamp, frame, values = _decode_stamped_doubles(payload, 7)
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
        CompressedImage, Image, CameraInfo, Float64, WrenchStamped, PoseStamped, TransformStamped, TFMessage,
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


# -- the stamped-series batch codec -------------------------------------------------------------------
# WrenchStamped and PoseStamped are a std_msgs/Header and then float64s only, so N messages with one
# frame_id are an (N, L) uint8 table with the stamps and values at fixed columns: encoded and decoded
# with numpy at once (a 1 kHz force series costs ~100 ns a message instead of ~10 us through
# CdrWriter/CdrReader). Little-endian CDR (ROS 2): encapsulation 00 01 00 00, int32 sec, uint32
# nanosec, uint32 length + frame_id + NUL, then the float64s aligned to 8 (counted after the
# encapsulation). ROS 1: uint32 seq, uint32 sec, uint32 nsec, uint32 length + frame_id, then the
# float64s, no alignment. The frame_id's length field and bytes start at column 12 in both.
_NAME_AT = 12


def _body_offset(name_length: int, ros1: bool) -> int:
    """Column of the first float64, after a frame_id field of `name_length` bytes (NUL included in CDR)."""
    body = 16 + name_length
    return body if ros1 else body + (-(body - 4)) % 8


def encode_stamped_batch(stamps_ns: np.ndarray, frame_id: str, values: np.ndarray) -> np.ndarray:
    """CDR payloads of N stamped messages whose body is float64 values only (WrenchStamped: (N, 6),
    PoseStamped: (N, 7)) -> (N, L) uint8; row i is byte for byte `WrenchStamped.encode()` /
    `PoseStamped.encode()` of message i. Stamps are int ns within ROS 2 time (0 .. 2**31 s)."""
    stamps_ns = np.asarray(stamps_ns, np.int64)
    values = np.ascontiguousarray(values, "<f8")
    name = frame_id.encode("utf-8") + b"\x00"
    body = _body_offset(len(name), ros1=False)
    table = np.zeros((len(stamps_ns), body + 8 * values.shape[1]), np.uint8)
    table[:, 1] = 1  # 00 01 00 00: little-endian CDR
    sec, nanosec = np.divmod(stamps_ns, NS_PER_S)
    table[:, 4:8] = sec.astype("<i4")[:, None].view(np.uint8)
    table[:, 8:12] = nanosec.astype("<u4")[:, None].view(np.uint8)
    table[:, 12:16] = np.frombuffer(np.uint32(len(name)).astype("<u4").tobytes(), np.uint8)
    table[:, 16:16 + len(name)] = np.frombuffer(name, np.uint8)
    table[:, body:] = values.view(np.uint8)
    return table


def encode_tf_batch(stamps_ns: np.ndarray, frame_id: str, child_frame_id: str, values: np.ndarray) -> np.ndarray:
    """CDR payloads of N TFMessages of one transform each, `frame_id` -> `child_frame_id`, values (N, 7):
    translation m, rotation xyzw -> (N, L) uint8; row i is byte for byte the `TFMessage.encode()` of
    message i (one message encoded as the template, then its stamp and values replaced per row)."""
    stamps_ns = np.asarray(stamps_ns, np.int64)
    values = np.ascontiguousarray(values, "<f8").reshape(-1, 7)
    template = np.frombuffer(TFMessage([TransformStamped(0, frame_id, child_frame_id, (0.0,) * 3, (0.0,) * 4)])
                             .encode(), np.uint8)
    table = np.tile(template, (len(stamps_ns), 1))
    sec, nanosec = np.divmod(stamps_ns, NS_PER_S)
    table[:, 8:12] = sec.astype("<i4")[:, None].view(np.uint8)  # after encapsulation and the list length
    table[:, 12:16] = nanosec.astype("<u4")[:, None].view(np.uint8)
    table[:, -56:] = values.view(np.uint8)  # the seven float64 end the message
    return table


def decode_stamped_batch(payloads: np.ndarray, n_doubles: int, ros1: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(N, L) uint8 payloads of stamped messages whose body is `n_doubles` float64 (all of one length,
    so of one frame_id length) -> header stamps (N,) int ns, values (N, n_doubles). Little-endian CDR,
    or ROS 1 serialisation when `ros1`. CdrError when they do not have that layout; the frame ids are
    not compared (`stamped_batch_frame_id` does)."""
    count, length = payloads.shape
    if count == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, n_doubles))
    if not ros1 and not (payloads[:, 1] == 1).all():
        raise CdrError("not a little-endian CDR payload (encapsulation header is not 00 01)")
    if length < 16:
        raise CdrError(f"payload of {length} bytes is shorter than a header")
    name_length = int(payloads[0, _NAME_AT:_NAME_AT + 4].copy().view("<u4")[0])
    body = _body_offset(name_length, ros1)
    if body + 8 * n_doubles != length:
        raise CdrError(f"payload of {length} bytes does not match its frame_id length {name_length}")
    sec = payloads[:, 4:8].copy().view("<u4" if ros1 else "<i4").ravel().astype(np.int64)
    nanosec = payloads[:, 8:12].copy().view("<u4").ravel().astype(np.int64)
    values = payloads[:, body:].copy().view("<f8").reshape(count, n_doubles)
    return sec * NS_PER_S + nanosec, values


def stamped_batch_frame_id(payloads: np.ndarray) -> str | None:
    """The one frame_id of an (N, L) uint8 table of stamped messages (CDR or ROS 1); None when the rows
    differ in it, or it is cut short or not UTF-8."""
    count, length = payloads.shape
    if count == 0 or length < 16:
        return None
    name_length = int(payloads[0, _NAME_AT:_NAME_AT + 4].copy().view("<u4")[0])
    field = slice(_NAME_AT, 16 + name_length)  # the length and the bytes
    if 16 + name_length > length or (payloads[:, field] != payloads[0, field]).any():
        return None
    try:  # CDR strings end with a NUL that ROS 1 strings do not have
        return payloads[0, 16:16 + name_length].tobytes().rstrip(b"\0").decode("utf-8")
    except UnicodeDecodeError:
        return None


def decode_wrench_batch(payloads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, L) uint8 WrenchStamped payloads of equal length -> header stamps (N,) ns, (N, 6) wrench."""
    return decode_stamped_batch(payloads, 6)


def decode_pose_batch(payloads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, L) uint8 PoseStamped payloads of equal length -> stamps (N,) ns, (N, 7) x y z qx qy qz qw."""
    return decode_stamped_batch(payloads, 7)
