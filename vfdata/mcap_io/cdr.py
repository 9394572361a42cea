"""Little-endian plain CDR (XCDR1), the ROS 2 wire format.

Payloads start with the 4-byte encapsulation header 00 01 00 00 (CDR_LE); primitives are aligned
to their size counted from the end of that header; strings are a uint32 length that counts the
terminating NUL, then the bytes and the NUL; sequences are a uint32 count then the elements."""

from __future__ import annotations

import struct

import numpy as np

ENCAPSULATION_LE = b"\x00\x01\x00\x00"
_HEADER = 4

_U8 = struct.Struct("<B")
_U32 = struct.Struct("<I")
_I32 = struct.Struct("<i")
_F64 = struct.Struct("<d")


class CdrError(ValueError):
    """A payload that is not valid little-endian CDR for the expected type."""


class CdrWriter:
    def __init__(self) -> None:
        self.buf = bytearray(ENCAPSULATION_LE)

    def _align(self, size: int) -> None:
        pad = (-(len(self.buf) - _HEADER)) % size
        if pad:
            self.buf += b"\x00" * pad

    def uint8(self, value: int) -> None:
        self.buf += _U8.pack(value)

    def bool(self, value: bool) -> None:
        self.buf += b"\x01" if value else b"\x00"

    def uint32(self, value: int) -> None:
        self._align(4)
        self.buf += _U32.pack(value)

    def int32(self, value: int) -> None:
        self._align(4)
        self.buf += _I32.pack(value)

    def float64(self, value: float) -> None:
        self._align(8)
        self.buf += _F64.pack(value)

    def float64s(self, values, sequence: bool) -> None:
        """A fixed-size array (sequence=False) or a sequence (with its count) of float64."""
        array = np.ascontiguousarray(values, dtype="<f8").ravel()
        if sequence:
            self.uint32(len(array))
        if len(array):
            self._align(8)
            self.buf += array.tobytes()

    def string(self, value: str) -> None:
        data = value.encode("utf-8")
        self.uint32(len(data) + 1)
        self.buf += data + b"\x00"

    def bytes_sequence(self, data: bytes | bytearray | memoryview) -> None:
        self.uint32(len(data))
        self.buf += data

    def getvalue(self) -> bytes:
        return bytes(self.buf)


class CdrReader:
    def __init__(self, data: bytes | memoryview) -> None:
        if len(data) < _HEADER or bytes(data[:2]) != b"\x00\x01":
            raise CdrError("not a little-endian CDR payload (encapsulation header is not 00 01)")
        self.data = memoryview(data)
        self.pos = _HEADER

    def _align(self, size: int) -> None:
        self.pos += (-(self.pos - _HEADER)) % size

    def _take(self, size: int) -> memoryview:
        end = self.pos + size
        if end > len(self.data):
            raise CdrError(f"payload truncated: needs {end} bytes, has {len(self.data)}")
        view = self.data[self.pos:end]
        self.pos = end
        return view

    def uint8(self) -> int:
        return self._take(1)[0]

    def bool(self) -> bool:
        return self._take(1)[0] != 0

    def uint32(self) -> int:
        self._align(4)
        return _U32.unpack(self._take(4))[0]

    def int32(self) -> int:
        self._align(4)
        return _I32.unpack(self._take(4))[0]

    def float64(self) -> float:
        self._align(8)
        return _F64.unpack(self._take(8))[0]

    def float64s(self, count: int | None = None) -> np.ndarray:
        """A fixed-size array of `count` float64, or a sequence when count is None."""
        if count is None:
            count = self.uint32()
        if count == 0:
            return np.zeros(0)
        self._align(8)
        return np.frombuffer(self._take(8 * count), dtype="<f8").astype(np.float64)

    def string(self) -> str:
        length = self.uint32()
        raw = self._take(length)
        return bytes(raw[:-1]).decode("utf-8") if length else ""

    def bytes_sequence(self) -> bytes:
        return bytes(self._take(self.uint32()))
