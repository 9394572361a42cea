"""The constant offset between a recording's video clock and its force (and ECM pose) clock, estimated
from the data itself (`vfdata sync`); `vfdata convert --time-offset-ms` applies it.

The video sees the tissue move; the force sensor feels it. Over each frame interval k the image motion
(dense optical flow, averaged over cells of a grid on the tissue region) should explain the change of
the force over the same interval, once the force's stamps are moved by the right offset. For every
candidate offset the force change (the force averaged over a frame period, at the interval's two ends,
subtracted) is regressed on the motion features; the offset is where the fit is best.

A tissue is viscoelastic: its force leads its deformation (F = K x + C dx/dt), by its time constant
at the slow motions of surgery (the simulator's tissue: 10-20 ms). A purely elastic fit (force change
from the velocity) therefore finds the offset minus that lead, sharply; a viscoelastic fit (velocity
and acceleration) finds the offset itself, but the acceleration can also mimic a shift of one frame.
So the elastic fit places the search, and the viscoelastic fit is taken within one frame period after
it (a passive tissue's force can only lead its motion, never lag it). The ECM pose moves the camera:
the whole image's motion follows it without delay, an elastic fit.

Confidence: the fit's R² at the offset, and the jackknife standard error of the offset over 8 blocks
of the recording (each left out in turn). Pure functions on arrays; `recording_offsets` reads a file."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from vfdata.errors import InputError, VisionForceError
from vfdata.recon.prompt import Prompt
from vfdata.recording import Recording, layout
from vfdata.rig import rig_for

MOTION_SCALE = 0.25  # optical flow on images a quarter the size: motion of the tissue, not of its texture
GRID = 4  # cells per side of the region whose mean flows are the motion features
BLOCKS = 8  # jackknife blocks
MIN_INTERVALS = 40  # fewer usable frame intervals: no estimate
CONFIDENT_R2 = 0.3
CONFIDENT_SE_NS = 10_000_000
POSE_STILL_MM, POSE_STILL_DEG = 0.5, 0.5  # an ECM that moves less over the whole recording does not move


@dataclass(frozen=True)
class OffsetEstimate:
    """How late a stream's stamps run against the video's (ns; negative: early). `offset_ns` None: no
    estimate, `reason` says why."""

    stream: str  # "force" or "ECM pose"
    offset_ns: float | None
    uncertainty_ns: float = float("nan")  # jackknife standard error
    fit_r2: float = float("nan")  # share of the stream's change the image motion explains at the offset
    lead_ns: float | None = None  # force: how far it leads the motion (the tissue's viscous response)
    intervals: int = 0  # frame intervals used
    reason: str = ""

    @property
    def confident(self) -> bool:
        return (self.offset_ns is not None and self.fit_r2 >= CONFIDENT_R2
                and self.uncertainty_ns <= CONFIDENT_SE_NS and not self.reason)


# ---- image motion ----------------------------------------------------------------------------------
def flows(images: Iterable[np.ndarray]) -> Iterator[np.ndarray]:
    """Dense optical flow (H', W', 2) between consecutive images, on images MOTION_SCALE the size, in
    full-size pixels per frame."""
    previous = None
    for image in images:
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
        grey = cv2.resize(grey, None, fx=MOTION_SCALE, fy=MOTION_SCALE, interpolation=cv2.INTER_AREA)
        if previous is not None:
            yield cv2.calcOpticalFlowFarneback(previous, grey, None, 0.5, 2, 9, 3, 5, 1.1, 0) / MOTION_SCALE
        previous = grey


def motion_features(flow: np.ndarray, region: tuple[int, int, int, int] | None = None, grid: int = GRID
                    ) -> np.ndarray:
    """(2 * (grid**2 + 1),) the mean flow over `region` (x0, y0, x1, y1 in full-size pixels; None: the
    whole image) and over each of its grid x grid cells, row by row."""
    if region is not None:
        x0, y0, x1, y1 = (int(round(v * MOTION_SCALE)) for v in region)
        flow = flow[max(y0, 0):max(y1, y0 + 1), max(x0, 0):max(x1, x0 + 1)]
    rows = np.linspace(0, flow.shape[0], grid + 1).astype(int)
    cols = np.linspace(0, flow.shape[1], grid + 1).astype(int)
    cells = [flow.reshape(-1, 2).mean(0)]
    cells += [flow[rows[i]:max(rows[i + 1], rows[i] + 1), cols[j]:max(cols[j + 1], cols[j] + 1)].reshape(-1, 2).mean(0)
              for i in range(grid) for j in range(grid)]
    return np.concatenate(cells).astype(np.float64)


def coarser(motion: np.ndarray, grid: int, to: int) -> np.ndarray:
    """Motion features of a grid x grid region on a `to` x `to` grid (`to` divides `grid`): the means of
    the cells each coarse cell holds (1: the region's mean alone)."""
    if to == grid:
        return motion
    whole = motion[:, :2]
    if to == 1:
        return whole
    cells = motion[:, 2:].reshape(len(motion), to, grid // to, to, grid // to, 2).mean(axis=(2, 4))
    return np.concatenate([whole, cells.reshape(len(motion), -1)], axis=1)


# ---- what the other streams do over each frame interval --------------------------------------------
def window_means(times_ns: np.ndarray, values: np.ndarray, width_ns: float) -> Callable[[np.ndarray], np.ndarray]:
    """at_ns -> the mean of a sampled series (times (N,), values (N, C)) over [t - width/2, t + width/2]
    for each t of `at_ns`, from its integral (trapezoids): noise averaged over a frame period, at any time."""
    t = (times_ns - times_ns[0]).astype(np.float64)
    integral = np.concatenate([np.zeros((1, values.shape[1])),
                               np.cumsum(0.5 * (values[1:] + values[:-1]) * np.diff(t)[:, None], axis=0)])

    def means(at_ns: np.ndarray) -> np.ndarray:
        at = (np.asarray(at_ns) - times_ns[0]).astype(np.float64)
        hi = np.stack([np.interp(at + width_ns / 2, t, integral[:, c]) for c in range(values.shape[1])], axis=1)
        lo = np.stack([np.interp(at - width_ns / 2, t, integral[:, c]) for c in range(values.shape[1])], axis=1)
        return (hi - lo) / width_ns

    return means


def force_changes(frame_ns: np.ndarray, force_ns: np.ndarray, force_n: np.ndarray) -> Callable[[float], np.ndarray]:
    """lag -> (F - 1, 3) change of the force (N) over each frame interval, the force's stamps moved by
    -lag (the force read at video time t + lag), averaged over a frame period at both ends."""
    means = window_means(force_ns, force_n, float(np.median(np.diff(frame_ns))))
    return lambda lag: np.diff(means(frame_ns + lag), axis=0)


def pose_changes(frame_ns: np.ndarray, pose_ns: np.ndarray, position_m: np.ndarray,
                 quaternion_xyzw: np.ndarray) -> Callable[[float], np.ndarray]:
    """lag -> (F - 1, 6) motion of the ECM over each frame interval: translation (mm) and rotation
    (rotation vector, degrees), the pose read at video time t + lag."""
    t = (pose_ns - pose_ns[0]).astype(np.float64)
    slerp = Slerp(t, Rotation.from_quat(quaternion_xyzw))

    def changes(lag: float) -> np.ndarray:
        at = np.clip((frame_ns - pose_ns[0]).astype(np.float64) + lag, t[0], t[-1])
        position = np.stack([np.interp(at, t, position_m[:, c]) for c in range(3)], axis=1) * 1e3
        rotation = slerp(at)
        turn = (rotation[:-1].inv() * rotation[1:]).as_rotvec(degrees=True)
        return np.concatenate([np.diff(position, axis=0), turn], axis=1)

    return changes


# ---- the fit ---------------------------------------------------------------------------------------
def usable_intervals(frame_ns: np.ndarray, series_ns: np.ndarray, max_offset_ns: float) -> np.ndarray:
    """(F - 1,) bool: frame intervals whose stream windows stay inside the stream at every offset tried."""
    period = float(np.median(np.diff(frame_ns))) if len(frame_ns) > 1 else 0.0
    margin = max_offset_ns + period
    return (frame_ns[:-1] - margin >= series_ns[0]) & (frame_ns[1:] + margin <= series_ns[-1])


def _r2_curves(design: np.ndarray, changes_at: Callable[[float], np.ndarray], lags: np.ndarray,
               use: np.ndarray, blocks: list[np.ndarray]) -> np.ndarray:
    """(1 + len(blocks), L): the R² (mean over the stream's channels) of the least-squares fit of the
    stream's change on `design` at each lag, for all intervals `use` and with each block left out."""
    subsets = [use] + [use & ~block for block in blocks]
    bases = []
    for subset in subsets:
        x = design[subset] - design[subset].mean(axis=0)
        q, r = np.linalg.qr(x)
        keep = np.abs(np.diag(r)) > 1e-9 * max(np.abs(np.diag(r)).max(), 1e-300)
        bases.append(q[:, keep])
    curves = np.empty((len(subsets), len(lags)))
    for j, lag in enumerate(lags):
        y_all = changes_at(float(lag))
        for i, (subset, q) in enumerate(zip(subsets, bases, strict=True)):
            y = y_all[subset] - y_all[subset].mean(axis=0)
            total = (y * y).sum(axis=0)
            residual = y - q @ (q.T @ y)
            curves[i, j] = 1.0 - float(np.mean((residual * residual).sum(axis=0) / np.maximum(total, 1e-300)))
    return curves


def _peak(lags: np.ndarray, curve: np.ndarray, window: np.ndarray | None = None) -> float:
    """The lag of the curve's maximum (inside `window`), refined by a parabola through it and its two
    neighbours."""
    allowed = np.ones(len(lags), bool) if window is None else window
    k = int(np.flatnonzero(allowed)[np.argmax(curve[allowed])])
    if 0 < k < len(lags) - 1 and allowed[k - 1] and allowed[k + 1]:
        a, b, c = curve[k - 1], curve[k], curve[k + 1]
        denominator = a - 2 * b + c
        if denominator < 0:
            return float(lags[k] + 0.5 * (a - c) / denominator * (lags[1] - lags[0]))
    return float(lags[k])


def _blocks(use: np.ndarray, count: int) -> list[np.ndarray]:
    """`count` contiguous blocks of the usable intervals, as masks over all intervals."""
    index = np.flatnonzero(use)
    out = []
    for part in np.array_split(index, count):
        mask = np.zeros(len(use), bool)
        mask[part] = True
        out.append(mask)
    return out


def estimate_offset(stream: str, motion: np.ndarray, frame_ns: np.ndarray, series_ns: np.ndarray,
                    changes_at: Callable[[float], np.ndarray], max_offset_ns: float = 500e6,
                    step_ns: float = 1e6, viscoelastic: bool = True) -> OffsetEstimate:
    """The offset of a stream (sampled at `series_ns`; `changes_at(lag)`: its change over each frame
    interval read at video time + lag) against the video (`frame_ns`, `motion`: image motion features
    per frame interval), searched within +-`max_offset_ns`. `viscoelastic`: the force's two-step fit
    (the module's docstring); else the elastic fit alone (the ECM pose)."""
    frame_ns = np.asarray(frame_ns, dtype=np.int64)
    use = usable_intervals(frame_ns, np.asarray(series_ns), max_offset_ns)
    intervals = int(use.sum())
    if intervals < MIN_INTERVALS:
        return OffsetEstimate(stream, None, intervals=intervals,
                              reason=f"only {intervals} frame intervals have the {stream} on both sides within "
                                     f"+-{max_offset_ns / 1e6:.0f} ms (at least {MIN_INTERVALS} needed)")
    # As many motion features as the intervals carry: a 4 x 4 grid from 400 intervals on.
    grid = GRID if intervals >= 400 else 2 if intervals >= 120 else 1
    velocity = coarser(motion, GRID, grid)
    lags = np.arange(-max_offset_ns, max_offset_ns + step_ns / 2, step_ns)
    blocks = _blocks(use, BLOCKS)
    # One BLAS thread (the project's thread policy, vfdata/threads.py): these small factorisations took
    # 0.8 s each instead of 4 ms with OpenBLAS's threads on a loaded 2-core machine.
    with threadpool_limits(1):
        elastic = _r2_curves(velocity, changes_at, lags, use, blocks)
        if viscoelastic:
            acceleration = np.zeros_like(velocity)
            acceleration[1:-1] = (velocity[2:] - velocity[:-2]) / 2
            full = _r2_curves(np.concatenate([velocity, acceleration], axis=1), changes_at, lags, use, blocks)
    period = float(np.median(np.diff(frame_ns)))
    offsets, leads = [], []
    for i in range(len(elastic)):
        first = _peak(lags, elastic[i])
        if not viscoelastic:
            offsets.append(first)
            continue
        window = (lags >= first - 2 * step_ns) & (lags <= first + period)
        offsets.append(_peak(lags, full[i], window))
        leads.append(offsets[-1] - first)
    estimate, rest = offsets[0], np.asarray(offsets[1:])
    spread = float(np.sqrt((len(rest) - 1) / len(rest) * ((rest - rest.mean()) ** 2).sum()))
    curve = full[0] if viscoelastic else elastic[0]
    r2 = float(np.interp(estimate, lags, curve))
    reason = ""
    if abs(offsets[0]) >= max_offset_ns - 2 * step_ns or (viscoelastic and abs(_peak(lags, elastic[0]))
                                                          >= max_offset_ns - 2 * step_ns):
        reason = f"the best fit lies at the edge of the search (+-{max_offset_ns / 1e6:.0f} ms): search wider"
    return OffsetEstimate(stream, estimate, spread, r2, leads[0] if leads else None, intervals, reason)


# ---- a recording -----------------------------------------------------------------------------------
REGION_MARGIN = 0.25  # the first frame's tissue box grown by this share of its size on every side


@dataclass(frozen=True)
class RecordingOffsets:
    frames: int
    duration_s: float
    region: tuple[int, int, int, int] | None  # where the image motion was measured (None: everywhere)
    applied_ns: int  # the offset its conversion already applied (`--time-offset-ms`), 0 if none
    force: OffsetEstimate
    pose: OffsetEstimate | None  # None: the recording has no ECM pose


def tissue_region(box: tuple[float, float, float, float], width: int, height: int) -> tuple[int, int, int, int]:
    """The prompt box grown by REGION_MARGIN of its size on every side (the tissue moves), in the image."""
    x0, y0, x1, y1 = box
    dx, dy = REGION_MARGIN * (x1 - x0), REGION_MARGIN * (y1 - y0)
    return (max(0, int(x0 - dx)), max(0, int(y0 - dy)), min(width, int(np.ceil(x1 + dx))),
            min(height, int(np.ceil(y1 + dy))))


def recording_offsets(path, max_offset_ms: float = 500.0, max_frames: int | None = None,
                      progress: bool = True) -> RecordingOffsets:
    """The force's (and the ECM pose's) offset against the video of a recording MCAP."""
    with Recording.open(path) as rec:
        frames = rec.num_frames if max_frames is None else min(rec.num_frames, max_frames)
        if frames < 3:
            raise InputError(path, f"{frames} frames: the offset needs the video to move")
        if not rec.has(layout.WRENCH):
            raise InputError(path, "no force topic: nothing to align with the video")
        frame_ns = rec.frame_times_ns[:frames]
        image = rig_for(rec, path).motion_image
        first = image(0)
        box = _prompt_box(rec)
        region = tissue_region(box, first.shape[1], first.shape[0]) if box is not None else None
        images = (image(i) for i in tqdm(range(frames), desc="image motion", unit="frame", disable=not progress))
        # One pass over the video for both: the tissue region's grid, and the whole image's for the ECM.
        pairs = [(motion_features(flow, region), motion_features(flow)) for flow in flows(images)]
        motion = np.stack([p[0] for p in pairs])
        whole = np.stack([p[1] for p in pairs])
        force = rec.force
        max_offset_ns = max_offset_ms * 1e6
        force_estimate = estimate_offset("force", motion, frame_ns, force.times_ns,
                                         force_changes(frame_ns, force.times_ns, force.wrench[:, :3]), max_offset_ns)
        pose_estimate = None
        if rec.has(layout.ECM_POSE):
            pose = rec.ecm_pose
            pose_estimate = _pose_offset(frame_ns, whole, pose, max_offset_ns)
        applied = int(rec.metadata.extra.get("sensor_time_offset_ns", "0") or 0)
        return RecordingOffsets(frames, float(frame_ns[-1] - frame_ns[0]) / 1e9, region, applied, force_estimate,
                                pose_estimate)


def _pose_offset(frame_ns: np.ndarray, whole: np.ndarray, pose, max_offset_ns: float) -> OffsetEstimate:
    if len(pose.times_ns) < 2:
        return OffsetEstimate("ECM pose", None, reason="fewer than two poses")
    travel_mm = float(np.linalg.norm(np.diff(pose.position_m, axis=0), axis=1).sum() * 1e3)
    rotations = Rotation.from_quat(pose.quaternion_xyzw)
    turn_deg = float(np.degrees((rotations[:-1].inv() * rotations[1:]).magnitude()).sum())
    if travel_mm < POSE_STILL_MM and turn_deg < POSE_STILL_DEG:
        return OffsetEstimate("ECM pose", None, reason=f"the ECM does not move (travel {travel_mm:.2f} mm, turn "
                                                       f"{turn_deg:.2f} deg): its clock cannot be seen in the video")
    changes = pose_changes(frame_ns, pose.times_ns, pose.position_m, pose.quaternion_xyzw)
    return estimate_offset("ECM pose", whole, frame_ns, pose.times_ns, changes, max_offset_ns, viscoelastic=False)


def _prompt_box(rec) -> tuple[float, float, float, float] | None:
    """The first frame's tissue box from the recording's metadata (`prompt_box`, or a prompt's box)."""
    extra = rec.metadata.extra
    try:
        if extra.get("prompt"):
            prompt = Prompt.parse(extra["prompt"])
            if prompt.box is not None:
                return prompt.box
            points = np.asarray(prompt.positive, dtype=float)
            return (*points.min(axis=0), *points.max(axis=0)) if len(points) > 1 else None
        if extra.get("prompt_box"):
            values = [float(v) for v in extra["prompt_box"].strip("[]").split(",")]
            return tuple(values) if len(values) == 4 and values[2] > values[0] and values[3] > values[1] else None
    except (ValueError, VisionForceError):  # a bad prompt in the metadata: measure the whole image
        return None
    return None
