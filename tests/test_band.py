"""The calibrated band of every force (`vfmodels.evaluation.band`): split-conformal scaling states its coverage,
training calibrates it on validation and the checkpoint carries it, the test and the experiment's
report give its coverage per view."""

from __future__ import annotations

import math

import lightning.pytorch as L
import numpy as np
import pytest
import torch
from clip_fixtures import SyntheticClipDataModule, single_thread  # noqa: F401
from lightning.pytorch.callbacks import EMAWeightAveraging

from vfdata.errors import InputError
from vfdata.split_forces import training_range
from vfmodels import ForceRegressor, SetTransformerLSTM
from vfmodels.evaluation.band import (
    BandCalibration,
    band_metrics,
    beyond_range,
    calibrate,
    conformal_quantile,
    half_width,
)
from vfmodels.reports.tables import band_markdown, run_metrics


def residuals(rng: np.random.Generator, frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pred, true, spread) (frames, 3) N: Fx's error grows with the views' spread, Fy's with the force
    (a relative error), Fz's is heavy-tailed (Student t, 3 degrees of freedom) and grows with the spread."""
    spread = rng.gamma(2.0, 0.25, (frames, 3))
    true = rng.normal(0, 5, (frames, 3))
    sigma = np.stack([0.2 + 2.0 * spread[:, 0], 0.1 + 0.2 * np.abs(true[:, 1]), 0.1 + 1.0 * spread[:, 2]], axis=1)
    noise = np.stack([rng.normal(size=frames), rng.normal(size=frames), rng.standard_t(3, frames)], axis=1)
    return true + sigma * noise, true, spread


def band_of(calibration: BandCalibration, spread: np.ndarray, pred: np.ndarray) -> np.ndarray:
    return half_width(spread, np.abs(pred), *(np.array(v) for v in (calibration.scale, calibration.weight,
                                                                     calibration.force_weight)))


def test_conformal_scaling_covers_the_stated_share_of_fresh_frames():
    rng = np.random.default_rng(0)
    calibration = calibrate(*residuals(rng, 2000))
    pred, true, spread = residuals(rng, 40000)
    result = band_metrics(pred, true, band_of(calibration, spread, pred))
    for c in ("fx", "fy", "fz"):
        assert 0.88 <= result[f"coverage_{c}"] <= 0.92, (c, result)
    # where the error follows the spread (Fx, Fz) or the force (Fy) the band does too, and is narrower than
    # a constant band of the same coverage
    assert calibration.weight[0] > 0 and calibration.weight[2] > 0 and calibration.force_weight[1] > 0
    assert calibration.weight[1] <= calibration.force_weight[1] / 4  # Fy's error does not follow the spread
    assert result["half_width_fx"] < 0.9 * np.quantile(np.abs(pred - true)[:, 0], 0.9)
    assert result["half_width_fy"] < 0.95 * np.quantile(np.abs(pred - true)[:, 1], 0.9)


@pytest.mark.parametrize("frames", [30, 240])
def test_the_coverage_holds_on_small_validation_sets(frames):
    """Split-conformal: on average over draws of a few validation frames, at least the stated 90%, and not
    much more (the rank ceil((n + 1) 0.9) of n gives at most 90% + 1 / (n + 1) in expectation). With 240
    the weight is chosen on half of them and the scale set on the other half."""
    rng = np.random.default_rng(1)
    covered = []
    for _ in range(300):
        calibration = calibrate(*residuals(rng, frames))
        pred, true, spread = residuals(rng, 300)
        covered.append(band_metrics(pred, true, band_of(calibration, spread, pred))["coverage"])
    assert 0.895 <= np.mean(covered) <= 0.93, np.mean(covered)


def test_the_conformal_quantile_is_the_rank_that_states_the_coverage():
    scores = np.arange(1.0, 10.0)  # 9 scores: rank ceil(10 * 0.9) = 9, the largest
    assert conformal_quantile(scores, 0.9) == 9.0
    assert conformal_quantile(scores[:8], 0.9) == math.inf  # 8 frames cannot state 90%
    assert conformal_quantile(np.arange(100.0), 0.5) == 50.0  # rank ceil(101 / 2) = 51
    assert calibrate(*residuals(np.random.default_rng(2), 10)) is None  # too few frames: no band


def test_beyond_the_training_range_by_the_split_reports_margin():
    low, high = np.array([-10.0, -2.0, 0.0]), np.array([10.0, 2.0, 20.0])  # slack 2, 0.4, 2 N
    force = np.array([[0.0, 0.0, 5.0], [-13.0, 2.3, 25.0], [11.9, -3.0, -1.0]])
    np.testing.assert_allclose(beyond_range(force, low, high), [[0, 0, 0], [-1.0, 0, 3.0], [0, -0.6, 0]], atol=1e-12)
    assert torch.allclose(beyond_range(torch.tensor(force), torch.tensor(low), torch.tensor(high)),
                          torch.tensor(beyond_range(force, low, high)))


def test_the_training_range_is_what_augmentation_shows_the_model():
    force = np.array([[1.0, 2.0, -3.0], [4.0, 0.5, 6.0], [np.nan, 0, 0]])
    low, high = training_range(force)
    np.testing.assert_allclose(low, [1.0, 0.5, -3.0])
    np.testing.assert_allclose(high, [4.0, 2.0, 6.0])
    low, high = training_range(force, mirror=True)
    np.testing.assert_allclose([low[1], high[1]], [-2.0, 2.0])
    low, high = training_range(force, rotate=True)  # every horizontal direction up to |(4, 0.5)|
    np.testing.assert_allclose(low[:2], -np.hypot(4.0, 0.5))
    np.testing.assert_allclose(high[:2], np.hypot(4.0, 0.5))


def test_a_calibration_is_plain_values_and_refuses_junk():
    calibration = BandCalibration((1.0, 2.0, 3.0), (0.0, 0.5, 1.0), (0.1, 0.0, 0.2), 0.9, 120, (-1.0, -1.0, 0.0),
                                  (1.0, 1.0, 5.0))
    assert BandCalibration.from_dict(calibration.to_dict()) == calibration
    assert BandCalibration.from_dict({"scale": [1, 2, 3], "weight": [0, 0, 0]}).force_weight == (0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="scale"):
        BandCalibration.from_dict({"scale": [1, 2], "weight": [0, 0, 0]})
    with pytest.raises(ValueError, match="coverage"):
        BandCalibration.from_dict({"scale": [1, 2, 3], "weight": [0, 0, 0], "coverage": 90})


def test_without_a_calibration_the_band_is_unknown():
    result = band_metrics(np.zeros((5, 3)), np.ones((5, 3)), np.full((5, 3), np.nan))
    assert math.isnan(result["coverage_fx"]) and math.isnan(result["half_width"])


class ValidatedClips(SyntheticClipDataModule):
    """Synthetic clips whose training forces' range the band's mark reads (as ForceDataModule's)."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        forces = torch.cat([c["force"] for c in self.clips]).numpy()
        self.force_range = training_range(forces)


def test_training_calibrates_the_band_on_validation_and_the_checkpoint_keeps_it(tmp_path):
    L.seed_everything(0)
    dm = ValidatedClips(clips=8, frames=8, points=16, batch_size=4)
    regressor = ForceRegressor(SetTransformerLSTM(in_features=6, dim=16, heads=2, inducing_points=4, lstm_hidden=16),
                               symmetry_turns=1)
    regressor.set_normalisation(**dm.normalisation)  # before EMAWeightAveraging copies the module (train.py)
    trainer = L.Trainer(max_epochs=2, logger=False, enable_progress_bar=False, enable_model_summary=False,
                        default_root_dir=tmp_path, callbacks=[EMAWeightAveraging(decay=0.9)], accelerator="cpu")
    trainer.fit(regressor, dm)
    path = trainer.checkpoint_callback.best_model_path
    checkpoint = torch.load(path, weights_only=True)
    saved = BandCalibration.from_dict(checkpoint["force_model"]["band"])
    assert saved.frames == 64 and saved.coverage == 0.9 and all(s > 0 for s in saved.scale)
    assert saved.train_min_n is not None and saved.train_max_n[2] > saved.train_min_n[2]

    # the checkpoint's weights on the validation clips: the band holds at least 90% of their frames
    loaded = ForceRegressor.load(path)
    assert loaded.band_calibration == saved
    batch = {k: torch.stack([c[k] for c in dm.clips]) for k in ("tokens", "valid", "force")}
    with torch.no_grad():
        estimate = loaded.estimate(batch)
    inside = (estimate.force_n - batch["force"]).abs() <= estimate.band_n
    assert (inside.float().mean(dim=(0, 1)) >= 0.9).all()

    # Lightning's own loading (train.py test --ckpt_path) restores it too, and the test reports coverage
    tester = L.Trainer(logger=False, enable_progress_bar=False, enable_model_summary=False, accelerator="cpu",
                       default_root_dir=tmp_path)
    fresh = ForceRegressor(SetTransformerLSTM(in_features=6, dim=16, heads=2, inducing_points=4, lstm_hidden=16),
                           symmetry_turns=1)
    tester.test(fresh, dm, ckpt_path=path)
    assert fresh.band_calibration == saved
    assert fresh.test_results["band"]["pooled"]["coverage"] >= 0.9
    assert tester.logged_metrics["test/band/coverage_fz"] >= 0.9


def test_a_damaged_band_in_a_checkpoint_is_named(tmp_path):
    regressor = ForceRegressor(SetTransformerLSTM(in_features=6, dim=16, heads=2, inducing_points=4, lstm_hidden=16))
    checkpoint = {"state_dict": regressor.state_dict(), "hyper_parameters": dict(regressor.hparams)}
    regressor.on_save_checkpoint(checkpoint)
    assert checkpoint["force_model"]["band"] is None
    assert ForceRegressor.load(_saved(tmp_path, checkpoint)).band_calibration is None
    checkpoint["force_model"]["band"] = {"scale": "wide"}
    with pytest.raises(InputError, match="band.ckpt.*scale"):
        ForceRegressor.load(_saved(tmp_path, checkpoint))


def _saved(tmp_path, checkpoint) -> str:
    torch.save(checkpoint, tmp_path / "band.ckpt")
    return str(tmp_path / "band.ckpt")


def test_the_report_lists_coverage_and_width_per_view():
    rng = np.random.default_rng(3)
    pred, true, spread = residuals(rng, 600)
    calibration = calibrate(pred[:200], true[:200], spread[:200])
    band = band_of(calibration, spread, pred)
    views = np.repeat([45.0, 135.0, 270.0], 200)
    pred[views == 270.0] = true[views == 270.0] + 3 * (pred - true)[views == 270.0]  # a view the model has not learnt
    predictions = {"recording": np.repeat(["a", "b", "c"], 200), "orientation_deg": views,
                   "frame_time_ns": np.tile(np.arange(200), 3), "pred": pred, "true": true, "band": band}
    run = run_metrics(predictions)
    assert run["band"]["groups"][270.0]["coverage"] < 0.7 < run["band"]["groups"][45.0]["coverage"]
    text = band_markdown({"visionforce": [run, run]}, {"visionforce": "VisionForce"}, "colon")
    row = next(line for line in text.splitlines() if "| 270° |" in line)
    cells = [c.strip() for c in row.split("|")]
    assert cells[3] == "2" and all(v.endswith("%") for v in cells[4].split(" / "))
    assert "Spearman(half-width, RMSE) over 6 views" in text and "validation recording" not in text
    one = band_markdown({"visionforce": [run]}, {"visionforce": "VisionForce"}, "colon", val_recordings=1)
    assert "calibrated on one validation recording" in one and "validate on 3 or more" in one
    assert "calibrated on 3 validation recordings" in band_markdown({"visionforce": [run]}, {}, "c", val_recordings=3)
    unlike = {"share": 0.05, "frames": 30, "rmse": 2.5, "rmse_rest": 1.2}
    text = band_markdown({"visionforce": [{**run, "unfamiliar": unlike}]}, {"visionforce": "VisionForce"}, "colon")
    assert "VisionForce: 5.0% of test frames have an input unlike training's" in text and "RMSE there 2.50 N" in text
    # a run without a band (ridge) is left out; none at all: no table
    assert band_markdown({"ridge": [run_metrics({k: v for k, v in predictions.items() if k != "band"})]}, {}, "x") == ""
