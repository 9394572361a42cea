"""RGB-D raw recording folder -> recording MCAP with the RGB-D topics (docs/raw_layout.md, "RGB-D
recordings"; docs/format.md). The same guarantees as the stereo folder (`raw_folder`): everything is
checked before or while writing, any problem is one InputError naming the file, and the atomic
writer leaves nothing behind.

    recording/  depth/000000.png ...  16-bit PNG, depth_unit_mm per count (default 1 mm), 0 = none
                color/000000.png ...  optional colour frames, as many as depth frames
                frames.csv, force.csv, ecm_pose.csv (optional), rgbd_calibration.yaml, meta.yaml (optional)

The depth frames are stored as sensor_msgs/Image 16UC1 in millimetres (lossless), the colour frames as
CompressedImage (JPEG or PNG, as for stereo)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from vfdata import __version__
from vfdata.atomic import check_output
from vfdata.conversion.options import ConvertOptions
from vfdata.conversion.raw_images import IMAGE_SUFFIXES
from vfdata.conversion.raw_meta import read_meta, recording_fields
from vfdata.conversion.raw_tables import read_folder_tables
from vfdata.conversion.rgbd_calibration import CALIBRATION_FILE, RgbdCalibration, camera_info, depth_to_color_tf
from vfdata.conversion.write_recording import (
    View,
    compressed_image_payload,
    encode_image,
    sensor_series,
    write_recording,
)
from vfdata.errors import InputError
from vfdata.force_coverage import check_force_covers
from vfdata.recording import layout
from vfdata.recording.messages import CompressedImage, Image

DEPTH_VIEW = View(layout.DEPTH_IMAGE, Image.msgtype, layout.DEPTH_INFO)
COLOR_VIEW = View(layout.COLOR_IMAGE, CompressedImage.msgtype, layout.COLOR_INFO)


def is_rgbd_folder(src: Path) -> bool:
    """A raw folder with a depth/ view and no stereo pair."""
    return (src / "depth").is_dir() and not (src / "left").is_dir() and not (src / "right").is_dir()


def _images(folder: Path) -> list[Path]:
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise InputError(folder, "no image files")
    return files


def depth_mm_image(path: Path, camera_size: tuple[int, int], unit_mm: float, calibration: Path) -> np.ndarray:
    """A depth PNG (16-bit, `unit_mm` per count, 0 = none) as uint16 millimetres; an InputError for
    anything else (8-bit, colour, a size other than the depth camera's)."""
    data = cv2.imdecode(np.frombuffer(path.read_bytes(), np.uint8), cv2.IMREAD_UNCHANGED) if path.stat().st_size \
        else None
    if data is None:
        raise InputError(path, "image cannot be decoded")
    if data.ndim != 2 or data.dtype != np.uint16:
        raise InputError(path, f"a depth image must be 16-bit single-channel, not {data.dtype} with "
                               f"{1 if data.ndim == 2 else data.shape[2]} channel(s)")
    if (data.shape[1], data.shape[0]) != camera_size:
        raise InputError(calibration, f"depth size {camera_size[0]}x{camera_size[1]} differs from "
                                      f"{path.parent.name}/{path.name} ({data.shape[1]}x{data.shape[0]})")
    if unit_mm != 1.0:
        data = np.clip(np.rint(data * unit_mm), 0, 65535).astype(np.uint16)
    return data


def convert_rgbd_folder(src: str | Path, out: str | Path, overwrite: bool = False,
                        options: ConvertOptions | None = None, calibration: str | Path | None = None,
                        meta: str | Path | None = None) -> Path:
    """Convert an RGB-D raw folder to a recording MCAP at `out`. `calibration` and `meta` name the
    calibration and meta files when they are not in the folder (a published data set is kept as it
    is). Returns `out`."""
    options = options or ConvertOptions()
    src, out = Path(src), Path(out)
    options.check_format(out)
    if not src.is_dir():
        raise InputError(src, "recording folder not found")
    calib_path = Path(calibration) if calibration is not None else src / CALIBRATION_FILE
    meta_path = Path(meta) if meta is not None else src / "meta.yaml"
    if meta is not None and not meta_path.is_file():
        raise InputError(meta_path, "meta file not found")
    check_output(out, overwrite, inputs=[src, calib_path, meta_path])
    calib = RgbdCalibration.load(calib_path)
    frame_ns, force, pose = read_folder_tables(src)
    force, pose = options.on_video_clock(force, src / "force.csv"), options.on_video_clock(pose, src / "ecm_pose.csv")
    meta_values = read_meta(meta_path)
    depth_files = _images(src / "depth")
    color_files = _images(src / "color") if (src / "color").is_dir() else None
    if color_files is not None and len(color_files) != len(depth_files):
        raise InputError(src / "color", f"{len(color_files)} frames but depth/ has {len(depth_files)}")
    if color_files is not None and calib.color is None:
        raise InputError(calib_path, "the folder has color/ frames: give the 'color' camera too")
    if len(depth_files) != len(frame_ns):
        raise InputError(src / "frames.csv", f"{len(frame_ns)} rows but the recording has {len(depth_files)} frames")
    check_force_covers(src / "force.csv", force[0], frame_ns, options.force_gap_tolerance_ns)

    depth_cam = calib.depth
    extra = {"camera": "rgbd", "depth_color_registered": str(calib.registered).lower(),
             **{f"calibration_{k}": v for k, v in calib.notes.items()}}
    fields = recording_fields(meta_values, meta_path, src.name, (depth_cam.width, depth_cam.height))
    fields["extra"] = {**extra, **fields["extra"]}
    record = layout.RecordingMeta(**fields, source=str(src.resolve()), converter="vfdata convert (RGB-D raw folder)",
                                  converter_version=__version__, units=dict(layout.RGBD_UNITS))
    series = sensor_series(force, pose)
    first = int(frame_ns[0])
    views, infos = [DEPTH_VIEW], [camera_info(depth_cam, layout.DEPTH_FRAME, first)]
    if color_files is not None:
        views.append(COLOR_VIEW)
        infos.append(camera_info(calib.color, layout.COLOR_FRAME, first))

    def encode(k: int) -> tuple[bytes, ...]:
        stamp = int(frame_ns[k])
        depth = depth_mm_image(depth_files[k], (depth_cam.width, depth_cam.height), calib.depth_unit_mm, calib_path)
        h, w = depth.shape
        payloads = [Image(stamp, layout.DEPTH_FRAME, h, w, "16UC1", 0, 2 * w, depth.astype("<u2").tobytes()).encode()]
        if color_files is not None:
            path = color_files[k]
            image = cv2.imdecode(np.frombuffer(path.read_bytes(), np.uint8), cv2.IMREAD_COLOR) \
                if path.stat().st_size else None
            if image is None:
                raise InputError(path, "image cannot be decoded")
            if (image.shape[1], image.shape[0]) != (calib.color.width, calib.color.height):
                raise InputError(calib_path, f"color size {calib.color.width}x{calib.color.height} differs from "
                                             f"color/{path.name} ({image.shape[1]}x{image.shape[0]})")
            data = encode_image(image, options)
            if data is None:
                raise InputError(path, "image cannot be encoded")
            payloads.append(compressed_image_payload(stamp, layout.COLOR_FRAME, options.image_format, data))
        return tuple(payloads)

    write_recording(out, overwrite, options, record, tuple(infos),
                    depth_to_color_tf(calib, layout.DEPTH_FRAME, layout.COLOR_FRAME, first), frame_ns,
                    range(len(frame_ns)), encode, series, src.name, views=tuple(views))
    return out
