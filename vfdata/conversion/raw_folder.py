"""Raw recording folder -> recording MCAP (layout v1). The folder layout is in docs/raw_layout.md.

Everything is validated before and while writing; any problem raises InputError naming the file,
and the atomic writer leaves no output behind. Images are decoded and JPEG/PNG-encoded on a thread
pool (OpenCV releases the GIL) and written by the converters' one write loop (`write_recording`).
Colour JPEG frames are stored as they are when the output is JPEG: a second lossy encoding would only
lose detail and time."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from vfdata import __version__
from vfdata.atomic import check_output
from vfdata.calibration import StereoCalibration
from vfdata.conversion.options import MAX_DEFAULT_WORKERS, ConvertOptions, default_workers
from vfdata.conversion.raw_images import StereoSource, jpeg_colour_size
from vfdata.conversion.raw_meta import read_meta, recording_fields
from vfdata.conversion.raw_tables import read_folder_tables, read_force_csv
from vfdata.conversion.write_recording import (
    camera_infos,
    compressed_image_payload,
    encode_image,
    sensor_series,
    stereo_tf,
    write_recording,
)
from vfdata.errors import InputError
from vfdata.force_coverage import check_force_covers
from vfdata.recording import layout

# Imported from here by other modules and the tests.
__all__ = ["MAX_DEFAULT_WORKERS", "ConvertOptions", "convert_raw_folder", "default_workers", "jpeg_colour_size",
           "read_force_csv"]


def convert_raw_folder(src: str | Path, out: str | Path, overwrite: bool = False,
                       options: ConvertOptions | None = None, meta: dict | None = None) -> Path:
    """Convert a raw recording folder to a recording MCAP at `out`. Returns `out`. `meta`: metadata
    keys that replace those of the folder's meta.yaml (`vfdata convert --meta KEY=VALUE`)."""
    options = options or ConvertOptions()
    src, out = Path(src), Path(out)
    options.check_format(out)
    if not src.is_dir():
        raise InputError(src, "recording folder not found")
    check_output(out, overwrite, inputs=[src])
    calib = StereoCalibration.load(src / "calibration.yaml")
    frame_ns, force, pose = read_folder_tables(src)
    force, pose = options.on_video_clock(force, src / "force.csv"), options.on_video_clock(pose, src / "ecm_pose.csv")
    meta = {**read_meta(src / "meta.yaml"), **(meta or {})}
    source = StereoSource(src)
    if source.count != len(frame_ns):
        raise InputError(src / "frames.csv", f"{len(frame_ns)} rows but the recording has {source.count} frames")
    check_force_covers(src / "force.csv", force[0], frame_ns, options.force_gap_tolerance_ns)

    record = layout.RecordingMeta(
        **recording_fields(meta, src / "meta.yaml", src.name, (calib.width, calib.height)),
        source=str(src.resolve()),
        converter="vfdata convert (raw folder)",
        converter_version=__version__,
    )
    series = sensor_series(force, pose)
    keep_jpeg = options.keep_jpeg and options.image_format == "jpeg"

    def encode_one(image: Path | np.ndarray, name: str) -> bytes | np.ndarray:
        """One image (a file, or a decoded video frame) as the stored JPEG/PNG data."""
        if isinstance(image, Path):
            path = image
            name = path.relative_to(src).as_posix()
            if keep_jpeg and path.suffix.lower() in (".jpg", ".jpeg"):
                data = path.read_bytes()
                size = jpeg_colour_size(data)
                # A reduced decode (1/8 scale) still walks every entropy-coded block, so a
                # damaged file is caught at a fraction of the cost of a full decode.
                if size is not None and _decoded(data, cv2.IMREAD_REDUCED_COLOR_8) is not None:
                    if size != (calib.width, calib.height):
                        raise InputError(src / "calibration.yaml", f"image size {calib.width}x{calib.height} "
                                                                   f"differs from {name} ({size[0]}x{size[1]})")
                    return data
            # Read here, so that an unreadable file says so (OSError) instead of "cannot be decoded".
            image = _decoded(path.read_bytes(), cv2.IMREAD_COLOR)
            if image is None:
                raise InputError(path, "image cannot be decoded")
        else:
            path = src / name
        if image.shape[:2] != (calib.height, calib.width):
            raise InputError(src / "calibration.yaml", f"image size {calib.width}x{calib.height} differs from "
                                                       f"{name} ({image.shape[1]}x{image.shape[0]})")
        data = encode_image(image, options)
        if data is None:
            raise InputError(path, "image cannot be encoded")
        return data

    def encode(item: tuple[int, str, object, object]) -> tuple[bytes, bytes]:
        k, name, left, right = item
        stamp, fmt = int(frame_ns[k]), options.image_format
        return (compressed_image_payload(stamp, layout.LEFT_FRAME, fmt, encode_one(left, name)),
                compressed_image_payload(stamp, layout.RIGHT_FRAME, fmt, encode_one(right, name)))

    write_recording(out, overwrite, options, record, camera_infos(calib, int(frame_ns[0])),
                    stereo_tf(calib, int(frame_ns[0])), frame_ns, _numbered(source, len(frame_ns), src / "frames.csv"),
                    encode, series, src.name)
    return out


def _decoded(data: bytes, flags: int) -> np.ndarray | None:
    """cv2.imdecode, None for anything it cannot decode (it raises on an empty buffer)."""
    if not data:
        return None
    try:
        return cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error:
        return None


def _numbered(source: StereoSource, count: int, frames_csv: Path) -> Iterator[tuple[int, str, object, object]]:
    """(k, name, left, right) for the frames of `source`, which must have exactly `count` (a video's
    frame count in its header is not always right)."""
    k = -1
    for k, (name, left, right) in enumerate(source):
        if k == count:
            raise InputError(frames_csv, f"{count} rows but the video has more frames")
        yield k, name, left, right
    if k + 1 != count:
        raise InputError(frames_csv, f"{count} rows but the video has {k + 1} frames")
