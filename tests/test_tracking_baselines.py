import numpy as np
import pytest
import torch

from vfdata import metrics
from vfdata.errors import BackendError, InputError
from vfdata.tracking import CoTrackerTracker, GroundTruthTracker, KLTTracker, ground_truth_tracks, load_cotracker
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


def _instrument_crossing(frames: int, **options):
    """A sheet sliding right under a flat grey instrument that covers a band of the image at frames 2-3,
    then leaves: the tracker, the points under the band, the last points and visibility, and the truth."""
    sheet = DeformingSheet(rigid_translation(frames, np.array([0.5, 0.0, 0.0])))
    views = [sheet.image(f) for f in range(frames)]
    tracker = KLTTracker(sheet.cloud(0), CAMERA, views[0][0], num_points=64, **options)
    under = (tracker.uv[:, 0] > 330) & (tracker.uv[:, 0] < 420)
    assert under.sum() > 3
    for f in range(1, frames):
        image, mask, depth = views[f]
        if f in (2, 3):
            image = image.copy()
            image[:, 320:430] = 90
            mask = mask.copy()
            mask[:, 320:430] = False
        points, visible = tracker.update(image, depth, mask)
        if f == 2:
            assert not visible[under].any()
    truth, normals = sheet.reference_tracks(tracker.reference)
    return tracker, under, points, visible, truth[-1], normals[-1]


def test_klt_by_default_drops_points_for_good_once_an_instrument_hides_them():
    tracker, under, points, visible, _, _ = _instrument_crossing(frames=8)  # `recover` is off by default
    lost = ~tracker.alive
    assert lost[under].mean() > 0.8 and not lost[~under].all()
    assert np.isnan(points[lost]).all() and not visible[lost].any()


def test_klt_finds_hidden_points_again_where_they_are_once_the_instrument_leaves():
    tracker, under, points, visible, truth, normals = _instrument_crossing(frames=8, recover=True)
    assert tracker.alive[under].mean() > 0.8 and visible[under].mean() > 0.8
    back = under & visible
    error = metrics.tracking_error(points[back], truth[back], normals[back])
    assert error.full_median_mm < 0.3 and error.full_p95_mm < 1.0  # the same point, not a neighbour's texture


def test_klt_recover_must_be_true_or_false():
    sheet = DeformingSheet(rigid_translation(2, np.zeros(3)))
    with pytest.raises(ValueError, match="recover 'yes' is not true or false"):
        KLTTracker(sheet.cloud(0), CAMERA, sheet.image(0)[0], num_points=16, recover="yes")


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
