"""Tracking-quality metrics of the paper (Table III) and errors against simulator ground truth.

Pure functions on arrays:
- `force_peaks`: frames of the force peaks at which tracking is judged (prominence 2.0 N, 15 frames
  apart, on the force magnitude).
- `mask_regions` / `coverage`: share of ~100 equal-area regions of the tissue mask holding at least one
  visible tracked point. Regions are k-means (k = 100, seeded) clusters of the mask's pixel coordinates:
  for a uniform density Lloyd's algorithm converges to a centroidal Voronoi tessellation, whose cells
  have nearly equal areas and compact shapes, whatever the outline of the mask.
- `nearest_neighbour_index`: mean nearest-neighbour distance of the tracked points at a frame over its
  value for the same points at the first frame (1 = as spread as at the start; < 1 = points bunching
  up).
- `tracking_error`: median and 95th percentile (mm) of the full 3D error and of its parts along the
  ground-truth surface normal and along the surface.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.signal import find_peaks
from scipy.spatial import cKDTree

PEAK_PROMINENCE_N = 2.0
PEAK_DISTANCE_FRAMES = 15
COVERAGE_REGIONS = 100
_KMEANS_SAMPLE = 20000  # mask pixels used to fit the regions; all pixels are then assigned


def force_magnitude(force_n: np.ndarray) -> np.ndarray:
    """(T, 3) force (N) -> (T,) magnitude; a (T,) array is taken as a magnitude already."""
    force_n = np.asarray(force_n, dtype=np.float64)
    if force_n.ndim == 1:
        return force_n
    if force_n.ndim != 2 or force_n.shape[1] != 3:
        raise ValueError(f"force must be (T,) or (T, 3), got {force_n.shape}")
    return np.linalg.norm(force_n, axis=1)


def force_peaks(
    force_n: np.ndarray,
    prominence_n: float = PEAK_PROMINENCE_N,
    distance_frames: int = PEAK_DISTANCE_FRAMES,
) -> np.ndarray:
    """Frame indices of the peaks of the force magnitude |F| (N), per frame.

    Peaks are taken on the magnitude rather than per component: a push or pull along any direction is
    one interaction, and the magnitude does not split it into several peaks or miss one whose force
    turns between axes."""
    magnitude = force_magnitude(force_n)
    peaks, _ = find_peaks(magnitude, prominence=prominence_n, distance=distance_frames)
    return peaks


def mask_regions(mask: np.ndarray, num_regions: int = COVERAGE_REGIONS, seed: int = 0) -> np.ndarray:
    """(H, W) int32 label image: -1 off the mask, else one of `num_regions` roughly equal-area regions
    (k-means on the pixel coordinates of the mask, seeded; fewer regions if the mask is that small)."""
    mask = np.asarray(mask).astype(bool)
    rows, cols = np.nonzero(mask)
    labels = np.full(mask.shape, -1, dtype=np.int32)
    if len(rows) == 0:
        return labels
    pixels = np.stack([cols, rows], axis=1).astype(np.float64)
    k = min(num_regions, len(pixels))
    rng = np.random.default_rng(seed)
    sample = pixels if len(pixels) <= _KMEANS_SAMPLE else pixels[rng.choice(len(pixels), _KMEANS_SAMPLE, replace=False)]
    centroids, _ = kmeans2(sample, k, iter=30, minit="++", seed=rng)
    _, assignment = cKDTree(centroids).query(pixels)
    # A centroid that no pixel picks leaves an empty region: renumber so labels are 0..n-1 and dense.
    _, dense = np.unique(assignment, return_inverse=True)
    labels[rows, cols] = dense
    return labels


def coverage(
    points_uv: np.ndarray,
    mask: np.ndarray | None = None,
    visible: np.ndarray | None = None,
    num_regions: int = COVERAGE_REGIONS,
    seed: int = 0,
    regions: np.ndarray | None = None,
) -> float:
    """Share (0..1) of the regions of the tissue mask that hold at least one visible tracked point.

    points_uv: (N, 2) pixel positions (u right, v down) of the tracked points, NaN for lost ones;
    visible: (N,) bool, all true when None; pass `regions` (from `mask_regions`) to reuse them,
    otherwise they are made from `mask`."""
    if regions is None:
        if mask is None:
            raise ValueError("coverage needs the tissue mask or precomputed regions")
        regions = mask_regions(mask, num_regions, seed)
    count = int(regions.max()) + 1
    if count <= 0:
        return 0.0
    points_uv = np.asarray(points_uv, dtype=np.float64)
    ok = np.isfinite(points_uv).all(axis=1)
    if visible is not None:
        ok &= np.asarray(visible, dtype=bool)
    u = np.floor(points_uv[ok, 0] + 0.5).astype(np.int64)
    v = np.floor(points_uv[ok, 1] + 0.5).astype(np.int64)
    h, w = regions.shape
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    hit = regions[v[inside], u[inside]]
    return len(np.unique(hit[hit >= 0])) / count


def mean_nearest_neighbour_distance(points: np.ndarray) -> float:
    """Mean distance (same unit as `points`, (N, D)) from each point to its nearest other point; NaN
    rows are ignored; NaN when fewer than two points remain."""
    points = np.asarray(points, dtype=np.float64)
    points = points[np.isfinite(points).all(axis=1)]
    if len(points) < 2:
        return float("nan")
    distance, _ = cKDTree(points).query(points, k=2)
    return float(distance[:, 1].mean())


def nearest_neighbour_index(
    points: np.ndarray,
    first_points: np.ndarray,
    visible: np.ndarray | None = None,
    first_visible: np.ndarray | None = None,
) -> float:
    """NNI = mean nearest-neighbour distance of the tracked points at a frame over that of the same
    points at the first frame. Points are (N, 3) mm (or (N, 2) pixels; the ratio has no unit), in the
    same order in both frames.

    The same points enter both means: those with finite positions in both frames and, when `visible` /
    `first_visible` ((N,) bool) are given, visible in both. Comparing the visible set of one frame with
    that of another would mix spreading with occlusion: hiding half the points alone raises the mean
    nearest-neighbour distance of the rest (by ~1.4x for a uniform spread) without any point moving."""
    points = np.asarray(points, dtype=np.float64)
    first_points = np.asarray(first_points, dtype=np.float64)
    if points.shape != first_points.shape:
        raise ValueError(f"points {points.shape} and first points {first_points.shape} differ in shape")
    same = np.isfinite(points).all(axis=1) & np.isfinite(first_points).all(axis=1)
    if visible is not None:
        same &= np.asarray(visible, dtype=bool)
    if first_visible is not None:
        same &= np.asarray(first_visible, dtype=bool)
    return mean_nearest_neighbour_distance(points[same]) / mean_nearest_neighbour_distance(first_points[same])


@dataclass(frozen=True)
class TrackingError:
    """Error statistics over every (frame, point) pair compared, mm."""

    full_median_mm: float
    full_p95_mm: float
    normal_median_mm: float
    normal_p95_mm: float
    tangential_median_mm: float
    tangential_p95_mm: float
    count: int

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def tracking_error(
    estimate: np.ndarray,
    truth: np.ndarray,
    truth_normals: np.ndarray,
    valid: np.ndarray | None = None,
) -> TrackingError:
    """Error of tracked positions against ground truth, split along the true surface normal.

    estimate, truth, truth_normals: (..., 3) in mm (e.g. (F, N, 3)); normals need not be unit length.
    valid: (...) bool of the pairs to compare (e.g. the points a tracker still reports); NaN estimates
    are always left out. The normal part is |e . n|, the tangential part |e - (e . n) n|."""
    estimate = np.asarray(estimate, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    normals = np.asarray(truth_normals, dtype=np.float64)
    if estimate.shape != truth.shape or truth.shape != normals.shape or truth.shape[-1] != 3:
        raise ValueError(f"shapes differ or are not (..., 3): {estimate.shape}, {truth.shape}, {normals.shape}")
    normals = normals / np.linalg.norm(normals, axis=-1, keepdims=True)
    ok = np.isfinite(estimate).all(axis=-1) & np.isfinite(truth).all(axis=-1) & np.isfinite(normals).all(axis=-1)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    error = (estimate - truth)[ok]
    n = normals[ok]
    along = np.sum(error * n, axis=1)
    full = np.linalg.norm(error, axis=1)
    normal = np.abs(along)
    tangential = np.linalg.norm(error - along[:, None] * n, axis=1)
    if len(full) == 0:
        nan = float("nan")
        return TrackingError(nan, nan, nan, nan, nan, nan, 0)
    return TrackingError(
        full_median_mm=float(np.median(full)),
        full_p95_mm=float(np.percentile(full, 95)),
        normal_median_mm=float(np.median(normal)),
        normal_p95_mm=float(np.percentile(normal, 95)),
        tangential_median_mm=float(np.median(tangential)),
        tangential_p95_mm=float(np.percentile(tangential, 95)),
        count=int(len(full)),
    )
