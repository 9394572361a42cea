"""Tissue point cloud: back-projection, voxel grid, outliers; numpy and open3d agree."""

from __future__ import annotations

import numpy as np
import pytest

from vfdata.calibration import PinholeCamera
from vfdata.errors import BackendError, InputError
from vfdata.recon import tissue_cloud
from vfdata.recon.cloud import remove_statistical_outliers, voxel_downsample

CAM = PinholeCamera(560.0, 560.0, 319.5, 255.5, 640, 512)


def _cylinder_depth(radius=12.0, distance=90.0):
    """Depth (mm) of a horizontal cylinder (axis along camera x) in front of a far plane, and its
    mask."""
    v = np.arange(CAM.height, dtype=np.float64)[:, None].repeat(CAM.width, 1)
    ray_y = (v - CAM.cy) / CAM.fy
    # Ray (x, ray_y * z, z) meets the cylinder y^2 + (z - distance)^2 = radius^2.
    a = ray_y**2 + 1
    b = -2 * distance
    c = distance**2 - radius**2
    disc = b * b - 4 * a * c
    z = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.nan)
    u = np.arange(CAM.width)[None, :].repeat(CAM.height, 0)
    mask = np.isfinite(z) & (np.abs(u - CAM.cx) < 200)
    depth = np.where(mask, z, 200.0).astype(np.float32)
    return depth, mask


def test_cloud_lies_on_the_surface_with_voxel_spacing():
    depth, mask = _cylinder_depth()
    points = tissue_cloud(depth, mask, CAM, voxel_mm=1.0)
    assert points.dtype == np.float32 and points.shape[1] == 3
    radial = np.hypot(points[:, 1], points[:, 2] - 90.0)
    assert np.abs(radial - 12.0).max() < 0.3
    # One point per 1 mm voxel: the nearest neighbour is about a voxel away, never much closer.
    from scipy.spatial import cKDTree

    nn = cKDTree(points).query(points, k=2)[0][:, 1]
    assert 0.5 < np.median(nn) < 1.5
    # The visible half cylinder, 200/560*90 mm ~ 64 mm wide: ~ pi * 12 * 64 / 1 mm^2 surface voxels.
    assert 1200 < len(points) < 3500


def test_outliers_and_the_background_are_removed():
    depth, mask = _cylinder_depth()
    rng = np.random.default_rng(0)
    noisy = depth.copy()
    ys, xs = np.nonzero(mask)
    pick = rng.choice(len(ys), 40, replace=False)
    noisy[ys[pick], xs[pick]] -= 30.0  # flying pixels 30 mm in front of the tissue
    points = tissue_cloud(noisy, mask, CAM, voxel_mm=0.5)
    radial = np.hypot(points[:, 1], points[:, 2] - 90.0)
    assert np.abs(radial - 12.0).max() < 1.0
    assert points[:, 2].max() < 200.0  # nothing from the far plane outside the mask


@pytest.mark.slow  # open3d comes with `make test-slow` (the extra `fast`), not with the default set-up
def test_numpy_and_open3d_agree():
    pytest.importorskip("open3d", exc_type=ImportError)
    depth, mask = _cylinder_depth()
    a = tissue_cloud(depth, mask, CAM, backend="numpy")
    b = tissue_cloud(depth, mask, CAM, backend="open3d")
    assert abs(len(a) - len(b)) <= 0.02 * len(a)
    from scipy.spatial import cKDTree

    assert np.median(cKDTree(a).query(b)[0]) < 0.05


def test_voxel_downsample_means():
    pts = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.5, 0.1, 0.1]], np.float32)
    out = voxel_downsample(pts, 1.0)
    np.testing.assert_allclose(sorted(out[:, 0]), [0.2, 1.5], atol=1e-6)


def test_statistical_outlier_removal_keeps_the_inliers():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(500, 3)).astype(np.float32)
    pts = np.vstack([pts, [[50, 50, 50]]]).astype(np.float32)
    kept = remove_statistical_outliers(pts, 16, 2.0)
    assert not (kept == [50, 50, 50]).all(axis=1).any()
    assert len(kept) > 450


def test_empty_mask_and_bad_inputs():
    depth, mask = _cylinder_depth()
    assert tissue_cloud(depth, np.zeros_like(mask), CAM).shape == (0, 3)
    with pytest.raises(InputError):
        tissue_cloud(depth[:10], mask, CAM)
    with pytest.raises(BackendError, match="auto, numpy, open3d"):
        tissue_cloud(depth, mask, CAM, backend="pcl")


def test_grazing_pixels_are_the_steep_ramp_not_the_frontal_surface():
    from vfdata.recon.cloud import grazing_pixels

    # A frontal plane at 100 mm, with a band of rows whose depth ramps toward the camera (the depth
    # of an instrument above the tissue, smeared into tissue pixels by the stereo matcher).
    depth = np.full((CAM.height, CAM.width), 100.0, np.float32)
    depth[200:215] = np.linspace(100.0, 70.0, 15, dtype=np.float32)[:, None]  # 2 mm per pixel row
    graze = grazing_pixels(depth, CAM, max_angle_deg=75.0)
    assert not graze[100:180, 50:600].any(), "a frontal surface is not grazing"
    assert graze[203:212, 50:600].all(), "a ramp of 2 mm depth per pixel at 0.18 mm per pixel is"
    # The border, where no normal can be formed, counts as grazing (unknown).
    assert graze[0].all() and graze[:, 0].all()
    # A cylinder's frontal face is kept; its rims, seen edge-on, are not.
    depth, mask = _cylinder_depth()
    graze = grazing_pixels(depth, CAM)
    rows = np.nonzero(mask[:, int(CAM.cx)])[0]
    middle = rows[len(rows) // 2]
    assert not graze[middle - 10 : middle + 10, 200:440].any()
    assert graze[rows[0], 200:440].all() and graze[rows[-1], 200:440].all()
