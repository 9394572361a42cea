"""The real-recording study's pieces: per-frame reference models, splits, forward-backward consistency."""

from __future__ import annotations

import numpy as np
import pytest

from vfdata.calibration import PinholeCamera
from vfdata.tracking.consistency import forward_backward_error
from vfmodels.experiment.frame_baselines import (
    depth_change_features,
    fit_ridge,
    masked_depth_features,
    random_indices,
    run_baselines,
    temporal_indices,
)


def test_ridge_recovers_a_linear_force_and_beats_the_constant():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(300, 20))
    w = rng.normal(size=(20, 3))
    y = x @ w + 0.01 * rng.normal(size=(300, 3))
    model = fit_ridge(x[:200], y[:200], x[200:250], y[200:250])
    np.testing.assert_allclose(model.predict(x[250:]), y[250:], atol=0.1)
    metrics, _ = run_baselines({"ridge": x}, y, temporal_indices({"train": (0, 200), "val": (200, 250),
                                                                   "test": (250, 300)}))
    assert metrics["ridge"]["r2"] > 0.99 and metrics["constant"]["r2"] < 0.05
    assert metrics["ridge"]["mae"] < metrics["constant"]["mae"]


def test_random_split_is_a_partition_and_depth_features_start_at_zero():
    split = random_indices(1000)
    joined = np.sort(np.concatenate(list(split.values())))
    np.testing.assert_array_equal(joined, np.arange(1000))
    assert len(split["test"]) == 200
    depths = np.full((3, 40, 40), 500.0)
    depths[2, 10:20, 10:20] = 490.0
    depths[1, 0, 0] = np.nan
    features = depth_change_features(depths, size=8)
    assert features.shape == (3, 64) and not features[0].any() and features[2].min() < 0
    masks = np.zeros((3, 40, 40), bool)
    masks[:, 5:35, 5:35] = True
    shape = masked_depth_features(depths, masks, size=8)
    assert not shape[0].any() and shape[2].min() < 0  # the dent, not the distance


@pytest.mark.parametrize("shift_mm", [0.0, 4.0])
def test_forward_backward_returns_points_where_they_started(shift_mm):
    camera = PinholeCamera(200.0, 200.0, 32.0, 32.0, 64, 64)
    v, u = np.mgrid[8:56, 8:56].reshape(2, -1)
    base = np.column_stack([(u - 32.0) * 500 / 200, (v - 32.0) * 500 / 200, 500.0 + 0.01 * (u - 32) ** 2])
    clouds = [base + [0.0, 0.0, -shift_mm * k / 5] for k in range(6)]
    masks = [np.ones((64, 64), bool)] * 6
    result = forward_backward_error(clouds, masks, camera, num_points=32, iterations=20)
    assert result["median_mm"] < 0.5 and result["frames"] == 6
    if shift_mm:
        assert result["forward_displacement_median_mm"] > 0.5 * shift_mm


def test_response_maps_find_where_each_force_moves_the_surface_and_whether_stretches_agree():
    from vfdata.split_forces import component_coupling
    from vfmodels.experiment.force_maps import depth_change, map_agreement, response_maps

    rng = np.random.default_rng(1)
    frames = 400
    force = rng.normal(size=(frames, 3))
    force[:200, 2] = -0.8 * force[:200, 0] + 0.2 * rng.normal(size=200)  # the first stretch couples Fz to Fx
    depths = np.full((frames, 30, 30), 700.0) + 0.05 * rng.normal(size=(frames, 30, 30))
    depths[:, 2:10, 2:10] += force[:, :1, None]  # Fx sinks the top-left corner, in both stretches
    depths[:200, 20:28, 2:10] -= force[:200, 2:3, None]  # Fz raises the bottom-left in the first...
    depths[200:, 20:28, 20:28] -= force[200:, 2:3, None]  # ...and another place in the second
    depths[5, 0, 0] = np.nan
    change = depth_change(depths, smooth_px=1)
    assert change[0].max() == 0.0 and change[5, 0, 0] == 0.0 and np.isfinite(change).all()
    first, second = response_maps(change, force, np.arange(200)), response_maps(change, force, np.arange(200, 400))
    assert first.shape == (3, 30, 30) and np.abs(first).max() <= 1.0 + 1e-9
    assert first[0, 5, 5] > 0.95 and second[2, 24, 24] < -0.95 and abs(second[2, 24, 5]) < 0.3
    agreement = map_agreement(first, second, np.ones((30, 30), bool))
    # Fx moves the same corner in both (its first map also holds the coupled Fz's place); Fz moved elsewhere
    assert agreement[0] > 0.6 and agreement[2] < 0.0
    assert component_coupling(force[:200])["fx_fz"] < -0.9
    assert abs(component_coupling(force[200:])["fx_fz"]) < 0.2
