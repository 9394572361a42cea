"""Choosing the tracked points: farthest-point sampling of the reference tissue cloud, isolated points left out."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def farthest_point_sampling(points: np.ndarray, num_points: int, seed: int = 0) -> np.ndarray:
    """Indices of `num_points` well-spread points of `points` (N, 3).

    Greedy farthest-point sampling: start from a seeded random point, then repeatedly add the point
    farthest from everything chosen so far. O(N * num_points); about 30 ms for 20,000 points and 256
    picks. When `num_points` >= N every index is returned (in sampling order)."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {points.shape}")
    n = len(points)
    if n == 0:
        raise ValueError("cannot sample from an empty point cloud")
    count = min(int(num_points), n)
    rng = np.random.default_rng(seed)
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = rng.integers(n)
    dist2 = np.sum((points - points[chosen[0]]) ** 2, axis=1)
    for i in range(1, count):
        chosen[i] = int(np.argmax(dist2))
        np.minimum(dist2, np.sum((points - points[chosen[i]]) ** 2, axis=1), out=dist2)
    return chosen


# A point whose 8th nearest neighbour is this many times farther than the cloud's median is isolated.
ISOLATION_FACTOR = 5.0
ISOLATION_NEIGHBOURS = 8


def isolated_points(points: np.ndarray, factor: float = ISOLATION_FACTOR, k: int = ISOLATION_NEIGHBOURS) -> np.ndarray:
    """(N,) bool: points of the cloud (N, 3) whose k-th nearest neighbour is more than `factor` times the
    cloud's median k-th-neighbour distance away; none when factor <= 0 or N <= k.

    Such points are depth outliers ("flying pixels": a mask pixel with the depth of what lies behind the
    tissue) or the sparse samples of a surface seen at a grazing angle. Farthest-point sampling picks them
    first, being far from everything, and the tracker's Chamfer term then pulls them towards a cloud
    that has no samples near them, dragging the whole shared displacement field (docs/tracking.md)."""
    points = np.asarray(points, dtype=np.float64)
    if factor <= 0 or len(points) <= k:
        return np.zeros(len(points), dtype=bool)
    distance = cKDTree(points).query(points, k + 1)[0][:, k]
    return distance > factor * np.median(distance)


def select_reference_points(
    points: np.ndarray, num_points: int, seed: int = 0, isolation_factor: float = ISOLATION_FACTOR
) -> np.ndarray:
    """Indices of the `num_points` tracked points in the reference cloud `points` (N, 3): farthest-point
    sampling over the points that are not isolated (`isolated_points`). Every tracker uses it, so all
    start from the same points for a seed."""
    points = np.asarray(points, dtype=np.float64)
    kept = np.flatnonzero(~isolated_points(points, isolation_factor))
    if len(kept) == 0:  # cannot happen with factor > 0 (the median point is kept); guards factor misuse
        kept = np.arange(len(points))
    return kept[farthest_point_sampling(points[kept], num_points, seed=seed)]
