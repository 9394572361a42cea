"""Stage 3: the tissue point cloud of one frame, in the left camera frame (mm).

Masked depth is back-projected with the rectified intrinsics, thinned on a voxel grid and cleaned of
statistical outliers (points whose mean distance to their k nearest neighbours is more than
`outlier_std` standard deviations above the cloud's average: stray stereo matches at the mask's
edge, flying pixels across depth discontinuities).

For speed the back-projection first averages the 3D points of small pixel blocks, sized so that a
block is at most half a voxel wide at the tissue's depth: it changes nothing the voxel grid would
keep, and leaves the voxel grid and the neighbour search a tenth of the points. The voxel grid and
the outlier removal run in open3d (`backend="open3d"`) or numpy/scipy (`backend="numpy"`); both give
the same cloud up to the order of the points; open3d's neighbour search is about twice as fast, so
"auto" takes it when it imports.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np
from scipy.spatial import cKDTree

from vfdata.calibration import PinholeCamera
from vfdata.errors import BackendError, InputError

CLOUD_BACKENDS = ("auto", "numpy", "open3d")


def tissue_cloud(
    depth_mm: np.ndarray,
    mask: np.ndarray,
    camera: PinholeCamera,
    *,
    voxel_mm: float = 1.0,
    outlier_neighbors: int = 16,
    outlier_std: float = 2.0,
    backend: str = "auto",
) -> np.ndarray:
    """(H, W) depth (mm, NaN or <= 0: none) and (H, W) tissue mask -> (N, 3) float32 camera-frame
    points (mm): one per occupied voxel of `voxel_mm` (the mean of its points), statistical
    outliers removed (`outlier_neighbors` = 0 turns that off). Empty (0, 3) if the mask is empty.
    `backend` "auto" is open3d when it imports (about twice as fast: its neighbour search), else numpy."""
    depth = np.asarray(depth_mm, dtype=np.float32)
    mask = np.asarray(mask)
    if depth.ndim != 2 or mask.shape[:2] != depth.shape:
        raise InputError(
            "tissue cloud", f"depth {depth.shape} and mask {mask.shape} must be (H, W) of one size"
        )
    if depth.shape != (camera.height, camera.width):
        raise InputError(
            "tissue cloud", f"depth {depth.shape} does not match the camera ({camera.height}, {camera.width})"
        )
    if backend not in CLOUD_BACKENDS:
        raise BackendError(f"unknown cloud backend '{backend}'; known: {', '.join(CLOUD_BACKENDS)}")
    if voxel_mm <= 0:
        raise InputError("tissue cloud", f"voxel_mm must be positive, not {voxel_mm}")
    points = backproject_binned(depth, mask.astype(bool), camera, voxel_mm / 2)
    if len(points) == 0:
        return np.zeros((0, 3), dtype=np.float32)
    if backend == "auto":
        backend = "open3d" if _open3d() is not None else "numpy"
    if backend == "open3d":
        return _open3d_clean(points, voxel_mm, outlier_neighbors, outlier_std)
    points = voxel_downsample(points, voxel_mm)
    if outlier_neighbors > 0:
        points = remove_statistical_outliers(points, outlier_neighbors, outlier_std)
    return points


def backproject_binned(
    depth: np.ndarray, mask: np.ndarray, camera: PinholeCamera, max_block_mm: float
) -> np.ndarray:
    """Masked depth -> (N, 3) float32 points, averaging the points of b x b pixel blocks where b is
    the largest block no wider than `max_block_mm` at the masked median depth (b = 1: one point per
    pixel). A block yields a point when at least half of its pixels are valid tissue."""
    # Work on the mask's bounding box only: the tissue covers a small part of the image.
    x, y, w, h = cv2.boundingRect(mask.astype(np.uint8))
    if w == 0 or h == 0:
        return np.zeros((0, 3), dtype=np.float32)
    depth = depth[y : y + h, x : x + w]
    valid = mask[y : y + h, x : x + w] & (depth > 0)  # NaN compares false
    if not valid.any():
        return np.zeros((0, 3), dtype=np.float32)
    median_z = float(np.median(depth[valid][:: max(1, int(valid.sum()) // 4096)]))
    block = max(1, int(max_block_mm / (median_z / max(camera.fx, camera.fy))))
    gx, gy = _ray_grids(camera)
    gx, gy = gx[y : y + h, x : x + w], gy[y : y + h, x : x + w]
    z = np.where(valid, depth, np.float32(0))
    if block == 1:
        v, u = np.nonzero(valid)
        zz = z[v, u]
        return np.stack([gx[v, u] * zz, gy[v, u] * zz, zz], axis=1).astype(np.float32)
    size = (w // block, h // block)
    if size[0] == 0 or size[1] == 0:
        return np.zeros((0, 3), dtype=np.float32)
    crop = (slice(0, size[1] * block), slice(0, size[0] * block))
    weight = valid[crop].astype(np.float32)
    z = z[crop]
    # INTER_AREA with an integer factor is an exact block mean.
    sums = [
        cv2.resize(a, size, interpolation=cv2.INTER_AREA) for a in (z * gx[crop], z * gy[crop], z, weight)
    ]
    x_s, y_s, z_s, frac = sums
    keep = frac >= 0.5
    n = frac[keep]
    return np.stack([x_s[keep] / n, y_s[keep] / n, z_s[keep] / n], axis=1).astype(np.float32)


def grazing_pixels(depth_mm: np.ndarray, camera: PinholeCamera, max_angle_deg: float = 75.0,
                   step_px: int = 2) -> np.ndarray:
    """(H, W) bool: pixels whose surface is seen more than `max_angle_deg` away from its viewing ray,
    or whose surface normal is unknown (no depth within `step_px` either way). These are the flying
    pixels of stereo at an occluding edge: beside an instrument shaft lying over the tissue, SGBM and
    the smoothing carry the shaft's depth into a band of tissue pixels, a steep ramp toward the camera
    (on the simulator's glove_011 a quarter of the first cloud). The tube's own silhouette rims are
    steep too, so this is a filter for a cross-check, not for every cloud."""
    z = np.asarray(depth_mm, dtype=np.float32)
    gx, gy = _ray_grids(camera)
    points = np.stack([gx * z, gy * z, z], axis=-1)
    s = step_px
    du = np.full_like(points, np.nan)
    dv = np.full_like(points, np.nan)
    du[:, s:-s] = points[:, 2 * s:] - points[:, : -2 * s]
    dv[s:-s] = points[2 * s:] - points[: -2 * s]
    normal = np.cross(du, dv)
    with np.errstate(invalid="ignore", divide="ignore"):
        norms = np.linalg.norm(normal, axis=-1) * np.linalg.norm(points, axis=-1)
        cos = np.abs((normal * points).sum(axis=-1)) / norms
    return ~(cos >= np.float32(np.cos(np.radians(max_angle_deg))))  # NaN (no normal) counts as grazing


@functools.lru_cache(maxsize=4)
def _ray_grids(camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel x/z and y/z of the viewing rays."""
    u = (np.arange(camera.width, dtype=np.float32) - np.float32(camera.cx)) / np.float32(camera.fx)
    v = (np.arange(camera.height, dtype=np.float32) - np.float32(camera.cy)) / np.float32(camera.fy)
    return (
        np.ascontiguousarray(np.broadcast_to(u[None, :], (camera.height, camera.width))),
        np.ascontiguousarray(np.broadcast_to(v[:, None], (camera.height, camera.width))),
    )


def voxel_downsample(points: np.ndarray, voxel_mm: float) -> np.ndarray:
    """One point per occupied voxel (the mean of its points), voxels ordered by their index. The
    grid starts half a voxel below the cloud's minimum, as open3d's voxel_down_sample does."""
    origin = points.min(axis=0).astype(np.float64) - voxel_mm / 2
    cells = np.floor((points - origin) / voxel_mm).astype(np.int64)
    dims = cells.max(axis=0) + 1
    key = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    out = np.empty((len(counts), 3), dtype=np.float32)
    for j in range(3):
        out[:, j] = np.bincount(inverse, weights=points[:, j], minlength=len(counts)) / counts
    return out


def remove_statistical_outliers(
    points: np.ndarray, neighbors: int = 16, std_ratio: float = 2.0
) -> np.ndarray:
    """Drop points whose mean distance to their `neighbors` nearest neighbours exceeds the cloud's
    mean of that distance by more than `std_ratio` standard deviations (open3d's definition)."""
    if len(points) <= neighbors:
        return points
    dist, _ = cKDTree(points).query(points, k=neighbors + 1)
    mean_dist = dist[:, 1:].mean(axis=1)
    return points[mean_dist <= mean_dist.mean() + std_ratio * mean_dist.std()]


@functools.lru_cache(maxsize=1)
def _open3d():
    """The open3d module, or None when it does not import (it needs libusb-1.0 on Linux)."""
    try:  # optional, and its import can fail at run time: imported on first use only
        import open3d as o3d
    except ImportError:
        return None
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


def _open3d_clean(points: np.ndarray, voxel_mm: float, neighbors: int, std_ratio: float) -> np.ndarray:
    o3d = _open3d()
    if o3d is None:
        raise BackendError(
            "cloud backend 'open3d' is not available (import failed; on Debian/Ubuntu it needs "
            "`apt-get install libusb-1.0-0`); use backend='numpy'"
        )
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    cloud = cloud.voxel_down_sample(voxel_mm)
    if neighbors > 0 and len(cloud.points) > neighbors:
        cloud, _ = cloud.remove_statistical_outlier(nb_neighbors=neighbors, std_ratio=std_ratio)
    return np.asarray(cloud.points, dtype=np.float32)
