"""Pure array functions from tracked points to model tokens, shared by training (the dataset) and
inference (prediction, the live estimator): clip layout in time, velocities, point features, the
top/bottom subset and the mirror across the object's XZ plane."""

from __future__ import annotations

import numpy as np

from vfdata.clips.spec import FEATURE_CHANNELS, TILTABLE_FEATURES, ClipSpec
from vfdata.errors import VisionForceError

GAP_FACTOR = 1.5  # a frame interval longer than this many nominal periods is a gap
TIP_PERCENTILE = 98.0  # the free end's z among a frame's points (`tissue_tip`)
TOP_BOTTOM_FRACTION = 0.2
DEFAULT_FPS = 30.0
# The relaxation's time constant (s). A viscoelastic tissue's force follows where it has been over the last
# seconds, not only where it is (the colon preset's Maxwell relaxation: 1-3 s). On the simulator's true
# material points (colon seed 108, ridge on the whole surface) the displacement less its average over
# 2 s cut the test error by a third (0.84/0.78/0.88 -> 0.57/0.50/0.57 N); 1 s or 3 s did less.
RELAX_TAU_S = 2.0


# ---- time ----------------------------------------------------------------------------------------


def frame_rate(times_ns: np.ndarray) -> float:
    """Frames/s from the median frame interval (30 for fewer than two frames)."""
    dt = np.diff(np.asarray(times_ns, dtype=np.int64))
    return 1e9 / float(np.median(dt)) if len(dt) else DEFAULT_FPS


def segments(times_ns: np.ndarray, gap_factor: float = GAP_FACTOR,
             period_ns: float | None = None) -> list[tuple[int, int]]:
    """Gap-free runs [start, stop) of frame indices: a new run starts after any interval longer than
    `gap_factor` times the nominal period, `period_ns` (default: the median interval of these times;
    a stream that holds only a few frames passes its longer history's)."""
    times = np.asarray(times_ns, dtype=np.int64)
    if len(times) < 2:
        return [(0, len(times))] if len(times) else []
    dt = np.diff(times)
    breaks = np.flatnonzero(dt > gap_factor * (np.median(dt) if period_ns is None else period_ns)) + 1
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


def latest_clip_frames(recording: np.ndarray, frame_time_ns: np.ndarray, position: np.ndarray) -> np.ndarray:
    """Indices that keep each (recording, frame time) once, from the clip in which the frame had the
    most history (the latest position in its clip), as a causal online estimator would give it:
    clips overlap, so a frame is predicted several times. Sorted by recording, then time."""
    rec = np.asarray(recording).astype(str)
    times = np.asarray(frame_time_ns, dtype=np.int64)
    order = np.lexsort((-np.asarray(position), times, rec))
    first = np.ones(len(order), dtype=bool)
    first[1:] = (rec[order][1:] != rec[order][:-1]) | (times[order][1:] != times[order][:-1])
    return order[first]


# ---- point features ------------------------------------------------------------------------------


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


def reference_positions(points_mm: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(N, 3) each point's position on the first frame where it is valid (NaN if never)."""
    p = np.asarray(points_mm, dtype=np.float64)
    ok = np.asarray(valid, dtype=bool) & np.isfinite(p).all(axis=-1)
    first = np.argmax(ok, axis=0)
    ref = p[first, np.arange(p.shape[1])]
    ref[~ok.any(axis=0)] = np.nan
    return ref


def relaxation_weight(fps: float, tau_s: float = RELAX_TAU_S) -> float:
    """The exponential average's weight of a new frame at `fps` frames/s, time constant `tau_s`."""
    return float(1.0 - np.exp(-1.0 / (fps * tau_s)))


def relaxation_step(average_mm: np.ndarray | None, displacement_mm: np.ndarray, ok: np.ndarray,
                    weight: float) -> np.ndarray:
    """One frame of the causal average of each point's displacement (N, 3) mm: a point seen for the first
    time starts at its displacement, a seen one moves `weight` of the way to it, an unseen one keeps its
    average (NaN until first seen). The offline recipe (`displacement_averages`) and the live estimator
    both step through this, so they agree."""
    d = np.asarray(displacement_mm, dtype=np.float64)
    avg = np.full_like(d, np.nan) if average_mm is None else np.array(average_mm, dtype=np.float64)
    ok = np.asarray(ok, dtype=bool)
    new = ok & np.isnan(avg).any(axis=-1)
    seen = ok & ~new
    avg[new] = d[new]
    avg[seen] += weight * (d[seen] - avg[seen])
    return avg


def displacement_averages(displacement_mm: np.ndarray, ok: np.ndarray, fps: float) -> np.ndarray:
    """(F, N, 3) displacements mm + (F, N) ok -> (F, N, 3) each frame's causal average (`relaxation_step`)."""
    weight = relaxation_weight(fps)
    out = np.empty(np.shape(displacement_mm), dtype=np.float64)
    avg = None
    for i in range(len(out)):
        avg = out[i] = relaxation_step(avg, displacement_mm[i], ok[i], weight)
    return out


def point_features(points_mm: np.ndarray, valid: np.ndarray, runs: list[tuple[int, int]], fps: float,
                   features: str, reference_mm: np.ndarray | None = None,
                   average_mm: np.ndarray | None = None, tip_mm: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Tokens (F, N, C) float32 and valid (F, N) (`ClipSpec.features`: C = 3 per 3-vector). Invalid
    or non-finite points are zeroed and marked invalid; velocities of points next to an invalid
    sample are too. Displacements are from `reference_mm` (N, 3), by default each point's first valid
    position in `points_mm`; the relaxation's averages are `average_mm` (F, N, 3) (a stream passes what it
    stepped through its whole history), by default stepped through these frames."""
    if features not in FEATURE_CHANNELS:
        raise VisionForceError(f"unknown features '{features}' (choose from {', '.join(FEATURE_CHANNELS)})")
    p = np.asarray(points_mm, dtype=np.float64)
    ok = np.asarray(valid, dtype=bool) & np.isfinite(p).all(axis=-1)
    p = np.where(ok[..., None], p, 0.0)
    parts = []
    if "disp" in features:
        ref = reference_positions(points_mm, valid) if reference_mm is None else np.asarray(reference_mm, float)
        has_ref = np.isfinite(ref).all(axis=-1)
        ok = ok & has_ref[None]
        ref = np.nan_to_num(ref)
        if features.startswith("ref"):
            parts.append(np.broadcast_to(ref, p.shape))
        elif features.startswith("polar"):
            parts.append(np.broadcast_to(polar_place(ref), p.shape))
            if features.startswith("polar_z"):
                parts.append(np.broadcast_to(along_from_tip(ref, has_ref, tip_mm), p.shape))
        parts.append(p - ref)
        if "relax" in features:
            if average_mm is None:
                average_mm = displacement_averages(p - ref, ok, fps)
            parts.append(np.nan_to_num(p - ref - np.asarray(average_mm, dtype=np.float64)))
    elif features in ("pos_vel", "pos"):
        parts.append(p)
    if features.endswith("vel"):
        parts.append(velocities(p, runs, fps))
        # a velocity from a neighbour the tracker lost is meaningless: use only fully seen stencils
        ok_prev, ok_next = ok.copy(), ok.copy()
        for start, stop in runs:
            ok_prev[start + 1:stop] = ok[start:stop - 1]
            ok_next[start:stop - 1] = ok[start + 1:stop]
        ok = ok & ok_prev & ok_next
    tokens = np.concatenate(parts, axis=-1)
    return np.where(ok[..., None], tokens, 0.0).astype(np.float32), ok


def polar_place(reference_mm: np.ndarray) -> np.ndarray:
    """(N, 3) object-frame positions -> (N, 3) (cos th, sin th, r mm): where each point sits around the
    Z axis, th from X (= up). Stored as a 3-vector whose x, y turn with a rotation about Z and whose y
    flips with the mirror across XZ, so `transform_tokens` handles it like the other channels."""
    ref = np.asarray(reference_mm, dtype=np.float64)
    r = np.hypot(ref[:, 0], ref[:, 1])
    th = np.arctan2(ref[:, 1], ref[:, 0])
    return np.stack([np.cos(th), np.sin(th), r], axis=-1)


def along_from_tip(reference_mm: np.ndarray, valid: np.ndarray, tip_mm: float | None = None) -> np.ndarray:
    """(N, 3) object-frame positions -> (N, 3) (0, 0, z - z_tip mm): each point's place along Z counted
    from the tissue's free end, `tip_mm` (default: `tissue_tip` of the valid points), not from the origin.
    A view that cuts the clamped end off moves the origin (18-21 mm on glove_016 and colon_006) but not the
    tip; a lever arm and an axial strain need a place along Z, and any fixed reference serves a strain.
    A 3-vector with zero x, y, so turns about Z and the mirror leave it alone."""
    ref = np.asarray(reference_mm, dtype=np.float64)
    if tip_mm is None:
        tip_mm = tissue_tip(ref, valid)
    out = np.zeros_like(ref)
    out[:, 2] = ref[:, 2] - (tip_mm or 0.0)
    return out


def tissue_tip(points_object_mm: np.ndarray, visible: np.ndarray, percentile: float = TIP_PERCENTILE) -> float | None:
    """z (mm) of the tissue's free end on one frame: the `percentile` of its visible points' z, object
    frame (a high percentile, not the maximum, so one stray point does not move it); None if none is seen."""
    p = np.asarray(points_object_mm, dtype=np.float64)
    ok = np.asarray(visible, dtype=bool) & np.isfinite(p).all(axis=-1)
    return float(np.percentile(p[ok, 2], percentile)) if ok.any() else None


def mirror_tokens(tokens: np.ndarray) -> np.ndarray:
    """Tokens (..., C) of 3-vectors in the object frame mirrored across its XZ plane (every y negated)."""
    flip = np.ones(tokens.shape[-1], dtype=tokens.dtype)
    flip[1::3] = -1
    return tokens * flip


def turn_about_z(angle_rad: float, mirror: bool = False) -> np.ndarray:
    """(3, 3) rotation about the object's Z axis by `angle_rad`, after the mirror across XZ if asked.
    Both keep z, so they act on every token 3-vector and on the force alike."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return turn @ np.diag([1.0, -1.0 if mirror else 1.0, 1.0])


def transform_tokens(tokens: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Tokens (..., C) of 3-vectors with `matrix` (3, 3) applied to each (a `turn_about_z`)."""
    shape = tokens.shape
    triples = tokens.reshape(*shape[:-1], shape[-1] // 3, 3)
    return (triples @ np.asarray(matrix, dtype=tokens.dtype).T).reshape(shape)


def tilt_about(axis_angle_rad: float, tilt_rad: float) -> np.ndarray:
    """(3, 3) rotation by `tilt_rad` about the axis across Z at `axis_angle_rad` from X: the columns are
    a tilted frame's axes in the original one."""
    k = np.array([np.cos(axis_angle_rad), np.sin(axis_angle_rad), 0.0])
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(tilt_rad) * cross + (1.0 - np.cos(tilt_rad)) * cross @ cross


def tilt_tokens(tokens: np.ndarray, features: str, rotation: np.ndarray) -> np.ndarray:
    """Tokens (..., C) as the same points give them in a frame whose axes are the columns of `rotation`
    (a `tilt_about`), turned about the tissue's free end for the `polar_z` features (their place is counted
    from there). All-zero tokens (invalid points) stay zero."""
    if features not in TILTABLE_FEATURES:
        raise VisionForceError(f"features '{features}' cannot be tilted (choose from {', '.join(TILTABLE_FEATURES)})")
    matrix = np.asarray(rotation, dtype=np.float64).T
    if not features.startswith("polar_z"):
        return transform_tokens(tokens, matrix.astype(tokens.dtype))
    t = np.asarray(tokens, dtype=np.float64)
    place = np.stack([t[..., 2] * t[..., 0], t[..., 2] * t[..., 1], t[..., 5]], axis=-1) @ matrix.T
    r = np.hypot(place[..., 0], place[..., 1])
    safe = np.where(r > 0, r, 1.0)
    out = np.concatenate([np.stack([place[..., 0] / safe, place[..., 1] / safe, r], axis=-1),
                          np.stack([np.zeros_like(r), np.zeros_like(r), place[..., 2]], axis=-1),
                          *(t[..., k:k + 3] @ matrix.T for k in range(6, t.shape[-1], 3))], axis=-1)
    return np.where((t != 0).any(axis=-1, keepdims=True), out, 0.0).astype(tokens.dtype)


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


def recording_side(spec: ClipSpec, points_object_mm: np.ndarray, visible: np.ndarray) -> float:
    """The y factor of a recording whose first frame's points (N, 3) and visibility are given:
    -1 to mirror it (`spec.canonical_side` and the y < 0 flank seen), else +1."""
    return seen_side(points_object_mm, visible) if spec.canonical_side else 1.0


def point_tokens(spec: ClipSpec, points_object_mm: np.ndarray, visible: np.ndarray, times_ns: np.ndarray | None = None,
                 object_frame: tuple[np.ndarray, np.ndarray] | None = None, keep: np.ndarray | None = None,
                 fps: float | None = None, reference_mm: np.ndarray | None = None,
                 period_ns: float | None = None, average_mm: np.ndarray | None = None,
                 tip_mm: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Tracks (F, N, 3) in the object frame (mm, already mirrored by the caller when it should be) +
    visibility (F, N) -> tokens (F, N', C) float32 and valid (F, N') as `spec` says. `times_ns` cuts
    velocities at gaps (None: one gap-free run); the camera frame needs `object_frame` (rotation (3, 3)
    with the object axes as columns, origin (3,) mm); `keep` fixes the top/bottom subset (default:
    chosen on the first frame); `reference_mm` (N, 3) the positions displacements start from (default:
    each point's first valid position in these frames; a stream passes the recording's first frame);
    `period_ns` the nominal frame interval gaps are judged against (`segments`); `average_mm` (F, N, 3) the
    relaxation's averages of the displacements, in the object frame; `tip_mm` the free end's z the `polar_z`
    place is counted from (`point_features`)."""
    points = np.asarray(points_object_mm, dtype=np.float64)
    visible = np.asarray(visible, dtype=bool)
    reference = None if reference_mm is None else np.asarray(reference_mm, dtype=np.float64)
    if spec.subset == "top_bottom_20":
        keep = top_bottom(points[0], TOP_BOTTOM_FRACTION) if keep is None else keep
        points, visible = points[:, keep], visible[:, keep]
        reference = None if reference is None else reference[keep]
        average = None if average_mm is None else np.asarray(average_mm)[:, keep]
    else:
        average = average_mm
    if spec.frame == "camera":
        if object_frame is None:
            raise VisionForceError("camera-frame tokens need the object frame's rotation and origin")
        rotation, origin = object_frame
        points = points @ np.asarray(rotation).T + np.asarray(origin)
        reference = None if reference is None else reference @ np.asarray(rotation).T + np.asarray(origin)
        average = None if average is None else np.asarray(average) @ np.asarray(rotation).T  # displacements turn
    runs = segments(times_ns, period_ns=period_ns) if times_ns is not None else [(0, len(points))]
    rate = fps or spec.fps or (frame_rate(times_ns) if times_ns is not None else DEFAULT_FPS)
    return point_features(points, visible, runs, rate, spec.features, reference, average, tip_mm)


def track_tokens(spec: ClipSpec, points_object_mm: np.ndarray, visible: np.ndarray, times_ns: np.ndarray | None = None,
                 object_frame: tuple[np.ndarray, np.ndarray] | None = None, *,
                 first: tuple[np.ndarray, np.ndarray] | None = None, fps: float | None = None,
                 reference_mm: np.ndarray | None = None, period_ns: float | None = None,
                 average_mm: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """The token recipe of a recording's tracks, the one training (`decode`), prediction and the live
    estimator share: tracks (F, N, 3) mm in the object frame + visibility (F, N) -> (tokens (F, N', C),
    valid (F, N'), side). The recording's first frame, `first` = (points (N, 3), visible (N,)) (default:
    these tracks' first), fixes the mirror to the canonical side (`recording_side`: the side is -1 when the
    points were mirrored; `mirror_y(force, side)` turns a force back), the top/bottom subset, the free end
    the `polar_z` place is counted from (`tissue_tip`; if the first frame sees nothing, the references') and, with
    `spec.radius` tissue, the radius r0 is counted in (`tissue_radius`; a first frame that sees nothing
    falls back to the median r0 of the frames given, which a stream and a recording then see apart). A stream
    that holds only its last frames passes `first`, `reference_mm` (each point's first visible position,
    unmirrored), `fps`, `period_ns` and `average_mm` (the relaxation's averages of its frames, unmirrored)
    (`point_tokens`) from its whole history."""
    points = np.asarray(points_object_mm, dtype=np.float64)
    visible = np.asarray(visible, dtype=bool)
    if first is None and len(points):
        first = (points[0], visible[0])
    side = recording_side(spec, *first) if first is not None else 1.0
    keep = top_bottom(first[0]) if spec.subset == "top_bottom_20" and first is not None else None
    reference = None if reference_mm is None else mirror_y(np.asarray(reference_mm, dtype=np.float64), side)
    average = None if average_mm is None else mirror_y(np.asarray(average_mm, dtype=np.float64), side)
    # the free end as the first frame sees it, as the radius: a point first seen later must not move it,
    # or a recording and a stream of it would count the place along Z from different ends
    tip = tissue_tip(*first) if first is not None and spec.frame == "object" else None
    tokens, valid = point_tokens(spec, mirror_y(points, side), visible, times_ns, object_frame, keep, fps=fps,
                                 reference_mm=reference, period_ns=period_ns, average_mm=average, tip_mm=tip)
    if spec.radius == "tissue":
        radius = tissue_radius(*first) if first is not None else None
        if radius is None and valid.any():  # nothing seen on the first frame: the radius these frames show
            radius = float(np.median(tokens[..., 2][valid]))
        tokens[..., 2] /= radius or 1.0
    return tokens, valid, side


def tissue_radius(points_object_mm: np.ndarray, visible: np.ndarray) -> float | None:
    """The tissue's radius on one frame, mm: the median distance of its visible points (N, 3), object
    frame, from the Z axis (None when none is seen). The median, because a few points the mask took off
    the bed or the instrument lie two or three radii out."""
    points = np.asarray(points_object_mm, dtype=np.float64)[np.asarray(visible, dtype=bool)]
    points = points[np.isfinite(points).all(axis=1)]
    radius = float(np.median(np.hypot(points[:, 0], points[:, 1]))) if len(points) else 0.0
    return radius if radius > 0 else None


def sample_cloud(points_mm: np.ndarray, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """`count` points of a cloud (M, 3), without replacement when M >= count; (count, 3) float32 and
    valid (count,) (all False for an empty cloud)."""
    points = np.asarray(points_mm, dtype=np.float32)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) == 0:
        return np.zeros((count, 3), np.float32), np.zeros(count, bool)
    idx = rng.choice(len(points), size=count, replace=len(points) < count)
    return points[idx], np.ones(count, bool)
