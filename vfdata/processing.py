"""`vfdata process`: recording MCAP -> derived MCAP (mask, depth, tissue cloud, object frame, tracks).

The stages are the pure functions of `vfdata.recon` and `vfdata.tracking`; this module only walks
the frames, feeds the stages and writes their results (docs/format.md, "Derived files"). Per-stage
wall times are kept in the derived file's metadata, so reports can show frames/s per stage."""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections import defaultdict, deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from vfdata import __version__
from vfdata.atomic import atomic_output
from vfdata.calibration import PinholeCamera
from vfdata.errors import InputError, VisionForceError
from vfdata.recon import Prompt, estimate_object_frame, make_depth_estimator, make_segmenter, tissue_cloud
from vfdata.recon.object_frame import ObjectFrame, origin_cut_by_view, up_in_camera
from vfdata.recon.preview import first_frame_preview
from vfdata.recording import Recording, layout
from vfdata.recording.messages import CompressedImage, Image, PointCloud2, TFMessage, TransformStamped
from vfdata.recording.writer import McapWriter

log = logging.getLogger(__name__)

TRACKERS = ("geometry", "geometry+", "klt", "cotracker", "groundtruth", "none")
DEPTH_UNIT_MM = 0.1  # /tissue/depth is 16UC1 in units of 0.1 mm: 6.5 m range, finer than any stereo

TRACK_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("visible", "u1")])
CLOUD_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")])


@dataclass
class ProcessOptions:
    depth: str = "sgbm"
    depth_options: dict = field(default_factory=dict)
    segment: str = "colortrack"
    segment_options: dict = field(default_factory=dict)
    prompt: str | None = None  # "box:x0,y0,x1,y1" or "points:x,y;x,y"; default: the recording's metadata
    tracker: str = "geometry"
    tracker_options: dict = field(default_factory=dict)
    num_points: int = 256
    seed: int = 0
    ground_truth: Path | None = None  # simulator ground truth (for depth 'recorded' and tracker 'groundtruth')
    # Nearest and farthest surface expected in front of the scope, mm: sets the stereo matcher's
    # disparity range unless depth_options give one. Without a floor, dark textureless background
    # matches at near-zero disparity (depth near infinity) and leaks into the tissue's edges.
    working_range_mm: tuple[float, float] = (40.0, 300.0)
    max_frames: int | None = None
    progress: bool = True


@dataclass
class StageClock:
    seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))

    def add(self, stage: str, started: float) -> float:
        now = time.perf_counter()
        self.seconds[stage] += now - started
        return now

    def fps(self, frames: int) -> dict[str, float]:
        return {stage: (frames / s if s > 0 else float("inf")) for stage, s in self.seconds.items()}


def default_output(src: Path) -> Path:
    """rec.mcap -> rec.processed.mcap, beside the source."""
    return src.with_name(src.name.removesuffix(".mcap") + ".processed.mcap")


def preview_path(out: Path) -> Path:
    """rec.processed.mcap -> rec.processed.png: the first-frame picture beside the derived MCAP."""
    return out.with_name(out.name.removesuffix(".mcap") + ".png")


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 22), b""):
            digest.update(block)
    return digest.hexdigest()


def find_ground_truth(rec: Recording, given: Path | None) -> Path | None:
    """The simulator's ground_truth/ folder: given, or beside the raw folder the recording came from."""
    if given is not None:
        if not Path(given).is_dir():
            raise InputError(given, "ground-truth folder not found")
        return Path(given)
    source = Path(rec.metadata.source) if rec.metadata.source else None
    if source is not None and (source / "ground_truth").is_dir():
        return source / "ground_truth"
    return None


def camera_up(rec: Recording) -> np.ndarray | None:
    """Gravity-up in the left camera frame at the first frame, from the ECM pose (None without one)."""
    if not rec.has(layout.ECM_POSE):
        return None
    _, quat = rec.ecm_pose_at(rec.frame_times_ns[:1])
    if not np.isfinite(quat).all():
        return None
    return up_in_camera(quat[0], rec.metadata.gravity_up_world)


def object_tf(frame: ObjectFrame, stamp_ns: int) -> TFMessage:
    """left camera -> object frame: origin in metres, rotation whose columns are X, Y, Z."""
    quat = Rotation.from_matrix(frame.rotation).as_quat()
    origin_m = tuple(float(v) * 1e-3 for v in frame.origin)
    return TFMessage([TransformStamped(stamp_ns, layout.LEFT_FRAME, layout.OBJECT_FRAME, origin_m, tuple(quat))])


def depth_image(depth_mm: np.ndarray, stamp_ns: int) -> Image:
    scaled = np.nan_to_num(depth_mm / DEPTH_UNIT_MM, nan=0.0, posinf=0.0, neginf=0.0)
    data = np.clip(np.rint(scaled), 0, 65535).astype("<u2")
    h, w = data.shape
    return Image(stamp_ns, layout.LEFT_FRAME, h, w, "16UC1", 0, 2 * w, data.tobytes())


def decode_depth(image: Image) -> np.ndarray:
    """A /tissue/depth message -> (H, W) float32 mm, NaN where unknown."""
    data = np.frombuffer(image.data, dtype="<u2").reshape(image.height, image.step // 2)[:, : image.width]
    depth = data.astype(np.float32) * np.float32(DEPTH_UNIT_MM)
    depth[data == 0] = np.nan
    return depth


def mask_image(mask: np.ndarray, stamp_ns: int) -> CompressedImage:
    import cv2

    ok, data = cv2.imencode(".png", mask.astype(np.uint8) * 255, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    return CompressedImage(stamp_ns, layout.LEFT_FRAME, "png", data.tobytes())


def tracks_cloud(points_object_mm: np.ndarray, visible: np.ndarray, stamp_ns: int) -> PointCloud2:
    array = np.zeros(len(points_object_mm), dtype=TRACK_DTYPE)
    for k, axis in enumerate("xyz"):
        array[axis] = points_object_mm[:, k]
    array["visible"] = visible.astype(np.uint8)
    return PointCloud2(stamp_ns, layout.OBJECT_FRAME, array)


def points_cloud(points_object_mm: np.ndarray, stamp_ns: int) -> PointCloud2:
    array = np.zeros(len(points_object_mm), dtype=CLOUD_DTYPE)
    for k, axis in enumerate("xyz"):
        array[axis] = points_object_mm[:, k]
    return PointCloud2(stamp_ns, layout.OBJECT_FRAME, array)


class _TrackerStage:
    """One interface over the trackers, whose inputs differ (clouds, images, depth, ground truth)."""

    def __init__(self, name: str, cloud: np.ndarray, camera: PinholeCamera, image: np.ndarray,
                 ground_truth: Path | None, options: ProcessOptions):
        self.name = name
        n, seed = options.num_points, options.seed
        if name in ("geometry", "geometry+"):
            from vfdata.tracking import GeometryTracker

            extra = {"mode": name, **options.tracker_options}
            if name == "geometry+":
                extra.setdefault("reference_image", image)
            self.tracker = GeometryTracker(cloud, camera=camera, num_points=n, seed=seed, **extra)
        elif name == "klt":
            from vfdata.tracking.klt import KLTTracker

            self.tracker = KLTTracker(cloud, camera, image, num_points=n, seed=seed, **options.tracker_options)
        elif name == "cotracker":
            from vfdata.tracking.cotracker import CoTrackerTracker

            tracker_options = dict(options.tracker_options)
            checkpoint = tracker_options.pop("checkpoint", None)
            self.tracker = CoTrackerTracker(cloud, camera, checkpoint, num_points=n, seed=seed, **tracker_options)
            self.clip: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        elif name == "groundtruth":
            from vfdata.tracking.groundtruth import GroundTruthTracker

            if ground_truth is None:
                raise InputError(Path("ground_truth"), "tracker 'groundtruth' needs the simulator's ground_truth/ "
                                 "folder (--ground-truth DIR, or beside the raw folder)")
            points = np.load(ground_truth / "points.npy", mmap_mode="r")
            normals = np.load(ground_truth / "normals.npy", mmap_mode="r")
            self.tracker = GroundTruthTracker(cloud, points, normals, camera=camera, num_points=n, seed=seed)
        else:
            raise VisionForceError(f"unknown tracker '{name}' (known: {', '.join(TRACKERS)})")

    @property
    def offline(self) -> bool:
        """Offline trackers (CoTracker) see the whole clip at once: frames are collected, and the
        tracks come from `finish()`."""
        return self.name == "cotracker"

    @property
    def points(self) -> np.ndarray:
        return self.tracker.reference if self.offline else self.tracker.points

    def update(self, index: int, cloud: np.ndarray, mask: np.ndarray, image: np.ndarray,
               depth_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.name in ("geometry", "geometry+"):
            return self.tracker.update(cloud, mask, image if self.name == "geometry+" else None)
        if self.name == "klt":
            return self.tracker.update(image, depth_mm, mask)
        return self.tracker.update(index, mask)

    def collect(self, mask: np.ndarray, image: np.ndarray, depth_mm: np.ndarray) -> None:
        self.clip.append((image[..., ::-1].copy(), depth_mm, mask))  # CoTracker takes RGB

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        images, depths, masks = (np.stack(parts) for parts in zip(*self.clip, strict=True))
        return self.tracker.track(images, depths, masks)


def process_recording(src: str | Path, out: str | Path | None = None, options: ProcessOptions | None = None,
                      overwrite: bool = False) -> Path:
    """Run depth, mask, cloud, object frame and tracking over a recording; write the derived MCAP."""
    options = options or ProcessOptions()
    src = Path(src)
    out = Path(out) if out is not None else default_output(src)
    if options.tracker not in TRACKERS:
        raise VisionForceError(f"unknown tracker '{options.tracker}' (known: {', '.join(TRACKERS)})")
    rec = Recording.open(src)
    for topic in (layout.LEFT_IMAGE, layout.RIGHT_IMAGE, layout.LEFT_INFO, layout.RIGHT_INFO):
        if not rec.has(topic):
            raise InputError(src, f"source has no {topic}: not a stereo recording")
    camera, baseline_mm = rec.camera, rec.stereo.baseline_mm
    prompt_text = options.prompt or rec.metadata.extra.get("prompt_box") and f"box:{_box_text(rec)}"
    if not prompt_text:
        raise InputError(src, "no tissue prompt: give --prompt box:x0,y0,x1,y1 (or points:x,y;...) or a "
                              "prompt_box in the recording's metadata")
    prompt = Prompt.parse(prompt_text)
    prompt.check_inside(camera.width, camera.height)
    ground_truth = find_ground_truth(rec, options.ground_truth)

    depth_options = dict(options.depth_options)
    if options.depth == "sgbm" and not {"min_disparity", "max_disparity"} & set(depth_options):
        near, far = options.working_range_mm
        depth_options["min_disparity"] = int(np.floor(camera.fx * baseline_mm / far))
        depth_options["max_disparity"] = int(np.ceil(camera.fx * baseline_mm / near))
    if options.depth == "recorded":
        if ground_truth is None:
            raise InputError(src, "depth 'recorded' needs the simulator's ground_truth/ (--ground-truth DIR)")
        depth_options.setdefault("depths", _recorded_depths(ground_truth))
    estimator = make_depth_estimator(options.depth, **depth_options)
    segmenter = make_segmenter(options.segment, **options.segment_options)
    up = camera_up(rec)

    n_frames = rec.num_frames if options.max_frames is None else min(rec.num_frames, options.max_frames)
    clock = StageClock()
    frame_info: ObjectFrame | None = None
    tracker = None
    with McapWriter(out, overwrite=overwrite) as writer:
        # The depth backend sees the frames as a stream, so it can overlap consecutive frames (sgbm
        # matches the next pair in a second thread while this one is refined).
        decoded: deque = deque()

        def pairs():
            for k in range(n_frames):
                started = time.perf_counter()
                decoded.append(rec.rectified_frame(k))
                clock.add("decode", started)
                yield decoded[-1].left, decoded[-1].right

        depths = estimator.depth_stream(pairs(), camera, baseline_mm)
        bar = tqdm(range(n_frames), desc=f"process {src.name}", unit="frame", disable=not options.progress)
        for i in bar:
            t = time.perf_counter()
            decode_before = clock.seconds["decode"]
            depth = next(depths)
            frame = decoded.popleft()
            # Waiting for the depth includes decoding the frames it pulled: count that as decode.
            t = clock.add("depth", t)
            clock.seconds["depth"] -= clock.seconds["decode"] - decode_before
            mask = segmenter.start(frame.left, prompt, depth) if i == 0 else segmenter.track(frame.left, depth)
            t = clock.add("mask", t)
            cloud = tissue_cloud(depth, mask, camera)
            t = clock.add("cloud", t)
            if i == 0:
                if not mask.any() or len(cloud) < 50:
                    raise InputError(src, f"the tissue mask of the first frame is empty ({int(mask.sum())} pixels, "
                                          f"{len(cloud)} points): check the prompt")
                frame_info = estimate_object_frame(cloud, up)
                origin_cut = origin_cut_by_view(cloud, frame_info, camera)
                if origin_cut:
                    log.warning("warning: %s: the tissue runs out of the image at its wide end: the object frame's "
                                "origin (2nd percentile along Z) may be where the view cuts it, not at the clamp "
                                "(see %s)", src, preview_path(out).name)
                t = clock.add("object_frame", t)
                writer.write(layout.TF_STATIC, object_tf(frame_info, frame.stamp_ns))
                if options.tracker != "none":
                    tracker = _TrackerStage(options.tracker, cloud, camera, frame.left, ground_truth, options)
                    points, visible = tracker.points, camera.in_mask(tracker.points, mask)
                    t = clock.add("tracking", t)
                preview = first_frame_preview(
                    frame.left, mask, camera, frame_info, points if tracker is not None else None, prompt.box,
                    warning="the tissue runs out of the image at its wide end: origin maybe not at the clamp"
                    if origin_cut else None)
            elif tracker is not None and not tracker.offline:
                points, visible = tracker.update(i, cloud, mask, frame.left, depth)
                t = clock.add("tracking", t)
            if tracker is not None and tracker.offline:
                tracker.collect(mask, frame.left, depth)
            writer.write(layout.TISSUE_MASK, mask_image(mask, frame.stamp_ns))
            writer.write(layout.TISSUE_DEPTH, depth_image(depth, frame.stamp_ns))
            writer.write(layout.TISSUE_POINTS, points_cloud(frame_info.to_object(cloud), frame.stamp_ns))
            if tracker is not None and not tracker.offline:
                writer.write(layout.TRACKING_POINTS, tracks_cloud(frame_info.to_object(points), visible,
                                                                  frame.stamp_ns))
            clock.add("write", t)
        bar.close()
        if tracker is not None and tracker.offline:
            t = time.perf_counter()
            all_points, all_visible = tracker.finish()
            clock.add("tracking", t)
            for i in range(n_frames):
                writer.write(layout.TRACKING_POINTS, tracks_cloud(frame_info.to_object(all_points[i]), all_visible[i],
                                                                  int(rec.frame_times_ns[i])))
        writer.add_metadata(layout.DERIVED_METADATA, {
            "stage": "process",
            "source": str(src.resolve()),
            "source_sha256": _sha256(src),
            "recording_id": rec.metadata.recording_id,
            "orientation_deg": str(rec.metadata.orientation_deg),
            "split": rec.metadata.split,
            "frames": str(n_frames),
            "depth": options.depth,
            "depth_parameters": json.dumps(_jsonable(estimator.parameters())),
            "segment": options.segment,
            "segment_parameters": json.dumps(_jsonable(getattr(segmenter, "parameters", lambda: {})())),
            "prompt": prompt_text,
            "tracker": options.tracker,
            "tracker_parameters": json.dumps(_jsonable({"num_points": options.num_points, "seed": options.seed,
                                                        **options.tracker_options})),
            "object_frame": json.dumps(_jsonable(frame_info.to_dict())),
            "origin_cut_by_view": str(origin_cut).lower(),
            "up_known": str(up is not None).lower(),
            "stage_fps": json.dumps({k: round(v, 2) for k, v in clock.fps(n_frames).items()}),
            "converter_version": __version__,
        })
    # Written once the MCAP is complete; it describes that MCAP, so it replaces an older picture.
    with atomic_output(preview_path(out), overwrite=True) as tmp:
        tmp.write_bytes(_png(preview))
    return out


def _png(image: np.ndarray) -> bytes:
    import cv2

    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise VisionForceError("the first-frame preview could not be encoded as PNG")
    return data.tobytes()


def _box_text(rec: Recording) -> str:
    text = rec.metadata.extra["prompt_box"]
    values = json.loads(text) if text.strip().startswith("[") else [float(v) for v in text.split(",")]
    return ",".join(str(int(round(float(v)))) for v in values)


def _recorded_depths(ground_truth: Path):
    import cv2

    for path in sorted((ground_truth / "depth").glob("*.png")):
        data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        depth = data.astype(np.float32) * np.float32(DEPTH_UNIT_MM)
        depth[data == 0] = np.nan
        yield depth


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items() if not isinstance(v, np.ndarray) or v.size <= 16}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return repr(value)
