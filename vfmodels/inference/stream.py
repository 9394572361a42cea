"""A recording streamed frame by frame through the live estimator (`vfdata predict --stream`): what the
live view would estimate, with the per-frame latency, written as a force file beside the recording.

The recording is decoded before each frame's clock starts (decoding stands in for the camera driver), so
the latency is the estimator's own: `StreamingForceEstimator.push` per frame."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from vfdata.confidence import Confidence
from vfdata.engine import EngineOptions
from vfdata.errors import OutputExistsError
from vfdata.recon.object_frame import x_axis_meaning
from vfdata.recording.derived import write_force_estimate
from vfdata.sources import RecordingReplay
from vfmodels.inference.live import StreamingForceEstimator
from vfmodels.inference.trained_model import TrainedModel


@dataclass
class StreamResult:
    """What a streamed recording gave: its force file, counts, latency (ms) and per-stage times (ms/frame)."""

    force_mcap: Path
    frames: int
    estimates: int
    confidence: Confidence
    latency_ms: np.ndarray  # per pushed frame after the first two (which also fix the object frame)
    stage_ms: dict[str, float] = field(default_factory=dict)  # wall, per frame
    stage_cpu_ms: dict[str, float] = field(default_factory=dict)  # CPU time of the stage's thread, per frame
    frames_beyond: int = 0  # estimates beyond the training range (as `PredictResult.frames_beyond`)
    frames_unfamiliar: int = 0  # estimates whose input is unlike training's
    lean_note: str | None = None  # the tissue hangs outside the training tissues (vfdata.tissue_lean), in words


def stream_recording(recording: Path, ckpt: TrainedModel | Path, out: Path | None, options: EngineOptions, *,
                     prompt: str | None = None, window: int | None = None, pipelined: bool = False,
                     device: str = "cpu", max_frames: int | None = None, overwrite: bool = False,
                     progress: bool = True) -> StreamResult:
    """Feed `recording`'s frames one by one to a `StreamingForceEstimator` of `ckpt` (a checkpoint file or the
    model loaded from one) and write
    OUT/<id>.force.mcap (/force/estimate with its band and beyond, as `predict_recording` writes;
    OUT defaults to the recording's folder). The recording's rig gives the stage defaults of its kind."""
    out = Path(out or recording.parent)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{recording.name.removesuffix('.mcap')}.force.mcap"
    if path.exists() and not overwrite:
        raise OutputExistsError(path)
    source = RecordingReplay(recording, speed=0.0, max_frames=max_frames)
    try:
        rig = source.rig
        estimator = StreamingForceEstimator(ckpt, rig, rig.prompt(prompt), options, window=window,
                                            pipelined=pipelined, device=device)
        n, camera_frame = source.frames, rig.camera_frame_id
        estimates, latencies = [], []
        for stamp_ns, left, right, depth_mm in tqdm(source.decoded(), total=n, desc="stream", unit="frame",
                                                    disable=not progress):
            started = time.perf_counter()
            result = estimator.push(left, right, stamp_ns, depth_mm)
            latencies.append(time.perf_counter() - started)
            if result is not None:
                estimates.append(result)
        object_frame = estimator.frame
        x_axis = x_axis_meaning(object_frame.kind, rig.up is not None)
        lean_note, lean_meta = estimator.lean  # before flush, which ends the stream and its object frame
        estimates += estimator.flush()
        estimator.close()
    finally:
        source.close()
    calibration = estimator.regressor.band_calibration
    confidence = estimator.confidence
    beyond = sum(e.beyond_training for e in estimates)
    unfamiliar = sum(e.unfamiliar for e in estimates)
    write_force_estimate(path, np.array([e.stamp_ns for e in estimates]), np.stack([e.force_n for e in estimates]),
                         object_frame, {"stage": "predict --stream", "window": str(estimator.window), "x_axis": x_axis,
                                        "object_frame_kind": object_frame.kind, "camera_frame_id": camera_frame,
                                        "band": json.dumps(None if calibration is None else calibration.to_dict()),
                                        "frames_beyond_training": str(beyond),
                                        "frames_unlike_training": str(unfamiliar),
                                        **confidence.metadata(), **lean_meta},
                         overwrite=overwrite, camera_frame_id=camera_frame,
                         band_n=np.stack([e.band_n for e in estimates]),
                         beyond_n=np.stack([e.beyond_n for e in estimates]),
                         unlike=np.array([e.unlike for e in estimates]))
    return StreamResult(path, n, len(estimates), confidence, np.array(latencies[2:]) * 1000.0,
                        {k: 1000.0 * v / n for k, v in estimator.stage_seconds.items()},
                        {k: 1000.0 * v / n for k, v in estimator.stage_cpu_seconds.items()}, beyond, unfamiliar,
                        lean_note)
