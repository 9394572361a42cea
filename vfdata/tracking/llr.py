"""Local linear reconstruction (LLR) weights, as in locally linear embedding (Roweis and Saul, 2000).

Each point is written as an affine combination of its k nearest neighbours: weights w_i (k,) with
sum(w_i) = 1 that minimise |x_i - sum_j w_ij x_j|^2. The weights do not change under rotation,
translation or uniform scaling of the neighbourhood, so the residual of a deformed cloud measures
how far each neighbourhood is from a similarity transform of the reference one (bending, tearing,
points leaving the surface), the local rigidity prior of the tracker.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree


def nearest_neighbours(points: np.ndarray, k: int) -> np.ndarray:
    """(N, k) indices of the k nearest other points of each of `points` (N, 3), closest first."""
    points = np.asarray(points, dtype=np.float64)
    if not 0 < k < len(points):
        raise ValueError(f"k must be in [1, {len(points) - 1}] for {len(points)} points, got {k}")
    _, idx = cKDTree(points).query(points, k=k + 1)
    # The nearest hit of a point is itself, unless duplicates tie with it: drop exactly its own index.
    own = idx == np.arange(len(points))[:, None]
    own[~own.any(axis=1), -1] = True
    return idx[~own].reshape(len(points), k)


def reconstruction_weights(
    points: np.ndarray,
    neighbours: np.ndarray,
    regularization: float = 1e-3,
    basis: np.ndarray | None = None,
) -> np.ndarray:
    """(N, k) affine LLE weights reconstructing each of `points` (N, 3) from `neighbours` (N, k), rows
    of `basis` (another (P, 3) cloud) when given, else of `points` itself.

    Solves the local Gram system C w = 1 with C_jl = (x_j - x_i) . (x_l - x_i), then normalises w to
    sum 1. C has rank <= 3 < k, so `regularization` times trace(C) is added to its diagonal (the usual
    LLE conditioning): it picks the smoothest of the exact solutions, with weights spread over the
    neighbours instead of a few large ones of opposite sign."""
    points = np.asarray(points, dtype=np.float64)
    neighbours = np.asarray(neighbours, dtype=np.int64)
    k = neighbours.shape[1]
    basis = points if basis is None else np.asarray(basis, dtype=np.float64)
    z = basis[neighbours] - points[:, None, :]  # (N, k, 3)
    gram = z @ z.transpose(0, 2, 1)
    trace = np.trace(gram, axis1=1, axis2=2)
    # Coincident neighbours (trace 0) still need a well-posed system: fall back to an absolute floor.
    eps = regularization * np.where(trace > 0, trace, 1.0)
    gram += eps[:, None, None] * np.eye(k)
    w = np.linalg.solve(gram, np.ones((len(points), k, 1)))[..., 0]
    return w / w.sum(axis=1, keepdims=True)


def llr_residual(points: torch.Tensor, neighbours: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """(N, 3) residual x_i - sum_j w_ij x_j of `points` (N, 3) under fixed neighbours and weights."""
    return points - torch.bmm(weights.unsqueeze(1), points[neighbours]).squeeze(1)


def normal_matrix(neighbours: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(N, N) matrix A^T A of the linear map A: points -> LLR residuals (A = I - W, W_i,n(i,j) = w_ij).

    sum_i |r_i(p) - r_i(q)|^2 = |A (p - q)|^2 is a quadratic form in the points, so its gradient
    2 A^T A (p - q) is one (N, N) x (N, 3) product: the tracker forms A^T A once per frame instead of
    gathering and scattering over the neighbours at every optimisation step."""
    neighbours = np.asarray(neighbours, dtype=np.int64)
    n, k = neighbours.shape
    # Row i of A has k + 1 non-zeros: 1 at i, -w_ij at its neighbours; A^T A = sum_i a_i a_i^T adds up
    # (k + 1)^2 products per row, far fewer than a dense (N, N) x (N, N) product.
    columns = np.concatenate([np.arange(n)[:, None], neighbours], axis=1)
    values = np.concatenate([np.ones((n, 1)), -np.asarray(weights, dtype=np.float64)], axis=1)
    flat = (columns[:, :, None] * n + columns[:, None, :]).reshape(-1)
    products = (values[:, :, None] * values[:, None, :]).reshape(-1)
    return np.bincount(flat, weights=products, minlength=n * n).reshape(n, n)
