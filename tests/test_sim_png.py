"""The 16-bit PNG writer of the ground-truth depth: standard PNG that decoders read back exactly."""

import zlib

import cv2
import numpy as np
import pytest

from vfdata.sim.png import encode_png16


@pytest.mark.parametrize("shape", [(512, 640), (3, 7), (1, 1)])
def test_round_trip_through_opencv(shape):
    rng = np.random.default_rng(0)
    img = rng.integers(0, 65536, shape, dtype=np.uint16)
    img.flat[0], img.flat[-1] = 0, 65535
    data = encode_png16(img)
    back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.uint16 and back.shape == shape
    assert np.array_equal(back, img)


def test_smooth_depth_compresses_and_chunks_are_valid():
    yy, xx = np.mgrid[:512, :640]
    depth = (900 + 0.5 * yy + 0.2 * xx).astype(np.uint16)
    data = encode_png16(depth)
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(data) < depth.nbytes / 10
    pos, kinds = 8, []
    while pos < len(data):
        n = int.from_bytes(data[pos:pos + 4], "big")
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + n]
        assert int.from_bytes(data[pos + 8 + n:pos + 12 + n], "big") == zlib.crc32(kind + body)
        kinds.append(kind)
        pos += 12 + n
    assert kinds == [b"IHDR", b"IDAT", b"IEND"]
    assert encode_png16(depth) == data  # deterministic


def test_rejects_other_images():
    with pytest.raises(ValueError):
        encode_png16(np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError):
        encode_png16(np.zeros((4, 4, 3), np.uint16))
