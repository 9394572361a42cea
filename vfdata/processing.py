"""`vfdata process`: recording MCAP -> derived MCAP (mask, depth, tissue cloud, object frame, tracks)
and a picture of the first frame beside it.

This module only connects files to the engine (`vfdata.engine.FrameEngine`, the stages; the recording's
rig, `vfdata.rig`, builds and feeds it) and the derived layout (`vfdata.recording.derived`). Per-stage
rates are kept in the derived file's metadata, with the torch thread count they were measured with, the
cores and the load average at the end."""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from vfdata import __version__
from vfdata.atomic import atomic_outputs, check_output, output_os_error
from vfdata.confidence import Confidence, ConfidenceWatch
from vfdata.engine import EngineOptions, FrameEngine
from vfdata.errors import VisionForceError
from vfdata.recon import Prompt
from vfdata.recon.preview import first_frame_preview
from vfdata.recording import Recording
from vfdata.recording.derived import DerivedWriter
from vfdata.rig import rig_for
from vfdata.threads import DEFAULT_THREADS, thread_limit
from vfdata.tissue_lean import frame_lean
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


def prompt_text(prompt: Prompt) -> str:
    """The prompt as `Prompt.parse` reads it, e.g. "box:10,20,300,400 neg:50,60"."""
    parts = [f"box:{','.join(f'{v:g}' for v in prompt.box)}"] if prompt.box else []
    for kind, points in (("points", prompt.positive), ("neg", prompt.negative)):
        if points:
            parts.append(f"{kind}:" + ";".join(f"{x:g},{y:g}" for x, y in points))
    return " ".join(parts)


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
    rig = rig_for(rec, src)
    n_frames = rec.num_frames if options.max_frames is None else min(rec.num_frames, options.max_frames)
    rig.check()
    prompt = rig.prompt(options.prompt)
    engine = rig.engine(rig.stage_options(options), prompt, rig.ground_truth(options.ground_truth), look_ahead=n_frames)
    results = engine.run(rig.frames(n_frames))
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
        preview = first_frame_preview(first.left, first.mask, rig.camera, engine.frame, first.points_mm,
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
                                                             "rest", "end", "doubtful")})),
        **confidence.metadata(),
        "up_known": str(engine.up is not None).lower(),
        **_lean(engine),
        "stage_fps": json.dumps({k: round(v, 2) for k, v in engine.clock.fps(frames).items()}),
        "stage_threads": str(threads),
        # Beside the rates: whether the machine was shared while they were measured (load > cores: it was).
        "stage_cores": str(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()),
        "stage_load_1min": f"{os.getloadavg()[0]:.2f}",
        "converter_version": __version__,
    }


def _lean(engine: FrameEngine) -> dict[str, str]:
    """The tissue's lean below level (deg, `vfdata.tissue_lean`), where gravity is known."""
    lean = frame_lean(engine.frame, engine.up)
    return {} if lean is None else {"tissue_lean_deg": f"{lean:.2f}"}


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
