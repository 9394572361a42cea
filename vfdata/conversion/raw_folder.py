"""Raw recording folder -> recording MCAP (layout v1). The folder layout is in docs/raw_layout.md.

Everything is validated before and while writing; any problem raises InputError naming the file,
and the atomic writer leaves no output behind. Images are decoded and JPEG/PNG-encoded on a thread
pool (OpenCV releases the GIL), written in frame order with the force and pose samples interleaved
by stamp. Colour JPEG frames are stored as they are when the output is JPEG: a second lossy encoding
would only lose detail and time."""

from __future__ import annotations

import csv
import os
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml
from tqdm import tqdm

from vfdata import __version__
from vfdata.calibration import StereoCalibration
from vfdata.conversion.ordered_map import ordered_map
from vfdata.errors import InputError
from vfdata.recording import layout
from vfdata.recording.messages import (
    CameraInfo,
    CompressedImage,
    PoseStamped,
    TFMessage,
    TransformStamped,
    WrenchStamped,
)
from vfdata.recording.reader import FORCE_GAP_TOLERANCE_NS
from vfdata.recording.writer import CHUNK_SIZE, IMAGE_LEVEL, McapWriter

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm")
ROSTOPIC_WRENCH_COLUMNS = [
    "field.header.stamp", "field.wrench.force.x", "field.wrench.force.y", "field.wrench.force.z",
    "field.wrench.torque.x", "field.wrench.torque.y", "field.wrench.torque.z",
]


MAX_DEFAULT_WORKERS = 8


def default_workers() -> int:
    """Image encoding threads when none are asked for: one per CPU core this process may use, at most
    MAX_DEFAULT_WORKERS. On the development machine a thread JPEG-encodes about 370 stereo frames/s
    and the main thread, which reads the input and writes the MCAP, keeps up with 1,300-2,000 a
    second, so more threads would only wait for it."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return max(1, min(cores, MAX_DEFAULT_WORKERS))


@dataclass(frozen=True)
class ConvertOptions:
    image_format: str = "jpeg"  # "jpeg" or "png"
    jpeg_quality: int = 95
    force_gap_tolerance_ns: int = FORCE_GAP_TOLERANCE_NS
    workers: int = field(default_factory=default_workers)
    progress: bool = True
    chunk_size: int = CHUNK_SIZE  # bytes of messages per MCAP chunk
    keep_jpeg: bool = True  # store colour JPEG input frames byte for byte (jpeg output only)


# -- tables ---------------------------------------------------------------------------------------
def read_frames_csv(path: Path) -> np.ndarray:
    """frames.csv (`frame,timestamp_ns`) -> (N,) int64 stamps, strictly increasing."""
    rows = _read_csv(path, ["frame", "timestamp_ns"])
    stamps = _int_column(path, rows, "timestamp_ns")
    frames = _int_column(path, rows, "frame")
    if len(stamps) == 0:
        raise InputError(path, "no rows")
    if not np.array_equal(frames, np.arange(len(frames))):
        bad = int(np.nonzero(frames != np.arange(len(frames)))[0][0])
        raise InputError(path, f"line {bad + 2}: frame numbers must run 0, 1, 2, ... (found {frames[bad]})")
    _check_increasing(path, stamps)
    return stamps


def read_force_csv(path: Path) -> tuple[np.ndarray, np.ndarray, str]:
    """force.csv, ours (`timestamp_ns,fx,fy,fz,tx,ty,tz`) or a `rostopic echo -p` WrenchStamped export
    (acquisition time = field.header.stamp) -> stamps (N,) int64, wrench (N, 6), frame_id."""
    with open(path, newline="") as handle:
        header = next(csv.reader(handle), None)
    if header is None:
        raise InputError(path, "file is empty")
    if "field.header.stamp" in header:
        rows = _read_csv(path, ROSTOPIC_WRENCH_COLUMNS)
        stamps = _int_column(path, rows, "field.header.stamp")
        wrench = _float_columns(path, rows, ROSTOPIC_WRENCH_COLUMNS[1:])
        frame_ids = {r.get("field.header.frame_id", "") for r in rows}
        frame_id = frame_ids.pop() if len(frame_ids) == 1 else layout.SENSOR_FRAME
    else:
        columns = ["fx", "fy", "fz", "tx", "ty", "tz"]
        rows = _read_csv(path, ["timestamp_ns", *columns])
        stamps = _int_column(path, rows, "timestamp_ns")
        wrench = _float_columns(path, rows, columns)
        frame_id = layout.SENSOR_FRAME
    if len(stamps) == 0:
        raise InputError(path, "no force samples")
    _check_finite(path, wrench)
    _check_increasing(path, stamps)
    return stamps, wrench, frame_id or layout.SENSOR_FRAME


def read_pose_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """ecm_pose.csv (`timestamp_ns,x,y,z,qx,qy,qz,qw`, metres) -> stamps, (N, 7) with unit quaternions."""
    columns = ["x", "y", "z", "qx", "qy", "qz", "qw"]
    rows = _read_csv(path, ["timestamp_ns", *columns])
    stamps = _int_column(path, rows, "timestamp_ns")
    values = _float_columns(path, rows, columns)
    if len(stamps) == 0:
        raise InputError(path, "no poses")
    _check_finite(path, values)
    _check_increasing(path, stamps)
    norms = np.linalg.norm(values[:, 3:], axis=1)
    if (norms < 1e-6).any():
        raise InputError(path, f"line {int(np.argmax(norms < 1e-6)) + 2}: quaternion has zero length")
    values[:, 3:] /= norms[:, None]
    return stamps, values


def _read_csv(path: Path, required: list[str]) -> list[dict[str, str]]:
    if not path.is_file():
        raise InputError(path, "file not found")
    with open(path, newline="") as handle:
        reader = csv.DictReader(handle)
        missing = [c for c in required if c not in (reader.fieldnames or [])]
        if missing:
            raise InputError(path, f"missing column(s) {', '.join(missing)}")
        return list(reader)


def _int_column(path: Path, rows: list[dict[str, str]], column: str) -> np.ndarray:
    try:
        return np.array([int(r[column]) for r in rows], dtype=np.int64)
    except (TypeError, ValueError):
        bad = next(i for i, r in enumerate(rows) if not str(r[column]).strip().lstrip("-").isdigit())
        raise InputError(path, f"line {bad + 2}: {column} '{rows[bad][column]}' is not an integer") from None


def _float_columns(path: Path, rows: list[dict[str, str]], columns: list[str]) -> np.ndarray:
    try:
        return np.array([[float(r[c]) for c in columns] for r in rows], dtype=np.float64).reshape(-1, len(columns))
    except (TypeError, ValueError):
        for i, r in enumerate(rows):
            for c in columns:
                try:
                    float(r[c])
                except (TypeError, ValueError):
                    raise InputError(path, f"line {i + 2}: {c} '{r[c]}' is not a number") from None
        raise


def _check_finite(path: Path, values: np.ndarray) -> None:
    bad = ~np.isfinite(values).all(axis=1)
    if bad.any():
        raise InputError(path, f"line {int(np.argmax(bad)) + 2}: NaN or inf value")


def _check_increasing(path: Path, stamps: np.ndarray) -> None:
    steps = np.diff(stamps)
    if (steps <= 0).any():
        i = int(np.argmax(steps <= 0))
        what = "repeats" if steps[i] == 0 else "goes backwards"
        raise InputError(path, f"line {i + 3}: timestamp {stamps[i + 1]} {what} (previous {stamps[i]})")


def check_force_covers(path: Path, force_ns: np.ndarray, frame_ns: np.ndarray, tolerance_ns: int) -> None:
    """The force stream must cover the video span with no gap longer than `tolerance_ns`."""
    first, last = int(frame_ns[0]), int(frame_ns[-1])
    if force_ns[0] > first + tolerance_ns:
        raise InputError(path, f"force starts {(force_ns[0] - first) / 1e6:.1f} ms after the first frame")
    if force_ns[-1] < last - tolerance_ns:
        raise InputError(path, f"force ends {(last - force_ns[-1]) / 1e6:.1f} ms before the last frame")
    lo = max(int(np.searchsorted(force_ns, first)) - 1, 0)
    hi = min(int(np.searchsorted(force_ns, last)) + 1, len(force_ns))
    gaps = np.diff(force_ns[lo:hi])
    if len(gaps) and gaps.max() > tolerance_ns:
        i = lo + int(np.argmax(gaps))
        raise InputError(
            path, f"gap of {gaps.max() / 1e6:.1f} ms in the force stream after {force_ns[i]} ns "
            f"(tolerance {tolerance_ns / 1e6:.0f} ms)",
        )


# -- image sources ----------------------------------------------------------------------------------
class StereoSource:
    """Yields (left, right) BGR frames with a name for error messages, from folders or videos."""

    def __init__(self, folder: Path):
        self.folder = folder
        left_dir, right_dir = folder / "left", folder / "right"
        self.kind = None
        if left_dir.is_dir() or right_dir.is_dir():
            for d in (left_dir, right_dir):
                if not d.is_dir():
                    raise InputError(d, "folder not found (left/ and right/ must both exist)")
            self.left_files = sorted(p for p in left_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            self.right_files = sorted(p for p in right_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not self.left_files:
                raise InputError(left_dir, "no image files")
            if len(self.left_files) != len(self.right_files):
                raise InputError(
                    right_dir, f"{len(self.right_files)} frames but left/ has {len(self.left_files)}"
                )
            self.kind = "folders"
            self.count = len(self.left_files)
            return
        left_video = _find_video(folder, "left")
        right_video = _find_video(folder, "right")
        stereo_video = _find_video(folder, "stereo")
        if left_video or right_video:
            for name, video in (("left", left_video), ("right", right_video)):
                if video is None:
                    raise InputError(folder / f"{name}.mp4", "video not found (left and right videos must both exist)")
            self.kind = "videos"
            self.left_video, self.right_video = left_video, right_video
            left_n, right_n = _video_frame_count(left_video), _video_frame_count(right_video)
            if left_n != right_n:
                raise InputError(right_video, f"{right_n} frames but {left_video.name} has {left_n}")
            self.count = left_n
            return
        if stereo_video:
            self.kind = "side_by_side"
            self.stereo_video = stereo_video
            self.count = _video_frame_count(stereo_video)
            return
        raise InputError(folder, "no images: expected left/ and right/ folders, left.mp4 and right.mp4, or stereo.mp4")

    def __iter__(self) -> Iterator[tuple[str, object, object]]:
        """(name, left, right): for folders the items are file paths (decoded by the workers), for
        videos decoded arrays."""
        if self.kind == "folders":
            for left, right in zip(self.left_files, self.right_files, strict=True):
                yield f"{left.parent.name}/{left.name}", left, right
        elif self.kind == "videos":
            yield from _iter_video_pair(self.left_video, self.right_video)
        else:
            yield from _iter_side_by_side(self.stereo_video)


def _find_video(folder: Path, stem: str) -> Path | None:
    for suffix in VIDEO_SUFFIXES:
        path = folder / f"{stem}{suffix}"
        if path.is_file():
            return path
    return None


def _open_video(path: Path) -> cv2.VideoCapture:
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise InputError(path, "video cannot be opened")
    return capture


def _video_frame_count(path: Path) -> int:
    capture = _open_video(path)
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    capture.release()
    return count


def _iter_video_pair(left_path: Path, right_path: Path):
    left, right = _open_video(left_path), _open_video(right_path)
    try:
        i = 0
        while True:
            ok_l, frame_l = left.read()
            ok_r, frame_r = right.read()
            if not ok_l and not ok_r:
                return
            if ok_l != ok_r:
                short = right_path if ok_l else left_path
                raise InputError(short, f"ends at frame {i} before the other video")
            yield f"frame {i}", frame_l, frame_r
            i += 1
    finally:
        left.release()
        right.release()


def _iter_side_by_side(path: Path):
    capture = _open_video(path)
    try:
        i = 0
        while True:
            ok, frame = capture.read()
            if not ok:
                return
            if frame.shape[1] % 2:
                raise InputError(path, f"frame {i}: side-by-side width {frame.shape[1]} is odd")
            half = frame.shape[1] // 2
            yield f"frame {i}", frame[:, :half], frame[:, half:]
            i += 1
    finally:
        capture.release()


# -- conversion -------------------------------------------------------------------------------------
def camera_infos(calib: StereoCalibration, stamp_ns: int) -> tuple[CameraInfo, CameraInfo]:
    """ROS CameraInfo of both views: raw K and D, rectifying R, rectified P (right P[0,3] = -fx*B, m)."""
    rect = calib.rectified
    p2 = rect.P2.copy()
    p2[0, 3] *= 1e-3  # ROS: metres
    infos = []
    for frame, K, D, R, P in (
        (layout.LEFT_FRAME, calib.K1, calib.D1, rect.R1, rect.P1),
        (layout.RIGHT_FRAME, calib.K2, calib.D2, rect.R2, p2),
    ):
        model = "plumb_bob" if len(D) <= 5 else "rational_polynomial"
        d = np.zeros(5 if len(D) <= 5 else 8)
        d[: len(D)] = D
        infos.append(CameraInfo(stamp_ns, frame, calib.height, calib.width, model, d, K, R, P))
    return infos[0], infos[1]


def stereo_tf(calib: StereoCalibration, stamp_ns: int) -> TFMessage:
    """left -> right optical frame of the rectified pair: the right camera sits `baseline` along +x."""
    baseline_m = calib.rectified.baseline_mm * 1e-3
    return TFMessage([
        TransformStamped(stamp_ns, layout.LEFT_FRAME, layout.RIGHT_FRAME, (baseline_m, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    ])


def read_meta(path: Path) -> dict:
    if not path.is_file():
        return {}
    try:
        meta = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise InputError(path, f"not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(meta, dict):
        raise InputError(path, "must be a mapping of keys to values")
    return meta


def convert_raw_folder(src: str | Path, out: str | Path, overwrite: bool = False,
                       options: ConvertOptions | None = None) -> Path:
    """Convert a raw recording folder to a recording MCAP at `out`. Returns `out`."""
    options = options or ConvertOptions()
    src, out = Path(src), Path(out)
    if options.image_format not in ("jpeg", "png"):
        raise InputError(out, f"image format must be jpeg or png, not {options.image_format}")
    if not src.is_dir():
        raise InputError(src, "recording folder not found")
    calib = StereoCalibration.load(src / "calibration.yaml")
    frame_ns = read_frames_csv(src / "frames.csv")
    force_path = src / "force.csv"
    force_ns, wrench, force_frame = read_force_csv(force_path)
    pose_path = src / "ecm_pose.csv"
    pose = read_pose_csv(pose_path) if pose_path.exists() else None
    meta = read_meta(src / "meta.yaml")
    source = StereoSource(src)
    if source.count != len(frame_ns):
        raise InputError(src / "frames.csv", f"{len(frame_ns)} rows but the recording has {source.count} frames")
    check_force_covers(force_path, force_ns, frame_ns, options.force_gap_tolerance_ns)

    record = layout.RecordingMeta(
        recording_id=str(meta.get("id", src.name)),
        study=str(meta.get("study", "")),
        tissue=str(meta.get("tissue", "")),
        orientation_deg=float(meta.get("orientation_deg", 0.0) or 0.0),
        split=str(meta.get("split", "")),
        source=str(src.resolve()),
        converter="vfdata convert (raw folder)",
        converter_version=__version__,
        gravity_up_world=tuple(float(v) for v in meta.get("gravity_up_world", (0.0, 0.0, 1.0))),
        extra={k: _meta_text(v) for k, v in meta.items() if k not in {
            "id", "study", "tissue", "orientation_deg", "split", "gravity_up_world"}},
    )
    encode_params = (
        [cv2.IMWRITE_JPEG_QUALITY, options.jpeg_quality] if options.image_format == "jpeg"
        else [cv2.IMWRITE_PNG_COMPRESSION, 1]
    )
    extension = ".jpg" if options.image_format == "jpeg" else ".png"

    keep_jpeg = options.keep_jpeg and options.image_format == "jpeg"

    def encode(item) -> tuple[bytes, bytes]:
        name, left, right = item
        pair = []
        for image in (left, right):
            if isinstance(image, Path):
                path = image
                name = path.relative_to(src).as_posix()
                if keep_jpeg and path.suffix.lower() in (".jpg", ".jpeg"):
                    data = path.read_bytes()
                    size = jpeg_colour_size(data)
                    # A reduced decode (1/8 scale) still walks every entropy-coded block, so a
                    # damaged file is caught at a fraction of the cost of a full decode.
                    if size is not None and cv2.imdecode(np.frombuffer(data, np.uint8),
                                                         cv2.IMREAD_REDUCED_COLOR_8) is not None:
                        if size != (calib.width, calib.height):
                            raise InputError(
                                src / "calibration.yaml",
                                f"image size {calib.width}x{calib.height} differs from {name} ({size[0]}x{size[1]})",
                            )
                        pair.append(data)
                        continue
                image = cv2.imread(str(path), cv2.IMREAD_COLOR)
                if image is None:
                    raise InputError(path, "image cannot be decoded")
            else:
                path = src / name
            if image.shape[:2] != (calib.height, calib.width):
                raise InputError(
                    src / "calibration.yaml",
                    f"image size {calib.width}x{calib.height} differs from {name} ({image.shape[1]}x{image.shape[0]})",
                )
            ok, data = cv2.imencode(extension, image, encode_params)
            if not ok:
                raise InputError(path, "image cannot be encoded")
            pair.append(data.tobytes())
        return pair[0], pair[1]

    force_i = 0
    pose_i = 0
    info_l, info_r = camera_infos(calib, int(frame_ns[0]))
    with McapWriter(out, overwrite=overwrite, chunk_size=options.chunk_size,
                     separate_topics=(layout.WRENCH, layout.ECM_POSE),
                     chunk_level=IMAGE_LEVEL) as writer:
        writer.add_metadata(layout.RECORDING_METADATA, record.to_record())
        writer.write(layout.TF_STATIC, stereo_tf(calib, int(frame_ns[0])))
        with ThreadPoolExecutor(max(1, options.workers)) as pool:
            i = -1
            encoded = ordered_map(pool, encode, iter(source), window=4 * max(1, options.workers))
            bar = tqdm(total=len(frame_ns), desc=f"convert {src.name}", unit="frame", disable=not options.progress)
            for i, (left_bytes, right_bytes) in enumerate(encoded):
                stamp = int(frame_ns[i])
                # Samples up to this frame's stamp go first, so the file is in time order.
                end = int(np.searchsorted(force_ns, stamp, side="right"))
                _write_force(writer, force_ns, wrench, force_frame, force_i, end)
                force_i = end
                if pose is not None:
                    end = int(np.searchsorted(pose[0], stamp, side="right"))
                    _write_pose(writer, pose, pose_i, end)
                    pose_i = end
                info_l.stamp_ns = info_r.stamp_ns = stamp
                writer.write(layout.LEFT_INFO, info_l)
                writer.write(layout.RIGHT_INFO, info_r)
                fmt = options.image_format
                writer.write(layout.LEFT_IMAGE, CompressedImage(stamp, layout.LEFT_FRAME, fmt, left_bytes))
                writer.write(layout.RIGHT_IMAGE, CompressedImage(stamp, layout.RIGHT_FRAME, fmt, right_bytes))
                bar.update()
            bar.close()
            if i + 1 != len(frame_ns):
                raise InputError(src / "frames.csv", f"{len(frame_ns)} rows but the video has {i + 1} frames")
        _write_force(writer, force_ns, wrench, force_frame, force_i, len(force_ns))
        if pose is not None:
            _write_pose(writer, pose, pose_i, len(pose[0]))
    return out


def jpeg_colour_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from the frame header of a 3-component (colour) baseline or progressive JPEG;
    None for anything else (grayscale, CMYK, not a JPEG, no frame header)."""
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        length = int.from_bytes(data[i + 2:i + 4], "big")
        # SOF0-SOF15 except DHT (C4), JPG (C8) and DAC (CC) carry the frame size.
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 10 > len(data):
                return None
            height = int.from_bytes(data[i + 5:i + 7], "big")
            width = int.from_bytes(data[i + 7:i + 9], "big")
            return (width, height) if data[i + 9] == 3 else None
        if marker == 0xDA:  # start of scan before any frame header
            return None
        i += 2 + length
    return None


def _meta_text(value) -> str:
    return value if isinstance(value, str) else yaml.safe_dump(value, default_flow_style=True).strip()


def _write_force(writer: McapWriter, stamps, wrench, frame_id: str, start: int, stop: int) -> None:
    for k in range(start, stop):
        w = wrench[k]
        writer.write(layout.WRENCH, WrenchStamped(int(stamps[k]), frame_id, (w[0], w[1], w[2]), (w[3], w[4], w[5])))


def _write_pose(writer: McapWriter, pose, start: int, stop: int) -> None:
    stamps, values = pose
    for k in range(start, stop):
        v = values[k]
        writer.write(layout.ECM_POSE, PoseStamped(int(stamps[k]), layout.WORLD_FRAME, (v[0], v[1], v[2]),
                                                  (v[3], v[4], v[5], v[6])))
