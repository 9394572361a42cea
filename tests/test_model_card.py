"""`vfdata model-info`: the card of a checkpoint, from the file alone, as a lab handed a model reads it."""

from __future__ import annotations

import json

import pytest
import torch
from test_predict import _regressor, _save_checkpoint

from vfdata.cli import main
from vfdata.errors import InputError
from vfmodels.evaluation.band import BandCalibration
from vfmodels.training.model_card import card_text, read_model_card

SPEC = {"input": "tracks", "features": "disp_vel", "frame": "object", "num_points": 64, "clip_frames": 16,
        "stride": 4, "fps": 30.0}


def _run_folder(tmp_path, features: str = "disp_vel", recordings: dict | None = None, run: str = "run",
                **spec):
    """A run folder as `vfdata experiment` leaves it: checkpoints/ with a best checkpoint, and metrics.json."""
    reg = _regressor(in_features=6)
    reg.band_calibration = BandCalibration(scale=(0.5, 0.6, 1.2), weight=(0.0, 0.0, 0.0), frames=480,
                                           train_min_n=(-3.0, -4.0, -1.0), train_max_n=(3.0, 4.0, 9.5))
    (tmp_path / run / "checkpoints").mkdir(parents=True)
    ckpt = _save_checkpoint(reg, tmp_path / run / "checkpoints" / "epoch003-val_loss0.50000.ckpt",
                            {"manifest": str(tmp_path / "gone.manifest.yaml"),
                             "spec": {**SPEC, "features": features, **spec}})
    state = torch.load(ckpt, weights_only=True)
    state["ForceDataModule"] = {"tracker": "klt", "tissue_lean_deg": [4.5, 6.1],
                                **({"recordings": recordings} if recordings else {})}
    state.update(epoch=3, global_step=120)
    torch.save(state, ckpt)
    (tmp_path / run / "metrics.json").write_text(json.dumps(
        {"variant": "visionforce", "seed": 0, "test_frames": 398, "pooled": {"rmse": 0.861, "r2": 0.79}}))
    return ckpt


def test_the_card_says_what_the_model_expects_and_has_seen(tmp_path, capsys):
    ckpt = _run_folder(tmp_path, recordings={"train": ["colon_001", "colon_002"], "val": ["colon_005"]})
    state = torch.load(ckpt, weights_only=True)
    state["ForceDataModule"]["doubtful"] = {"colon_002": ["taper"]}
    torch.save(state, ckpt)
    assert main(["model-info", str(tmp_path / "run")]) == 0
    out = capsys.readouterr().out
    assert "forces averaged over 2 symmetry views" in out
    assert "train:      2 recordings: colon_001, colon_002" in out and "val:        1 recording: colon_005" in out
    assert "64 points tracked by klt, tokens disp_vel in the object frame, clips of 16 frames (stride 4) at 30 " \
           "fps" in out
    assert "Fx -3.0..+3.0, Fy -4.0..+4.0, Fz -1.0..+9.5 N" in out
    assert "90% band calibrated on 480 validation frames (scale Fx 0.50, Fy 0.60, Fz 1.20 N)" in out
    assert "hang 4.5-6.1 deg below level" in out
    assert "although `vfdata process` judged them doubtful: colon_002 (taper)" in out
    assert "RMSE 0.861 N, R2 0.790 over 398 frames (visionforce, seed 0)" in out
    assert "4 epochs, 120 steps" in out and "runs in `vfdata predict` and `vfdata live`" in out


def test_the_card_says_when_r0_is_in_tissue_radii(tmp_path, capsys):
    _run_folder(tmp_path, features="polar_z_disp_vel", radius="tissue")
    assert main(["model-info", str(tmp_path / "run")]) == 0
    assert "tokens polar_z_disp_vel (r0 in tissue radii) in the object frame" in capsys.readouterr().out


def test_an_experiments_model_names_what_it_left_out(tmp_path, capsys):
    """In `vfdata experiment`'s folder the card adds the recordings the experiment left out as doubtful (its
    doubtful.json, for the tracker the model was trained on)."""
    _run_folder(tmp_path, recordings={"train": ["colon_001"], "val": ["colon_005"]}, run="out/runs/visionforce/seed0")
    (tmp_path / "out" / "doubtful.json").write_text(json.dumps([
        {"id": "colon_000", "split": "train", "tracker": "klt", "reasons": ["end"], "left_out": True},
        {"id": "colon_007", "split": "test", "tracker": "klt", "reasons": ["axis"], "left_out": False},
        {"id": "colon_002", "split": "train", "tracker": "geometry", "reasons": ["axis"], "left_out": True}]))
    assert main(["model-info", str(tmp_path / "out" / "runs" / "visionforce" / "seed0")]) == 0
    out = capsys.readouterr().out
    assert "left out:   colon_000 (train; end): judged doubtful" in out and "colon_007" not in out
    assert "colon_002" not in out
    (tmp_path / "out" / "doubtful.json").write_text("{not json")
    assert main(["model-info", str(tmp_path / "out" / "runs" / "visionforce" / "seed0")]) == 1
    assert "doubtful.json: not the doubtful report" in capsys.readouterr().err


def test_json_card_and_a_model_predict_cannot_run(tmp_path, capsys):
    ckpt = _run_folder(tmp_path, features="polar_z_disp_vel")  # 12 token features for a model of 6
    assert main(["model-info", str(ckpt), "--json"]) == 0
    card = json.loads(capsys.readouterr().out)
    assert card["runs_frame_by_frame"] is False and "features per point" in card["why_not_frame_by_frame"]
    assert card["inputs"]["tracker"] == "klt" and card["training"]["recordings"] is None
    assert card["test"]["rmse_n"] == 0.861  # a checkpoint in run/checkpoints/ finds its run's metrics
    assert "not named (a checkpoint from before 2026-12-07, its manifest gone)" in card_text(card)


def test_an_older_checkpoint_names_its_recordings_from_its_manifest(tmp_path):
    ckpt = _run_folder(tmp_path)
    (tmp_path / "gone.manifest.yaml").write_text(
        "name: m\nrecordings:\n- {id: a, split: train}\n- {id: b, split: val}\n- {id: c, split: test}\n")
    card = read_model_card(ckpt)
    assert card["training"]["recordings"] == {"train": ["a"], "val": ["b"]}
    assert "as the training manifest lists them now" in card_text(card)


def test_not_a_model_is_one_line(tmp_path, capsys):
    (tmp_path / "x.ckpt").write_bytes(b"hello")
    assert main(["model-info", str(tmp_path / "x.ckpt")]) == 1
    assert capsys.readouterr().err.strip().count("\n") == 0
    torch.save({"state_dict": {}}, tmp_path / "plain.ckpt")
    with pytest.raises(InputError, match="plain.ckpt: not a ForceRegressor checkpoint"):
        read_model_card(tmp_path / "plain.ckpt")
    torch.save({"force_model": {"band": {"train_min_n": "low", "train_max_n": [1, 2, 3]}},
                "datamodule_hyper_parameters": [1, 2]}, tmp_path / "odd.ckpt")
    with pytest.raises(InputError, match="odd.ckpt: damaged checkpoint"):
        read_model_card(tmp_path / "odd.ckpt")
    torch.save({"force_model": {}, "ForceDataModule": {"recordings": ["a"]}}, tmp_path / "odd2.ckpt")
    with pytest.raises(InputError, match="odd2.ckpt: damaged checkpoint.*recordings"):
        read_model_card(tmp_path / "odd2.ckpt")
    _run_folder(tmp_path)
    assert main(["info", str(tmp_path / "run")]) == 1
    assert "`vfdata model-info` describes models" in capsys.readouterr().err
