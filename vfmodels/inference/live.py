"""Live force estimation: stereo pairs (or RGB-D frames) in, one at a time, forces out.

`StreamingForceEstimator.push(left, right, stamp_ns)` runs the per-frame engine (`vfdata.engine`:
depth, mask, cloud, object frame, tracking) on one rectified pair and the model on its tracks; an
RGB-D camera's frame comes as `push(view, None, stamp_ns, depth_mm)`, its depth replacing matching.
The input's rig (`vfdata.rig`) builds the engine, with the stage defaults of its kind.
Velocities are central differences (as in training), so frame t's force is known once frame t+1 has
arrived: `push` returns the estimate of the previous frame (one frame of latency, 33 ms at 30
frames/s), None on the first call. Over a whole recording the forces equal `vfmodels.inference.predict`'s.

`pipelined=True` runs the image stages (depth, mask, cloud) of frame t in a worker thread while the
calling thread tracks frame t-1 and runs the model (OpenCV, NumPy and PyTorch release the GIL): on two
cores the throughput is set by the slower half instead of the sum, for one more frame of latency.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from vfdata.clips.spec import ClipSpec
from vfdata.clips.tokens import mirror_y, relaxation_step, relaxation_weight, track_tokens
from vfdata.confidence import Confidence, ConfidenceWatch
from vfdata.engine import EngineOptions, FrameResult, ImageStages
from vfdata.errors import VisionForceError
from vfdata.recon import Prompt
from vfdata.rig import Rig
from vfdata.tissue_lean import frame_lean, lean_metadata
from vfmodels.evaluation.band import unlikeness
from vfmodels.inference.trained_model import TrainedModel, history, model_device
from vfmodels.training.regressor import ForceRegressor

# The live default of the depth's region of interest (`EngineOptions.depth_roi_margin_px`): depth
# only in the previous mask's box grown by this many pixels. On the simulated mini recording it cut
# depth's CPU time ~4x with the same depth error inside the tissue (bench/study_live_depth.py,
# docs/live.md); offline processing keeps the whole image.
LIVE_DEPTH_ROI_MARGIN_PX = 24
STAMP_HISTORY = 64  # frames whose median interval is a stream's period (a recording's: all of them)


@dataclass
class ForceEstimate:
    stamp_ns: int  # the frame the force belongs to (one frame before the latest push)
    force_n: np.ndarray  # (3,) object frame
    latency_s: float  # wall time of the push that produced it (all stages + model)
    band_n: np.ndarray  # (3,) N, the half-width of each component's calibrated band (NaN: no calibration)
    beyond_n: np.ndarray  # (3,) N, how far each component lies beyond the training range (0 inside)
    # Why the stream is doubtful so far (keys of vfdata.confidence.REASONS; empty: not doubtful).
    doubtful: tuple[str, ...] = ()
    unlike: float = float("nan")  # the input's embedding distance over its limit (band.unlikeness; NaN: unknown)

    @property
    def beyond_training(self) -> bool:
        """Some component lies beyond the training range (`/force/estimate/beyond` nonzero)."""
        return bool(np.any(self.beyond_n != 0))

    @property
    def unfamiliar(self) -> bool:
        """The frame's input is unlike training's (`vfmodels.evaluation.band.unfamiliar`)."""
        return bool(self.unlike > 1.0)


def skipped_frame_rate(fps: float, stamps_ns: np.ndarray) -> float:
    """The rate velocities use over consecutive pushes: the model's `fps`, divided by the whole number
    of frame periods between pushes when a source skipped frames (a live camera the estimator could
    not keep up with: `vfdata live`), so a velocity stays mm/s. Jitter under half a period keeps `fps`."""
    if len(stamps_ns) < 2:
        return fps
    steps = round(float(np.median(np.diff(stamps_ns.astype(np.float64)))) * fps / 1e9)
    return fps / max(1, steps)


class StreamingForceModel:
    """The model half of live estimation: object-frame tracks in, one frame at a time, forces out.

    `push(stamp_ns, points_object_mm (N, 3), visible (N,))` -> (stamp, force (3,) N, band half-width (3,)
    N, embedding distance from training's) of the previous frame, or None on the first frame; `flush()`
    gives the last frame's. Each frame's tokens follow the recipe of training
    (`vfdata.clips.tokens.track_tokens`), and its force and band are the regressor's
    (`ForceRegressor.encode_frames` / `decode_frames`, symmetry views included) on the last `window` frames
    (None: the clip length it was trained on; 0: the state carried over the whole stream)."""

    def __init__(self, regressor: ForceRegressor, spec: ClipSpec, rotation: np.ndarray, origin_mm: np.ndarray,
                 window: int | None = None):
        self.regressor, self.spec, self.window = regressor, spec, history(spec, window)
        self.object_frame = (np.asarray(rotation), np.asarray(origin_mm))
        self.recent: deque = deque(maxlen=3)  # (stamp, object-frame points, visible) of the last frames
        self.stamps: deque = deque(maxlen=STAMP_HISTORY)  # the source's period, as a recording's median
        self.embeddings: deque = deque(maxlen=self.window or 1)  # (V, 1, D) per frame
        self.state = None  # the temporal model's, when the window is the whole stream
        self.first: tuple[np.ndarray, np.ndarray] | None = None  # the first frame: mirror side, subset
        self.reference: np.ndarray | None = None  # each point's first visible position (displacements)
        # the relaxation's average of each point's displacement at the frames in `recent` (the last: now)
        self.averages: deque = deque(maxlen=3)

    def push(self, stamp_ns: int, points_object_mm: np.ndarray, visible: np.ndarray
             ) -> tuple[int, np.ndarray, np.ndarray, float] | None:
        points, visible = np.asarray(points_object_mm, dtype=np.float64), np.asarray(visible, dtype=bool)
        self.recent.append((int(stamp_ns), points, visible))
        self.stamps.append(int(stamp_ns))
        if self.reference is None:
            self.reference = np.full_like(points, np.nan)
        first_seen = np.isnan(self.reference).any(axis=1) & visible & np.isfinite(points).all(axis=1)
        self.reference[first_seen] = points[first_seen]
        if "relax" in self.spec.features:  # stepped through every frame, as over a whole recording
            ok = visible & np.isfinite(points).all(axis=1) & np.isfinite(self.reference).all(axis=1)
            rate = skipped_frame_rate(self.spec.fps or 30.0, np.array(self.stamps, dtype=np.int64))
            last = self.averages[-1] if self.averages else None
            self.averages.append(relaxation_step(last, points - self.reference, ok, relaxation_weight(rate)))
        if self.first is None:
            self.first = (points, visible)
            return None
        # The middle frame of the last three (the first frame, from the first two): its velocity is
        # a central difference (one-sided at the start), as over a whole recording.
        return self._estimate(len(self.recent) - 2)

    def flush(self) -> tuple[int, np.ndarray, np.ndarray, float] | None:
        """The last frame's estimate (one-sided velocity), at the end of a stream; then resets."""
        result = None
        if len(self.recent) >= 2:
            while len(self.recent) > 2:
                self.recent.popleft()
            while len(self.averages) > 2:
                self.averages.popleft()
            result = self._estimate(1)
        self.recent.clear()
        self.stamps.clear()
        self.embeddings.clear()
        self.averages.clear()
        self.state = self.first = self.reference = None
        return result

    @torch.no_grad()
    def _estimate(self, target: int) -> tuple[int, np.ndarray, np.ndarray, float]:
        recent = list(self.recent)
        # Velocities as over a whole recording: one-sided across a dropped frame (an interval over
        # GAP_FACTOR periods: a Kinect's, 70 ms of 30), at the rate of the source's usual period.
        history_ns = np.array(self.stamps, dtype=np.int64)
        tokens, valid, side = track_tokens(
            self.spec, np.stack([p[1] for p in recent]), np.stack([p[2] for p in recent]),
            np.array([p[0] for p in recent]), self.object_frame, first=self.first,
            fps=skipped_frame_rate(self.spec.fps or 30.0, history_ns), reference_mm=self.reference,
            period_ns=float(np.median(np.diff(history_ns))) if len(history_ns) > 1 else None,
            average_mm=np.stack(list(self.averages)) if self.averages else None)
        device = model_device(self.regressor)
        z = self.regressor.encode_frames(torch.from_numpy(tokens[target])[None, None].to(device),
                                         torch.from_numpy(valid[target])[None, None].to(device))  # (V, 1, D)
        if self.window == 0:
            estimate, self.state = self.regressor.decode_frames(z, self.state)
        else:
            self.embeddings.append(z)
            estimate, _ = self.regressor.decode_frames(torch.cat(list(self.embeddings), dim=1))
        force, band = (field[0, -1].cpu().numpy().astype(np.float64) for field in estimate[:2])
        return recent[target][0], mirror_y(force, side), band, float(estimate.distance[0, -1])


class StreamingForceEstimator:
    """Frame-by-frame force estimation from a live source (see the module docstring).

    `push(left, right, stamp_ns)` (BGR uint8 images) -> a `ForceEstimate` of an earlier frame, or None
    while the pipeline fills; `flush()` returns what is still in it, and the next push starts a new
    stream. `engine.clock` holds each stage's wall time and the CPU time of the thread that ran it."""

    def __init__(self, ckpt: TrainedModel | str | Path, rig: Rig, prompt: str | Prompt,
                 options: EngineOptions | None = None, window: int | None = None, pipelined: bool = False,
                 device: str = "cpu"):
        """`ckpt`: a checkpoint file or the model loaded from one; `rig`: the input (a recording replayed or a
        camera, `vfdata.rig`); `options` get its kind's defaults (`Rig.stage_options`); `device`: where the
        force model runs (the tracker's is `options.tracker_options["device"]`); `window`: frames of history
        (None: the clip length the model was trained on; 0: the whole stream)."""
        self.rig, self.options = rig, rig.stage_options(options or EngineOptions())
        model = TrainedModel.of(ckpt, device)
        self.regressor, self.spec = model.regressor, model.spec
        self.training_lean = model.lean_deg  # how low the training tissues hang (deg; vfdata.tissue_lean)
        self.prompt = prompt if isinstance(prompt, Prompt) else Prompt.parse(prompt)
        self.window, self.pipelined = history(self.spec, window), pipelined
        self._pool: ThreadPoolExecutor | None = None
        self._finished_clock = None
        self._finished_confidence: Confidence | None = None
        # Called with each tracked frame's FrameResult before its force is estimated (the live view).
        self.on_frame: Callable[[FrameResult], None] | None = None
        self._reset()

    def _reset(self) -> None:
        self.engine = self.rig.engine(self.options, self.prompt)
        self.model: StreamingForceModel | None = None
        self.watch: ConfidenceWatch | None = None
        self.frames = 0
        self._pending: tuple[ImageStages, np.ndarray, int] | None = None

    @property
    def frame(self):
        """The object frame, fixed on the first frame of the stream."""
        return self.engine.frame

    def _track(self, images: ImageStages, left: np.ndarray, stamp_ns: int
               ) -> tuple[int, np.ndarray, np.ndarray, float] | None:
        result = self.engine.track(self.engine.frames, stamp_ns, left, images)
        if self.engine.offline_tracker:
            raise VisionForceError(f"tracker '{self.options.tracker}' is offline (whole clip): not for streaming")
        if self.on_frame is not None:
            self.on_frame(result)
        if self.model is None:
            self.model = StreamingForceModel(self.regressor, self.spec, self.frame.rotation, self.frame.origin,
                                             self.window)
            self.watch = ConfidenceWatch(self.frame.diagnostics.get("doubtful", []))
        # The verdict as far as the stream has come: what `vfdata process` says of a whole recording, without
        # the look ahead at its motion (a stream has no future frames), so the end may be told by fewer cues.
        self.watch.add(result.mask, result.depth_mm, result.visible)
        t = self.engine.clock.now()
        estimate = self.model.push(stamp_ns, self.frame.to_object(result.points_mm), result.visible)
        self.engine.clock.add("force", t)
        return estimate

    def push(self, left: np.ndarray, right: np.ndarray | None, stamp_ns: int,
             depth_mm: np.ndarray | None = None) -> ForceEstimate | None:
        """One frame: a rectified stereo pair, or an RGB-D camera's `depth_mm` (H, W) mm with its view
        as `left` (`vfdata.rig.depth_view`) and no `right`."""
        t0 = time.perf_counter()
        first = self.frames == 0
        self.frames += 1
        if not self.pipelined:
            result = self._track(self.engine.image_stages(left, right, first, depth_mm), left, stamp_ns)
        else:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(1, thread_name_prefix="vf-image-stages")
            future = self._pool.submit(self.engine.image_stages, left, right, first, depth_mm)
            result = self._track(*self._pending) if self._pending is not None else None
            self._pending = (future.result(), left, stamp_ns)
        return None if result is None else self._estimate(result, t0)

    def _estimate(self, result: tuple[int, np.ndarray, np.ndarray, float], t0: float) -> ForceEstimate:
        stamp, force, band, distance = result
        reasons = tuple(self.watch.verdict().reasons) if self.watch is not None else ()
        return ForceEstimate(stamp, force, time.perf_counter() - t0, band, self.regressor.beyond_range(force),
                             reasons, float(unlikeness(np.asarray(distance), self.regressor.band_calibration)))

    @property
    def lean(self) -> tuple[str | None, dict[str, str]]:
        """The stream's tissue's lean against the training tissues' (`vfdata.tissue_lean.lean_metadata`: the words
        when it hangs outside their range, and the force file's metadata), once its object frame is fixed."""
        frame = self.engine.frame if self.model is not None else None
        return lean_metadata(None if frame is None else frame_lean(frame, self.engine.up), self.training_lean)

    @property
    def confidence(self) -> Confidence | None:
        """The verdict on the current stream so far, or on the one `flush` ended (None before any frame)."""
        if self.watch is not None:
            return self.watch.verdict()
        return self._finished_confidence

    def flush(self) -> list[ForceEstimate]:
        """The estimates still in the pipeline at the end of a stream, in frame order."""
        out = []
        t0 = time.perf_counter()
        if self._pending is not None:
            result = self._track(*self._pending)
            if result is not None:
                out.append(self._estimate(result, t0))
        if self.model is not None:
            result = self.model.flush()
            if result is not None:
                out.append(self._estimate(result, t0))
        self._finished_clock = self.engine.clock
        self._finished_confidence = self.confidence
        self._reset()
        return out

    @property
    def clock(self):
        """Stage times of the current stream, or of the one `flush` ended when none has started."""
        return self.engine.clock if self.frames or self._finished_clock is None else self._finished_clock

    @property
    def stage_seconds(self) -> dict[str, float]:
        return dict(self.clock.seconds)

    @property
    def stage_cpu_seconds(self) -> dict[str, float]:
        return dict(self.clock.cpu_seconds)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
