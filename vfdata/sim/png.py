"""A lossless 16-bit greyscale PNG encoder for the ground-truth depth maps.

OpenCV's PNG writer spends about as much CPU time outside zlib as in it on a 640x512 16-bit image
(about 6 ms even with compression off). Here the SUB filter is one numpy subtraction and zlib runs
once on the whole filtered image: the same file format (and the same compressed size) in about half
the time. The output is a standard PNG (signature, IHDR, one IDAT, IEND), deterministic for a given
zlib version.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_FILTER_SUB = 1


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(data, zlib.crc32(kind)))


def encode_png16(image: np.ndarray, level: int = 1) -> bytes:
    """PNG bytes of a (H, W) uint16 image: greyscale, 16 bits, every row SUB-filtered (each byte minus
    the same byte of the pixel to its left), zlib `level` (1: fastest)."""
    if image.dtype != np.uint16 or image.ndim != 2:
        raise ValueError(f"encode_png16 takes a (H, W) uint16 image, not {image.dtype} {image.shape}")
    h, w = image.shape
    raw = image.astype(">u2").view(np.uint8).reshape(h, 2 * w)  # PNG stores 16-bit samples big-endian
    rows = np.empty((h, 2 * w + 1), np.uint8)
    rows[:, 0] = _FILTER_SUB
    rows[:, 1:3] = raw[:, :2]
    np.subtract(raw[:, 2:], raw[:, :-2], out=rows[:, 3:])  # modulo 256, as the filter is defined
    header = struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0)  # bit depth 16, greyscale, no interlace
    return (_SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(rows, level))
            + _chunk(b"IEND", b""))
