"""The `groundtruth` tracker: the simulator's material points carried to the tracked points.

The simulator moves P material points (ground_truth/points.npy, (F, P, 3) mm, with normals.npy). The
tracked points are picked on the reference tissue cloud, not on material points, so each one is
written once, on frame 0, as an affine combination of its k nearest material points (LLE weights);
the same combination of the same material points gives its true position and normal in every later
frame. This is both the upper-bound tracker and the reference of `vfdata.metrics.tracking_error`.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from vfdata.calibration import PinholeCamera
from vfdata.tracking.llr import reconstruction_weights
from vfdata.tracking.sampling import select_reference_points


def ground_truth_tracks(
    reference: np.ndarray,
    material_points: np.ndarray,
    material_normals: np.ndarray,
    k: int = 6,
    reference_frame: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """True trajectories (F, n, 3) mm and unit normals (F, n, 3) of the `reference` points (n, 3),
    which lie on the surface at `reference_frame`, from material points/normals (F, P, 3)."""
    material_points = np.asarray(material_points, dtype=np.float64)
    material_normals = np.asarray(material_normals, dtype=np.float64)
    if material_points.ndim != 3 or material_points.shape != material_normals.shape:
        raise ValueError(f"material points and normals must be (F, P, 3) alike: {material_points.shape}, "
                         f"{material_normals.shape}")
    at_reference = material_points[reference_frame]
    _, neighbours = cKDTree(at_reference).query(reference, k=k)
    # Small regularisation: the weights must reproduce the point, not just be smooth.
    weights = reconstruction_weights(reference, neighbours, regularization=1e-6, basis=at_reference)
    tracks = np.einsum("nk,fnkd->fnd", weights, material_points[:, neighbours])
    normals = np.einsum("nk,fnkd->fnd", weights, material_normals[:, neighbours])
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return tracks, normals


class GroundTruthTracker:
    """The upper bound: `.update(frame, mask)` -> (true points (n, 3) mm, visible (n,) bool), for the
    same reference selection as the other trackers."""

    def __init__(
        self,
        reference_points: np.ndarray,
        material_points: np.ndarray,
        material_normals: np.ndarray,
        camera: PinholeCamera | None = None,
        num_points: int = 256,
        seed: int = 0,
    ):
        reference_points = np.asarray(reference_points, dtype=np.float64)
        reference_points = reference_points[np.isfinite(reference_points).all(axis=1)]
        self.reference = reference_points[select_reference_points(reference_points, num_points, seed=seed)]
        self.camera = camera
        self.tracks, self.normals = ground_truth_tracks(self.reference, material_points, material_normals)
        self._points = self.reference.copy()

    @property
    def points(self) -> np.ndarray:
        return self._points.copy()

    def update(self, frame: int, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        self._points = self.tracks[frame].copy()
        if mask is None or self.camera is None:
            return self._points.copy(), np.ones(len(self._points), dtype=bool)
        return self._points.copy(), self.camera.in_mask(self._points, np.asarray(mask))
