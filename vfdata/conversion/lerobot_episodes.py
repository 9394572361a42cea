"""One episode of a LeRobot dataset (v2.x or v3.0; docs/lerobot.md) -> a recording MCAP of our layout,
with the guarantees of the other converters: everything is checked before or while writing, any
problem is one InputError naming the file, the atomic writer leaves nothing behind, the dataset is
only read.

What comes from where:
- frames: the stereo pair (or the colour view and the depth) chosen by `lerobot.features`, decoded
  from the MP4s at the episode's timestamps (or from `image` columns), stored as JPEG/PNG;
- stamps: our exact `observation.meta.stamp_ns` when the dataset is one of our exports, else the
  `timestamp` column (seconds from the episode's start);
- force: our native-rate windows when present (every sample, exactly), else the force/torque
  feature at the frame stamps (torque zero when the feature has fx fy fz only);
- ECM pose: the feature named as the pose (x y z m, qx qy qz qw), at the frame stamps;
- camera: `--calibration`, else the dataset's `meta/calibration/episode_NNNNNN.yaml` or
  `meta/calibration.yaml` (`rgbd_calibration.yaml` for RGB-D), the raw folder's formats;
- metadata: the recording's own record when the dataset is one of our exports, the split from
  info.json `splits`, then `--meta KEY=VALUE`."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from vfdata import __version__
from vfdata.atomic import check_output
from vfdata.calibration import StereoCalibration
from vfdata.conversion.options import ConvertOptions
from vfdata.conversion.raw_meta import recording_fields
from vfdata.conversion.raw_rgbd import COLOR_VIEW, DEPTH_VIEW
from vfdata.conversion.rgbd_calibration import RgbdCalibration, camera_info, depth_to_color_tf
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
from vfdata.lerobot import features as names
from vfdata.lerobot.columns import image_bytes, read_rows, to_numpy
from vfdata.lerobot.features import FeatureChoice, choose_features
from vfdata.lerobot.folder import DatasetFolder, Episode, inside, read_dataset
from vfdata.lerobot.video import read_frames
from vfdata.lerobot.windows import unpack_windows
from vfdata.recording import layout
from vfdata.recording.messages import MAX_STAMP_NS, Image

# Keys of our metadata record that a conversion writes anew (never carried over from the dataset).
_WRITTEN = ("source", "converter", "converter_version", "layout_version", "units", "camera", "depth_color_registered")


@dataclass(frozen=True)
class EpisodeTables:
    """An episode's non-image data, checked: stamps, the `timestamp` column (s, for the videos), the
    force series, the pose series (or None), and the rows of image/array view columns."""

    frame_ns: np.ndarray
    video_s: np.ndarray
    force: tuple[np.ndarray, np.ndarray, str]
    pose: tuple[np.ndarray, np.ndarray] | None
    rows: dict


def calibration_path(ds: DatasetFolder, episode: int, rgbd: bool, given: Path | None) -> Path:
    """The camera calibration of an episode: given, else the dataset's own (per episode, then shared)."""
    if given is not None:
        return Path(given)
    name = "rgbd_calibration.yaml" if rgbd else "calibration.yaml"
    per_episode = ds.root / "meta" / name.replace(".yaml", "") / f"episode_{episode:06d}.yaml"
    if per_episode.is_file():
        return per_episode
    shared = ds.root / "meta" / name
    if shared.is_file():
        return shared
    raise InputError(ds.root, f"no camera calibration: the dataset has no meta/{name}; give --calibration FILE (the "
                              f"{'RGB-D ' if rgbd else ''}raw folder's {name}, docs/raw_layout.md)")


CLOCKS = ("timestamp", "frame_index")


def read_tables(ds: DatasetFolder, episode: Episode, choice: FeatureChoice, clock: str = "timestamp",
                ) -> EpisodeTables:
    """The episode's rows, turned into stamps and series and checked. `clock`: where the frames'
    times come from when the dataset has no exact stamps of ours: the `timestamp` column, or
    `frame_index` / fps (for datasets whose `timestamp` does not hold LeRobot's clock, such as absolute
    epoch seconds squeezed into float32)."""
    path = episode.data_file
    if episode.length == 0:
        raise InputError(path, f"episode {episode.index} has no frames")
    array_views = [k for k in (choice.left, choice.right, choice.color, choice.depth)
                   if k is not None and ds.features[k]["dtype"] != "video"]
    columns = ["timestamp", choice.force, *([choice.pose] if choice.pose else []),
               *([choice.stamp] if choice.stamp else []), *array_views,
               *((names.SAMPLES, names.SAMPLE_STAMPS, names.SAMPLE_COUNT) if choice.samples else ())]
    rows = read_rows(path, episode.index, episode.length, list(dict.fromkeys(columns)))
    what = f"episode {episode.index}"

    def numbers(name: str) -> np.ndarray:
        return to_numpy(rows[name], ds.features[name]["shape"], path, name)

    video_s = numbers("timestamp").reshape(-1).astype(np.float64)
    if clock == "frame_index":
        video_s = np.arange(episode.length) / ds.fps
    if choice.stamp:
        frame_ns = numbers(choice.stamp).reshape(-1).astype(np.int64)
    else:
        if not np.isfinite(video_s).all():
            raise InputError(path, f"{what}: timestamp holds NaN or inf")
        steps = np.diff(video_s)
        if (steps <= 0).any():
            k = int(np.argmax(steps <= 0)) + 1
            raise InputError(path, f"{what}: timestamp of row {k} ({video_s[k]:.6f} s) does not come after the row "
                                   f"before ({video_s[k - 1]:.6f} s); --clock frame_index times the frames by "
                                   "frame_index / fps instead")
        frame_ns = np.rint(video_s * 1e9).astype(np.int64)
    _check_stamps(path, what, frame_ns, choice.stamp or "timestamp")
    frame_id = _sensor_frame(ds.features[choice.force])
    if choice.samples:
        force_ns, wrench = unpack_windows(numbers(names.SAMPLES), numbers(names.SAMPLE_STAMPS),
                                          numbers(names.SAMPLE_COUNT))
        _check_stamps(path, f"{what} force samples", force_ns, names.SAMPLE_STAMPS)
    else:
        values = numbers(choice.force).astype(np.float64)[:, list(choice.force_columns)]
        wrench = np.zeros((len(values), 6))
        wrench[:, :values.shape[1]] = values
        force_ns = frame_ns
    _check_finite(path, what, wrench, choice.force)
    pose = None
    if choice.pose:
        values = numbers(choice.pose).astype(np.float64)[:, list(choice.pose_columns)]
        _check_finite(path, what, values, choice.pose)
        norms = np.linalg.norm(values[:, 3:], axis=1)
        if (norms < 1e-6).any():
            raise InputError(path, f"{what} frame {int(np.argmax(norms < 1e-6))}: {choice.pose} quaternion has zero "
                                   "length")
        values[:, 3:] /= norms[:, None]
        pose = (frame_ns, values)
    return EpisodeTables(frame_ns, video_s, (force_ns, wrench, frame_id), pose, {k: rows[k] for k in array_views})


def _check_stamps(path: Path, what: str, stamps: np.ndarray, name: str) -> None:
    if len(stamps) and (stamps.min() < 0 or stamps.max() > MAX_STAMP_NS):
        raise InputError(path, f"{what}: {name} outside 0 .. 2^31 s")
    steps = np.diff(stamps)
    if (steps <= 0).any():
        k = int(np.argmax(steps <= 0)) + 1
        raise InputError(path, f"{what}: {name} of row {k} ({stamps[k]}) does not come after the row before "
                               f"({stamps[k - 1]})")


def _check_finite(path: Path, what: str, values: np.ndarray, name: str) -> None:
    bad = ~np.isfinite(values).all(axis=1)
    if bad.any():
        raise InputError(path, f"{what} row {int(np.argmax(bad))}: NaN or inf in {name}")


def _sensor_frame(feature: dict) -> str:
    """Open-H puts the sensor's name in the feature's info ("sensor": "wrist_ft"); else ours."""
    sensor = (feature.get("info") or {}).get("sensor")
    ok = isinstance(sensor, str) and 0 < len(sensor) <= 64 and sensor.replace("_", "").replace("/", "").isalnum()
    return sensor if ok else layout.SENSOR_FRAME


def recording_meta_values(ds: DatasetFolder, episode: Episode) -> dict:
    """meta.yaml-like values of the episode: our recording's own record when we exported it (its
    checked fields as they were), the split from info.json, the task."""
    values: dict = {}
    text = episode.extra.get(names.RECORDING_KEY)
    if isinstance(text, str):
        try:
            record = json.loads(text)
        except json.JSONDecodeError:
            raise InputError(ds.root, f"episode {episode.index}: {names.RECORDING_KEY} is not JSON") from None
        if not isinstance(record, dict):
            raise InputError(ds.root, f"episode {episode.index}: {names.RECORDING_KEY} is not a JSON object")
        for key, value in record.items():
            if key in _WRITTEN or key.startswith("calibration_") or not isinstance(value, str):
                continue
            name = {"recording_id": "id"}.get(key, key)
            values[name] = _json_or_text(value) if key not in ("recording_id", "study", "tissue", "split") else value
    split = ds.split_of(episode.index)
    if "split" not in values and split in ("train", "val", "test"):
        values["split"] = split
    if episode.tasks:
        values.setdefault("lerobot_task", episode.tasks[0])
    return values


def _json_or_text(text: str):
    """A metadata value as it was before it was written: metadata holds text as it is and other values
    as JSON (docs/format.md), so text that is JSON exactly as JSON writes it was a value, the rest text."""
    try:
        value = json.loads(text, parse_constant=lambda name: math.nan)
    except json.JSONDecodeError:
        return text
    plain = isinstance(value, (dict, list, bool, int, float)) and json.dumps(value) == text
    return value if plain and "NaN" not in text else text


def convert_lerobot_episode(src: str | Path, episode: int, out: str | Path, overwrite: bool = False,
                            options: ConvertOptions | None = None, topics: dict[str, str] | None = None,
                            calibration: str | Path | None = None, meta: dict | None = None,
                            dataset: DatasetFolder | None = None, clock: str = "timestamp") -> Path:
    """Convert episode `episode` of the LeRobot dataset at `src` to a recording MCAP at `out`.
    `topics`: features named (`--topics`), `calibration`: a calibration file instead of the dataset's,
    `meta`: metadata keys that replace the episode's (`--meta KEY=VALUE`), `clock`: see `read_tables`.
    Returns `out`."""
    options = options or ConvertOptions()
    src, out = Path(src), Path(out)
    options.check_format(out)
    ds = dataset or read_dataset(src)
    choice = choose_features(ds, topics)
    ep = ds.episode(episode)
    calib_path = calibration_path(ds, episode, choice.is_rgbd, Path(calibration) if calibration else None)
    check_output(out, overwrite, inputs=[src, calib_path])
    if clock not in CLOCKS:
        raise InputError("--clock", f"{clock!r}: choose {' or '.join(CLOCKS)}")
    tables = read_tables(ds, ep, choice, clock)
    # --time-offset-ms: the force and pose onto the video's clock, as the other converters do
    tables = replace(tables, force=options.on_video_clock(tables.force, ep.data_file),
                     pose=options.on_video_clock(tables.pose, ep.data_file))
    check_force_covers(ep.data_file, tables.force[0], tables.frame_ns, options.force_gap_tolerance_ns)
    name = f"{ds.name} episode {episode}"
    default_id = f"{ds.name}_episode_{episode:06d}"
    values = {**recording_meta_values(ds, ep), **(meta or {})}
    extra = {"lerobot_dataset": str(src.resolve()), "lerobot_episode": str(episode),
             "lerobot_codebase_version": ds.version}
    where = Path("--meta") if meta else ds.info_path
    if choice.is_rgbd:
        _write_rgbd(ds, ep, choice, tables, RgbdCalibration.load(calib_path), calib_path, out, overwrite, options,
                    values, where, default_id, extra, name)
        return out
    calib = StereoCalibration.load(calib_path)
    fields = recording_fields(values, where, default_id, (calib.width, calib.height))
    fields["extra"] = {**fields["extra"], **extra}
    record = layout.RecordingMeta(**fields, source=f"{src.resolve()}#episode={episode}",
                                  converter="vfdata convert (LeRobot dataset)", converter_version=__version__)
    first = int(tables.frame_ns[0])
    frames = zip(range(ep.length), _view(ds, ep, choice.left, tables), _view(ds, ep, choice.right, tables),
                 strict=True)

    def encode(item) -> tuple[bytes, bytes]:
        k, left, right = item
        stamp = int(tables.frame_ns[k])
        return tuple(compressed_image_payload(stamp, frame_id, options.image_format,
                                              _encoded(image, (calib.width, calib.height), calib_path, key, options))
                     for frame_id, image, key in ((layout.LEFT_FRAME, left, choice.left),
                                                  (layout.RIGHT_FRAME, right, choice.right)))

    write_recording(out, overwrite, options, record, camera_infos(calib, first), stereo_tf(calib, first),
                    tables.frame_ns, frames, encode, sensor_series(tables.force, tables.pose), name)
    return out


def _write_rgbd(ds: DatasetFolder, ep: Episode, choice: FeatureChoice, tables: EpisodeTables, calib: RgbdCalibration,
                calib_path: Path, out: Path, overwrite: bool, options: ConvertOptions, values: dict, where: Path,
                default_id: str, extra: dict, name: str) -> None:
    if choice.color is not None and calib.color is None:
        raise InputError(calib_path, f"the dataset has a colour view ({choice.color}): give the 'color' camera too")
    depth_cam = calib.depth
    fields = recording_fields(values, where, default_id, (depth_cam.width, depth_cam.height))
    fields["extra"] = {"camera": "rgbd", "depth_color_registered": str(calib.registered).lower(),
                       **{f"calibration_{k}": v for k, v in calib.notes.items()}, **fields["extra"], **extra}
    record = layout.RecordingMeta(**fields, source=f"{Path(ds.root).resolve()}#episode={ep.index}",
                                  converter="vfdata convert (LeRobot dataset, RGB-D)", converter_version=__version__,
                                  units=dict(layout.RGBD_UNITS))
    first = int(tables.frame_ns[0])
    views, infos = [DEPTH_VIEW], [camera_info(depth_cam, layout.DEPTH_FRAME, first)]
    colors = iter(())
    if choice.color is not None:
        views.append(COLOR_VIEW)
        infos.append(camera_info(calib.color, layout.COLOR_FRAME, first))
        colors = _view(ds, ep, choice.color, tables)
    depths = _depths(ds, ep, choice.depth, tables, calib.depth_unit_mm)
    frames = (zip(range(ep.length), depths, colors, strict=True) if choice.color is not None
              else ((k, d, None) for k, d in zip(range(ep.length), depths, strict=True)))

    def encode(item) -> tuple[bytes, ...]:
        k, depth, color = item
        stamp = int(tables.frame_ns[k])
        if (depth.shape[1], depth.shape[0]) != (depth_cam.width, depth_cam.height):
            raise InputError(calib_path, f"depth size {depth_cam.width}x{depth_cam.height} differs from "
                                         f"{choice.depth} ({depth.shape[1]}x{depth.shape[0]})")
        h, w = depth.shape
        payloads = [Image(stamp, layout.DEPTH_FRAME, h, w, "16UC1", 0, 2 * w, depth.astype("<u2").tobytes()).encode()]
        if color is not None:
            data = _encoded(color, (calib.color.width, calib.color.height), calib_path, choice.color, options)
            payloads.append(compressed_image_payload(stamp, layout.COLOR_FRAME, options.image_format, data))
        return tuple(payloads)

    write_recording(out, overwrite, options, record, tuple(infos),
                    depth_to_color_tf(calib, layout.DEPTH_FRAME, layout.COLOR_FRAME, first), tables.frame_ns,
                    frames, encode, sensor_series(tables.force, tables.pose), name, views=tuple(views))


def _encoded(image: np.ndarray, size: tuple[int, int], calib_path: Path, key: str, options: ConvertOptions):
    if (image.shape[1], image.shape[0]) != size:
        raise InputError(calib_path, f"image size {size[0]}x{size[1]} differs from {key} "
                                     f"({image.shape[1]}x{image.shape[0]})")
    data = encode_image(image, options)
    if data is None:
        raise InputError(calib_path, f"{key}: a frame cannot be encoded")
    return data


def _view(ds: DatasetFolder, ep: Episode, key: str, tables: EpisodeTables) -> Iterator[np.ndarray]:
    """A camera's frames (BGR uint8) in order: decoded from its MP4, or from its image column."""
    what = f"episode {ep.index} {key}"
    if ds.features[key]["dtype"] == "video":
        span = ep.videos[key]
        yield from read_frames(span.path, span.from_s, tables.video_s, what)
        return
    for k, encoded in enumerate(_encoded_images(ds, ep, key, tables)):
        image = cv2.imdecode(np.frombuffer(encoded, np.uint8), cv2.IMREAD_COLOR) if encoded else None
        if image is None:
            raise InputError(ep.data_file, f"{what} frame {k}: image cannot be decoded")
        yield image


def _encoded_images(ds: DatasetFolder, ep: Episode, key: str, tables: EpisodeTables) -> Iterator[bytes | None]:
    for data, relative in image_bytes(tables.rows[key], ep.data_file, key):
        if data is None and relative:
            path = inside(ds.root, relative, ep.data_file)
            data = path.read_bytes() if path.is_file() else None
        yield data


def _depths(ds: DatasetFolder, ep: Episode, key: str, tables: EpisodeTables, unit_mm: float) -> Iterator[np.ndarray]:
    """Depth frames as uint16 mm: 16-bit images (`unit_mm` per count), or numeric arrays (integers:
    mm, floats: metres, as LeRobot reads them)."""
    feature = ds.features[key]
    what = f"episode {ep.index} {key}"
    if feature["dtype"] == "image":
        for k, encoded in enumerate(_encoded_images(ds, ep, key, tables)):
            depth = cv2.imdecode(np.frombuffer(encoded, np.uint8), cv2.IMREAD_UNCHANGED) if encoded else None
            if depth is None:
                raise InputError(ep.data_file, f"{what} frame {k}: image cannot be decoded")
            if depth.ndim != 2 or depth.dtype != np.uint16:
                channels = 1 if depth.ndim == 2 else depth.shape[2]
                raise InputError(ep.data_file, f"{what} frame {k}: a depth image must be 16-bit single-channel, not "
                                               f"{depth.dtype} with {channels} channel(s)")
            yield np.clip(np.rint(depth * unit_mm), 0, 65535).astype(np.uint16) if unit_mm != 1.0 else depth
        return
    values = to_numpy(tables.rows[key], feature["shape"], ep.data_file, key)
    values = values.reshape(len(values), *[n for n in feature["shape"] if n != 1][:2])
    scale = 1000.0 if np.issubdtype(values.dtype, np.floating) else unit_mm
    for depth in values:
        mm = np.where(np.isfinite(depth) & (depth > 0), depth * scale, 0)
        yield np.clip(np.rint(mm), 0, 65535).astype(np.uint16)
