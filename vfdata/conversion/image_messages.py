"""The fields of a serialised sensor_msgs Image or CompressedImage (ROS 1, or little-endian CDR for
ROS 2), read straight from its bytes instead of through a general deserialiser: the stamp, encoding
and size from the first bytes (what the bag scan needs of every image), and the pixel or compressed
data as a view into the message (what the encoding threads need)."""

from __future__ import annotations

import struct
from dataclasses import dataclass

from vfdata.conversion.bag_topics import COMPRESSED_IMAGE
from vfdata.recording.messages import NS_PER_S

_U32 = struct.Struct("<I")
_I32 = struct.Struct("<i")


@dataclass(frozen=True)
class ImageHead:
    """What the scan needs of an image message: stamp (header.stamp, ns), the Image encoding or the
    CompressedImage format, and the size (0 x 0 for compressed images: known only once decoded)."""

    stamp_ns: int
    encoding: str
    width: int = 0
    height: int = 0


class _Cursor:
    """Reads the leading fields of a ROS 1 (plain little-endian) or CDR (aligned, strings counting their
    NUL) message from its first bytes; IndexError when they run out."""

    def __init__(self, buf: bytes | memoryview, cdr: bool):
        self.buf, self.cdr, self.pos = buf, cdr, 4 if cdr else 0

    def u32(self) -> int:
        if self.cdr:
            self.pos += (-(self.pos - 4)) % 4
        if self.pos + 4 > len(self.buf):
            raise IndexError("message too short")
        value = _U32.unpack_from(self.buf, self.pos)[0]
        self.pos += 4
        return value

    def i32(self) -> int:
        value = self.u32()
        return _I32.unpack(_U32.pack(value))[0]

    def u8(self) -> int:
        if self.pos >= len(self.buf):
            raise IndexError("message too short")
        self.pos += 1
        return self.buf[self.pos - 1]

    def string(self) -> str:
        length = self.u32()
        if self.pos + length > len(self.buf):
            raise IndexError("message too short")
        data = bytes(self.buf[self.pos:self.pos + length])
        self.pos += length
        return (data[:-1] if self.cdr and data.endswith(b"\0") else data).decode("utf-8")


@dataclass(frozen=True)
class ImageMessage:
    """A whole Image or CompressedImage message: its head, the pixel (or compressed) data as a view
    into the serialised message, and for an Image its byte order and row length."""

    head: ImageHead
    data: memoryview
    is_bigendian: int = 0
    step: int = 0


def image_head(buf: bytes | memoryview, msgtype: str, ros2: bool) -> ImageHead | None:
    """The leading fields of a serialised sensor_msgs Image or CompressedImage (ROS 1, or little-endian
    CDR for ROS 2) from its first bytes. None when they are not all in `buf`, the CDR payload is
    big-endian, or a string is not UTF-8: the caller then deserialises the whole message."""
    return _read_image(buf, msgtype, ros2, whole=False)


def image_message(buf: bytes | memoryview, msgtype: str, ros2: bool) -> ImageMessage | None:
    """A whole serialised Image or CompressedImage, parsed without copying its data (what the encoding
    threads need, cheaper than a general deserialiser); None as for `image_head`, or when the data
    length runs past the message."""
    return _read_image(buf, msgtype, ros2, whole=True)


def _read_image(buf: bytes | memoryview, msgtype: str, ros2: bool, whole: bool):
    if ros2 and (len(buf) < 4 or buf[1] != 1):
        return None
    r = _Cursor(buf, cdr=ros2)
    try:
        if ros2:
            sec = r.i32()
        else:
            r.u32()  # seq
            sec = r.u32()
        stamp = sec * NS_PER_S + r.u32()
        r.string()  # frame_id
        if msgtype == COMPRESSED_IMAGE:
            head, layout = ImageHead(stamp, r.string()), {}
        else:
            height, width = r.u32(), r.u32()
            head = ImageHead(stamp, r.string(), width, height)
            if whole:
                layout = {"is_bigendian": r.u8(), "step": r.u32()}
        if not whole:
            return head
        length = r.u32()
    except (IndexError, UnicodeDecodeError):
        return None
    if r.pos + length > len(buf):
        return None
    return ImageMessage(head, memoryview(buf)[r.pos:r.pos + length], **layout)
