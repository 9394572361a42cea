"""One recording of a manifest -> the arrays its clips are cut from (`Decoded`), as a `ClipSpec` says:
frame times, the force at each frame, and the model input (point tokens + valid, images or depth).

Sources: "processed" reads the derived MCAP (`vfdata.recording.derived`) and the force from the
recording MCAP; "ground_truth" reads the simulator's `ground_truth/` (material points, force) and the
raw folder's `frames.csv`. A manifest entry's `frames: [start, stop]` keeps only those frames.

With `cache_dir`, the arrays are also kept on disk, keyed by the source files' sizes and modification
times and the spec, so a later run does not decode the MCAPs again.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vfdata.clips.spec import ClipSpec
from vfdata.clips.tokens import mirror_y, sample_cloud, track_tokens
from vfdata.errors import InputError
from vfdata.manifest import ManifestEntry
from vfdata.recording import Recording, layout
from vfdata.recording.derived import DerivedRecording

CACHE_VERSION = 4  # bump when the decoded arrays change for the same spec


@dataclass
class Decoded:
    """One recording's frames: times, force, and the chosen input (tokens+valid, images or depth)."""

    times_ns: np.ndarray  # (F,) int64
    force_n: np.ndarray  # (F, 3) float32, object frame (mirrored when side is -1)
    inputs: np.ndarray  # tokens (F, N, C) float32 | images (F, 3, S, S) uint8 | depth (F, 1, S, S) float16 mm
    valid: np.ndarray | None  # (F, N) bool for tokens
    side: float = 1.0  # the y factor applied to points and force (`ClipSpec.canonical_side`)

    def window(self, frames: tuple[int, int] | None) -> Decoded:
        if frames is None:
            return self
        cut = slice(*frames)
        return Decoded(self.times_ns[cut], self.force_n[cut], self.inputs[cut],
                       None if self.valid is None else self.valid[cut], self.side)


def force_at(entry: ManifestEntry, times_ns: np.ndarray) -> np.ndarray:
    """(F, 3) float32 N in the object frame: the recording's force at `times_ns` (`object_force_at`)."""
    if not entry.mcap.is_file():
        raise InputError(entry.mcap, f"recording '{entry.id}' not found (convert it with `vfdata convert`)")
    with Recording.open(entry.mcap) as rec:
        if not rec.has(layout.WRENCH):
            raise InputError(entry.mcap, f"recording '{entry.id}' has no {layout.WRENCH}: no force to train on")
        return object_force_at(rec, times_ns).astype(np.float32)


def object_force_at(rec: Recording, times_ns: np.ndarray) -> np.ndarray:
    """(F, 3) N in the object frame: the recording's force interpolated at `times_ns` (NaN across sensor
    gaps), turned by the metadata's `sensor_to_object` rotation when the sensor's frame is not the
    object's (docs/bags.md)."""
    force = rec.force_at(times_ns)[:, :3]
    rotation = rec.metadata.extra.get("sensor_to_object")
    return force @ np.asarray(json.loads(rotation), dtype=np.float64).T if rotation else force


def decoded_tracks(spec: ClipSpec, times_ns: np.ndarray, points_object_mm: np.ndarray, visible: np.ndarray,
                   force_n: np.ndarray, rotation: np.ndarray, origin_mm: np.ndarray) -> Decoded:
    """Tracked points (F, N, 3) mm in the object frame (`rotation`, `origin_mm`: object -> camera) with
    their visibility (F, N) and the force (F, 3) N -> the spec's tokens, mirrored to the canonical side
    when the spec asks."""
    tokens, valid, side = track_tokens(spec, points_object_mm, visible, times_ns, (rotation, origin_mm))
    return Decoded(times_ns, mirror_y(force_n, side).astype(np.float32), tokens, valid, side)


def _cloud_draws(spec: ClipSpec, clouds_object_mm, rotation: np.ndarray, origin_mm: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    points, valid = [], []
    for i, cloud in enumerate(clouds_object_mm):
        if spec.frame == "camera":
            cloud = cloud @ rotation.T + origin_mm
        # the same points every epoch and run: the draw depends on the seed and frame only
        p, ok = sample_cloud(cloud, spec.cloud_points, np.random.default_rng([spec.seed, i]))
        points.append(p)
        valid.append(ok)
    return np.asarray(points, np.float32), np.asarray(valid, bool)


def _decode_processed(entry: ManifestEntry, spec: ClipSpec) -> Decoded:
    if spec.input == "rgb":
        return _decode_rgb(entry, spec)
    with DerivedRecording.open(entry.processed) as derived:
        frame = derived.object_frame
        if spec.input == "tracks":
            tracks = derived.tracks()
            return decoded_tracks(spec, tracks.times_ns, tracks.points_object_mm, tracks.visible,
                           force_at(entry, tracks.times_ns), frame.rotation, frame.origin)
        if spec.input == "cloud":
            stamps, clouds = zip(*derived.clouds_mm(), strict=True)
            times_ns = np.asarray(stamps, dtype=np.int64)
            points, valid = _cloud_draws(spec, clouds, frame.rotation, frame.origin)
            return Decoded(times_ns, force_at(entry, times_ns), points, valid)
        size = spec.image_size  # input "depth": the tissue-masked depth, resized
        times, frames = [], []
        for stamp, depth, mask in derived.depths_and_masks():
            depth = np.where(mask, np.nan_to_num(depth, nan=0.0), 0.0).astype(np.float32)
            frames.append(cv2.resize(depth, (size, size), interpolation=cv2.INTER_NEAREST)[None])
            times.append(stamp)
        times_ns = np.asarray(times, dtype=np.int64)
        return Decoded(times_ns, force_at(entry, times_ns), np.asarray(frames, np.float16), None)


def _decode_rgb(entry: ManifestEntry, spec: ClipSpec) -> Decoded:
    """The left images of the recording MCAP itself (the RGB baseline needs no processing)."""
    if not entry.mcap.is_file():
        raise InputError(entry.mcap, f"recording '{entry.id}' not found (convert it with `vfdata convert`)")
    size = spec.image_size
    with Recording.open(entry.mcap) as rec:
        times_ns = np.asarray(rec.frame_times_ns, dtype=np.int64)
        images = np.empty((len(times_ns), 3, size, size), np.uint8)
        for i in range(len(times_ns)):
            bgr = cv2.resize(rec.left_image(i), (size, size), interpolation=cv2.INTER_AREA)
            images[i] = bgr[:, :, ::-1].transpose(2, 0, 1)
    return Decoded(times_ns, force_at(entry, times_ns), images, None)


def _decode_ground_truth(entry: ManifestEntry, spec: ClipSpec) -> Decoded:
    gt = entry.ground_truth
    for name in ("points.npy", "force.npy", "object_frame.json"):
        if not (gt / name).is_file():
            raise InputError(gt / name, f"simulator ground truth of recording '{entry.id}' not found")
    frames_csv = entry.raw / "frames.csv"
    if not frames_csv.is_file():
        raise InputError(frames_csv, f"frame times of recording '{entry.id}' not found")
    if spec.input not in ("tracks", "cloud"):
        raise InputError(gt, f"input '{spec.input}' needs processed recordings (source: processed)")
    times_ns = np.loadtxt(frames_csv, delimiter=",", skiprows=1, dtype=np.int64, ndmin=2)[:, 1]
    points_cam = np.load(gt / "points.npy").astype(np.float64)
    force = np.load(gt / "force.npy").astype(np.float32)[:, :3]
    visible = np.load(gt / "visible.npy") if (gt / "visible.npy").is_file() else np.ones(points_cam.shape[:2], bool)
    if not (len(times_ns) == len(points_cam) == len(force)):
        raise InputError(gt, f"{len(times_ns)} frame times, {len(points_cam)} point frames, {len(force)} forces")
    frame = json.loads((gt / "object_frame.json").read_text())
    rotation, origin = np.asarray(frame["rotation"]), np.asarray(frame["origin_mm"])
    points_obj = (points_cam - origin) @ rotation  # camera -> object: R^T (p - o)
    if spec.input == "cloud":  # a fresh draw of surface points each frame: no correspondences
        clouds = (p[v] for p, v in zip(points_obj, visible, strict=True))
        points, valid = _cloud_draws(spec, clouds, rotation, origin)
        return Decoded(times_ns, force, points, valid)
    # a fixed subset of the material points stands in for the tracked points: among those the first
    # frame shows (as tracking starts from them), or from the whole surface, all valid
    surface = spec.source == "ground_truth_surface"
    pool = np.arange(points_obj.shape[1]) if surface else np.flatnonzero(visible[0])
    rng = np.random.default_rng(spec.seed)
    keep = np.sort(rng.choice(pool, size=min(spec.num_points, len(pool)), replace=False))
    valid = np.ones((len(points_obj), len(keep)), bool) if surface else visible[:, keep]
    return decoded_tracks(spec, times_ns, points_obj[:, keep], valid, force, rotation, origin)


def _source_files(entry: ManifestEntry, spec: ClipSpec) -> list[Path]:
    if spec.source != "processed":
        return [entry.raw / "frames.csv", entry.ground_truth / "points.npy", entry.ground_truth / "force.npy"]
    return [entry.mcap] if spec.input == "rgb" else [entry.mcap, entry.processed]


def _cache_path(entry: ManifestEntry, spec: ClipSpec, cache_dir: Path) -> Path:
    files = _source_files(entry, spec)
    stamp = [(str(p.resolve()), p.stat().st_size, p.stat().st_mtime_ns) for p in files if p.exists()]
    # clip_frames and stride cut clips from the arrays; they do not change the arrays themselves
    keyed = {k: v for k, v in spec.to_dict().items() if k not in ("clip_frames", "stride")}
    key = hashlib.sha256(json.dumps([CACHE_VERSION, stamp, sorted(keyed.items())], default=str).encode())
    return cache_dir / f"{entry.id}-{key.hexdigest()[:20]}.npz"


def decode_recording(entry: ManifestEntry, spec: ClipSpec, cache_dir: str | Path | None = None) -> Decoded:
    """The recording's arrays for `spec`, from the disk cache when valid; then the entry's frame range."""
    cache = _cache_path(entry, spec, Path(cache_dir)) if cache_dir is not None else None
    if cache is not None and cache.is_file():
        with np.load(cache) as z:
            decoded = Decoded(z["times_ns"], z["force_n"], z["inputs"], z["valid"] if "valid" in z else None,
                              float(z["side"]))
        return decoded.window(entry.frames)
    decode = _decode_processed if spec.source == "processed" else _decode_ground_truth
    decoded = decode(entry, spec)
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_name(f".{cache.name}.tmp-{os.getpid()}.npz")
        arrays = dict(times_ns=decoded.times_ns, force_n=decoded.force_n, inputs=decoded.inputs,
                      side=np.float64(decoded.side))
        if decoded.valid is not None:
            arrays["valid"] = decoded.valid
        np.savez(tmp, **arrays)
        tmp.replace(cache)  # atomic: concurrent runs see a whole file or none
    return decoded.window(entry.frames)
