"""The tissue's axis, the paper's way: from its point cloud by slicing and fitting ellipses.

For each of 36 x 36 candidate directions c covering a hemisphere, the cloud is cut into slabs
perpendicular to c, each slab's points are projected onto the slab plane and fitted with an ellipse, the
ellipse centres are mapped back to 3D and a line is fitted through them (PCA) with direction d; the
candidate's score is the unsigned angle between c and d (a direction that really is the centreline
reproduces itself), and the best candidate's d is the axis, refined by re-slicing along it with circles.

Everything is vectorised over candidates: 1296 candidates of a 3000-point cloud take well under a second
on two cores. Which end of the axis is clamped is another question (`vfdata.recon.clamped_end`), and the
frame built on the axis another still (`vfdata.recon.object_frame`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vfdata.errors import InputError

CANDIDATE_STEPS = 36  # per angle: 36 x 36 candidate directions, as in the paper
N_SLABS = 24
MIN_SLAB_POINTS = 12
MIN_SLABS = 5
MAX_POINTS = 2000  # the fit subsamples larger clouds (deterministically): the axis needs no more
_CHUNK = 216  # candidates per vectorised batch (memory ~ chunk x points x 20 doubles)


@dataclass(frozen=True)
class TubeAxis:
    """The tissue's centreline: a unit `direction` (3,) (its sign is arbitrary here), a `point` (3,) on
    it, both in the cloud's coordinates (mm), and `score_deg`, the chosen candidate's angle between
    slicing direction and centreline (0: the direction reproduces itself)."""

    direction: np.ndarray
    point: np.ndarray
    score_deg: float
    points_used: int


def tube_axis(points: np.ndarray, *, steps: int = CANDIDATE_STEPS, refine: int = 3) -> TubeAxis:
    """The centreline of an (N, 3) tissue cloud (see the module docstring). `refine` re-slices along the
    found axis that many times, which removes the candidate grid's quantisation."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError("tissue cloud", f"expected (N, 3) points, got shape {pts.shape}")
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < MIN_SLABS * MIN_SLAB_POINTS:
        raise InputError("tissue cloud", f"{len(pts)} points are too few to find the object frame")
    if len(pts) > MAX_POINTS:
        pts = pts[np.linspace(0, len(pts) - 1, MAX_POINTS).astype(np.int64)]
    centre = pts.mean(axis=0)
    local = pts - centre

    candidates = hemisphere_directions(steps)
    fits = [_slice_and_fit(local, candidates[i : i + _CHUNK]) for i in range(0, len(candidates), _CHUNK)]
    scores = np.concatenate([f.score for f in fits])
    if not np.isfinite(scores).any():
        raise InputError(
            "tissue cloud", "no slicing direction gave enough elliptical slices (not a tube-like cloud)"
        )
    # Ties are common (several candidates near the axis reproduce it): prefer the longest cut, i.e.
    # the candidate whose slabs span the most, as the centreline is the tissue's long axis.
    extent = np.concatenate([f.extent for f in fits])
    best_score = np.nanmin(scores)
    near = np.isfinite(scores) & (scores <= best_score + np.deg2rad(0.5))
    best = int(np.argmax(np.where(near, extent, -np.inf)))
    chunk, within = divmod(best, _CHUNK)
    axis = fits[chunk].direction[within]
    score = float(scores[best])
    # Refinement along the found axis, with circles: slabs perpendicular to the true centreline
    # of a round tube are circles, and a circle's centre is well defined from the partial arc the
    # camera sees, where a free ellipse can slide along the arc (biased by the changing viewpoint
    # along the tissue).
    # The centreline is refitted robustly: slices at the ends, where an instrument or the clamp
    # touches the tissue, carry depth that bled over from the occluder and bend a plain fit.
    line_point = fits[chunk].line_point[within]
    for _ in range(refine):
        fit = _slice_and_fit(local, axis[None, :], circles=True)
        centres = fit.centres[0]
        centres = centres[np.isfinite(centres).all(axis=1)]
        if len(centres) < MIN_SLABS:
            break
        new_axis, line_point = robust_line(centres)
        axis = new_axis if new_axis @ axis >= 0 else -new_axis
        score = float(np.arccos(min(1.0, abs(float(fit.direction[0] @ axis)))))
    return TubeAxis(axis / np.linalg.norm(axis), centre + line_point, float(np.rad2deg(score)), len(pts))


def tube_residual(points: np.ndarray, axis: TubeAxis, n_slabs: int = 12) -> float:
    """How far an (N, 3) cloud is from a round tube about `axis`: per slab along it (2nd to 98th
    percentile), the median of |r - R| / R over its points, r a point's distance from the axis and R the
    slab's median; the median over the slabs with 20 points or more (inf without any). A tube's visible
    surface about its true axis gives a few percent; about a tilted axis, or with bed or instrument depth
    among the points, tens of percent."""
    pts = np.asarray(points, dtype=np.float64)
    pts = pts[np.isfinite(pts).all(axis=1)] - axis.point
    t = pts @ axis.direction
    radial = np.linalg.norm(pts - np.outer(t, axis.direction), axis=1)
    if len(t) == 0:
        return float("inf")
    edges = np.percentile(t, np.linspace(2, 98, n_slabs + 1))
    slab = np.searchsorted(edges, t, side="right") - 1
    spreads = []
    for k in range(n_slabs):
        r = radial[slab == k]
        if len(r) >= 20:
            median = np.median(r)
            spreads.append(np.median(np.abs(r - median)) / max(median, 1e-9))
    return float(np.median(spreads)) if spreads else float("inf")


def hemisphere_directions(steps: int = CANDIDATE_STEPS) -> np.ndarray:
    """(steps*steps, 3) unit directions covering the hemisphere z >= 0: `steps` polar angles (cell
    centres from the pole to the equator) times `steps` azimuths. A hemisphere suffices because a
    line's direction is only defined up to sign."""
    polar = (np.arange(steps) + 0.5) * (np.pi / 2) / steps
    azimuth = np.arange(steps) * (2 * np.pi) / steps
    p, a = np.meshgrid(polar, azimuth, indexing="ij")
    return np.stack([np.sin(p) * np.cos(a), np.sin(p) * np.sin(a), np.cos(p)], axis=-1).reshape(-1, 3)


def robust_line(centres: np.ndarray, iterations: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Line (unit direction, point) through (K, 3) points by PCA, refitted without the points farther
    from the line than 2.5 times the median distance (and 0.3 mm)."""
    keep = np.ones(len(centres), bool)
    for _ in range(iterations):
        point = centres[keep].mean(axis=0)
        _vals, vecs = np.linalg.eigh(np.cov((centres[keep] - point).T))
        direction = vecs[:, -1]
        offset = centres - point
        dist = np.linalg.norm(offset - np.outer(offset @ direction, direction), axis=1)
        new_keep = dist <= max(2.5 * np.median(dist[keep]), 0.3)
        if new_keep.sum() < MIN_SLABS or (new_keep == keep).all():
            break
        keep = new_keep
    return direction, point


def slab_widths(points: np.ndarray, axis: np.ndarray, view: np.ndarray, n_slabs: int = N_SLABS):
    """Per slab along `axis`: (centre position along the axis, width of the slice across the line
    of sight). The width seen across the viewing direction is the slice's silhouette width, the
    size measure least affected by depth noise and by how much of the slice's ellipse the camera
    sees (a fitted ellipse's axes vary by a millimetre from slab to slab on a partial arc, more than
    a tapered tissue's taper over its length). `view` is the direction from the camera to the cloud."""
    across = np.cross(axis, view)
    if np.linalg.norm(across) < 1e-9:  # looking along the axis: any perpendicular will do
        across = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    across /= np.linalg.norm(across)
    t = points @ axis
    w = points @ across
    lo, hi = np.percentile(t, [1, 99])
    edges = np.linspace(lo, hi, n_slabs + 1)
    slab = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, n_slabs - 1)
    centres, widths = [], []
    for k in range(n_slabs):
        sel = w[slab == k]
        if len(sel) >= MIN_SLAB_POINTS:
            lo_w, hi_w = np.percentile(sel, [2, 98])
            centres.append((edges[k] + edges[k + 1]) / 2)
            widths.append(hi_w - lo_w)
    return np.array(centres), np.array(widths)


# ------------------------------------------------------------------------------------ slicing


@dataclass
class _Fit:
    """Per candidate (C of them): centreline direction and point, score (rad, NaN: no fit), the
    span of the usable slabs, and per slab the ellipse centre."""

    direction: np.ndarray
    line_point: np.ndarray
    score: np.ndarray
    extent: np.ndarray
    centres: np.ndarray  # (C, K, 3) ellipse/circle centres in 3D, NaN where the slab is unusable


def _basis(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (C, 3) spanning the plane perpendicular to each direction in c (C, 3)."""
    helper = np.where(np.abs(c[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(c, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(c, e1)


def _slice_and_fit(points: np.ndarray, c: np.ndarray, circles: bool = False) -> _Fit:
    """Slice the (N, 3) centred cloud perpendicular to each candidate c (C, 3), fit an ellipse per
    slab (Halir & Flusser's direct least-squares fit on normalised slab coordinates), and fit the
    centreline through the ellipse centres."""
    n_c = len(c)
    e1, e2 = _basis(c)
    t = points @ c.T  # (N, C) position along the candidate
    # Slab-plane coordinates, scaled by the cloud's size so the algebraic fit is well conditioned.
    unit = np.sqrt((points**2).sum(axis=1).mean()) + 1e-12
    x = points @ (e1.T / unit)  # (N, C)
    y = points @ (e2.T / unit)
    sample = t[:: max(1, len(t) // 512)]  # the slab range from a subsample: quantiles are costly
    lo, hi = np.percentile(sample, [1, 99], axis=0)
    width = np.maximum(hi - lo, 1e-9) / N_SLABS
    slab = np.floor((t - lo) / width).astype(np.int64)
    inside = (slab >= 0) & (slab < N_SLABS)
    # Per-slab sums as one bincount over the flat (candidate, slab) index; points outside the
    # trimmed range go to a spill bin that is dropped.
    n_bins = n_c * N_SLABS
    flat = np.where(inside, np.arange(n_c)[None, :] * N_SLABS + slab, n_bins).ravel()

    def slab_sum(values: np.ndarray) -> np.ndarray:  # values (N, C) -> (C, K)
        return np.bincount(flat, weights=values.ravel(), minlength=n_bins + 1)[:n_bins].reshape(n_c, N_SLABS)

    count = np.bincount(flat, minlength=n_bins + 1)[:n_bins].reshape(n_c, N_SLABS).astype(np.float64)
    safe = np.maximum(count, 1)
    # Sums over each slab of the 15 monomials of degree <= 4 that the scatter matrix needs.
    x2, y2, xy = x * x, y * y, x * y
    monomials = (
        x2 * x2,
        x2 * xy,
        x2 * y2,
        xy * y2,
        y2 * y2,
        x2 * x,
        x2 * y,
        x * y2,
        y2 * y,
        x2,
        xy,
        y2,
        x,
        y,
    )
    m = np.stack([slab_sum(mono) for mono in monomials] + [count], axis=-1)  # (C, K, 15)
    mu_t = slab_sum(t) / safe
    mu_x, mu_y = m[..., 12] / safe, m[..., 13] / safe
    spread = np.sqrt(np.maximum(m[..., 9] / safe - mu_x**2 + m[..., 11] / safe - mu_y**2, 0))
    if circles:
        centre_xy, axes = _circle_fit(m)
    else:
        conic = _direct_ellipse_fit(m)  # (C, K, 6) conic a x^2 + b xy + c y^2 + d x + e y + f
        centre_xy, axes = _ellipse_geometry(conic)
    cx, cy = centre_xy[..., 0], centre_xy[..., 1]
    size = unit * np.sqrt(axes[..., 0] * axes[..., 1])
    # A usable slab: enough points and a real ellipse of plausible size near its points (a slab that
    # cuts the tube lengthwise gives a degenerate, huge or far-away conic).
    good = (count >= MIN_SLAB_POINTS) & np.isfinite(size) & (axes[..., 0] < 4 * spread) & (axes[..., 1] > 0)
    good &= np.hypot(cx - mu_x, cy - mu_y) < 3 * spread
    cu, cv_ = unit * cx, unit * cy
    centres = (
        cu[..., None] * e1[:, None, :] + cv_[..., None] * e2[:, None, :] + mu_t[..., None] * c[:, None, :]
    )  # (C, K, 3)
    w = good.astype(np.float64)
    n_good = w.sum(axis=1)
    w_safe = np.maximum(n_good, 1)[:, None]
    mean = np.einsum("ck,ckj->cj", w, np.nan_to_num(centres)) / w_safe
    d = np.nan_to_num(centres) - mean[:, None, :]
    cov = np.einsum("ck,cki,ckj->cij", w, d, d) / w_safe[..., None]
    _vals, vecs = np.linalg.eigh(cov)
    direction = vecs[:, :, -1]
    direction *= np.where((direction * c).sum(axis=1) < 0, -1.0, 1.0)[:, None]
    cosang = np.clip(np.abs((direction * c).sum(axis=1)), 0, 1)
    score = np.arccos(cosang)
    score[n_good < MIN_SLABS] = np.nan
    t_good = np.where(good, mu_t, np.nan)
    with np.errstate(invalid="ignore"):
        extent = np.nanmax(t_good, axis=1, initial=-np.inf) - np.nanmin(t_good, axis=1, initial=np.inf)
    return _Fit(
        direction=direction,
        line_point=mean,
        score=score,
        extent=extent,
        centres=np.where(good[..., None], centres, np.nan),
    )


def _circle_fit(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched algebraic (Kasa) circle fit from monomial sums m (..., 15) -> centre (..., 2) and
    radius twice (..., 2). Minimises sum (x^2 + y^2 + D x + E y + F)^2: a 3x3 linear system."""
    x3, xy2, x2y, y3 = m[..., 5], m[..., 7], m[..., 6], m[..., 8]
    x2, xy, y2, x1, y1, one = m[..., 9], m[..., 10], m[..., 11], m[..., 12], m[..., 13], m[..., 14]
    a = np.stack(
        [np.stack([x2, xy, x1], -1), np.stack([xy, y2, y1], -1), np.stack([x1, y1, one], -1)], axis=-2
    )
    rhs = -np.stack([x3 + xy2, x2y + y3, x2 + y2], axis=-1)
    a = a + np.eye(3) * 1e-12
    with np.errstate(invalid="ignore", divide="ignore"):
        sol = np.linalg.solve(a, rhs[..., None])[..., 0]
        centre = -sol[..., :2] / 2
        radius = np.sqrt(np.maximum((centre**2).sum(axis=-1) - sol[..., 2], 0))
    radius[~(radius > 0)] = np.nan
    return centre, np.stack([radius, radius], axis=-1)


def _direct_ellipse_fit(m: np.ndarray) -> np.ndarray:
    """Batched Halir & Flusser direct ellipse fit from monomial sums m (..., 15) -> conic (..., 6);
    NaN where no ellipse fits."""
    x4, x3y, x2y2, xy3, y4, x3, x2y, xy2, y3, x2, xy, y2, x1, y1, one = np.moveaxis(m, -1, 0)

    def mat(rows):
        return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)

    # Design rows D1 = [x^2, xy, y^2], D2 = [x, y, 1]; S1 = D1'D1, S2 = D1'D2, S3 = D2'D2.
    s1 = mat([[x4, x3y, x2y2], [x3y, x2y2, xy3], [x2y2, xy3, y4]])
    s2 = mat([[x3, x2y, x2], [x2y, xy2, xy], [xy2, y3, y2]])
    s3 = mat([[x2, xy, x1], [xy, y2, y1], [x1, y1, one]])
    s3 = s3 + np.eye(3) * 1e-9
    tmat = -np.linalg.solve(s3, np.swapaxes(s2, -1, -2))
    red = s1 + s2 @ tmat
    # Premultiply by the inverse of the ellipse constraint matrix C1 = [[0,0,2],[0,-1,0],[2,0,0]].
    red = np.stack([red[..., 2, :] / 2, -red[..., 1, :], red[..., 0, :] / 2], axis=-2)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        _vals, vecs = np.linalg.eig(red)
        vecs = vecs.real
        cond = 4 * vecs[..., 0, :] * vecs[..., 2, :] - vecs[..., 1, :] ** 2  # (..., 3)
        pick = np.argmax(np.where(cond > 0, cond, -np.inf), axis=-1)
        a1 = np.take_along_axis(vecs, pick[..., None, None].repeat(3, axis=-2), axis=-1)[..., 0]
        ok = np.take_along_axis(cond, pick[..., None], axis=-1)[..., 0] > 0
        a2 = (tmat @ a1[..., None])[..., 0]
    conic = np.concatenate([a1, a2], axis=-1)
    conic[~ok] = np.nan
    return conic


def _ellipse_geometry(conic: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Conic (..., 6) -> centre (..., 2) and semi-axes (..., 2) (major, minor); NaN if degenerate."""
    a, b, c, d, e, f = np.moveaxis(conic, -1, 0)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        det = 4 * a * c - b * b
        x0 = (b * e - 2 * c * d) / det
        y0 = (b * d - 2 * a * e) / det
        # Value of the conic at the centre; the ellipse is q(x) = 0 with q(centre) = f0.
        f0 = a * x0 * x0 + b * x0 * y0 + c * y0 * y0 + d * x0 + e * y0 + f
        root = np.sqrt((a - c) ** 2 + b * b)
        lam1 = (a + c + root) / 2
        lam2 = (a + c - root) / 2
        ax1 = np.sqrt(-f0 / lam2)
        ax2 = np.sqrt(-f0 / lam1)
    major = np.fmax(ax1, ax2)
    minor = np.fmin(ax1, ax2)
    bad = ~(np.isfinite(major) & np.isfinite(minor))
    major[bad] = np.nan
    minor[bad] = np.nan
    centre = np.stack([x0, y0], axis=-1)
    return centre, np.stack([major, minor], axis=-1)
