"""Force estimation on recordings without a force sensor (the paper's in vivo case), offline.

`predict_recording` (`vfdata predict`) runs the per-frame engine over a recording (depth, tissue
mask, cloud, object frame, tracks: `vfdata.engine`), keeps the derived recording beside its outputs,
turns the tracks into forces with the trained model, and writes
- `<id>.force.mcap`: `/force/estimate` (WrenchStamped in the object frame `tissue_object`, N), beside it
  `/force/estimate/band` (the half-width of each component's calibrated 90% band, N: `vfmodels.evaluation.band`)
  `/force/estimate/beyond` (how far each component lies beyond the training forces' range, N) and
  `/force/estimate/unlike` (how unlike training's each frame's input is: > 1 unlike), and the object frame
  on `/tf_static` (`vfdata.recording.derived.write_force_estimate`);
- `<id>.force.png`: Fx, Fy, Fz against the frame index, the band shaded and frames beyond training
  marked, with the measured force when there is one;
- `<id>.overlay.mp4`: the paper's Fig. 8, the force drawn on the left image at the tissue origin, with
  the band in its label.

Without an ECM pose (gravity unknown) the object frame's X axis is arbitrary: the image's up made
perpendicular to the tissue axis Z (`vfdata.recon.object_frame`), so Fx and Fy are meaningful only up
to that choice; on an RGB-D recording the frame is the board's (X: the image's right made perpendicular
to the board's normal) or the camera's. The output metadata says which (`x_axis`).

The model is causal: frame t's force uses frames up to t (and t+1 for its central-difference
velocity). It runs through `ForceRegressor.encode_frames` / `decode_frames`, the one inference path
(normalisation and symmetry views as in the test): by default frame t's force is the model's on the
latest clip ending at t (its last `spec.clip_frames` frames, the clip length it was trained on, from a
zero state); `window=N` takes N frames, `window=0` carries the state over the whole recording.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from vfdata.clips.decode import object_force_at
from vfdata.clips.spec import ClipSpec
from vfdata.clips.tokens import frame_rate, mirror_y, track_tokens
from vfdata.confidence import Confidence
from vfdata.errors import InputError, OutputExistsError, VisionForceError
from vfdata.processing import ProcessOptions, process_recording
from vfdata.recon.object_frame import ObjectFrame, x_axis_meaning
from vfdata.recording import Recording, layout
from vfdata.recording.derived import Tracks, read_tracker_name, read_tracks, write_force_estimate
from vfdata.rig import rig_for
from vfdata.tissue_lean import lean_metadata, recording_lean
from vfmodels.evaluation.band import band_metrics, describe, unfamiliar, unlikeness
from vfmodels.evaluation.metrics import force_metrics
from vfmodels.inference.overlay import OverlayVideo, draw_force_overlay, force_to_camera, overlay_scale
from vfmodels.inference.trained_model import TrainedModel, history, model_device
from vfmodels.reports.figures import plot_force_series
from vfmodels.training.regressor import Estimate, ForceRegressor

# ---- the model: tracks -> forces ---------------------------------------------------------------


@torch.no_grad()
def frame_embeddings(regressor: ForceRegressor, tokens: np.ndarray, valid: np.ndarray, batch: int = 256
                     ) -> torch.Tensor:
    """Per-frame embeddings (V, T, D) of every symmetry view (`ForceRegressor.encode_frames`; frames are
    independent before the temporal model, so they are batched freely)."""
    device = model_device(regressor)

    def tensor(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a))[None].to(device)

    return torch.cat([regressor.encode_frames(tensor(tokens[s:s + batch]), tensor(valid[s:s + batch]))
                      for s in range(0, len(tokens), batch)], dim=1)


@torch.no_grad()
def windowed_estimate(regressor: ForceRegressor, z: torch.Tensor, window: int) -> Estimate:
    """The `Estimate` (forces, band, spread: each (T, 3) N, NumPy) from per-frame embeddings (V, T, D):
    frame t from the temporal model run over frames max(0, t - window + 1)..t from a zero state (window
    0: one run over everything)."""
    t = z.shape[1]
    if window == 0 or t <= window:
        return Estimate(*(field[0].cpu().numpy() for field in regressor.decode_frames(z)[0]))
    index = np.arange(t)[:, None] + np.arange(-window + 1, 1)[None, :]  # all windows at once: (T, window)
    windows = z[:, torch.from_numpy(np.clip(index, 0, None)).to(z.device)]  # (V, T, window, D)
    out = regressor.decode_frames(windows.flatten(0, 1))[0]
    # Frames 0..window-2 have shorter histories: their windows start at frame 0 and repeat it; run
    # them exactly instead, from the one full run over the first window.
    first = regressor.decode_frames(z[:, :window])[0]
    fields = []
    for every, head in zip(out, first, strict=True):
        field = every[:, -1].clone()
        field[: window - 1] = head[0, : window - 1]
        fields.append(field.cpu().numpy())
    return Estimate(*fields)


def estimate_from_tracks(regressor: ForceRegressor, spec: ClipSpec, tracks: Tracks, window: int | None = None
                         ) -> tuple[Estimate, float]:
    """A whole recording's tracks -> (the `Estimate`: forces, band and spread, each (T, 3) N in the object
    frame, NumPy; the side it was read from: -1 when `spec.canonical_side` mirrored it, and the forces are
    turned back). `window`: frames of history (None: the clip length the model was trained on,
    `spec.clip_frames`; 0: the whole recording)."""
    tokens, valid, side = track_tokens(spec, tracks.points_object_mm, tracks.visible, tracks.times_ns,
                                       (tracks.frame.rotation, tracks.frame.origin))
    if not len(tokens):
        return Estimate(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)), side
    estimate = windowed_estimate(regressor, frame_embeddings(regressor, tokens, valid), history(spec, window))
    return estimate._replace(force_n=mirror_y(estimate.force_n, side)), side


# ---- offline pipeline ----------------------------------------------------------------------------


@dataclass
class PredictResult:
    force_mcap: Path
    plot: Path
    video: Path | None
    processed: Path
    frames: int
    force_fps: float  # model frames/s (tokens + encoder + LSTM), measured
    stage_fps: dict[str, float]
    up_known: bool
    x_axis: str  # what the object frame's X is (vfdata.recon.object_frame.x_axis_meaning)
    metrics: dict[str, float] | None = None  # against the recording's force sensor, as Table I (none without)
    band: str = ""  # the model's band calibration in words (vfmodels.evaluation.band.describe)
    band_metrics: dict[str, float] | None = None  # coverage and half-width against the sensor (none without)
    frames_beyond: int = 0  # frames with a component beyond the training range
    frames_unfamiliar: int = 0  # frames whose input is unlike training's (vfmodels.evaluation.band.unfamiliar)
    confidence: Confidence | None = None  # the processed recording's verdict (vfdata.confidence)
    lean_note: str | None = None  # the tissue hangs outside the training tissues (vfdata.tissue_lean), in words


def output_paths(src: Path, out_dir: Path, video: bool) -> dict[str, Path]:
    stem = src.name.removesuffix(".mcap")
    paths = {"force": out_dir / f"{stem}.force.mcap", "plot": out_dir / f"{stem}.force.png",
             "processed": out_dir / f"{stem}.predict.processed.mcap"}
    if video:
        paths["video"] = out_dir / f"{stem}.overlay.mp4"
    return paths


def _tracked_by(processed: Path) -> str | None:
    """The tracker named in a derived MCAP's metadata (None if unreadable: it is then redone)."""
    try:
        return read_tracker_name(processed)
    except VisionForceError:
        return None


def predict_recording(src: str | Path, ckpt: TrainedModel | str | Path, out_dir: str | Path | None = None,
                      options: ProcessOptions | None = None, window: int | None = None, video: bool = True,
                      progress: bool = True, overwrite: bool = False, reuse_processed: bool = True,
                      device: str = "cpu") -> PredictResult:
    """The whole pipeline on a recording MCAP (force channel and ECM pose not needed). Existing
    outputs are refused unless `overwrite`; an existing `<id>.predict.processed.mcap` (the tracks of
    an earlier run) is reused unless `reuse_processed` is False. `ckpt`: a checkpoint file or the model
    loaded from one (then `device` is the one it was loaded on)."""
    src = Path(src)
    if not src.is_file():
        raise InputError(src, "recording not found")
    model = TrainedModel.of(ckpt, device)
    regressor, spec = model.regressor, model.spec
    out_dir = Path(out_dir) if out_dir is not None else src.parent
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = output_paths(src, out_dir, video)
    for key in ("force", "plot", "video"):
        if key in paths and paths[key].exists() and not overwrite:
            raise OutputExistsError(paths[key])
    options = options or ProcessOptions()
    options.progress = progress
    if not (reuse_processed and paths["processed"].is_file() and _tracked_by(paths["processed"]) == options.tracker):
        process_recording(src, paths["processed"], options, overwrite=True)
    tracks = read_tracks(paths["processed"])

    started = time.perf_counter()
    window = history(spec, window)
    estimate, side = estimate_from_tracks(regressor, spec, tracks, window)
    force = estimate.force_n
    beyond = regressor.beyond_range(force)
    force_fps = len(force) / max(time.perf_counter() - started, 1e-9)
    x_axis = x_axis_meaning(tracks.metadata.object_frame_kind, tracks.metadata.up_known)
    calibration = regressor.band_calibration
    frames_beyond = int((beyond != 0).any(axis=1).sum())
    unlike = unfamiliar(estimate.distance, calibration)
    confidence = tracks.metadata.confidence
    lean_note, lean_meta = lean_metadata(recording_lean(tracks.metadata, tracks.frame, src), model.lean_deg)
    meta = {**(confidence.metadata() if confidence is not None else {}), **lean_meta,
            "stage": "predict", "source": str(src.resolve()), "processed": str(paths["processed"].resolve()),
            "checkpoint": str(model.path.resolve()), "clip_spec": json.dumps(spec.to_dict()),
            "window": str(window), "x_axis": x_axis, "side": str(side), "force_fps": f"{force_fps:.1f}",
            "band": json.dumps(None if calibration is None else calibration.to_dict()),
            "frames_beyond_training": str(frames_beyond), "frames_unlike_training": str(int(unlike.sum()))}
    force_mcap = write_force_estimate(paths["force"], tracks.times_ns, force, tracks.frame, meta, overwrite=overwrite,
                                      camera_frame_id=tracks.metadata.camera_frame_id, band_n=estimate.band_n,
                                      beyond_n=beyond, unlike=unlikeness(estimate.distance, calibration))
    with Recording.open(src) as rec:
        measured = object_force_at(rec, tracks.times_ns) if rec.has(layout.WRENCH) else None
        stem = src.name.removesuffix(".mcap")
        title = f"{stem}: estimated force (object frame; X {x_axis.split(':')[0]})"
        if confidence is not None and confidence.doubtful:
            title = f"DOUBTFUL ({', '.join(confidence.reasons)}): {title}"
        plot = plot_force_series(force, paths["plot"], measured_n=measured, title=title,
                                 band_n=estimate.band_n, beyond_n=beyond, unfamiliar=unlike,
                                 coverage=None if calibration is None else calibration.coverage)
        video_path = write_overlay_video(rec, paths["video"], tracks, force, measured, progress,
                                         band_n=estimate.band_n, beyond_n=beyond, unfamiliar=unlike) if video else None
    known = np.zeros(0, bool) if measured is None else np.isfinite(measured).all(axis=1)
    metrics = force_metrics(force[known], measured[known]) if known.sum() > 1 else None
    coverage = band_metrics(force[known], measured[known], estimate.band_n[known]) \
        if known.sum() > 1 and calibration is not None else None
    return PredictResult(force_mcap, plot, video_path, paths["processed"], len(force), force_fps,
                         tracks.metadata.json("stage_fps", {}), tracks.metadata.up_known, x_axis, metrics,
                         describe(calibration), coverage, frames_beyond, int(unlike.sum()), confidence, lean_note)


def write_overlay_video(rec: Recording, path: Path, tracks: Tracks, force_object_n: np.ndarray,
                        measured_object_n: np.ndarray | None, progress: bool = True, band_n: np.ndarray | None = None,
                        beyond_n: np.ndarray | None = None, unfamiliar: np.ndarray | None = None) -> Path:
    """The overlay video of a recording: the estimated (and measured) force at the object origin; its
    label gives |F| and, with `band_n` (T, 3) N, the band's half-width of each component, and says when
    a component lies beyond the training range (`beyond_n` (T, 3) N nonzero) or the input is unlike
    training's (`unfamiliar` (T,) bool)."""
    frame: ObjectFrame = tracks.frame
    force_cam = force_to_camera(force_object_n, frame.rotation)
    measured_cam = None if measured_object_n is None else force_to_camera(measured_object_n, frame.rotation)
    camera = rec.camera
    scale = overlay_scale(force_cam if measured_cam is None else np.concatenate([force_cam, measured_cam]),
                          camera.width)
    origin_uv = tuple(camera.project(frame.origin[None])[0])
    times = tracks.times_ns
    rig = rig_for(rec)
    with OverlayVideo(path, frame_rate(times)) as writer:
        for i in tqdm(range(len(force_cam)), desc="overlay video", unit="frame", disable=not progress):
            image = rig.image(rec.frame_index_at(int(times[i])))
            label = overlay_label(i, force_object_n[i], None if band_n is None else band_n[i],
                                  beyond_n is not None and bool((beyond_n[i] != 0).any()),
                                  unfamiliar is not None and bool(unfamiliar[i]))
            writer.write(draw_force_overlay(image, origin_uv, force_cam[i], scale, label,
                                            None if measured_cam is None else measured_cam[i]))
    return writer.path


def overlay_label(i: int, force_n: np.ndarray, band_n: np.ndarray | None, beyond: bool, unlike: bool) -> str:
    """Frame i's label in the overlay video: |F| (N), the band's half-widths (N) when calibrated, and the
    marks of a force beyond the training range and of an input unlike training's."""
    label = f"frame {i}  |F| = {np.linalg.norm(force_n):.2f} N"
    if band_n is not None and np.isfinite(band_n).all():
        label += "  band +-" + "/".join(f"{b:.1f}" for b in band_n) + " N"
    return label + ("  BEYOND TRAINING" if beyond else "") + ("  UNLIKE TRAINING" if unlike else "")


__all__ = ["PredictResult", "estimate_from_tracks", "frame_embeddings", "overlay_label", "predict_recording",
           "windowed_estimate", "write_overlay_video"]
