import numpy as np
import pytest

from vfdata import metrics


def test_force_peaks_prominence_and_distance_on_the_magnitude():
    t = np.arange(200)
    magnitude = np.zeros(200)
    for centre, height in [(30, 5.0), (40, 4.0), (100, 1.5), (150, 6.0)]:
        magnitude += height * np.exp(-0.5 * ((t - centre) / 2.0) ** 2)
    # Split the magnitude between axes so that no single component shows the full peak.
    direction = np.stack([np.cos(t / 30.0), np.sin(t / 30.0), np.zeros(200)], axis=1)
    peaks = metrics.force_peaks(magnitude[:, None] * direction)
    # 40 is within 15 frames of the higher peak at 30; 100 is below 2 N prominence.
    assert peaks.tolist() == [30, 150]
    assert metrics.force_peaks(magnitude, distance_frames=5).tolist() == [30, 40, 150]


def test_mask_regions_are_100_roughly_equal_areas_of_the_mask():
    mask = np.zeros((240, 320), bool)
    yy, xx = np.mgrid[:240, :320]
    mask[(xx - 160) ** 2 / 140**2 + (yy - 120) ** 2 / 100**2 < 1] = True
    labels = metrics.mask_regions(mask, seed=3)
    assert (labels[~mask] == -1).all() and (labels[mask] >= 0).all()
    areas = np.bincount(labels[mask])
    assert len(areas) == 100
    assert areas.max() / areas.min() < 2.5
    assert np.array_equal(labels, metrics.mask_regions(mask, seed=3))


def test_coverage_counts_regions_holding_a_visible_point():
    mask = np.ones((100, 100), bool)
    regions = metrics.mask_regions(mask, num_regions=4, seed=0)
    centres = [np.argwhere(regions == r).mean(axis=0)[::-1] for r in range(4)]  # (u, v)
    uv = np.array(centres[:3] + [[np.nan, np.nan]])
    assert metrics.coverage(uv, regions=regions) == pytest.approx(0.75)
    assert metrics.coverage(uv, regions=regions, visible=[True, False, False, True]) == pytest.approx(0.25)
    # Two points in one region count once; points off the image are ignored.
    assert metrics.coverage(np.array([centres[0], centres[0], [500, 500]]), regions=regions) == 0.25
    assert metrics.coverage(np.array(centres), mask, num_regions=4) == 1.0


def test_nni_is_one_for_a_rigid_motion_and_drops_when_points_bunch():
    rng = np.random.default_rng(0)
    first = rng.uniform(0, 50, (256, 3))
    rotation = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    assert metrics.nearest_neighbour_index(first @ rotation.T + 7.0, first) == pytest.approx(1.0)
    assert metrics.nearest_neighbour_index(first * 0.5, first) == pytest.approx(0.5)
    # The same points at both frames: hiding some (or losing them, NaN) does not by itself spread the rest.
    half = np.arange(256) < 128
    assert metrics.nearest_neighbour_index(first, first, visible=half) == pytest.approx(1.0)
    assert metrics.nearest_neighbour_index(first, first, first_visible=half) == pytest.approx(1.0)
    lost = first.copy()
    lost[128:] = np.nan
    assert metrics.nearest_neighbour_index(lost, first) == pytest.approx(1.0)
    # ... while bunching the visible ones does lower it.
    bunched = first.copy()
    bunched[:128] *= 0.5
    assert metrics.nearest_neighbour_index(bunched, first, visible=half) == pytest.approx(0.5)


def test_tracking_error_splits_normal_and_tangential_parts():
    truth = np.zeros((2, 4, 3))
    normals = np.tile([0.0, 0.0, 2.0], (2, 4, 1))  # not unit: normalised inside
    estimate = truth + np.array([3.0, 0.0, 4.0])
    err = metrics.tracking_error(estimate, truth, normals)
    assert err.full_median_mm == pytest.approx(5.0)
    assert err.normal_median_mm == pytest.approx(4.0)
    assert err.tangential_p95_mm == pytest.approx(3.0)
    assert err.count == 8
    estimate[0, 0] = np.nan
    valid = np.ones((2, 4), bool)
    valid[1] = False
    assert metrics.tracking_error(estimate, truth, normals, valid=valid).count == 3
    with pytest.raises(ValueError):
        metrics.tracking_error(estimate[:1], truth, normals)
