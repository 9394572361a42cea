"""The derived recording (`vfdata process`, `vfdata predict`): its layout, read and written in one
place (docs/format.md, "Derived files").

Per frame, stamped like the source frame: `/tissue/mask` (PNG CompressedImage, 255 = tissue),
`/tissue/depth` (Image 16UC1, millimetres, 0 = unknown: REP 118), `/tissue/points` (PointCloud2 x, y,
z float32 in metres in the object frame `tissue_object`: REP 103) and `/tracking/points` (the same plus
`visible` uint8). Once: `/tf_static` (left camera -> object frame, metres) and the
`visionforce.derived` metadata (provenance, the object frame, the stage rates). A force file holds
`/force/estimate` (WrenchStamped in the object frame, N; torque is not estimated: zeros, with
`torque_estimated: false` in its metadata), beside it `/force/estimate/band` (the half-width of each
component's calibrated band, N), `/force/estimate/beyond` (how far each component lies beyond the
training range, N) and `/force/estimate/unlike` (Float64: how unlike training's the frame's input is,
> 1 beyond the limit) when the model gives them, and the same `/tf_static`.

Arrays cross this module's edge in the project's units (mm, N, ns). Files written before REP 103/118
units (`derived_version` 1 or absent: clouds in mm, depth in 0.1 mm) read the same.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from vfdata.confidence import Confidence
from vfdata.errors import InputError
from vfdata.recon.object_frame import ObjectFrame
from vfdata.recording import layout
from vfdata.recording.messages import (
    CompressedImage,
    Float64,
    Image,
    PointCloud2,
    TFMessage,
    TransformStamped,
    WrenchStamped,
)
from vfdata.recording.reader import Recording
from vfdata.recording.writer import McapWriter

DERIVED_VERSION = 2  # 2: clouds in m, depth 16UC1 in mm (REP 103/118); 1: clouds in mm, depth in 0.1 mm
MM_PER_M = 1000.0
_DEPTH_UNIT_MM = {1: 0.1, 2: 1.0}
_CLOUD_UNIT_MM = {1: 1.0, 2: MM_PER_M}
TRACK_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("visible", "u1")])
CLOUD_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")])


# ---- messages ------------------------------------------------------------------------------------


def object_tf(rotation: np.ndarray, origin_mm: np.ndarray, stamp_ns: int,
              camera_frame_id: str = layout.LEFT_FRAME) -> TFMessage:
    """camera (the left view's, or an RGB-D recording's depth camera's) -> object frame: origin in metres,
    rotation whose columns are X, Y, Z."""
    quat = tuple(float(q) for q in Rotation.from_matrix(np.asarray(rotation)).as_quat())
    origin_m = tuple(float(v) / MM_PER_M for v in origin_mm)
    return TFMessage([TransformStamped(int(stamp_ns), camera_frame_id, layout.OBJECT_FRAME, origin_m, quat)])


def mask_message(mask: np.ndarray, stamp_ns: int, camera_frame_id: str = layout.LEFT_FRAME) -> CompressedImage:
    _, data = cv2.imencode(".png", mask.astype(np.uint8) * 255, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    return CompressedImage(int(stamp_ns), camera_frame_id, "png", data.tobytes())


def decode_mask(message: CompressedImage) -> np.ndarray:
    """A /tissue/mask message -> (H, W) bool."""
    return cv2.imdecode(np.frombuffer(message.data, np.uint8), cv2.IMREAD_GRAYSCALE) > 127


def depth_message(depth_mm: np.ndarray, stamp_ns: int, camera_frame_id: str = layout.LEFT_FRAME) -> Image:
    """Depth (H, W) mm, NaN unknown -> Image 16UC1 in mm, 0 unknown (REP 118)."""
    data = np.clip(np.rint(np.nan_to_num(depth_mm, nan=0.0, posinf=0.0, neginf=0.0)), 0, 65535).astype("<u2")
    h, w = data.shape
    return Image(int(stamp_ns), camera_frame_id, h, w, "16UC1", 0, 2 * w, data.tobytes())


def decode_depth(message: Image, version: int = DERIVED_VERSION) -> np.ndarray:
    """A /tissue/depth message -> (H, W) float32 mm, NaN where unknown."""
    data = np.frombuffer(message.data, dtype="<u2").reshape(message.height, message.step // 2)[:, : message.width]
    depth = data.astype(np.float32) * np.float32(_DEPTH_UNIT_MM[version])
    depth[data == 0] = np.nan
    return depth


def cloud_message(points_object_mm: np.ndarray, stamp_ns: int, visible: np.ndarray | None = None) -> PointCloud2:
    """Object-frame points (N, 3) mm [+ visible (N,)] -> PointCloud2 in metres."""
    array = np.zeros(len(points_object_mm), dtype=CLOUD_DTYPE if visible is None else TRACK_DTYPE)
    for k, axis in enumerate("xyz"):
        array[axis] = np.asarray(points_object_mm)[:, k] / MM_PER_M
    if visible is not None:
        array["visible"] = np.asarray(visible).astype(np.uint8)
    return PointCloud2(int(stamp_ns), layout.OBJECT_FRAME, array)


def decode_cloud(message: PointCloud2, version: int = DERIVED_VERSION) -> tuple[np.ndarray, np.ndarray]:
    """A /tissue/points or /tracking/points message -> (points (N, 3) float64 mm, visible (N,) bool)."""
    arr = message.points
    points = np.stack([arr["x"], arr["y"], arr["z"]], axis=1).astype(np.float64) * _CLOUD_UNIT_MM[version]
    visible = arr["visible"].astype(bool) if "visible" in arr.dtype.names else np.ones(len(arr), bool)
    return points, visible


# ---- metadata ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DerivedMeta:
    """The `visionforce.derived` metadata record, typed (MCAP metadata is a string map: scalars as
    text, lists and dicts as JSON). `values` keeps every key as written."""

    values: dict[str, str]
    version: int
    object_frame: ObjectFrame | None

    @classmethod
    def from_record(cls, path: Path, record: dict[str, str]) -> DerivedMeta:
        try:
            version = int(record.get("derived_version", "1"))
            frame = record.get("object_frame")
            frame = ObjectFrame.from_dict({"up_known": False, "score_deg": float("nan"), **json.loads(frame)}) \
                if frame else None
        except (ValueError, KeyError, TypeError) as exc:
            raise InputError(path, f"the {layout.DERIVED_METADATA} metadata is malformed ({exc})") from None
        if version not in _DEPTH_UNIT_MM:
            raise InputError(path, f"derived_version {version} is newer than this vfdata reads (1-{DERIVED_VERSION})")
        return cls(dict(record), version, frame)

    def get(self, key: str, default: str | None = None) -> str | None:
        """The value as written (text)."""
        return self.values.get(key, default)

    def value(self, key: str, default=None):
        """The value typed: numbers, true/false, lists and dicts parsed (JSON), other text as it is."""
        text = self.values.get(key)
        if text is None:
            return default
        try:
            return json.loads(text)
        except ValueError:
            return text

    def number(self, key: str, default: float | None = None) -> float | int | None:
        """A numeric value (e.g. `frames`, `stage_threads`); an InputError naming the key if it is not one."""
        value = self.value(key, default)
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise InputError(self.values.get("source", "derived metadata"), f"'{key}' is not a number: {value!r}")
        return value

    def typed(self) -> dict:
        """Every key with its typed value (see `value`)."""
        return {key: self.value(key) for key in self.values}

    def flag(self, key: str) -> bool:
        return str(self.values.get(key, "false")).lower() == "true"

    def json(self, key: str, default=None):
        text = self.values.get(key)
        return default if text is None else json.loads(text)

    @property
    def up_known(self) -> bool:
        """Whether the object frame's X came from gravity (the ECM pose), not the image's up."""
        return self.flag("up_known")

    @property
    def tissue_lean_deg(self) -> float | None:
        """The tissue's lean below level (deg, `vfdata.tissue_lean`); None without gravity, for a frame that is
        not the tissue's, and in files from before 2026-12-06."""
        return self.number("tissue_lean_deg")

    @property
    def object_frame_kind(self) -> str:
        """'tissue', 'board_plane' or 'camera' (files before 2026-12-03: 'tissue')."""
        return self.values.get("object_frame_kind", "tissue")

    @property
    def camera_frame_id(self) -> str:
        """The camera frame the object frame, mask and depth hang off (files before: the left view's)."""
        return self.values.get("camera_frame_id", layout.LEFT_FRAME)

    @property
    def confidence(self) -> Confidence | None:
        """The verdict `vfdata process` wrote on the recording (`vfdata.confidence`); None in files from
        before 2026-12-04, which were not judged."""
        try:
            values = self.json("confidence")
        except ValueError:
            raise InputError(self.values.get("source", "derived metadata"), "'confidence' is not JSON") from None
        return None if values is None else Confidence.from_dict(values)


# ---- writing -------------------------------------------------------------------------------------


class DerivedWriter:
    """Writes a derived MCAP frame by frame (atomically, as `McapWriter`); `close(metadata)` adds the
    metadata record, with `derived_version`, and publishes the file. Mask, depth and the object frame's
    parent are in `camera_frame_id`: the left view's, or an RGB-D recording's depth camera's."""

    def __init__(self, path: str | Path, overwrite: bool = False, inputs: tuple[str | Path, ...] = (),
                 camera_frame_id: str = layout.LEFT_FRAME):
        self.path = Path(path)
        self._writer = McapWriter(self.path, overwrite=overwrite, inputs=inputs)
        self.camera_frame_id = camera_frame_id
        self.frames = 0

    def object_frame(self, frame: ObjectFrame, stamp_ns: int) -> None:
        self._writer.write(layout.TF_STATIC, object_tf(frame.rotation, frame.origin, stamp_ns, self.camera_frame_id))

    def frame(self, stamp_ns: int, mask: np.ndarray, depth_mm: np.ndarray, cloud_object_mm: np.ndarray) -> None:
        self._writer.write(layout.TISSUE_MASK, mask_message(mask, stamp_ns, self.camera_frame_id))
        self._writer.write(layout.TISSUE_DEPTH, depth_message(depth_mm, stamp_ns, self.camera_frame_id))
        self._writer.write(layout.TISSUE_POINTS, cloud_message(cloud_object_mm, stamp_ns))
        self.frames += 1

    def tracks(self, stamp_ns: int, points_object_mm: np.ndarray, visible: np.ndarray) -> None:
        self._writer.write(layout.TRACKING_POINTS, cloud_message(points_object_mm, stamp_ns, visible))

    def close(self, metadata: dict[str, str]) -> Path:
        self._writer.add_metadata(layout.DERIVED_METADATA,
                                  {**{k: str(v) for k, v in metadata.items()}, "derived_version": str(DERIVED_VERSION)})
        self._writer.close()
        return self.path

    def abort(self) -> None:
        self._writer.abort()

    def __enter__(self) -> DerivedWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()


def write_force_estimate(path: str | Path, times_ns: np.ndarray, force_object_n: np.ndarray, frame: ObjectFrame,
                         metadata: dict[str, str], overwrite: bool = False,
                         camera_frame_id: str = layout.LEFT_FRAME, band_n: np.ndarray | None = None,
                         beyond_n: np.ndarray | None = None, unlike: np.ndarray | None = None) -> Path:
    """`/force/estimate` (WrenchStamped in `tissue_object`, N, torque zeros: not estimated), with
    `band_n` (T, 3) N the band's half-width on `/force/estimate/band`, `beyond_n` (T, 3) N the
    distance beyond the training range on `/force/estimate/beyond` and `unlike` (T,) the embedding
    distance over its limit on `/force/estimate/unlike` (each stamped or logged like its estimate),
    and the object frame on /tf_static (child of `camera_frame_id`)."""
    times_ns = np.asarray(times_ns, dtype=np.int64)
    series = [(layout.FORCE_ESTIMATE, force_object_n), (layout.FORCE_BAND, band_n), (layout.FORCE_BEYOND, beyond_n)]
    with McapWriter(path, overwrite=overwrite) as writer:
        first = int(times_ns[0]) if len(times_ns) else 0
        writer.write(layout.TF_STATIC, object_tf(frame.rotation, frame.origin, first, camera_frame_id))
        for i, stamp in enumerate(times_ns):
            for topic, values in series:
                if values is not None:
                    writer.write(topic, wrench_of(int(stamp), values[i]))
            if unlike is not None:
                writer.write(layout.FORCE_UNLIKE, Float64(float(unlike[i])), log_time_ns=int(stamp))
        writer.add_metadata(layout.DERIVED_METADATA, {
            **{k: str(v) for k, v in metadata.items()}, "object_frame": json.dumps(frame.to_dict()),
            "torque_estimated": "false", "derived_version": str(DERIVED_VERSION)})
    return Path(path)


def wrench_of(stamp_ns: int, force_n) -> WrenchStamped:
    """A force (3,) N in the object frame as the WrenchStamped of `/force/estimate` and the topics beside it."""
    return WrenchStamped(int(stamp_ns), layout.OBJECT_FRAME, tuple(float(f) for f in force_n), (0.0, 0.0, 0.0))


# ---- reading -------------------------------------------------------------------------------------


@dataclass
class Tracks:
    """The tracks of a derived recording: object-frame positions (mm) and visibility per frame."""

    times_ns: np.ndarray  # (T,) int64
    points_object_mm: np.ndarray  # (T, N, 3) float64
    visible: np.ndarray  # (T, N) bool
    frame: ObjectFrame
    metadata: DerivedMeta | None = field(default=None, repr=False)

    def points_camera_mm(self, i: int) -> np.ndarray:
        """(N, 3) positions of frame i in the left camera frame."""
        return self.frame.to_camera(self.points_object_mm[i])


@dataclass(frozen=True)
class DerivedFrame:
    """One frame of a derived file, what `DerivedRecording.frame(i)` returns (None: not in the file)."""

    index: int
    stamp_ns: int
    mask: np.ndarray | None  # (H, W) bool
    depth_mm: np.ndarray | None  # (H, W) float, NaN unknown
    cloud_mm: np.ndarray | None  # (M, 3) tissue cloud, object frame
    points_mm: np.ndarray | None  # (N, 3) tracked points, object frame
    visible: np.ndarray | None  # (N,) bool


class DerivedRecording:
    """A derived MCAP opened for reading, frame by frame like a `Recording`: `num_frames`,
    `frame_times_ns`, `frame(i)`, `mask(i)`, `depth_mm(i)`, `cloud_mm(i)`, `tracks()`, typed `meta`."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(self.path, "derived recording not found (run `vfdata process` on its recording)")
        self.recording = Recording.open(self.path)
        record = self.recording.metadata_records.get(layout.DERIVED_METADATA)
        if record is None:
            self.recording.close()
            raise InputError(self.path, f"not a derived recording (no {layout.DERIVED_METADATA} metadata)")
        self.meta = DerivedMeta.from_record(self.path, record)

    @classmethod
    def open(cls, path: str | Path) -> DerivedRecording:
        return cls(path)

    def close(self) -> None:
        self.recording.close()

    def __enter__(self) -> DerivedRecording:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def object_frame(self) -> ObjectFrame:
        if self.meta.object_frame is None:
            raise InputError(self.path, f"no object_frame in the {layout.DERIVED_METADATA} metadata")
        return self.meta.object_frame

    def has(self, topic: str) -> bool:
        return self.recording.has(topic)

    def _require(self, topic: str, what: str) -> None:
        if not self.recording.has(topic):
            raise InputError(self.path, f"no {what} ({topic}): process the recording with it first")

    @property
    def frame_times_ns(self) -> np.ndarray:
        """(F,) int64: the stamps of the per-frame messages (those of the source's frames)."""
        topic = layout.TISSUE_MASK if self.recording.has(layout.TISSUE_MASK) else layout.TRACKING_POINTS
        self._require(topic, "per-frame messages")
        return self.recording.log_times_ns(topic)

    @property
    def num_frames(self) -> int:
        return len(self.frame_times_ns)

    def frame(self, i: int) -> DerivedFrame:
        """Everything the file holds for frame i (negative i counts from the end, as in a list)."""
        n = self.num_frames
        if not -n <= i < n:
            raise IndexError(f"{self.path}: frame {i} of {n}")
        i %= n
        stamp = int(self.frame_times_ns[i])
        points = visible = None
        if self.has(layout.TRACKING_POINTS):
            times = self.recording.log_times_ns(layout.TRACKING_POINTS)
            j = int(np.searchsorted(times, stamp))
            if j < len(times) and times[j] == stamp:
                points, visible = decode_cloud(self.recording.message(layout.TRACKING_POINTS, j), self.meta.version)
        return DerivedFrame(i, stamp, self.mask(i) if self.has(layout.TISSUE_MASK) else None,
                            self.depth_mm(i) if self.has(layout.TISSUE_DEPTH) else None,
                            self.cloud_mm(i) if self.has(layout.TISSUE_POINTS) else None, points, visible)

    def frames(self):
        """`frame(i)` for every frame, in order."""
        for i in range(self.num_frames):
            yield self.frame(i)

    def mask(self, i: int) -> np.ndarray:
        self._require(layout.TISSUE_MASK, "tissue mask")
        return decode_mask(self.recording.message(layout.TISSUE_MASK, i))

    def depth_mm(self, i: int) -> np.ndarray:
        self._require(layout.TISSUE_DEPTH, "tissue depth")
        return decode_depth(self.recording.message(layout.TISSUE_DEPTH, i), self.meta.version)

    def cloud_mm(self, i: int) -> np.ndarray:
        """(M, 3) tissue cloud of frame i in the object frame."""
        self._require(layout.TISSUE_POINTS, "tissue cloud")
        return decode_cloud(self.recording.message(layout.TISSUE_POINTS, i), self.meta.version)[0]

    def clouds_mm(self):
        """(stamp_ns, (M, 3) object-frame cloud) of every frame, in order."""
        self._require(layout.TISSUE_POINTS, "tissue cloud")
        for stamp, message in self.recording.messages(layout.TISSUE_POINTS):
            yield stamp, decode_cloud(message, self.meta.version)[0]

    def depths_and_masks(self):
        """(stamp_ns, depth (H, W) mm NaN unknown, mask (H, W) bool) of every frame, in order."""
        self._require(layout.TISSUE_DEPTH, "tissue depth")
        self._require(layout.TISSUE_MASK, "tissue mask")
        mask_times = self.recording.log_times_ns(layout.TISSUE_MASK)
        for stamp, message in self.recording.messages(layout.TISSUE_DEPTH):
            j = min(int(np.searchsorted(mask_times, stamp)), len(mask_times) - 1)
            yield stamp, decode_depth(message, self.meta.version), self.mask(j)

    def tracks(self) -> Tracks:
        self._require(layout.TRACKING_POINTS, "tracks")
        times, points, visible = [], [], []
        for stamp, message in self.recording.messages(layout.TRACKING_POINTS):
            p, v = decode_cloud(message, self.meta.version)
            times.append(stamp)
            points.append(p)
            visible.append(v)
        n = len(times)
        return Tracks(np.asarray(times, dtype=np.int64), np.asarray(points, dtype=np.float64).reshape(n, -1, 3),
                      np.asarray(visible, dtype=bool).reshape(n, -1), self.object_frame, self.meta)


def read_confidence(path: str | Path) -> Confidence | None:
    """The verdict on a processed recording (`DerivedMeta.confidence`), from its metadata alone."""
    with DerivedRecording.open(path) as derived:
        return derived.meta.confidence


def read_tracker_name(path: str | Path) -> str | None:
    """The tracker named in a derived MCAP's metadata (None when it does not say)."""
    with DerivedRecording.open(path) as derived:
        return derived.meta.get("tracker")


def read_tracks(path: str | Path) -> Tracks:
    """The tracks and object frame of a derived MCAP."""
    with DerivedRecording.open(path) as derived:
        return derived.tracks()


def read_force_estimate(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(times_ns (T,), force (T, 3) N) of a `/force/estimate` MCAP."""
    with Recording.open(path) as rec:
        if not rec.has(layout.FORCE_ESTIMATE):
            raise InputError(Path(path), f"no {layout.FORCE_ESTIMATE}: not a force file of `vfdata predict`")
        return _series(rec, layout.FORCE_ESTIMATE)


def read_force_band(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(times_ns (T,), band half-width (T, 3) N, beyond the training range (T, 3) N) of a force file, None
    when it has no band (written before bands, or by a writer without one)."""
    with Recording.open(path) as rec:
        if not rec.has(layout.FORCE_BAND):
            return None
        times, half = _series(rec, layout.FORCE_BAND)
        beyond = _series(rec, layout.FORCE_BEYOND)[1] if rec.has(layout.FORCE_BEYOND) else np.zeros_like(half)
    if len(beyond) != len(half):
        raise InputError(Path(path), f"{len(half)} {layout.FORCE_BAND} messages but {len(beyond)} "
                                     f"{layout.FORCE_BEYOND}")
    return times, half, beyond


def read_force_unlike(path: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(log times (T,) ns, how unlike training's each frame's input is (T,): the embedding distance over
    its limit, > 1 unlike training, NaN unknown) of a force file, None when it has no such topic."""
    with Recording.open(path) as rec:
        if not rec.has(layout.FORCE_UNLIKE):
            return None
        pairs = [(t, m.data) for t, m in rec.messages(layout.FORCE_UNLIKE)]
    return (np.array([p[0] for p in pairs], dtype=np.int64), np.array([p[1] for p in pairs], dtype=np.float64))


def _series(rec: Recording, topic: str) -> tuple[np.ndarray, np.ndarray]:
    pairs = [(t, m.force) for t, m in rec.messages(topic)]
    return (np.array([p[0] for p in pairs], dtype=np.int64),
            np.array([p[1] for p in pairs], dtype=np.float64).reshape(-1, 3))
