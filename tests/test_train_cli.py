"""train.py through Lightning's CLI: fast_dev_run, then fit / test --ckpt_path best / predict in
separate CLI runs (the best checkpoint is found from the run folder)."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).parent))

import train  # noqa: E402

SYNTHETIC = [
    "--model.model=vfmodels.SetTransformerLSTM", "--model.model.in_features=6",
    "--data=clip_fixtures.SyntheticClipDataModule", "--data.clips=4", "--data.batch_size=2",
    "--trainer.enable_progress_bar=false", "--trainer.accelerator=cpu",
]


def test_fast_dev_run(tmp_path):
    train.main(["fit", *SYNTHETIC, f"--trainer.default_root_dir={tmp_path}", "--trainer.fast_dev_run=true"])


@pytest.mark.slow
def test_fit_then_test_and_predict_best(tmp_path, capsys):
    run = [*SYNTHETIC, f"--trainer.default_root_dir={tmp_path / 'run'}"]
    train.main(["fit", *run, "--trainer.max_epochs=2"])
    ckpts = sorted((tmp_path / "run" / "checkpoints").glob("epoch*.ckpt"))
    assert ckpts and (tmp_path / "run" / "checkpoints" / "last.ckpt").is_file()
    assert (tmp_path / "run" / "csv" / "version_0" / "metrics.csv").is_file()
    assert list((tmp_path / "run" / "tb" / "version_0").glob("events.out.tfevents.*"))
    state = torch.load(ckpts[0], weights_only=True)
    assert state["force_model"]["class_path"] == "vfmodels.set_transformer.SetTransformerLSTM"

    best = train.best_checkpoint(tmp_path / "run" / "checkpoints")
    assert best in ckpts
    train.main(["test", *run, "--ckpt_path=best"])
    metrics = (tmp_path / "run" / "csv" / "version_1" / "metrics.csv").read_text()
    assert "test/rmse_fz" in metrics and "test/mean/rmse" in metrics
    train.main(["predict", *run, "--ckpt_path=best", f"--prediction_writer.output_dir={tmp_path / 'pred'}"])
    from vfdata.predict import read_force_estimate

    times, force = read_force_estimate(tmp_path / "pred" / "synthetic_000.force.mcap")
    assert len(times) == 16 and force.shape == (16, 3) and np.isfinite(force).all()


def test_best_without_checkpoints_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        train.main(["test", *SYNTHETIC, f"--trainer.default_root_dir={tmp_path}", "--ckpt_path=best"])
    assert exit_info.value.code == 1
    assert "no checkpoint to use as 'best'" in capsys.readouterr().err
