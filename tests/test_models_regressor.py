"""ForceRegressor: a tiny overfit, checkpoints that reload (weights_only) to the same predictions,
normalisation, and test metrics over overlapping clips."""

import lightning.pytorch as L
import numpy as np
import pytest
import torch
from clip_fixtures import ClipList, SyntheticClipDataModule, make_clips, single_thread  # noqa: F401
from torch.utils.data import DataLoader

from vfdata.errors import InputError
from vfmodels import ForceRegressor, SetTransformerLSTM
from vfmodels.evaluation.band import BandCalibration


def trainer(tmp_path, epochs, **kw):
    return L.Trainer(
        max_epochs=epochs, default_root_dir=tmp_path, logger=False, enable_progress_bar=False,
        enable_model_summary=False, accelerator="cpu", **kw,
    )


def test_tiny_overfit():
    """Four clips, the regressor's own loss, normalisation and optimiser: the loss falls 20-fold."""
    torch.manual_seed(0)
    dm = SyntheticClipDataModule(clips=4, frames=8, points=16, batch_size=4)
    model = SetTransformerLSTM(in_features=6, dim=32, heads=4, inducing_points=4, lstm_hidden=48)
    regressor = ForceRegressor(model, lr=5e-3)
    regressor.set_normalisation(**dm.normalisation)
    optimiser = regressor.configure_optimizers()
    batch = next(iter(dm.train_dataloader()))
    losses = []
    for _ in range(120):
        loss = regressor._loss(regressor(batch), batch["force"])
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    assert min(losses[-5:]) < 0.05 * losses[0], (losses[0], losses[-5:])


def test_checkpoint_reload_reproduces_predictions(tmp_path):
    L.seed_everything(0)
    dm = SyntheticClipDataModule(clips=4, batch_size=2)
    regressor = ForceRegressor(SetTransformerLSTM(in_features=6))
    t = trainer(tmp_path, 2)
    t.fit(regressor, dm)
    best = t.checkpoint_callback.best_model_path
    assert best
    checkpoint = torch.load(best, weights_only=True)  # no pickled objects in the checkpoint
    torch.testing.assert_close(checkpoint["state_dict"]["force_std"], dm.normalisation["force_std"])

    # the trained module as it is now, saved and rebuilt from the file alone
    t.save_checkpoint(tmp_path / "now.ckpt")
    batch = next(iter(dm.predict_dataloader()))
    with torch.no_grad():
        torch.testing.assert_close(ForceRegressor.load(tmp_path / "now.ckpt").predict_forces(batch),
                                   regressor.eval().predict_forces(batch))
    reloaded = ForceRegressor.load(best)
    via_lightning = trainer(tmp_path, 1).predict(
        ForceRegressor(SetTransformerLSTM(in_features=6)), dm, ckpt_path=best
    )
    torch.testing.assert_close(via_lightning[0]["force_n"], reloaded.predict_forces(batch))
    # predictions are de-normalised: in N, on the scale of the targets
    assert via_lightning[0]["force_n"][..., 2].mean() > 0.5

    # the symmetry views are an evaluation choice: recorded beside the model, not a hyper-parameter that
    # Lightning's CLI would merge over the command line's
    regressor.symmetry_turns = 2
    t.save_checkpoint(tmp_path / "views.ckpt")
    saved = torch.load(tmp_path / "views.ckpt", weights_only=True)
    assert "symmetry_turns" not in saved["hyper_parameters"] and saved["force_model"]["symmetry_turns"] == 2
    assert ForceRegressor.load(tmp_path / "views.ckpt").symmetry_turns == 2


def test_compiled_regressor_saves_and_loads_plain_state_dicts(tmp_path):
    """`compile_model=True` wraps the model for speed only: the state dict (and so every checkpoint)
    has the same keys as without it, and checkpoints written by compiled training before that fix,
    which held every weight a second time under `_compiled._orig_mod.`, still load."""
    torch.manual_seed(0)
    regressor = ForceRegressor(SetTransformerLSTM(in_features=6, dim=32, lstm_hidden=48), compile_model=True)
    regressor.trainer = trainer(tmp_path, 1)  # setup() looks for the datamodule's statistics
    regressor.setup("fit")  # wraps the model; torch.compile compiles only at the first call
    assert regressor._compiled is not None
    plain = ForceRegressor(SetTransformerLSTM(in_features=6, dim=32, lstm_hidden=48))
    assert list(regressor.state_dict()) == list(plain.state_dict())

    doubled = dict(regressor.state_dict())
    doubled.update({f"_compiled._orig_mod.{k[len('model.'):]}": v for k, v in regressor.state_dict().items()
                    if k.startswith("model.")})
    plain.load_state_dict(doubled)  # strict
    x = torch.randn(2, 4, 16, 6)
    with torch.no_grad():
        torch.testing.assert_close(plain.model(x, None), regressor.model(x, None))


def test_normalisation_applies_and_checks():
    regressor = ForceRegressor(SetTransformerLSTM(in_features=2))
    regressor.set_normalisation([1.0, 2.0], [2.0, 4.0], [0.0, 0.0, 10.0], [1.0, 1.0, 5.0])
    x = torch.tensor([3.0, 6.0]).expand(1, 1, 1, 2)
    torch.testing.assert_close(regressor.normalise_input(x), torch.ones(1, 1, 1, 2))
    torch.testing.assert_close(regressor.denormalise_force(torch.tensor([0.0, 1.0, 2.0])), torch.tensor([0.0, 1, 20]))
    with pytest.raises(ValueError):
        regressor.set_normalisation([0.0, 0.0], [1.0, 0.0], [0.0] * 3, [1.0] * 3)


def test_nan_force_frames_are_left_out_of_the_loss():
    regressor = ForceRegressor(SetTransformerLSTM(in_features=6))
    pred = torch.zeros(1, 4, 3)
    force = torch.ones(1, 4, 3)
    force[0, 1] = torch.nan
    assert regressor._loss(pred, force).item() == pytest.approx(1.0)


def test_test_metrics_count_each_frame_once(tmp_path):
    # Two overlapping clips of one recording (frames 0-15 and 8-23): 24 distinct frames.
    clips = make_clips(clips=2, frames=16)
    second = dict(clips[1])
    second["recording"] = clips[0]["recording"]
    second["orientation_deg"] = clips[0]["orientation_deg"]
    second["frame_time_ns"] = clips[0]["frame_time_ns"] + 8 * 33_333_333
    regressor = ForceRegressor(SetTransformerLSTM(in_features=6))
    t = trainer(tmp_path, 1)
    t.test(regressor, DataLoader(ClipList([clips[0], second]), batch_size=2))
    assert regressor.test_results is not None
    assert set(regressor.test_results["groups"]) == {0.0}
    # the pooled RMSE is over 24 frames: recompute it from a per-frame prediction
    with torch.no_grad():
        batch = next(iter(DataLoader(ClipList([clips[0], second]), batch_size=2)))
        pred = regressor.predict_forces(batch).numpy()
    true = batch["force"].numpy()
    # frames 8-15 are in both clips; they count once, from the first clip, where they have more history
    frames_pred = np.concatenate([pred[0], pred[1, 8:]])
    frames_true = np.concatenate([true[0], true[1, 8:]])
    rmse_fx = np.sqrt(((frames_pred[:, 0] - frames_true[:, 0]) ** 2).mean())
    assert regressor.test_results["pooled"]["rmse_fx"] == pytest.approx(rmse_fx, rel=1e-5)


def test_load_errors(tmp_path):
    with pytest.raises(InputError):
        ForceRegressor.load(tmp_path / "missing.ckpt")
    torch.save({"state_dict": {}}, tmp_path / "other.ckpt")
    with pytest.raises(InputError, match="not a ForceRegressor checkpoint"):
        ForceRegressor.load(tmp_path / "other.ckpt")


@pytest.mark.parametrize("turns", [1, 4])
def test_symmetry_views_make_predictions_equivariant(turns):
    # Averaging over a group of views makes any network equivariant under that group: the mirror across
    # XZ (and the quarter turns about Z) of the tokens gives the same map of the forces.
    from vfmodels.training.regressor import symmetry_views

    torch.manual_seed(0)
    model = SetTransformerLSTM(in_features=6, dim=16, heads=2, inducing_points=4, isab_blocks=1, lstm_hidden=8)
    reg = ForceRegressor(model, symmetry_turns=turns).eval()
    plain = ForceRegressor(model).eval()
    x = torch.randn(2, 5, 12, 6)
    with torch.no_grad():
        base = reg({"tokens": x})
        for view in symmetry_views(turns):
            turned = reg({"tokens": (x.unflatten(-1, (-1, 3)) @ view.T).flatten(-2)})
            torch.testing.assert_close(turned, base @ view.T, atol=1e-5, rtol=1e-4)
        # Not so without the views: the network alone is not equivariant.
        mirror = symmetry_views(1)[1]
        assert not torch.allclose(plain({"tokens": (x.unflatten(-1, (-1, 3)) @ mirror.T).flatten(-2)}),
                                  plain({"tokens": x}) @ mirror.T, atol=1e-3)
    reg.train()
    assert reg({"tokens": x}).shape == (2, 5, 3)  # training sees one view
    with pytest.raises(ValueError):
        ForceRegressor(model, symmetry_turns=-1)


@pytest.mark.parametrize("turns", [0, 1, 2])
def test_the_causal_interface_gives_the_tested_forces(turns):
    """`encode_frames` then `decode_frames` (what prediction and the live estimator run) give the forces
    the test scores (`predict_forces`) and the band it scores (`estimate`), views and normalisation
    included; the state carried over two halves gives one run over the whole."""
    torch.manual_seed(1)
    model = SetTransformerLSTM(in_features=6, dim=16, heads=2, inducing_points=4, isab_blocks=1, lstm_hidden=8)
    reg = ForceRegressor(model, symmetry_turns=turns).eval()
    reg.set_normalisation(torch.zeros(6), torch.full((6,), 3.0), torch.tensor([0.5, 0.0, -1.0]), torch.ones(3) * 2)
    reg.band_calibration = BandCalibration((0.4, 0.5, 0.6), (2.0, 0.0, 1.0))
    x, valid = torch.randn(3, 7, 10, 6) * 3, torch.rand(3, 7, 10) > 0.2
    with torch.no_grad():
        tested, scored = reg.predict_forces({"tokens": x, "valid": valid}), reg.estimate({"tokens": x, "valid": valid})
        z = reg.encode_frames(x, valid)
        assert z.shape == (max(1, 2 * turns) * 3, 7, 16)
        estimate, _ = reg.decode_frames(z)
        torch.testing.assert_close(estimate.force_n, tested, atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(estimate.band_n, scored.band_n, atol=1e-5, rtol=1e-4)
        first, state = reg.decode_frames(z[:, :4])
        rest, _ = reg.decode_frames(z[:, 4:], state)
        torch.testing.assert_close(torch.cat([first.force_n, rest.force_n], dim=1), tested, atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(torch.cat([first.band_n, rest.band_n], dim=1), scored.band_n, atol=1e-5, rtol=1e-4)
    # the band: the calibrated scale where the views agree, wider where they do not (Fy's weight is 0: constant)
    assert (estimate.band_n >= torch.tensor([0.4, 0.5, 0.6]) - 1e-6).all()
    assert torch.allclose(estimate.band_n[..., 1], torch.tensor(0.5))
    assert (estimate.spread_n > 0).any() == (turns > 0)
    assert reg.causal
