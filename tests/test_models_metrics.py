"""RMSE, NRMSE, R^2 against values worked out by hand."""

import math

import numpy as np
import pytest
from clip_fixtures import single_thread  # noqa: F401 - autouse fixture

from vfmodels.evaluation.metrics import force_metrics, format_table, grouped_force_metrics


def test_force_metrics_by_hand():
    true = np.array([[0.0, 1.0, -2.0], [2.0, 1.0, 0.0], [4.0, 4.0, 2.0], [6.0, 2.0, 4.0]])
    pred = true + np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 2.0], [-1.0, 0.0, 0.0]])
    m = force_metrics(pred, true)
    # Fx: errors +-1 -> RMSE 1; range 6; SS_tot = 9+1+1+9 = 20, SS_res = 4 -> R^2 0.8
    assert m["rmse_fx"] == pytest.approx(1.0)
    assert m["nrmse_fx"] == pytest.approx(1 / 6)
    assert m["r2_fx"] == pytest.approx(0.8)
    # Fy: perfect
    assert m["rmse_fy"] == 0 and m["nrmse_fy"] == 0 and m["r2_fy"] == pytest.approx(1.0)
    # Fz: one error of 2 -> RMSE sqrt(4/4) = 1; range 6; mean 1, SS_tot = 9+1+1+9 = 20 -> R^2 0.8
    assert m["rmse_fz"] == pytest.approx(1.0)
    assert m["r2_fz"] == pytest.approx(0.8)
    assert m["rmse"] == pytest.approx(2 / 3)
    assert m["r2"] == pytest.approx((0.8 + 1 + 0.8) / 3)
    assert m["nrmse"] == pytest.approx((1 / 6 + 0 + 1 / 6) / 3)


def test_constant_truth_gives_nan_r2():
    true = np.ones((5, 3))
    m = force_metrics(true + 0.1, true)
    assert math.isnan(m["r2_fx"]) and math.isnan(m["nrmse_fx"])
    assert m["rmse_fx"] == pytest.approx(0.1)


def test_grouped_metrics_by_hand():
    true = np.array([[0.0, 0, 0], [2, 0, 0], [0, 0, 0], [4, 0, 0]])
    true[:, 1:] = np.arange(8).reshape(4, 2)  # non-constant Fy, Fz
    pred = true.copy()
    pred[:2, 0] += 1.0  # group 0: Fx RMSE 1
    pred[2:, 0] += 3.0  # group 30: Fx RMSE 3
    r = grouped_force_metrics(pred, true, np.array([0, 0, 30, 30]))
    assert set(r["groups"]) == {0, 30}
    assert r["groups"][0]["rmse_fx"] == pytest.approx(1.0)
    assert r["groups"][30]["rmse_fx"] == pytest.approx(3.0)
    assert r["mean"]["rmse_fx"] == pytest.approx(2.0)
    assert r["std"]["rmse_fx"] == pytest.approx(1.0)
    assert r["pooled"]["rmse_fx"] == pytest.approx(math.sqrt((1 + 1 + 9 + 9) / 4))
    # NRMSE of a group uses the pooled range (4 N for Fx)
    assert r["groups"][30]["nrmse_fx"] == pytest.approx(3 / 4)
    assert "RMSE N" in format_table(r)


def test_rejects_mismatched_shapes():
    with pytest.raises(ValueError):
        force_metrics(np.zeros((3, 3)), np.zeros((4, 3)))
