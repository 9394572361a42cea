"""sensor_msgs/Image and sensor_msgs/CompressedImage data -> BGR pixels, as the bag converter needs them:
every common raw encoding (bgr8, rgb8, bgra8, rgba8, mono8/16, bayer_*8/16, yuv422) and JPEG or PNG."""

from __future__ import annotations

import cv2
import numpy as np

# sensor_msgs/Image encodings: name -> (channels, bytes per channel).
RAW_ENCODINGS: dict[str, tuple[int, int]] = {
    "bgr8": (3, 1), "rgb8": (3, 1), "bgra8": (4, 1), "rgba8": (4, 1), "mono8": (1, 1),
    "8UC1": (1, 1), "8UC3": (3, 1), "8UC4": (4, 1),
    "bgr16": (3, 2), "rgb16": (3, 2), "mono16": (1, 2), "16UC1": (1, 2),
    "bayer_rggb8": (1, 1), "bayer_bggr8": (1, 1), "bayer_gbrg8": (1, 1), "bayer_grbg8": (1, 1),
    "bayer_rggb16": (1, 2), "bayer_bggr16": (1, 2), "bayer_gbrg16": (1, 2), "bayer_grbg16": (1, 2),
    "yuv422": (2, 1), "uyvy": (2, 1), "yuv422_yuy2": (2, 1), "yuyv": (2, 1),
}
# Depth in metres (some RGB-D drivers): read by the RGB-D converter (vfdata.conversion.rgbd_bags), not as a picture.
DEPTH_ENCODINGS = ("32FC1",)
# To BGR. ROS bayer_rggb8 names the first 2x2 block, as OpenCV's RGGB-style codes do (its older
# BG-style names for the same codes describe the second row; cv_bridge uses those).
_COLOR_CODES = {
    "rgb": cv2.COLOR_RGB2BGR, "bgra": cv2.COLOR_BGRA2BGR, "rgba": cv2.COLOR_RGBA2BGR, "mono": cv2.COLOR_GRAY2BGR,
    "bayer_rggb": cv2.COLOR_BayerRGGB2BGR, "bayer_bggr": cv2.COLOR_BayerBGGR2BGR,
    "bayer_gbrg": cv2.COLOR_BayerGBRG2BGR, "bayer_grbg": cv2.COLOR_BayerGRBG2BGR,
    "uyvy": cv2.COLOR_YUV2BGR_UYVY, "yuyv": cv2.COLOR_YUV2BGR_YUY2,
}
_ENCODING_FAMILY = {
    "rgb8": "rgb", "rgb16": "rgb", "bgra8": "bgra", "8UC4": "bgra", "rgba8": "rgba",
    "mono8": "mono", "8UC1": "mono", "mono16": "mono", "16UC1": "mono",
    "yuv422": "uyvy", "uyvy": "uyvy", "yuv422_yuy2": "yuyv", "yuyv": "yuyv",
    **{f"bayer_{p}{b}": f"bayer_{p}" for p in ("rggb", "bggr", "gbrg", "grbg") for b in (8, 16)},
}


class UnsupportedImage(ValueError):
    """An image message this converter cannot turn into BGR pixels (the caller names the topic)."""


def raw_image_to_bgr(height: int, width: int, encoding: str, is_bigendian: int, step: int,
                     data: np.ndarray | bytes) -> np.ndarray:
    """sensor_msgs/Image fields -> (height, width, 3) BGR uint8. 16-bit values are scaled to 8 bits
    over their full range (v * 255 / 65535); Bayer mosaics are demosaiced (bilinear)."""
    if encoding not in RAW_ENCODINGS:
        raise UnsupportedImage(f"unsupported image encoding '{encoding}'")
    channels, depth = RAW_ENCODINGS[encoding]
    row_bytes = width * channels * depth
    buffer = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data.view(np.uint8).ravel()
    if step < row_bytes or len(buffer) < step * (height - 1) + row_bytes:
        raise UnsupportedImage(f"{encoding} image of {width}x{height} needs {row_bytes} bytes a row, "
                               f"has step {step} and {len(buffer)} bytes")
    if len(buffer) < step * height:  # the last row may lack its padding
        buffer = np.concatenate([buffer, np.zeros(step * height - len(buffer), np.uint8)])
    rows = buffer[: step * height].reshape(height, step)[:, :row_bytes]
    if depth == 2:
        pixels = np.ascontiguousarray(rows).view(">u2" if is_bigendian else "<u2").astype(np.uint16)
        pixels = ((pixels.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)
    else:
        pixels = rows
    family = _ENCODING_FAMILY.get(encoding)
    if family in ("uyvy", "yuyv"):
        image = pixels.reshape(height, width, 2)
    else:
        image = pixels.reshape(height, width, channels) if channels > 1 else pixels.reshape(height, width)
    image = np.ascontiguousarray(image)
    if family is None:  # bgr8, 8UC3, bgr16
        return image
    return cv2.cvtColor(image, _COLOR_CODES[family])


def compressed_format(fmt: str) -> str:
    """The codec of a CompressedImage `format` ('jpeg', 'png', or image_transport's 'rgb8; jpeg
    compressed bgr8') -> 'jpeg' or 'png'."""
    text = fmt.lower()
    if "compresseddepth" in text:
        raise UnsupportedImage(f"unsupported image format '{fmt}' (compressedDepth is a depth image)")
    if "jpeg" in text or "jpg" in text:
        return "jpeg"
    if "png" in text:
        return "png"
    raise UnsupportedImage(f"unsupported image format '{fmt}' (expected jpeg or png)")


def compressed_to_bgr(fmt: str, data: np.ndarray | bytes) -> np.ndarray:
    """CompressedImage data -> BGR uint8 (image_transport compresses colour images as bgr8)."""
    compressed_format(fmt)
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise UnsupportedImage(f"{fmt} image data cannot be decoded")
    return image
