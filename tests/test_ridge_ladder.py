"""The ridge rung (vfmodels.networks.ridge) and the attribution ladder's variants and table."""

from __future__ import annotations

import numpy as np
import pytest
from test_datasets import T0, frame_times, write_manifest, write_recording
from test_experiment import _fake_runs
from test_experiment import write_manifest as write_toy_manifest

from vfdata.clips.dataset import ForceClipDataset
from vfdata.clips.spec import ClipSpec
from vfdata.manifest import load_manifest
from vfmodels.experiment import report, runner
from vfmodels.experiment.ridge_run import config_spec
from vfmodels.experiment.variants import ALL_VARIANTS, LADDER, LADDER_MODELS, LADDER_RUNGS
from vfmodels.networks.ridge import RidgeForceModel, pooled_moments, with_lags


def test_pooled_moments_and_lags():
    tokens = np.arange(2 * 3 * 2, dtype=float).reshape(2, 3, 2)
    valid = np.array([[True, True, False], [False, False, False]])
    moments = pooled_moments(tokens, valid)
    np.testing.assert_allclose(moments[0, :2], tokens[0, :2].mean(0))
    np.testing.assert_allclose(moments[0, 2], (tokens[0, :2, 0] ** 2).mean())  # the (0, 0) product
    np.testing.assert_allclose(moments[1], 0.0)  # nothing visible
    times = np.array([0, 1, 2, 30, 31]) * 33_333_333  # a gap after frame 2
    lagged = with_lags(np.arange(5.0)[:, None], times, lags=(0, 1))
    np.testing.assert_allclose(lagged[:, 1], [0, 0, 1, 3, 3])  # never across the gap


def test_ridge_learns_a_force_that_follows_the_deformation(tmp_path):
    """The fixture's points move at 6 mm/s while fx = t: the displacement predicts fx exactly."""
    for rid, frames in (("a", 60), ("b", 40), ("c", 40)):
        write_recording(tmp_path, rid, frame_times(frames))
    manifest = load_manifest(write_manifest(tmp_path, [{"id": "a", "split": "train"}, {"id": "b", "split": "val"},
                                                        {"id": "c", "split": "test", "orientation_deg": 90}]))
    spec = ClipSpec(features="disp_vel")
    data = {s: ForceClipDataset(manifest.split(s), spec, progress=False) for s in ("train", "val", "test")}
    model = RidgeForceModel().fit(data["train"].recordings, data["val"].recordings)
    test = data["test"].recordings[0]
    pred = model.predict(test)
    assert pred.shape == (40, 3) and len(model.chosen_alphas) == 3
    t_s = (test.times_ns - T0) / 1e9
    np.testing.assert_allclose(pred[:, 0], t_s, atol=0.05)  # fx = t, found from the displacement alone
    np.testing.assert_allclose(pred[:, 1], 2.0, atol=0.05)
    # With mirrored copies a constant Fy under y-symmetric motion cannot be told from its mirror: 0 N
    mirrored = RidgeForceModel(mirror=True).fit(data["train"].recordings, data["val"].recordings)
    np.testing.assert_allclose(mirrored.predict(test)[:, 1], 0.0, atol=0.05)


def test_ladder_variants_replace_one_stage_each():
    assert set(LADDER) == {f"{m}@{r}" for m in LADDER_MODELS for r in LADDER_RUNGS} | set(LADDER_MODELS)
    for model in LADDER_MODELS:
        base = ALL_VARIANTS[model]
        assert ALL_VARIANTS[f"{model}@surface"].config == base.config
        assert ALL_VARIANTS[f"{model}@truetracks"].tracker == "groundtruth"
        assert ALL_VARIANTS[f"{model}@truedepth"].tracker == "truedepth"
        spec = config_spec(runner.CONFIGS / base.config, ALL_VARIANTS[f"{model}@surface"].overrides)
        assert spec.source == "ground_truth_surface"
    assert config_spec(runner.CONFIGS / "visionforce.yaml").features == "polar_z_disp_vel"
    names = [v.name for v in runner.ExperimentOptions(variants=["visionforce"], ladder=True).chosen()]
    assert names[0] == "visionforce" and set(LADDER) <= set(names)


def test_ladder_table(tmp_path):
    manifest = write_toy_manifest(tmp_path)
    out = tmp_path / "results"
    _fake_runs(out, {"visionforce@surface": 0.05, "visionforce@truetracks": 0.1, "visionforce": 0.3, "ridge": 0.4},
               seeds=1)
    paths = report.write_reports(out, manifest)
    text = paths["ladder.md"].read_text()
    assert "| visionforce |" in text and "| ridge |" in text and "| proposed |" not in text
    row = next(line for line in text.splitlines() if line.startswith("| visionforce |"))
    cells = [c.strip() for c in row.strip("|").split("|")][1:]
    assert cells[1] == "–" and cells[0] != "–" and cells[-1] != "–"  # visible rung not run


@pytest.mark.parametrize("name", ["visionforce_displacement_only", "visionforce_velocity_only"])
def test_visionforce_feature_ablations_build_a_model_for_their_tokens(name):
    """The ablations of the project's pipeline parse through the LightningCLI with their overrides, and
    the network's input width matches the tokens the spec makes (3 channels each)."""
    from vfmodels.training.train import make_cli

    variant = ALL_VARIANTS[name]
    cli = make_cli([f"--config={runner.CONFIGS / variant.config}", "--trainer.accelerator=cpu",
                    "--trainer.logger=false", *variant.overrides], run=False)
    spec = cli.datamodule.spec
    assert spec.channels == 3 and spec.features in ("disp", "vel")
    assert cli.model.model.embed.in_features == spec.channels
