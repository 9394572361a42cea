"""Force estimation on recordings without a force sensor (the paper's in vivo case), offline and live.

Offline (`predict_recording`, `vfdata predict`): the recording is processed (depth, tissue mask,
cloud, object frame, tracks; `vfdata.processing`), the trained model turns the tracks into forces,
and the results are written as
- `<id>.force.mcap`: `/force/estimate` (geometry_msgs/msg/WrenchStamped, frame_id `tissue_object`, N;
  torque is not estimated and is NaN) and the object frame on `/tf_static`;
- `<id>.force.png`: Fx, Fy, Fz against the frame index;
- `<id>.overlay.mp4`: the paper's Fig. 8, the force drawn on the left image at the tissue origin.

Without an ECM pose (gravity unknown) the object frame's X axis is arbitrary: it is the image's up
direction made perpendicular to the tissue axis Z (`vfdata.recon.object_frame`), so Fx and Fy are
only meaningful up to that choice; the output metadata states it (`x_axis`).

Live (`StreamingForceEstimator`, `vfdata predict --stream`): `push(left, right, stamp_ns)` runs the
per-frame stages on one stereo pair as it arrives. Velocities are central differences (as in
training), so frame t's force is known once frame t+1 has arrived: `push` returns the estimate of the
previous frame (one frame of latency, 33 ms at 30 frames/s), None on the first call.

The model is causal: an estimate uses the frames up to its own. By default the LSTM runs from a zero
state over the last `window` = 16 frames (the clip length it was trained and tested on), so its
state never sees more history than in training; `window=None` carries the LSTM state over the whole
stream instead (constant cost per frame, but a state regime the model was not trained on).
"""

from __future__ import annotations

import json
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from vfdata.calibration import PinholeCamera
from vfdata.errors import InputError, VisionForceError
from vfdata.recon.preview import draw_label
from vfdata.recording import McapWriter, Recording, layout
from vfdata.recording.messages import TFMessage, TransformStamped, WrenchStamped

CLIP_FRAMES = 16

# ---- the force overlay (Fig. 8) ------------------------------------------------------------------


def force_to_camera(force_object_n: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(..., 3) forces in the object frame -> left camera frame. `rotation` (3, 3) has the object
    axes X, Y, Z as columns in camera coordinates (`ObjectFrame.rotation`)."""
    return np.asarray(force_object_n, dtype=np.float64) @ np.asarray(rotation, dtype=np.float64).T


def project_point(camera: PinholeCamera, point_mm: np.ndarray) -> tuple[float, float]:
    """Pixel (u, v) of a 3D point (mm) in the left camera frame."""
    x, y, z = (float(v) for v in point_mm)
    return camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy


def draw_force_overlay(image_bgr: np.ndarray, origin_uv: tuple[float, float], force_camera_n: np.ndarray,
                       px_per_n: float = 40.0, label: str | None = None) -> np.ndarray:
    """A copy of `image_bgr` with the force drawn at `origin_uv` (pixels), as the paper's Fig. 8.

    The in-plane part (Fx, Fy of the camera frame: right, down) is an arrow of `px_per_n` pixels per
    newton; the part along the optical axis is a circle of radius `px_per_n` * |Fz|, green when the
    force points away from the camera (into the scene), red when it points toward it. A NaN force
    draws only the origin marker."""
    import cv2

    out = np.ascontiguousarray(image_bgr).copy()
    u0, v0 = (int(round(c)) for c in origin_uv)
    cv2.drawMarker(out, (u0, v0), (255, 255, 255), cv2.MARKER_CROSS, 10, 1, cv2.LINE_AA)
    force = np.asarray(force_camera_n, dtype=np.float64)
    if np.isfinite(force).all():
        tip = (int(round(u0 + px_per_n * force[0])), int(round(v0 + px_per_n * force[1])))
        radius = int(round(px_per_n * abs(force[2])))
        if radius > 0:
            colour = (60, 200, 60) if force[2] > 0 else (60, 60, 230)
            cv2.circle(out, (u0, v0), radius, colour, 2, cv2.LINE_AA)
        if tip != (u0, v0):
            cv2.arrowedLine(out, (u0, v0), tip, (0, 220, 255), 3, cv2.LINE_AA, tipLength=0.2)
    if label:
        draw_label(out, label, (10, 24), scale=0.6)
    return out


def overlay_scale(force_camera_n: np.ndarray, image_width: int) -> float:
    """Pixels per newton so that the largest in-plane force (99th percentile) spans a fifth of the
    image width: readable arrows whatever the force range of the recording."""
    force = np.asarray(force_camera_n, dtype=np.float64).reshape(-1, 3)
    magnitude = np.linalg.norm(force[np.isfinite(force).all(axis=1)], axis=1)
    big = float(np.percentile(magnitude, 99)) if len(magnitude) else 0.0
    return 0.2 * image_width / big if big > 1e-6 else 40.0


def plot_force_series(force_n: np.ndarray, path: str | Path, frame_index: np.ndarray | None = None,
                      measured_n: np.ndarray | None = None, title: str = "", frame_label: str = "object frame"
                      ) -> Path:
    """Fx, Fy, Fz (N) against the frame index (one panel each); the measured force, when a recording
    has one, dashed on top."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from vfdata.reports import save_figure

    force = np.asarray(force_n, dtype=np.float64).reshape(-1, 3)
    index = np.arange(len(force)) if frame_index is None else np.asarray(frame_index)
    fig, axes = plt.subplots(3, 1, figsize=(10, 6.5), sharex=True)
    for k, (ax, name, colour) in enumerate(zip(axes, "xyz", ("tab:red", "tab:green", "tab:blue"), strict=True)):
        ax.plot(index, force[:, k], color=colour, lw=1.2, label="estimated")
        if measured_n is not None:
            ax.plot(index, np.asarray(measured_n)[:, k], color="black", lw=1.0, ls="--", label="measured")
        ax.set_ylabel(f"F{name} (N)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("frame")
    fig.suptitle(title or f"estimated force ({frame_label})")
    return save_figure(fig, path)


class OverlayVideo:
    """An MP4 (mp4v) writer for overlay frames; the size comes from the first frame. Written to a
    temporary name and renamed on close, like every other output."""

    def __init__(self, path: str | Path, fps: float = 30.0):
        self.path = Path(path)
        self.tmp = self.path.with_name(self.path.stem + ".partial" + self.path.suffix)
        self.fps = fps
        self.writer = None
        self.frames = 0

    def write(self, image_bgr: np.ndarray) -> None:
        import cv2

        if self.writer is None:
            h, w = image_bgr.shape[:2]
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.writer = cv2.VideoWriter(str(self.tmp), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w, h))
            if not self.writer.isOpened():
                raise VisionForceError(f"{self.path}: OpenCV cannot write mp4v video here")
        self.writer.write(np.ascontiguousarray(image_bgr))
        self.frames += 1

    def close(self) -> Path:
        if self.writer is not None:
            self.writer.release()
            self.tmp.replace(self.path)
        return self.path

    def __enter__(self) -> OverlayVideo:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        elif self.writer is not None:
            self.writer.release()
            self.tmp.unlink(missing_ok=True)


# ---- model input ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class TokenSpec:
    """How the point tokens of a model are made from tracks, with the names and meaning of
    `vfdata.datasets.ForceDataModule` (the model must see what it was trained on): frame "object" or
    "camera"; features "pos_vel", "pos" or "vel"; subset "all" or "top_bottom_20" (the top and bottom
    20% of the points by object-frame z on the first frame); `fps` for velocities in mm/s;
    `canonical_side` as `ForceClipDataset`'s (the caller mirrors the tracks and the forces: `side`)."""

    def side(self, points_object_mm: np.ndarray, visible: np.ndarray) -> float:
        """The y factor for a recording whose first frame is given: -1 to mirror it, else +1."""
        from vfdata.datasets import seen_side

        return seen_side(points_object_mm, visible) if self.canonical_side else 1.0

    frame: str = "object"
    features: str = "pos_vel"
    subset: str = "all"
    fps: float = 30.0
    canonical_side: bool = False  # mirror y when the first frame shows the y < 0 flank (and Fy back)

    def __post_init__(self):
        if self.canonical_side and self.frame != "object":
            raise VisionForceError("canonical_side mirrors tracks in the object frame, not the camera frame")

    @property
    def channels(self) -> int:
        return 6 if self.features == "pos_vel" else 3


def point_tokens(points_object_mm: np.ndarray, visible: np.ndarray, spec: TokenSpec,
                 rotation: np.ndarray | None = None, origin_mm: np.ndarray | None = None,
                 keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Consecutive tracks (T, N, 3) in the object frame (mm) + visibility (T, N) -> tokens (T, N', C)
    float32 and valid (T, N') bool, exactly as the training data (`vfdata.datasets.point_features`:
    central-difference velocities, one-sided at the ends; a point whose stencil has a lost neighbour
    is invalid). The camera-frame variant needs the object frame (`rotation`, `origin_mm`); `keep`
    fixes the top/bottom subset (default: chosen on the first of these frames)."""
    from vfdata.datasets import TOP_BOTTOM_FRACTION, point_features, top_bottom

    points = np.asarray(points_object_mm, dtype=np.float64)
    visible = np.asarray(visible, dtype=bool)
    if spec.subset == "top_bottom_20":
        keep = top_bottom(points[0], TOP_BOTTOM_FRACTION) if keep is None else keep
        points, visible = points[:, keep], visible[:, keep]
    elif spec.subset != "all":
        raise VisionForceError(f"unknown point subset '{spec.subset}'")
    if spec.frame == "camera":
        if rotation is None or origin_mm is None:
            raise VisionForceError("camera-frame tokens need the object frame's rotation and origin")
        points = points @ np.asarray(rotation).T + np.asarray(origin_mm)
    try:
        return point_features(points, visible, [(0, len(points))], spec.fps, spec.features)
    except ValueError as exc:
        raise VisionForceError(str(exc)) from None


# ---- the model ---------------------------------------------------------------------------------


def load_force_model(ckpt: str | Path, spec: TokenSpec | None = None):
    """The trained regressor (eval mode, CPU) and its token spec: from the checkpoint's datamodule
    hyper-parameters when it saved them, else `spec`, else the defaults (the proposed model)."""
    from vfmodels.regressor import ForceRegressor

    regressor = ForceRegressor.load(ckpt)
    if regressor.model.input_key != "tokens":
        raise InputError(ckpt, f"{type(regressor.model).__name__} takes {regressor.model.input_key}, not tracked "
                               "points: vfdata predict runs the point-based models (proposed and its ablations)")
    if spec is None:
        spec = token_spec_from_checkpoint(ckpt)
    if getattr(regressor.model, "config", {}).get("in_features", spec.channels) != spec.channels:
        raise InputError(ckpt, f"model takes {regressor.model.config['in_features']} features per point, the "
                               f"token spec gives {spec.channels} ({spec.features})")
    return regressor, spec


def token_spec_from_checkpoint(ckpt: str | Path) -> TokenSpec:
    """The token spec saved with a checkpoint (Lightning's `datamodule_hyper_parameters`), read by
    the names `vfdata.datasets.ForceDataModule` uses; defaults where it saved none."""
    state = torch.load(ckpt, map_location="cpu", weights_only=True)
    hp = dict(state.get("datamodule_hyper_parameters", {}) or {})
    if hp.get("input", "tracks") != "tracks":
        raise InputError(ckpt, f"the model was trained on '{hp['input']}' inputs, not tracked points")
    values = {key: str(hp[key]) for key in ("frame", "features", "subset") if hp.get(key) is not None}
    if hp.get("fps") is not None:
        values["fps"] = float(hp["fps"])
    return TokenSpec(**values, canonical_side=bool(hp.get("canonical_side", False)))


@torch.no_grad()
def frame_embeddings(model, tokens: np.ndarray, valid: np.ndarray, regressor, batch: int = 256) -> torch.Tensor:
    """Per-frame set embeddings z_t (T, D) of a SetTransformerLSTM-like model (frames are independent
    before the LSTM, so they are batched freely)."""
    out = []
    for start in range(0, len(tokens), batch):
        x = torch.from_numpy(tokens[start:start + batch])[None]
        m = torch.from_numpy(valid[start:start + batch])[None]
        out.append(model.encode_frames(regressor.normalise_input(x), m)[0])
    return torch.cat(out) if out else torch.zeros(0, model.config.get("dim", 64))


@torch.no_grad()
def windowed_forces(regressor, z: torch.Tensor, window: int | None = CLIP_FRAMES) -> np.ndarray:
    """Forces (T, 3) in N from per-frame embeddings (T, D): frame t from the LSTM run over frames
    max(0, t - window + 1)..t from a zero state (window None: one run over everything)."""
    decoder = regressor.model.decoder
    if window is None or len(z) <= window:
        h, _ = decoder.lstm(z[None])
        return regressor.denormalise_force(decoder.heads(h[0])).numpy()
    # All windows at once: (T, window, D).
    t = len(z)
    index = np.arange(t)[:, None] + np.arange(-window + 1, 1)[None, :]
    h, _ = decoder.lstm(z[torch.from_numpy(np.clip(index, 0, None))])
    # Frames 0..window-2 have shorter histories: their windows start at frame 0 and repeat it; run
    # them exactly instead, from the one full run over the first window.
    out = decoder.heads(h[:, -1])
    head, _ = decoder.lstm(z[None, :window])
    out[: window - 1] = decoder.heads(head[0, : window - 1])
    return regressor.denormalise_force(out).numpy()


def forces_from_tracks(regressor, spec: TokenSpec, points_object_mm: np.ndarray, visible: np.ndarray,
                       rotation: np.ndarray, origin_mm: np.ndarray, window: int | None = CLIP_FRAMES
                       ) -> np.ndarray:
    """Tracks of a whole recording -> forces (T, 3) in N, object frame."""
    from vfdata.datasets import mirror_y

    side = spec.side(points_object_mm[0], visible[0]) if len(points_object_mm) else 1.0
    tokens, valid = point_tokens(mirror_y(points_object_mm, side), visible, spec, rotation, origin_mm)
    z = frame_embeddings(regressor.model, tokens, valid, regressor)
    return mirror_y(windowed_forces(regressor, z, window), side)


# ---- derived files -------------------------------------------------------------------------------


@dataclass
class Tracks:
    """The tracks and object frame of a derived (processed) MCAP."""

    times_ns: np.ndarray  # (T,) int64
    points_object_mm: np.ndarray  # (T, N, 3)
    visible: np.ndarray  # (T, N) bool
    rotation: np.ndarray  # (3, 3) object axes in the camera frame
    origin_mm: np.ndarray  # (3,)
    metadata: dict = field(default_factory=dict)

    @property
    def up_known(self) -> bool:
        return str(self.metadata.get("up_known", "false")).lower() == "true"


def read_tracks(path: str | Path) -> Tracks:
    """/tracking/points and the object frame of a processed MCAP."""
    path = Path(path)
    with Recording.open(path) as rec:
        if not rec.has(layout.TRACKING_POINTS):
            raise InputError(path, f"no {layout.TRACKING_POINTS}: process the recording with a tracker first")
        meta = rec.metadata_records.get(layout.DERIVED_METADATA, {})
        if "object_frame" not in meta:
            raise InputError(path, f"no object_frame in the {layout.DERIVED_METADATA} metadata")
        frame = json.loads(meta["object_frame"])
        times, points, visible = [], [], []
        for stamp, cloud in rec.messages(layout.TRACKING_POINTS):
            arr = cloud.points
            times.append(stamp)
            points.append(np.stack([arr["x"], arr["y"], arr["z"]], axis=1))
            visible.append(arr["visible"].astype(bool) if "visible" in arr.dtype.names else np.ones(len(arr), bool))
    return Tracks(np.asarray(times, dtype=np.int64), np.asarray(points, dtype=np.float64),
                  np.asarray(visible, dtype=bool), np.asarray(frame["rotation"], dtype=np.float64),
                  np.asarray(frame["origin"], dtype=np.float64), dict(meta))


def write_force_mcap(path: str | Path, times_ns: np.ndarray, force_object_n: np.ndarray, rotation: np.ndarray,
                     origin_mm: np.ndarray, metadata: dict[str, str], overwrite: bool = True) -> Path:
    """`/force/estimate` (WrenchStamped in `tissue_object`, torque NaN) and the object frame on /tf_static
    (left camera -> tissue_object, translation in m as ROS wants)."""
    from scipy.spatial.transform import Rotation

    quat = tuple(float(q) for q in Rotation.from_matrix(np.asarray(rotation)).as_quat())
    origin_m = tuple(float(v) * 1e-3 for v in origin_mm)
    tf = TFMessage([TransformStamped(int(times_ns[0]), layout.LEFT_FRAME, layout.OBJECT_FRAME, origin_m, quat)])
    nan3 = (float("nan"),) * 3
    with McapWriter(path, overwrite=overwrite) as writer:
        writer.write(layout.TF_STATIC, tf)
        for stamp, force in zip(times_ns, force_object_n, strict=True):
            writer.write(layout.FORCE_ESTIMATE, WrenchStamped(int(stamp), layout.OBJECT_FRAME,
                                                              tuple(float(f) for f in force), nan3))
        writer.add_metadata(layout.DERIVED_METADATA, {k: str(v) for k, v in metadata.items()})
    return Path(path)


def read_force_estimate(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(times_ns (T,), force (T, 3) N) from a `/force/estimate` MCAP."""
    with Recording.open(path) as rec:
        pairs = [(t, m.force) for t, m in rec.messages(layout.FORCE_ESTIMATE)]
    return np.array([p[0] for p in pairs], dtype=np.int64), np.array([p[1] for p in pairs], dtype=np.float64)


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


def predict_recording(src: str | Path, ckpt: str | Path, out_dir: str | Path | None = None,
                      prompt: str | None = None, process_options=None, window: int | None = CLIP_FRAMES,
                      video: bool = True, spec: TokenSpec | None = None, progress: bool = True,
                      reuse_processed: bool = True) -> PredictResult:
    """The whole pipeline on a recording MCAP (force channel and ECM pose not needed)."""
    from tqdm import tqdm

    from vfdata.processing import ProcessOptions, process_recording

    src = Path(src)
    if not src.is_file():
        raise InputError(src, "recording not found")
    regressor, spec = load_force_model(ckpt, spec)
    out_dir = Path(out_dir) if out_dir is not None else src.parent
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = src.name.removesuffix(".mcap")
    options = process_options or ProcessOptions()
    if prompt is not None:
        options.prompt = prompt
    options.progress = progress
    processed = out_dir / f"{stem}.predict.processed.mcap"
    if not (reuse_processed and processed.is_file()):
        process_recording(src, processed, options, overwrite=True)
    tracks = read_tracks(processed)

    started = time.perf_counter()
    force = forces_from_tracks(regressor, spec, tracks.points_object_mm, tracks.visible, tracks.rotation,
                               tracks.origin_mm, window)
    force_fps = len(force) / max(time.perf_counter() - started, 1e-9)
    x_axis = ("gravity up made perpendicular to Z (from the ECM pose)" if tracks.up_known else
              "arbitrary: the image's up direction made perpendicular to Z (no ECM pose)")
    meta = {
        "stage": "predict", "source": str(src.resolve()), "processed": str(processed.resolve()),
        "checkpoint": str(Path(ckpt).resolve()), "token_spec": json.dumps(spec.__dict__),
        "window": str(window), "x_axis": x_axis, "torque": "not estimated (NaN)",
        # -1: the first frame shows the y < 0 flank, mirrored in and out (token_spec canonical_side)
        "side": str(spec.side(tracks.points_object_mm[0], tracks.visible[0]) if len(tracks.times_ns) else 1.0),
        "object_frame": json.dumps({"rotation": tracks.rotation.tolist(), "origin": tracks.origin_mm.tolist()}),
        "force_fps": f"{force_fps:.1f}",
    }
    force_mcap = write_force_mcap(out_dir / f"{stem}.force.mcap", tracks.times_ns, force, tracks.rotation,
                                  tracks.origin_mm, meta)
    measured = None
    with Recording.open(src) as rec:
        if rec.has(layout.WRENCH):
            measured = rec.force_at(tracks.times_ns)[:, :3]
        camera = rec.camera
        plot = plot_force_series(force, out_dir / f"{stem}.force.png", measured_n=measured,
                                 title=f"{stem}: estimated force (object frame; X {x_axis.split(':')[0]})")
        video_path = None
        if video:
            force_cam = force_to_camera(force, tracks.rotation)
            scale = overlay_scale(force_cam, camera.width)
            origin_uv = project_point(camera, tracks.origin_mm)
            fps = _frame_rate(tracks.times_ns)
            with OverlayVideo(out_dir / f"{stem}.overlay.mp4", fps) as writer:
                for i in tqdm(range(len(force)), desc="overlay video", unit="frame", disable=not progress):
                    image = rec.rectified_frame(rec.frame_index_at(int(tracks.times_ns[i]))).left
                    label = f"frame {i}  |F| = {np.linalg.norm(force[i]):.2f} N"
                    writer.write(draw_force_overlay(image, origin_uv, force_cam[i], scale, label))
            video_path = writer.path
    stage_fps = json.loads(tracks.metadata.get("stage_fps", "{}"))
    return PredictResult(force_mcap, plot, video_path, processed, len(force), force_fps, stage_fps, tracks.up_known)


def _frame_rate(times_ns: np.ndarray) -> float:
    if len(times_ns) < 2:
        return 30.0
    return float(1e9 / np.median(np.diff(times_ns)))


# ---- live ----------------------------------------------------------------------------------------


@dataclass
class ForceEstimate:
    stamp_ns: int  # the frame the force belongs to (one frame before the latest push)
    force_n: np.ndarray  # (3,) object frame
    latency_s: float  # wall time of the push that produced it (all stages + model)


class StreamingForceModel:
    """The model half of live estimation: object-frame tracks in, one frame at a time, forces out.

    `push(stamp_ns, points_object_mm (N, 3), visible (N,))` -> (stamp, force (3,) N) of the previous
    frame, or None on the first frame; `flush()` gives the last frame's. Over a whole recording the
    results equal `forces_from_tracks` with the same window."""

    def __init__(self, regressor, spec: TokenSpec, rotation: np.ndarray, origin_mm: np.ndarray,
                 window: int | None = CLIP_FRAMES):
        self.regressor, self.spec, self.window = regressor, spec, window
        self.rotation, self.origin_mm = np.asarray(rotation), np.asarray(origin_mm)
        self.recent: deque = deque(maxlen=3)  # (stamp, object-frame points, visible) of the last frames
        self.embeddings: deque = deque(maxlen=window or 1)
        self.state = None  # LSTM (h, c) when window is None
        self.keep: np.ndarray | None = None  # top/bottom subset, fixed on the first frame
        self.side = 1.0  # the y mirror (`TokenSpec.canonical_side`), fixed on the first frame

    def push(self, stamp_ns: int, points_object_mm: np.ndarray, visible: np.ndarray) -> tuple[int, np.ndarray] | None:
        self.recent.append((int(stamp_ns), np.asarray(points_object_mm, dtype=np.float64),
                            np.asarray(visible, dtype=bool)))
        if len(self.recent) == 1:
            self.side = self.spec.side(self.recent[0][1], self.recent[0][2])
            if self.spec.subset == "top_bottom_20":
                from vfdata.datasets import TOP_BOTTOM_FRACTION, top_bottom

                self.keep = top_bottom(self.recent[0][1], TOP_BOTTOM_FRACTION)
            return None
        # The middle frame of the last three (the first frame, from the first two): its velocity is
        # a central difference (one-sided at the start), as over a whole recording.
        return self._estimate(len(self.recent) - 2)

    def flush(self) -> tuple[int, np.ndarray] | None:
        """The last frame's estimate (one-sided velocity), at the end of a stream; then resets."""
        if len(self.recent) < 2:
            self.recent.clear()
            return None
        while len(self.recent) > 2:
            self.recent.popleft()
        result = self._estimate(1)
        self.recent.clear()
        self.embeddings.clear()
        self.state = None
        return result

    @torch.no_grad()
    def _estimate(self, target: int) -> tuple[int, np.ndarray]:
        from vfdata.datasets import mirror_y

        recent = list(self.recent)
        points = mirror_y(np.stack([p[1] for p in recent]), self.side)
        visible = np.stack([p[2] for p in recent])
        tokens, valid = point_tokens(points, visible, self.spec, self.rotation, self.origin_mm, self.keep)
        tokens, valid = tokens[target], valid[target]
        model = self.regressor.model
        x = self.regressor.normalise_input(torch.from_numpy(tokens)[None, None])
        z = model.encode_frames(x, torch.from_numpy(valid)[None, None])[0]  # (1, D)
        decoder = model.decoder
        if self.window is None:
            h, self.state = decoder.lstm(z[None], self.state)
        else:
            self.embeddings.append(z[0])
            h, _ = decoder.lstm(torch.stack(list(self.embeddings))[None])
        force = self.regressor.denormalise_force(decoder.heads(h[0, -1])).numpy().astype(np.float64)
        return recent[target][0], mirror_y(force, self.side)


class StreamingForceEstimator:
    """Frame-by-frame force estimation from a live rectified stereo source.

    `push(left, right, stamp_ns)` (BGR uint8 images) -> a `ForceEstimate` of an earlier frame, or
    None while the pipeline fills. Stages per frame: depth, tissue mask, tissue cloud (the image
    stages), then tracking and `StreamingForceModel` (tokens, the set encoder of the frame, the LSTM).
    The first frame also fixes the object frame and the tracked points.

    `pipelined=True` runs the image stages of frame t in a worker thread while the calling thread
    tracks frame t-1 and runs the model (OpenCV, NumPy and PyTorch release the GIL): on two cores
    the throughput is set by the slower half instead of the sum, for one more frame of latency.
    Serially, `push` returns the previous frame's estimate (its velocity needs the next frame's
    points); pipelined, the one before that. `flush()` returns what is still in the pipeline.

    `stage_seconds` accumulates wall time per stage, `stage_cpu_seconds` the CPU time of the thread
    that ran it (the wall time of an idle core; a fair figure on a loaded machine)."""

    def __init__(self, ckpt: str | Path, camera: PinholeCamera, baseline_mm: float, prompt: str,
                 depth: str = "sgbm", segment: str = "colortrack", tracker: str = "geometry",
                 up: np.ndarray | None = None, window: int | None = CLIP_FRAMES, num_points: int = 256,
                 seed: int = 0, spec: TokenSpec | None = None, depth_options: dict | None = None,
                 segment_options: dict | None = None, tracker_options: dict | None = None,
                 pipelined: bool = False):
        from vfdata.recon import Prompt, make_depth_estimator, make_segmenter

        self.regressor, self.spec = load_force_model(ckpt, spec)
        self.camera, self.baseline_mm = camera, float(baseline_mm)
        self.prompt = Prompt.parse(prompt)
        self.prompt.check_inside(camera.width, camera.height)
        self.depth = make_depth_estimator(depth, **(depth_options or {}))
        self.segmenter = make_segmenter(segment, **(segment_options or {}))
        self.tracker_name, self.tracker_options = tracker, dict(tracker_options or {})
        self.up, self.window, self.num_points, self.seed = up, window, num_points, seed
        self.tracker = None
        self.frame = None  # ObjectFrame, fixed on the first frame
        self.model: StreamingForceModel | None = None
        self.stage_seconds: dict[str, float] = {}
        self.stage_cpu_seconds: dict[str, float] = {}
        self.frames = 0  # frames whose image stages have been started
        self.tracked = 0  # frames tracked
        self.pipelined = pipelined
        self._pool = None
        self._pending = None  # (future or result of the image stages, left image, stamp) of the last frame

    def _clock(self, stage: str, started: tuple[float, float]) -> tuple[float, float]:
        now = (time.perf_counter(), time.thread_time())
        self.stage_seconds[stage] = self.stage_seconds.get(stage, 0.0) + now[0] - started[0]
        self.stage_cpu_seconds[stage] = self.stage_cpu_seconds.get(stage, 0.0) + now[1] - started[1]
        return now

    def _image_stages(self, left: np.ndarray, right: np.ndarray, first: bool):
        from vfdata.recon import tissue_cloud

        t = (time.perf_counter(), time.thread_time())
        depth = self.depth.depth_mm(left, right, self.camera, self.baseline_mm)
        t = self._clock("depth", t)
        mask = self.segmenter.start(left, self.prompt, depth) if first else self.segmenter.track(left, depth)
        t = self._clock("mask", t)
        cloud = tissue_cloud(depth, mask, self.camera)
        self._clock("cloud", t)
        return depth, mask, cloud

    def _start(self, left: np.ndarray, cloud: np.ndarray) -> None:
        from vfdata.processing import ProcessOptions, _TrackerStage
        from vfdata.recon import estimate_object_frame

        if len(cloud) < 50:
            raise InputError("stream", f"the first frame's tissue cloud has {len(cloud)} points: check the prompt")
        self.frame = estimate_object_frame(cloud, self.up)
        options = ProcessOptions(tracker=self.tracker_name, tracker_options=self.tracker_options,
                                 num_points=self.num_points, seed=self.seed, progress=False)
        self.tracker = _TrackerStage(self.tracker_name, cloud, self.camera, left, None, options)
        if self.tracker.offline:
            raise VisionForceError(f"tracker '{self.tracker_name}' is offline (whole clip): not for streaming")
        self.model = StreamingForceModel(self.regressor, self.spec, self.frame.rotation, self.frame.origin,
                                         self.window)

    def _track(self, images, left: np.ndarray, stamp_ns: int) -> tuple[int, np.ndarray] | None:
        depth, mask, cloud = images
        t = (time.perf_counter(), time.thread_time())
        if self.tracked == 0:
            self._start(left, cloud)
            points, visible = self.tracker.points, self.camera.in_mask(self.tracker.points, mask)
        else:
            points, visible = self.tracker.update(self.tracked, cloud, mask, left, depth)
        t = self._clock("tracking", t)
        self.tracked += 1
        result = self.model.push(stamp_ns, self.frame.to_object(points), visible)
        self._clock("force", t)
        return result

    def push(self, left: np.ndarray, right: np.ndarray, stamp_ns: int) -> ForceEstimate | None:
        t0 = time.perf_counter()
        first = self.frames == 0
        self.frames += 1
        if not self.pipelined:
            result = self._track(self._image_stages(left, right, first), left, stamp_ns)
        else:
            if self._pool is None:
                from concurrent.futures import ThreadPoolExecutor

                self._pool = ThreadPoolExecutor(1, thread_name_prefix="vf-image-stages")
            future = self._pool.submit(self._image_stages, left, right, first)
            result = None
            if self._pending is not None:
                images, previous_left, previous_stamp = self._pending
                result = self._track(images, previous_left, previous_stamp)
            self._pending = (future.result(), left, stamp_ns)
        return None if result is None else ForceEstimate(result[0], result[1], time.perf_counter() - t0)

    def flush(self) -> list[ForceEstimate]:
        """The estimates still in the pipeline at the end of a stream, in frame order; the next push
        starts a new stream (new object frame, tracks and LSTM state)."""
        out = []
        t0 = time.perf_counter()
        if self._pending is not None:
            result = self._track(*self._pending)
            self._pending = None
            if result is not None:
                out.append(ForceEstimate(result[0], result[1], time.perf_counter() - t0))
        if self.model is not None:
            result = self.model.flush()
            if result is not None:
                out.append(ForceEstimate(result[0], result[1], time.perf_counter() - t0))
        self.frames = self.tracked = 0
        return out

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
