"""Clips of processed recordings for the force models: `ForceClipDataset` (a plain torch Dataset) and
`ForceDataModule` (Lightning), plus dataset-manifest loading.

A clip is T = 16 consecutive frames (stride 4 between clip starts) of one recording. Each item is a
dict (the batch contract of `vfmodels.ForceRegressor`):

- the model input: `tokens` (T, N, C) float32 with `valid` (T, N) bool for the point inputs, or
  `images` (T, 3, S, S) uint8 RGB, or `depth` (T, 1, S, S) float32 mm (0 off the tissue mask);
- `force` (T, 3) float32 N: the sensor's force interpolated at each frame time (NaN where the
  sensor stream has a gap); the sensor is mounted under the tissue and turns with it, so its frame is
  fixed to the object;
- `orientation_deg`, `recording` (id), `frame_time_ns` (T,) int64, `frame_index` (T,) int64;
- `side` (float, +1 or -1): the factor applied to the y of the points and of the force (see
  `canonical_side`); multiply a predicted Fy by it to get the sensor's.

Point inputs (`input`):
- "tracks" (default): the 256 tracked points of `/tracking/points`, in the object frame (default)
  or the camera frame (`frame`), features (`features`) position in mm and/or velocity in mm/s,
  v_t = fps/2 (p_{t+1} - p_{t-1}), one-sided at the first and last frame of a recording and on each
  side of a gap (never across one); all points or only the top and bottom 20% by object-frame z on
  the recording's first frame (`subset`);
  With `canonical_side` (beyond the paper), a recording whose first frame shows the object's y < 0
  side (mean y of the visible tracked points) is mirrored across the object's XZ plane, the y of its
  points and of its force negated (`seen_side`, `mirror_y`): the object frame fixes Z along the tissue
  and X against gravity, but not which flank of the tissue the camera sees, and a test view from
  the other flank (e.g. rotated 180 degrees) puts every point where no training point was. The
  mirror is a symmetry of an axisymmetric tissue hanging from a clamp under gravity along X.
- "cloud": the tissue point cloud `/tissue/points` itself, `cloud_points` points drawn per frame
  (no correspondences, so positions only);
- "rgb": the left image (the RGB baseline); "depth": the tissue-masked depth (the ViT baseline).

Sources (`source`): "processed" reads `<id>.processed.mcap` (`/tracking/points` etc.) and the
force from `<id>.mcap`; "ground_truth" reads the simulator's `ground_truth/` (material points,
`force.npy`) and `frames.csv` from the raw folder (for developing models before tracking; tracks
and cloud inputs only).

Clips never span a gap (consecutive frames more than 1.5 nominal frame periods apart): a recording
is cut into gap-free segments, clips start every `stride` frames in each segment, and a last clip
ends on the segment's last frame so no frame is left out; segments shorter than T give no clip.

Decoded arrays are made once, when the dataset is built (in the main process, so DataLoader
workers share them), and with `cache_dir` also kept on disk, keyed by the source files' sizes and
modification times and the input options, so a later run does not decode the MCAPs again.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import yaml
from torch.utils.data import DataLoader, Dataset
from tqdm import tqdm

from vfdata.errors import InputError

SPLITS = ("train", "val", "test")
INPUTS = ("tracks", "cloud", "rgb", "depth")
FEATURES = ("pos_vel", "pos", "vel")
SUBSETS = ("all", "top_bottom_20")
GAP_FACTOR = 1.5  # a frame interval longer than this many nominal periods is a gap
TOP_BOTTOM_FRACTION = 0.2


# ---- manifests -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class ManifestEntry:
    id: str
    orientation_deg: float
    split: str
    raw: Path  # raw recording folder (simulator ground truth lives in raw/ground_truth)
    mcap: Path  # the recording MCAP (force)
    processed: Path  # the derived MCAP (tracks, cloud, mask, depth)


def load_manifest(path: str | Path) -> tuple[str, list[ManifestEntry]]:
    """(name, recordings) of a dataset manifest (docs/architecture.md), paths made absolute."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "dataset manifest not found")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise InputError(path, f"not valid YAML ({exc})") from exc
    if not isinstance(data, dict) or not isinstance(data.get("recordings"), list) or not data["recordings"]:
        raise InputError(path, "a manifest needs a non-empty 'recordings' list")
    root = (path.parent / str(data.get("root", "."))).resolve()
    entries = []
    for item in data["recordings"]:
        if not isinstance(item, dict) or "id" not in item or item.get("split") not in SPLITS:
            raise InputError(path, f"recording entry {item!r} needs an id and a split (train, val or test)")
        rid = str(item["id"])
        entries.append(ManifestEntry(
            rid, float(item.get("orientation_deg", 0.0)), item["split"], root / str(item.get("raw", rid)),
            root / str(item.get("mcap", f"{rid}.mcap")), root / str(item.get("processed", f"{rid}.processed.mcap")),
        ))
    ids = [e.id for e in entries]
    if len(set(ids)) != len(ids):
        raise InputError(path, "recording ids are not unique")
    return str(data.get("name", path.stem)), entries


# ---- pure array functions ------------------------------------------------------------------------


def segments(times_ns: np.ndarray, gap_factor: float = GAP_FACTOR) -> list[tuple[int, int]]:
    """Gap-free runs [start, stop) of frame indices: a new run starts after any interval longer than
    `gap_factor` times the median interval."""
    times = np.asarray(times_ns, dtype=np.int64)
    if len(times) < 2:
        return [(0, len(times))] if len(times) else []
    dt = np.diff(times)
    breaks = np.flatnonzero(dt > gap_factor * np.median(dt)) + 1
    bounds = [0, *breaks.tolist(), len(times)]
    return list(zip(bounds[:-1], bounds[1:], strict=True))


def clip_starts(runs: list[tuple[int, int]], clip_frames: int, stride: int) -> np.ndarray:
    """First frame of each clip: every `stride` frames within each gap-free run, plus one clip ending
    on the run's last frame when the stride does not land there. Runs shorter than a clip give none."""
    starts: list[int] = []
    for start, stop in runs:
        if stop - start < clip_frames:
            continue
        last = stop - clip_frames
        run_starts = list(range(start, last + 1, stride))
        if run_starts[-1] != last:
            run_starts.append(last)
        starts.extend(run_starts)
    return np.asarray(starts, dtype=np.int64)


def velocities(points_mm: np.ndarray, runs: list[tuple[int, int]], fps: float) -> np.ndarray:
    """(F, N, 3) positions -> velocities in mm/s: central differences within each gap-free run,
    one-sided at the ends of a run (zero for a one-frame run)."""
    p = np.asarray(points_mm, dtype=np.float64)
    v = np.zeros_like(p)
    for start, stop in runs:
        q = p[start:stop]
        if len(q) < 2:
            continue
        w = v[start:stop]
        w[1:-1] = 0.5 * fps * (q[2:] - q[:-2])
        w[0] = fps * (q[1] - q[0])
        w[-1] = fps * (q[-1] - q[-2])
    return v


def top_bottom(reference_mm: np.ndarray, fraction: float = TOP_BOTTOM_FRACTION) -> np.ndarray:
    """Indices (sorted) of the points in the lowest and highest `fraction` by z."""
    z = np.asarray(reference_mm, dtype=np.float64)[:, 2]
    z = np.where(np.isfinite(z), z, np.nanmedian(z) if np.isfinite(z).any() else 0.0)
    order = np.argsort(z, kind="stable")
    k = max(1, int(round(fraction * len(z))))
    return np.sort(np.unique(np.concatenate([order[:k], order[-k:]])))


def seen_side(points_object_mm: np.ndarray, visible: np.ndarray) -> float:
    """+1.0 when a frame's visible points (N, 3), object frame, lie on the y >= 0 side on average,
    else -1.0: the flank of the tissue the camera sees."""
    points = np.asarray(points_object_mm, dtype=np.float64)
    seen = np.asarray(visible, dtype=bool) & np.isfinite(points).all(axis=1)
    return -1.0 if seen.any() and points[seen, 1].mean() < 0 else 1.0


def mirror_y(values: np.ndarray, side: float) -> np.ndarray:
    """`values` (..., 3) with y multiplied by `side` (+1 or -1); its own inverse."""
    return np.asarray(values) * np.array([1.0, side, 1.0], dtype=np.asarray(values).dtype)


def point_features(points_mm: np.ndarray, valid: np.ndarray, runs: list[tuple[int, int]], fps: float,
                   features: str) -> tuple[np.ndarray, np.ndarray]:
    """Tokens (F, N, C) float32 (C = 6 for pos_vel, else 3) and valid (F, N): invalid or non-finite
    points are zeroed and marked invalid; velocities of points next to an invalid sample are too."""
    p = np.asarray(points_mm, dtype=np.float64)
    ok = np.asarray(valid, dtype=bool) & np.isfinite(p).all(axis=-1)
    p = np.where(ok[..., None], p, 0.0)
    parts = []
    if features in ("pos_vel", "pos"):
        parts.append(p)
    if features in ("pos_vel", "vel"):
        parts.append(velocities(p, runs, fps))
        # a velocity from a neighbour the tracker lost is meaningless: use only fully seen stencils
        ok_prev, ok_next = ok.copy(), ok.copy()
        for start, stop in runs:
            ok_prev[start + 1:stop] = ok[start:stop - 1]
            ok_next[start:stop - 1] = ok[start + 1:stop]
        ok = ok & ok_prev & ok_next
    if not parts:
        raise ValueError(f"unknown features '{features}' (choose from {', '.join(FEATURES)})")
    tokens = np.concatenate(parts, axis=-1)
    return np.where(ok[..., None], tokens, 0.0).astype(np.float32), ok


def sample_cloud(points_mm: np.ndarray, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """`count` points of a cloud (M, 3), without replacement when M >= count; (count, 3) float32 and
    valid (count,) (all False for an empty cloud)."""
    points = np.asarray(points_mm, dtype=np.float32)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) == 0:
        return np.zeros((count, 3), np.float32), np.zeros(count, bool)
    idx = rng.choice(len(points), size=count, replace=len(points) < count)
    return points[idx], np.ones(count, bool)


# ---- decoding one recording ----------------------------------------------------------------------


@dataclass
class Decoded:
    """One recording's frames: times, force, and the chosen input (tokens+valid, images or depth)."""

    times_ns: np.ndarray  # (F,) int64
    force_n: np.ndarray  # (F, 3) float32
    inputs: np.ndarray  # tokens (F, N, C) float32 | images (F, 3, S, S) uint8 | depth (F, 1, S, S) float16 mm
    valid: np.ndarray | None  # (F, N) bool for tokens
    side: float = 1.0  # the y factor applied to points and force (`canonical_side`)


def _fps(times_ns: np.ndarray) -> float:
    dt = np.diff(np.asarray(times_ns, dtype=np.int64))
    return 1e9 / float(np.median(dt)) if len(dt) else 30.0


def _object_frame_of(processed: Path, metadata: dict[str, str]) -> tuple[np.ndarray, np.ndarray]:
    from vfdata.recording import layout

    if "object_frame" not in metadata:
        raise InputError(processed, f"no object_frame in the {layout.DERIVED_METADATA} metadata")
    frame = json.loads(metadata["object_frame"])
    return np.asarray(frame["rotation"], dtype=np.float64), np.asarray(frame["origin"], dtype=np.float64)


def _force_at(entry: ManifestEntry, times_ns: np.ndarray) -> np.ndarray:
    from vfdata.recording import Recording, layout

    if not entry.mcap.is_file():
        raise InputError(entry.mcap, f"recording '{entry.id}' not found (convert it with `vfdata convert`)")
    with Recording.open(entry.mcap) as rec:
        if not rec.has(layout.WRENCH):
            raise InputError(entry.mcap, f"recording '{entry.id}' has no {layout.WRENCH}: no force to train on")
        return rec.force_at(times_ns)[:, :3].astype(np.float32)


def _decode_processed(entry: ManifestEntry, opts: dict) -> Decoded:
    import cv2

    from vfdata.recording import Recording, layout

    if opts["input"] == "rgb":
        return _decode_rgb(entry, opts)
    path = entry.processed
    if not path.is_file():
        raise InputError(path, f"processed recording '{entry.id}' not found "
                               f"(run `vfdata process` on {entry.mcap.name})")
    kind = opts["input"]
    with Recording.open(path) as rec:
        meta = rec.metadata_records.get(layout.DERIVED_METADATA, {})
        if kind == "tracks":
            if not rec.has(layout.TRACKING_POINTS):
                raise InputError(path, f"recording '{entry.id}' has no tracks ({layout.TRACKING_POINTS}): "
                                       "process it with a tracker")
            times, points, visible = [], [], []
            for stamp, cloud in rec.messages(layout.TRACKING_POINTS):
                arr = cloud.points
                times.append(stamp)
                points.append(np.stack([arr["x"], arr["y"], arr["z"]], axis=1))
                visible.append(arr["visible"].astype(bool) if "visible" in arr.dtype.names
                               else np.ones(len(arr), bool))
            times_ns = np.asarray(times, dtype=np.int64)
            return _point_tokens(entry, times_ns, np.asarray(points, np.float64), np.asarray(visible, bool),
                                 _object_frame_of(path, meta) if opts["frame"] == "camera" else None, opts)
        if kind == "cloud":
            if not rec.has(layout.TISSUE_POINTS):
                raise InputError(path, f"recording '{entry.id}' has no tissue cloud ({layout.TISSUE_POINTS})")
            rotation, origin = _object_frame_of(path, meta) if opts["frame"] == "camera" else (None, None)
            times, clouds, valid = [], [], []
            for i, (stamp, cloud) in enumerate(rec.messages(layout.TISSUE_POINTS)):
                arr = cloud.points
                pts = np.stack([arr["x"], arr["y"], arr["z"]], axis=1)
                if rotation is not None:
                    pts = pts @ rotation.T + origin
                # the same points every epoch and run: the draw depends on the seed and frame only
                p, ok = sample_cloud(pts, opts["cloud_points"], np.random.default_rng([opts["seed"], i]))
                times.append(stamp)
                clouds.append(p)
                valid.append(ok)
            times_ns = np.asarray(times, dtype=np.int64)
            return Decoded(times_ns, _force_at(entry, times_ns), np.asarray(clouds, np.float32),
                           np.asarray(valid, bool))
        size = opts["image_size"]
        if kind == "depth":
            from vfdata.processing import decode_depth

            for topic in (layout.TISSUE_DEPTH, layout.TISSUE_MASK):
                if not rec.has(topic):
                    raise InputError(path, f"recording '{entry.id}' has no {topic}")
            mask_times = rec.log_times_ns(layout.TISSUE_MASK)
            times, frames = [], []
            for stamp, image in rec.messages(layout.TISSUE_DEPTH):
                depth = np.nan_to_num(decode_depth(image), nan=0.0)
                j = min(int(np.searchsorted(mask_times, stamp)), len(mask_times) - 1)
                mask_msg = rec.message(layout.TISSUE_MASK, j)
                mask = cv2.imdecode(np.frombuffer(mask_msg.data, np.uint8), cv2.IMREAD_GRAYSCALE) > 127
                depth = np.where(mask, depth, 0.0).astype(np.float32)
                frames.append(cv2.resize(depth, (size, size), interpolation=cv2.INTER_NEAREST)[None])
                times.append(stamp)
            times_ns = np.asarray(times, dtype=np.int64)
            return Decoded(times_ns, _force_at(entry, times_ns), np.asarray(frames, np.float16), None)
    raise ValueError(f"unknown input kind {kind!r}")


def _decode_rgb(entry: ManifestEntry, opts: dict) -> Decoded:
    """The left images of the recording MCAP itself (the RGB baseline needs no processing)."""
    import cv2

    from vfdata.recording import Recording

    if not entry.mcap.is_file():
        raise InputError(entry.mcap, f"recording '{entry.id}' not found (convert it with `vfdata convert`)")
    size = opts["image_size"]
    with Recording.open(entry.mcap) as rec:
        times_ns = np.asarray(rec.frame_times_ns, dtype=np.int64)
        images = np.empty((len(times_ns), 3, size, size), np.uint8)
        for i in range(len(times_ns)):
            bgr = cv2.resize(rec.left_image(i), (size, size), interpolation=cv2.INTER_AREA)
            images[i] = bgr[:, :, ::-1].transpose(2, 0, 1)
    return Decoded(times_ns, _force_at(entry, times_ns), images, None)


def _point_tokens(entry: ManifestEntry, times_ns: np.ndarray, points_object_mm: np.ndarray, visible: np.ndarray,
                  object_frame: tuple[np.ndarray, np.ndarray] | None, opts: dict,
                  force_n: np.ndarray | None = None) -> Decoded:
    points = points_object_mm
    force = _force_at(entry, times_ns) if force_n is None else force_n
    side = seen_side(points[0], visible[0]) if opts["canonical_side"] and len(points) else 1.0
    points, force = mirror_y(points, side), mirror_y(force, side).astype(np.float32)
    if opts["subset"] == "top_bottom_20":
        keep = top_bottom(points_object_mm[0], TOP_BOTTOM_FRACTION)
        points, visible = points[:, keep], visible[:, keep]
    if object_frame is not None:  # camera-frame variant
        rotation, origin = object_frame
        points = points @ rotation.T + origin
    runs = segments(times_ns)
    fps = opts["fps"] or _fps(times_ns)
    tokens, valid = point_features(points, visible, runs, fps, opts["features"])
    return Decoded(times_ns, force, tokens, valid, side)


def _decode_ground_truth(entry: ManifestEntry, opts: dict) -> Decoded:
    gt = entry.raw / "ground_truth"
    for name in ("points.npy", "force.npy", "object_frame.json"):
        if not (gt / name).is_file():
            raise InputError(gt / name, f"simulator ground truth of recording '{entry.id}' not found")
    frames_csv = entry.raw / "frames.csv"
    if not frames_csv.is_file():
        raise InputError(frames_csv, f"frame times of recording '{entry.id}' not found")
    times_ns = np.loadtxt(frames_csv, delimiter=",", skiprows=1, dtype=np.int64, ndmin=2)[:, 1]
    points_cam = np.load(gt / "points.npy").astype(np.float64)
    force = np.load(gt / "force.npy").astype(np.float32)[:, :3]
    visible = np.load(gt / "visible.npy") if (gt / "visible.npy").is_file() else np.ones(points_cam.shape[:2], bool)
    if not (len(times_ns) == len(points_cam) == len(force)):
        raise InputError(gt, f"{len(times_ns)} frame times, {len(points_cam)} point frames, {len(force)} forces")
    frame = json.loads((gt / "object_frame.json").read_text())
    rotation, origin = np.asarray(frame["rotation"]), np.asarray(frame["origin_mm"])
    points_obj = (points_cam - origin) @ rotation  # camera -> object: R^T (p - o)
    rng = np.random.default_rng(opts["seed"])
    if opts["input"] == "cloud":  # a fresh draw of surface points each frame: no correspondences
        count = opts["cloud_points"]
        clouds, valid = zip(*(sample_cloud(p[v], count, np.random.default_rng([opts["seed"], i]))
                              for i, (p, v) in enumerate(zip(points_obj, visible, strict=True))), strict=True)
        clouds = np.asarray(clouds, np.float64)
        if opts["frame"] == "camera":
            clouds = clouds @ rotation.T + origin
        return Decoded(times_ns, force, clouds.astype(np.float32), np.asarray(valid, bool))
    if opts["input"] != "tracks":
        raise InputError(gt, f"input '{opts['input']}' needs processed recordings (source: processed)")
    # a fixed subset of the material points stands in for the tracked points
    keep = np.sort(rng.choice(points_obj.shape[1], size=min(opts["num_points"], points_obj.shape[1]), replace=False))
    return _point_tokens(entry, times_ns, points_obj[:, keep], visible[:, keep],
                         (rotation, origin) if opts["frame"] == "camera" else None, opts, force_n=force)


def _source_files(entry: ManifestEntry, opts: dict) -> list[Path]:
    if opts["source"] == "ground_truth":
        return [entry.raw / "frames.csv", entry.raw / "ground_truth" / "points.npy",
                entry.raw / "ground_truth" / "force.npy"]
    return [entry.mcap] if opts["input"] == "rgb" else [entry.mcap, entry.processed]


def decode_recording(entry: ManifestEntry, opts: dict, cache_dir: Path | None = None) -> Decoded:
    """The recording's arrays for `opts` (see ForceClipDataset), from the disk cache when valid."""
    cache = None
    if cache_dir is not None:
        files = _source_files(entry, opts)
        stamp = [(str(p.resolve()), p.stat().st_size, p.stat().st_mtime_ns) for p in files if p.exists()]
        # An option added later is left out of the key at its default, so existing caches stay valid.
        keyed = {k: v for k, v in opts.items() if not (k == "canonical_side" and not v)}
        key = hashlib.sha256(json.dumps([stamp, sorted(keyed.items())], default=str).encode()).hexdigest()[:20]
        cache = Path(cache_dir) / f"{entry.id}-{key}.npz"
        if cache.is_file():
            with np.load(cache) as z:
                return Decoded(z["times_ns"], z["force_n"], z["inputs"], z["valid"] if "valid" in z else None,
                               float(z["side"]) if "side" in z else 1.0)
    decode = _decode_ground_truth if opts["source"] == "ground_truth" else _decode_processed
    decoded = decode(entry, opts)
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_name(cache.name + f".tmp-{np.random.randint(1 << 30)}.npz")
        arrays = dict(times_ns=decoded.times_ns, force_n=decoded.force_n, inputs=decoded.inputs,
                      side=np.float64(decoded.side))
        if decoded.valid is not None:
            arrays["valid"] = decoded.valid
        np.savez(tmp, **arrays)
        tmp.replace(cache)  # atomic: concurrent runs see a whole file or none
    return decoded


# ---- the dataset ---------------------------------------------------------------------------------


class ForceClipDataset(Dataset):
    """Clips of T frames (stride between starts) from the given manifest entries; see the module
    docstring for the item layout and the options."""

    def __init__(self, recordings: list[ManifestEntry], input: str = "tracks", source: str = "processed",
                 frame: str = "object", features: str = "pos_vel", subset: str = "all", clip_frames: int = 16,
                 stride: int = 4, cloud_points: int = 256, num_points: int = 256, image_size: int = 112,
                 fps: float | None = None, seed: int = 0, cache_dir: str | Path | None = None,
                 progress: bool = True, canonical_side: bool = False):
        choices = dict(input=(input, INPUTS), source=(source, ("processed", "ground_truth")),
                       frame=(frame, ("object", "camera")), features=(features, FEATURES), subset=(subset, SUBSETS))
        for name, (value, allowed) in choices.items():
            if value not in allowed:
                raise ValueError(f"{name} '{value}' is not one of {', '.join(allowed)}")
        if clip_frames < 1 or stride < 1:
            raise ValueError("clip_frames and stride must be positive")
        if canonical_side and (input != "tracks" or frame != "object"):
            raise ValueError("canonical_side mirrors tracked points in the object frame (input tracks, frame object)")
        self.opts = dict(input=input, source=source, frame=frame, features=features, subset=subset, fps=fps,
                         cloud_points=cloud_points, num_points=num_points, image_size=image_size, seed=seed,
                         canonical_side=canonical_side)
        self.clip_frames = clip_frames
        self.entries = list(recordings)
        self.input_key = {"tracks": "tokens", "cloud": "tokens", "rgb": "images", "depth": "depth"}[input]
        cache = Path(cache_dir) if cache_dir else None
        self.recordings: list[Decoded] = [
            decode_recording(e, self.opts, cache)
            for e in tqdm(self.entries, desc=f"decoding {input}", unit="recording", disable=not progress)
        ]
        index = []
        for r, decoded in enumerate(self.recordings):
            for start in clip_starts(segments(decoded.times_ns), clip_frames, stride):
                index.append((r, int(start)))
        self.index = np.asarray(index, dtype=np.int64).reshape(-1, 2)

    @property
    def fps(self) -> float:
        """The frame rate used for velocities: given, or the median over the recordings."""
        if self.opts["fps"]:
            return float(self.opts["fps"])
        rates = [_fps(d.times_ns) for d in self.recordings if len(d.times_ns) > 1]
        return float(np.median(rates)) if rates else 30.0

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict:
        r, start = (int(v) for v in self.index[i])
        entry, d = self.entries[r], self.recordings[r]
        window = slice(start, start + self.clip_frames)
        item = {
            self.input_key: torch.from_numpy(np.ascontiguousarray(d.inputs[window])),
            "force": torch.from_numpy(np.ascontiguousarray(d.force_n[window])),
            "orientation_deg": torch.tensor(entry.orientation_deg, dtype=torch.float32),
            "recording": entry.id,
            "frame_time_ns": torch.from_numpy(np.ascontiguousarray(d.times_ns[window])),
            "frame_index": torch.arange(start, start + self.clip_frames, dtype=torch.int64),
            "side": torch.tensor(d.side, dtype=torch.float32),
        }
        if self.input_key == "depth":
            item["depth"] = item["depth"].float()
        if d.valid is not None:
            item["valid"] = torch.from_numpy(np.ascontiguousarray(d.valid[window]))
        return item

    def normalisation(self) -> dict[str, torch.Tensor]:
        """Input and force statistics of this dataset (every frame of its recordings once):
        tokens per feature over valid points; depth over tissue pixels; RGB none (the model
        normalises RGB itself with its backbone's statistics)."""
        force = np.concatenate([d.force_n for d in self.recordings])
        force = force[np.isfinite(force).all(axis=1)]
        if len(force) < 2:
            raise InputError(self.entries[0].mcap if self.entries else Path("."), "no force samples for statistics")
        stats = {"force_mean": torch.tensor(force.mean(0)), "force_std": torch.tensor(force.std(0) + 1e-6)}
        if self.input_key == "tokens":
            values = np.concatenate([d.inputs[d.valid] for d in self.recordings]).astype(np.float64)
            stats["input_mean"] = torch.tensor(values.mean(0), dtype=torch.float32)
            stats["input_std"] = torch.tensor(values.std(0) + 1e-6, dtype=torch.float32)
        elif self.input_key == "depth":
            values = np.concatenate([d.inputs[d.inputs > 0] for d in self.recordings]).astype(np.float64)
            stats["input_mean"] = torch.tensor([values.mean()], dtype=torch.float32)
            stats["input_std"] = torch.tensor([values.std() + 1e-6], dtype=torch.float32)
        else:
            stats["input_mean"], stats["input_std"] = torch.zeros(0), torch.zeros(0)
        return {k: v.float() for k, v in stats.items()}


def collate_clips(items: list[dict]) -> dict:
    """Stack tensors; keep the recording ids as a list."""
    out = {}
    for key in items[0]:
        values = [item[key] for item in items]
        out[key] = values if isinstance(values[0], str) else torch.stack(values)
    return out


# ---- the Lightning data module -------------------------------------------------------------------

try:
    import lightning.pytorch as _L

    _DataModuleBase = _L.LightningDataModule
except ImportError:  # the dataset works without Lightning
    _DataModuleBase = object  # type: ignore[assignment,misc]


class ForceDataModule(_DataModuleBase):
    """Train/val/test clips from a dataset manifest (splits as the manifest says; train and val share
    an orientation, test recordings are at others). Normalisation statistics come from the training
    split only and are exposed as `normalisation` for `ForceRegressor`. The options are those of
    `ForceClipDataset`; `predict` runs over the test split unless `predict_split` says otherwise."""

    def __init__(self, manifest: str, input: str = "tracks", source: str = "processed", frame: str = "object",
                 features: str = "pos_vel", subset: str = "all", clip_frames: int = 16, stride: int = 4,
                 cloud_points: int = 256, num_points: int = 256, image_size: int = 112, fps: float | None = None,
                 batch_size: int = 32, num_workers: int = 0, cache_dir: str | None = None, seed: int = 0,
                 predict_split: str = "test", progress: bool = True, canonical_side: bool = False):
        super().__init__()
        self.save_hyperparameters()
        self.hparams["frame"] = frame  # Lightning's collector drops an argument named `frame`
        self.manifest_name, self.entries = load_manifest(manifest)
        self.datasets: dict[str, ForceClipDataset] = {}
        self.normalisation: dict[str, torch.Tensor] | None = None

    def _dataset(self, split: str) -> ForceClipDataset:
        if split not in self.datasets:
            entries = [e for e in self.entries if e.split == split]
            if not entries:
                raise InputError(self.hparams.manifest, f"no '{split}' recordings in the manifest")
            hp = self.hparams
            self.datasets[split] = ForceClipDataset(
                entries, input=hp.input, source=hp.source, frame=hp.frame, features=hp.features, subset=hp.subset,
                clip_frames=hp.clip_frames, stride=hp.stride, cloud_points=hp.cloud_points,
                num_points=hp.num_points, image_size=hp.image_size, fps=hp.fps, seed=hp.seed,
                cache_dir=hp.cache_dir, progress=hp.progress, canonical_side=hp.canonical_side,
            )
            if len(self.datasets[split]) == 0:
                raise InputError(self.hparams.manifest, f"the '{split}' recordings are shorter than one clip "
                                                        f"({hp.clip_frames} frames)")
        return self.datasets[split]

    def setup(self, stage: str | None = None) -> None:
        if stage in (None, "fit", "validate"):
            train = self._dataset("train")
            self._dataset("val")
            if self.normalisation is None:
                self.normalisation = train.normalisation()
            if self.hparams.fps is None:  # saved with the checkpoint, for `vfdata predict`
                self.hparams.fps = train.fps
        if stage in (None, "test"):
            self._dataset("test")
        if stage == "predict":
            self._dataset(self.hparams.predict_split)

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        workers = self.hparams.num_workers
        return DataLoader(self._dataset(split), batch_size=self.hparams.batch_size, shuffle=shuffle,
                          num_workers=workers, persistent_workers=workers > 0, collate_fn=collate_clips,
                          drop_last=False)

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", shuffle=False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", shuffle=False)

    def predict_dataloader(self) -> DataLoader:
        return self._loader(self.hparams.predict_split, shuffle=False)
