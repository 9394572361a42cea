"""`vfdata process`: recording MCAP -> derived MCAP (mask, depth, tissue cloud, object frame, tracks)
and a picture of the first frame beside it.

This module only connects files to the engine (`vfdata.engine.FrameEngine`, the stages) and the
derived layout (`vfdata.recording.derived`). Per-stage rates are kept in the derived file's metadata,
with the torch thread count they were measured with, the cores and the load average at the end."""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from vfdata import __version__
from vfdata.atomic import atomic_outputs, check_output, output_os_error
from vfdata.confidence import Confidence, ConfidenceWatch
from vfdata.engine import SENSOR_DEPTH, EngineOptions, FrameEngine
from vfdata.errors import InputError, VisionForceError
from vfdata.object_frames import TUBE_FRAMES
from vfdata.recon import Prompt
from vfdata.recon.object_frame import up_in_camera
from vfdata.recon.preview import first_frame_preview
from vfdata.recording import Recording, layout
from vfdata.recording.derived import DerivedWriter
from vfdata.threads import DEFAULT_THREADS, thread_limit
from vfdata.tracker_kinds import IMAGE_TRACKERS, TRACKER_KINDS
from vfdata.tracking.motion_scan import scan_stride
from vfdata.tracking.registry import TRACKERS as TRACKER_NAMES

log = logging.getLogger(__name__)

TRACKERS = (*TRACKER_NAMES, "none")
ORIGIN_CUT_WARNING = "the tissue runs out of the image at its wide end: origin maybe not at the clamp"


@dataclass
class ProcessOptions(EngineOptions):
    """The engine's stages and settings, plus where the prompt and ground truth come from."""

    prompt: str | None = None  # "box:x0,y0,x1,y1" or "points:x,y;x,y"; default: the recording's metadata
    ground_truth: Path | None = None  # simulator ground truth (depth 'recorded', tracker 'groundtruth')
    max_frames: int | None = None
    progress: bool = True
    threads: int | None = DEFAULT_THREADS  # torch/OpenCV threads while processing (vfdata.threads); None: as set


def default_output(src: Path) -> Path:
    """rec.mcap -> rec.processed.mcap, beside the source."""
    return src.with_name(src.name.removesuffix(".mcap") + ".processed.mcap")


def preview_path(out: Path) -> Path:
    """rec.processed.mcap -> rec.processed.png: the first-frame picture beside the derived MCAP."""
    return out.with_name(out.name.removesuffix(".mcap") + ".png")


def sha256(path: Path) -> str:
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
    """Gravity-up in the left camera frame at the first frame, from the ECM pose (None without one, or
    when the converter had to assume the up direction of the pose's frame: a bag without gravity_up)."""
    if not rec.has(layout.ECM_POSE) or rec.metadata.extra.get("gravity_up_assumed") == "true":
        return None
    _, quat = rec.ecm_pose_at(rec.frame_times_ns[:1])
    if not np.isfinite(quat).all():
        return None
    return up_in_camera(quat[0], rec.metadata.gravity_up_world)


def recording_prompt(rec: Recording, src: Path, given: str | None) -> Prompt:
    """The first frame's tissue prompt: given, else the recording metadata's `prompt` or `prompt_box`."""
    if given:
        return Prompt.parse(given)
    if rec.metadata.extra.get("prompt"):
        return Prompt.parse(rec.metadata.extra["prompt"])
    box = rec.metadata.extra.get("prompt_box")
    if not box:
        raise InputError(src, "no tissue prompt: give --prompt box:x0,y0,x1,y1 (or points:x,y;...) or a "
                              "prompt_box in the recording's metadata")
    try:
        values = json.loads(box) if box.strip().startswith("[") else [float(v) for v in box.split(",")]
        return Prompt.from_box([float(v) for v in values])
    except (ValueError, TypeError) as exc:
        raise InputError(src, f"prompt_box {box!r} in the metadata is not x0,y0,x1,y1 ({exc})") from None


def prompt_text(prompt: Prompt) -> str:
    """The prompt as `Prompt.parse` reads it, e.g. "box:10,20,300,400 neg:50,60"."""
    parts = [f"box:{','.join(f'{v:g}' for v in prompt.box)}"] if prompt.box else []
    for kind, points in (("points", prompt.positive), ("neg", prompt.negative)):
        if points:
            parts.append(f"{kind}:" + ";".join(f"{x:g},{y:g}" for x, y in points))
    return " ".join(parts)


def stereo_engine(rec: Recording, src: Path, options: EngineOptions, prompt: str | None = None,
                  ground_truth: Path | None = None, frames: int | None = None) -> FrameEngine:
    """The engine for a stereo recording: its camera, baseline, prompt and gravity-up (ECM pose), and a
    look ahead over its first `frames` frames (default all) for the tube's frame."""
    for topic in (layout.LEFT_IMAGE, layout.RIGHT_IMAGE, layout.LEFT_INFO, layout.RIGHT_INFO):
        if not rec.has(topic):
            raise InputError(src, f"source has no {topic}: not a stereo recording")
    return FrameEngine(rec.camera, rec.stereo.baseline_mm, recording_prompt(rec, src, prompt), options,
                       up=camera_up(rec), ground_truth=ground_truth, look_ahead=lambda: scan_images(rec, frames))


def scan_images(rec: Recording, frames: int | None = None):
    """The left images a motion scan of the first `frames` frames looks at (vfdata.tracking.motion_scan):
    the first, then every k-th."""
    frames = rec.num_frames if frames is None else min(frames, rec.num_frames)
    return (rec.rectified_left(k) for k in range(0, frames, scan_stride(frames)))


def rgbd_options(options: EngineOptions, src: Path) -> EngineOptions:
    """An RGB-D recording's stages: its recorded depth (no matching), the `plane` mask unless another
    is asked for (the stereo default, colortrack, needs a colour view registered to the depth), and the
    board frame unless the camera frame is asked for. The geometry trackers get a weak anchor to the
    reference positions (`lambda_anchor` 1 unless given): an organ on a board stays in place and only
    dents, and without it the points slid 3 mm along the surface over 200 frames at rest (measured on
    the Gao et al. recording; with it 0.2 mm, and the tracked press follows Fz more closely). `klt` lifts
    with the recorded depth (`lift=depth`): there is no right image to match in."""
    if options.depth not in ("sgbm", SENSOR_DEPTH):
        raise InputError(src, f"an RGB-D recording brings its depth: depth '{options.depth}' does not apply "
                              f"(leave --depth out, or --depth {SENSOR_DEPTH})")
    if options.object_frame in TUBE_FRAMES:
        raise InputError(src, "the tube's object frame does not apply to an RGB-D recording of a flat organ: "
                              "--object-frame board (default) or camera")
    if options.tracker in IMAGE_TRACKERS:
        log.warning(f"warning: {src}: tracker '{options.tracker}' follows the image, and an RGB-D recording's image "
                    "here is its depth drawn as grey, whose brightness a press changes: --tracker geometry "
                    "needs only the depth (docs/tracking.md)")
    tracker_options = dict(options.tracker_options)
    kind = TRACKER_KINDS.get(options.tracker)
    for key, value in (kind.rgbd_options if kind is not None else {}).items():
        tracker_options.setdefault(key, value)
    if tracker_options.get("lift", "depth") != "depth":
        raise InputError(src, f"an RGB-D recording has no right image: {options.tracker}'s lift "
                              f"'{tracker_options['lift']}' does not apply (lift=depth)")
    return replace(options, depth=SENSOR_DEPTH, segment="plane" if options.segment == "colortrack" else options.segment,
                   object_frame="board" if options.object_frame == "auto" else options.object_frame,
                   tracker_options=tracker_options)


def rgbd_engine(rec: Recording, src: Path, options: EngineOptions, prompt: str | None = None) -> FrameEngine:
    """The engine for an RGB-D recording: the depth camera, its recorded depth, the board frame."""
    for topic in (layout.DEPTH_IMAGE, layout.DEPTH_INFO):
        if not rec.has(topic):
            raise InputError(src, f"source has no {topic}: not an RGB-D recording")
    return FrameEngine(rec.depth_camera, 0.0, recording_prompt(rec, src, prompt), rgbd_options(options, src),
                       up=camera_up(rec))


def depth_view(depth_mm: np.ndarray, near_mm: float, far_mm: float) -> np.ndarray:
    """A depth image drawn as grey BGR (near bright, unknown black): the image the segmenter, the
    image-based trackers and the preview see when the colour view is not registered to the depth."""
    scaled = np.nan_to_num((far_mm - depth_mm) / max(far_mm - near_mm, 1e-6), nan=0.0)
    grey = np.clip(scaled * 255.0, 0, 255).astype(np.uint8)
    return cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)


def depth_frames(rec: Recording, frames: int):
    """(stamp_ns, depth view, depth_mm) of the first `frames` frames of an RGB-D recording; the view's
    grey range is the first frame's 1st-99th depth percentiles."""
    near = far = None
    for k in range(frames):
        depth = rec.depth_mm(k)
        if near is None:
            valid = depth[np.isfinite(depth)]
            if valid.size == 0:
                raise InputError(rec.path, "the first depth frame has no depth")
            near, far = (float(v) for v in np.percentile(valid, [1, 99]))
        yield int(rec.frame_times_ns[k]), depth_view(depth, near, far), depth


def frame_image(rec: Recording, i: int) -> np.ndarray:
    """The BGR image processing saw of frame i: the rectified left view, or an RGB-D recording's depth
    view (`depth_frames`' grey range)."""
    if not rec.is_rgbd:
        return rec.rectified_frame(i).left
    first = rec.depth_mm(0)
    near, far = (float(v) for v in np.percentile(first[np.isfinite(first)], [1, 99]))
    return depth_view(rec.depth_mm(i), near, far)


def stereo_pairs(rec: Recording, frames: int):
    """(stamp_ns, left, right) rectified pairs of the first `frames` frames."""
    for k in range(frames):
        frame = rec.rectified_frame(k)
        yield frame.stamp_ns, frame.left, frame.right


def process_recording(src: str | Path, out: str | Path | None = None, options: ProcessOptions | None = None,
                      overwrite: bool = False) -> Path:
    """Run depth, mask, cloud, object frame and tracking over a recording; write the derived MCAP.
    Runs with `options.threads` torch/OpenCV threads (default 1, vfdata.threads) and restores the
    caller's counts afterwards."""
    options = options or ProcessOptions()
    src = Path(src)
    out = Path(out) if out is not None else default_output(src)
    if options.tracker not in TRACKERS:
        raise VisionForceError(f"unknown tracker '{options.tracker}' (known: {', '.join(TRACKERS)})")
    with thread_limit(options.threads) as threads:
        return _process(src, out, options, overwrite, threads)


def _process(src: Path, out: Path, options: ProcessOptions, overwrite: bool, threads: int) -> Path:
    check_output(out, overwrite, inputs=[src])  # before the work: the source is never replaced
    check_output(preview_path(out), True, inputs=[src])
    rec = Recording.open(src)
    n_frames = rec.num_frames if options.max_frames is None else min(rec.num_frames, options.max_frames)
    if rec.is_rgbd:
        engine = rgbd_engine(rec, src, options, options.prompt)
    else:
        if options.object_frame == "auto":
            options = replace(options, object_frame="tissue")
        engine = stereo_engine(rec, src, options, options.prompt, find_ground_truth(rec, options.ground_truth),
                               frames=n_frames)
    results = engine.run_depth(depth_frames(rec, n_frames)) if rec.is_rgbd else engine.run(stereo_pairs(rec, n_frames))
    first = None
    watch: ConfidenceWatch | None = None  # the verdict on the recording (vfdata.confidence)
    # One transaction: the MCAP and its picture (which replaces an older one) are written to temporaries
    # and published together at the end; neither is left without the other.
    with atomic_outputs([preview_path(out), out], overwrite=(True, overwrite), inputs=[src]) as (png_tmp, mcap_tmp), \
            DerivedWriter(mcap_tmp, overwrite=True, camera_frame_id=rec.camera_frame_id) as writer:
        bar = tqdm(total=n_frames, desc=f"process {src.name}", unit="frame", disable=not options.progress)
        for result in results:
            t = engine.clock.now()
            if result.index == 0:
                writer.object_frame(engine.frame, result.stamp_ns)
                first = result
                watch = ConfidenceWatch(engine.frame.diagnostics.get("doubtful", []))
            writer.frame(result.stamp_ns, result.mask, result.depth_mm, engine.frame.to_object(result.cloud_mm))
            if result.points_mm is not None:
                writer.tracks(result.stamp_ns, engine.frame.to_object(result.points_mm), result.visible)
            watch.add(result.mask, result.depth_mm, result.visible)
            engine.clock.add("write", t)
            bar.update()
        bar.close()
        offline = engine.finish()
        if offline is not None:
            for i, (points, visible) in enumerate(zip(*offline, strict=True)):
                writer.tracks(int(rec.frame_times_ns[i]), engine.frame.to_object(points), visible)
            watch.set_tracks(offline[1])
        confidence = watch.verdict()
        if confidence.doubtful:
            log.warning(f"warning: {src}: doubtful: {confidence.describe()}")
        if confidence.notes:
            log.warning(f"note: {src}: {confidence.describe(confidence.notes)}")
        preview = first_frame_preview(first.left, first.mask, rec.camera, engine.frame, first.points_mm,
                                      engine.prompt.box, warning=("doubtful: " + ", ".join(confidence.reasons))
                                      if confidence.doubtful else ORIGIN_CUT_WARNING if engine.origin_cut else None)
        _write_png(png_tmp, preview, preview_path(out))
        writer.close(_metadata(rec, src, options, engine, n_frames, threads, confidence))
    return out


def _write_png(tmp: Path, image: np.ndarray, name: Path) -> None:
    """The preview `name` into its temporary `tmp`; its errors name the preview, not the MCAP."""
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise VisionForceError(f"{name}: the first-frame preview could not be encoded as PNG")
    try:
        tmp.write_bytes(data.tobytes())
    except OSError as exc:
        raise output_os_error(name, exc) or exc from exc


def _metadata(rec: Recording, src: Path, options: ProcessOptions, engine: FrameEngine, frames: int,
              threads: int, confidence: Confidence) -> dict:
    parameters = engine.parameters
    return {
        "stage": "process",
        "source": str(src.resolve()),
        "source_sha256": sha256(src),
        "recording_id": rec.metadata.recording_id,
        "orientation_deg": str(rec.metadata.orientation_deg),
        "split": rec.metadata.split,
        "frames": str(frames),
        "depth": engine.options.depth,
        "depth_parameters": json.dumps(_jsonable(parameters["depth"])),
        "segment": engine.options.segment,
        "segment_parameters": json.dumps(_jsonable(parameters["segment"])),
        "prompt": prompt_text(engine.prompt),
        "tracker": options.tracker,
        "tracker_parameters": json.dumps(_jsonable({k: v for k, v in parameters["tracker"].items() if k != "name"})),
        "object_frame": json.dumps(_jsonable(engine.frame.to_dict())),
        # tissue: the tube's object frame; board_plane: Z = the board's normal (up), origin under the
        # tissue's centroid; camera: the camera frame itself (docs/reconstruction.md)
        "object_frame_kind": engine.frame.kind,
        "camera_frame_id": rec.camera_frame_id,
        "origin_cut_by_view": str(engine.origin_cut).lower(),
        # the axis fits and the clamped end's cues (vfdata.recon.tissue_frame), and the verdict (vfdata.confidence)
        "object_frame_check": json.dumps(_jsonable({k: v for k, v in engine.frame.diagnostics.items()
                                                    if k in ("axis_from", "axis_doubtful", "axis_fits", "axis_rivals",
                                                             "end", "doubtful")})),
        **confidence.metadata(),
        "up_known": str(engine.up is not None).lower(),
        "stage_fps": json.dumps({k: round(v, 2) for k, v in engine.clock.fps(frames).items()}),
        "stage_threads": str(threads),
        # Beside the rates: whether the machine was shared while they were measured (load > cores: it was).
        "stage_cores": str(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()),
        "stage_load_1min": f"{os.getloadavg()[0]:.2f}",
        "converter_version": __version__,
    }


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
