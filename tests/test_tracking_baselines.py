import numpy as np
import pytest
import torch

from vfdata import metrics
from vfdata.errors import BackendError, InputError
from vfdata.tracking import (
    CoTrackerTracker,
    GroundTruthTracker,
    KLTTracker,
    ProbeTracker,
    ground_truth_tracks,
    load_cotracker,
)
from vfdata.tracking.synthetic import CAMERA, DeformingSheet, press_and_stretch, rigid_translation


def test_klt_follows_textured_motion_and_lifts_it_with_depth():
    frames = 8
    sheet = DeformingSheet(rigid_translation(frames, np.array([2.0, -1.0, -2.0])))
    views = [sheet.image(f) for f in range(frames)]  # (image, mask, depth)
    cloud = sheet.cloud(0)
    tracker = KLTTracker(cloud, CAMERA, views[0][0], num_points=64)
    assert np.array_equal(tracker.points, tracker.reference)
    truth, normals = sheet.reference_tracks(tracker.reference)
    for f in range(1, frames):
        points, visible = tracker.update(views[f][0], views[f][2], views[f][1])
    assert points.shape == (64, 3) and visible.shape == (64,)
    ok = np.isfinite(points).all(axis=1)
    assert ok.mean() > 0.8 and np.array_equal(visible, ok & CAMERA.in_mask(points, views[-1][1]))
    error = metrics.tracking_error(points, truth[-1], normals[-1])
    assert error.full_median_mm < 0.3  # the motion is 3 mm


def test_klt_drops_points_for_good_once_an_instrument_hides_them():
    frames = 6
    sheet = DeformingSheet(rigid_translation(frames, np.array([0.5, 0.0, 0.0])))
    views = [sheet.image(f) for f in range(frames)]
    tracker = KLTTracker(sheet.cloud(0), CAMERA, views[0][0], num_points=64)
    under = (tracker.uv[:, 0] > 330) & (tracker.uv[:, 0] < 420)
    assert under.sum() > 3
    for f in range(1, frames):
        image, mask, depth = views[f]
        if f in (2, 3):  # a flat grey instrument covers a band of the image, then leaves
            image = image.copy()
            image[:, 320:430] = 90
            mask = mask.copy()
            mask[:, 320:430] = False
        points, visible = tracker.update(image, depth, mask)
        if f == 2:
            assert not visible[under].any()
    lost = ~tracker.alive
    assert lost[under].mean() > 0.8 and not lost[~under].all()
    assert np.isnan(points[lost]).all() and not visible[lost].any()


def test_ground_truth_tracks_interpolate_material_points():
    frames = 10
    sheet = DeformingSheet(press_and_stretch(frames))
    uv = sheet.material_grid(80)
    material = np.stack([sheet.surface(uv, f) for f in range(frames)])
    material_normals = np.stack([sheet.normals(uv, f) for f in range(frames)])
    tracker = GroundTruthTracker(sheet.cloud(0), material, material_normals, camera=CAMERA, num_points=100)
    exact, exact_normals = sheet.reference_tracks(tracker.reference)
    tracks, normals = ground_truth_tracks(tracker.reference, material, material_normals)
    assert tracks.shape == normals.shape == (frames, 100, 3)
    assert np.abs(tracks - exact).max() < 0.05  # mm; material spacing is 0.76 mm
    assert np.einsum("fnd,fnd->fn", normals, exact_normals).min() > 0.999
    points, visible = tracker.update(frames - 1, mask=np.ones((CAMERA.height, CAMERA.width), bool))
    assert np.array_equal(points, tracks[-1]) and visible.all()


def test_cotracker_needs_a_checkpoint(tmp_path):
    with pytest.raises(BackendError, match="no checkpoint"):
        load_cotracker(None)
    missing = tmp_path / "scaled_offline.pth"
    with pytest.raises(BackendError, match="checkpoint not found"):
        CoTrackerTracker(np.zeros((10, 3)), CAMERA, missing)
    missing.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="not a readable CoTracker3 checkpoint"):
        load_cotracker(missing)
    torch.save({"model": {"weight": torch.zeros(2)}}, missing)  # tensors, but not CoTracker's
    try:
        import cotracker  # noqa: F401
    except ImportError:
        with pytest.raises(BackendError, match="not installed"):
            load_cotracker(missing)
    else:
        with pytest.raises(BackendError, match="not a CoTracker3"):
            load_cotracker(missing)


def _board(h: int = 120, w: int = 160, z_mm: float = 700.0) -> np.ndarray:
    return np.full((h, w), z_mm, dtype=np.float32)


def _cloud(depth: np.ndarray, step: int = 2) -> np.ndarray:
    v, u = np.mgrid[0:depth.shape[0]:step, 0:depth.shape[1]:step]
    z = depth[v, u].astype(np.float64)
    return np.column_stack([(u.ravel() - CAMERA.cx) * z.ravel() / CAMERA.fx,
                            (v.ravel() - CAMERA.cy) * z.ravel() / CAMERA.fy, z.ravel()])


def test_probe_reads_how_far_the_surface_sinks_under_each_fixed_pixel():
    depth0 = _board()
    tracker = ProbeTracker(_cloud(depth0), CAMERA, num_points=64, seed=1)
    uv0 = CAMERA.project(tracker.reference)
    pressed = depth0.copy()
    v, u = np.mgrid[0:depth0.shape[0], 0:depth0.shape[1]]
    centre = np.round(uv0[0]).astype(int)
    dent = 4.0 * np.exp(-((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / (2 * 6.0 ** 2))
    pressed += dent.astype(np.float32)  # farther from the camera: the surface sinks up to 4 mm
    points, visible = tracker.update(pressed)
    assert visible.all()
    np.testing.assert_allclose(CAMERA.project(points), uv0, atol=1e-9)  # each point stays on its pixel
    sink = points[:, 2] - tracker.reference[:, 2]
    assert 3.3 < sink[0] <= 4.0  # the window's median, a little under the dent's 4 mm apex
    far = np.linalg.norm(uv0 - uv0[0], axis=1) > 30
    assert far.any() and np.abs(sink[far]).max() < 0.01


def test_probe_ignores_a_spike_and_holds_points_without_depth_under_them():
    depth0 = _board()
    tracker = ProbeTracker(_cloud(depth0), CAMERA, num_points=32, seed=2, radius_px=2)
    u, v = np.round(CAMERA.project(tracker.reference)[0]).astype(int)
    spiky = depth0.copy()
    spiky[v, u] = 900.0  # one wrong pixel (a Kinect edge artefact): the median keeps the surface
    points, visible = tracker.update(spiky)
    assert visible[0] and points[0, 2] == pytest.approx(700.0)
    moved = depth0 + 2.0
    mask = np.ones_like(depth0, dtype=bool)
    mask[v - 5:v + 6, u - 5:u + 6] = False  # the instrument hides the first point's window
    points, visible = tracker.update(moved, mask)
    assert not visible[0] and points[0, 2] == pytest.approx(700.0)  # held where it was last read
    assert visible[1:].all() and np.allclose(points[1:, 2], 702.0)
    points, visible = tracker.update(np.zeros_like(depth0))  # a frame without depth (0 = none)
    assert not visible.any() and np.allclose(points[1:, 2], 702.0)


def test_probe_refuses_bad_options():
    with pytest.raises(ValueError, match="radius_px"):
        ProbeTracker(_cloud(_board()), CAMERA, radius_px=-1)
    with pytest.raises(ValueError, match="min_valid"):
        ProbeTracker(_cloud(_board()), CAMERA, min_valid=0.0)
