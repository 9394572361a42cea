"""train.py through Lightning's CLI: fast_dev_run, then fit / test --ckpt_path best / predict in
separate CLI runs (the best checkpoint is found from the run folder)."""

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).parent))

from clip_fixtures import single_thread  # noqa: E402, F401 - autouse fixture

import train  # noqa: E402
from vfdata.errors import InputError  # noqa: E402
from vfmodels.training.checkpoint import best_checkpoint  # noqa: E402

SYNTHETIC = [
    "--model.model=vfmodels.SetTransformerLSTM", "--model.model.in_features=6",
    "--data=clip_fixtures.SyntheticClipDataModule", "--data.clips=4", "--data.batch_size=2",
    "--trainer.enable_progress_bar=false", "--trainer.accelerator=cpu",
]


def _fit(args: list[str]):
    """train.py fit in-process (what `train.main` runs): the finished CLI, to look at its trainer and model."""
    from vfmodels.training.train import make_cli

    return make_cli(["fit", *args])


def _check_one_step(cli) -> None:
    """A fast_dev_run fit: one training step, a finite loss, the training split's statistics in the model."""
    assert cli.trainer.state.finished and cli.trainer.global_step == 1
    assert torch.isfinite(cli.trainer.callback_metrics["train/loss_step"])
    for key, value in cli.datamodule.normalisation.items():
        torch.testing.assert_close(getattr(cli.model, key), value.float())


def test_fast_dev_run(tmp_path):
    _check_one_step(_fit([*SYNTHETIC, f"--trainer.default_root_dir={tmp_path}", "--trainer.fast_dev_run=true"]))


def test_threads_option_sets_the_training_process(tmp_path):
    """train.py runs with one torch thread unless --threads says otherwise (vfdata/threads.py)."""
    torch.set_num_threads(3)
    train.main(["fit", *SYNTHETIC, f"--trainer.default_root_dir={tmp_path / 'a'}", "--trainer.fast_dev_run=true"])
    assert torch.get_num_threads() == 1
    train.main(["fit", *SYNTHETIC, f"--trainer.default_root_dir={tmp_path / 'b'}", "--trainer.fast_dev_run=true",
                "--threads=2"])
    assert torch.get_num_threads() == 2


def test_epoch_times_are_logged(tmp_path):
    train.main(["fit", *SYNTHETIC, f"--trainer.default_root_dir={tmp_path}", "--trainer.max_epochs=2",
                "--checkpoint.save_last=false"])
    import csv

    rows = list(csv.DictReader((tmp_path / "csv" / "version_0" / "metrics.csv").open()))
    epochs = [(int(r["epoch"]), float(r["time/epoch_s"]), float(r["time/epoch_cpu_s"]))
              for r in rows if r.get("time/epoch_s")]
    assert [e for e, _, _ in epochs] == [0, 1]
    assert all(0 < wall < 60 and 0 < cpu < 120 for _, wall, cpu in epochs)


def test_last_checkpoint_follows_every_epoch(tmp_path):
    """last.ckpt must hold the latest epoch even when the best one is early (Lightning's own save_last
    only rewrites it with a new best), or resuming would repeat every epoch after the best one. With
    lr = 0 the validation loss never improves after epoch 0."""
    train.main(["fit", *SYNTHETIC, f"--trainer.default_root_dir={tmp_path}", "--trainer.max_epochs=3",
                "--model.lr=0"])
    checkpoints = tmp_path / "checkpoints"
    assert torch.load(checkpoints / "last.ckpt", weights_only=True)["epoch"] == 2
    best = best_checkpoint(checkpoints)
    assert best.name.startswith("epoch000") and torch.load(best, weights_only=True)["epoch"] == 0


@pytest.mark.slow
def test_fit_then_test_and_predict_best(tmp_path, capsys):
    run = [*SYNTHETIC, f"--trainer.default_root_dir={tmp_path / 'run'}"]
    train.main(["fit", *run, "--trainer.max_epochs=2"])
    ckpts = sorted((tmp_path / "run" / "checkpoints").glob("epoch*.ckpt"))
    assert ckpts and (tmp_path / "run" / "checkpoints" / "last.ckpt").is_file()
    assert (tmp_path / "run" / "csv" / "version_0" / "metrics.csv").is_file()
    assert list((tmp_path / "run" / "tb" / "version_0").glob("events.out.tfevents.*"))
    state = torch.load(ckpts[0], weights_only=True)
    assert state["force_model"]["class_path"] == "vfmodels.networks.set_transformer.SetTransformerLSTM"

    best = best_checkpoint(tmp_path / "run" / "checkpoints")
    assert best in ckpts
    train.main(["test", *run, "--ckpt_path=best"])
    metrics = (tmp_path / "run" / "csv" / "version_1" / "metrics.csv").read_text()
    assert "test/rmse_fz" in metrics and "test/mean/rmse" in metrics
    assert "test/band/coverage_fz" in metrics and "test/band/half_width_fz" in metrics  # the band, calibrated in fit
    train.main(["predict", *run, "--ckpt_path=best", f"--prediction_writer.output_dir={tmp_path / 'pred'}"])
    from vfdata.recording.derived import read_force_band, read_force_estimate, read_force_unlike

    times, force = read_force_estimate(tmp_path / "pred" / "synthetic_000.force.mcap")
    assert len(times) == 16 and force.shape == (16, 3) and np.isfinite(force).all()
    band_times, band, beyond = read_force_band(tmp_path / "pred" / "synthetic_000.force.mcap")
    np.testing.assert_array_equal(band_times, times)
    assert (band > 0).all() and beyond.shape == (16, 3)
    unlike_times, unlike = read_force_unlike(tmp_path / "pred" / "synthetic_000.force.mcap")
    np.testing.assert_array_equal(unlike_times, times)
    assert unlike.shape == (16,)  # NaN here: the synthetic set is too small for an embedding reference
    from vfdata.recording import Recording

    with Recording.open(tmp_path / "pred" / "synthetic_000.force.mcap") as rec:
        lean = json.loads(rec.metadata_records["visionforce.derived"]["tissue_lean"])
    assert lean == {"lean_deg": None, "training_deg": None, "unlike_training": None}  # no gravity in this set


def test_best_without_checkpoints_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        train.main(["test", *SYNTHETIC, f"--trainer.default_root_dir={tmp_path}", "--ckpt_path=best"])
    assert exit_info.value.code == 1
    assert "no checkpoint to use as 'best'" in capsys.readouterr().err


CONFIGS = sorted((ROOT / "configs").glob("*.yaml"))
POINT_CONFIGS = [c for c in CONFIGS if "baseline" not in c.name and "point_cloud" not in c.name]


@pytest.mark.slow  # eight full CLI parses
def test_every_config_parses(capsys):
    assert {c.stem for c in CONFIGS} >= {"proposed", "ablation_camera_frame", "ablation_position_only",
                                         "ablation_velocity_only", "ablation_top_bottom", "ablation_point_cloud",
                                         "baseline_rgb", "baseline_depth_vit"}
    for config in CONFIGS:
        with pytest.raises(SystemExit) as exit_info:
            train.main(["fit", f"--config={config}", "--print_config"])
        assert exit_info.value.code == 0, config
        assert "class_path: vfdata.clips.datamodule.ForceDataModule" in capsys.readouterr().out


@pytest.mark.parametrize("config", [
    pytest.param(c, marks=() if c.stem == "proposed" else pytest.mark.slow, id=c.stem) for c in POINT_CONFIGS
])
def test_point_configs_fast_dev_run_on_tracks(config, tmp_path):
    from test_datasets import frame_times, write_manifest, write_recording

    for rid, frames in (("a", 24), ("b", 20), ("c", 20)):
        write_recording(tmp_path, rid, frame_times(frames))
    manifest = write_manifest(tmp_path, [{"id": "a", "split": "train"}, {"id": "b", "split": "val"},
                                         {"id": "c", "orientation_deg": 30, "split": "test"}])
    cli = _fit([f"--config={config}", f"--data.manifest={manifest}", "--data.cache_dir=null", "--data.progress=false",
                f"--trainer.default_root_dir={tmp_path / 'run'}", "--trainer.fast_dev_run=true",
                "--trainer.enable_progress_bar=false", "--trainer.accelerator=cpu"])
    _check_one_step(cli)
    assert cli.model.input_mean.shape == (cli.datamodule.spec.channels,)  # the config's tokens reach the model
    assert cli.model.model.config["in_features"] == cli.datamodule.spec.channels


def test_the_visionforce_config_fits_one_epoch_and_tests_what_it_saved(tmp_path, capsys):
    """configs/visionforce.yaml as a user runs it, one epoch on tiny recordings: the checkpoint keeps what
    prediction needs (the model, its symmetry views, the spec, the tracker), and `train.py test` on it
    logs the RMSE of its forces, which we compute here from the saved model."""
    from test_datasets import frame_times, write_manifest, write_recording

    from vfdata.clips.dataset import ForceClipDataset
    from vfdata.clips.tokens import latest_clip_frames
    from vfmodels.training.model_card import read_model_card
    from vfmodels.training.regressor import ForceRegressor

    for rid, frames in (("a", 24), ("b", 20), ("c", 20)):  # b judged doubtful: the user trains on it anyway
        write_recording(tmp_path, rid, frame_times(frames), tracker="klt", doubtful=("end",) if rid == "b" else ())
    manifest = write_manifest(tmp_path, [{"id": "a", "split": "train"}, {"id": "b", "split": "val"},
                                         {"id": "c", "orientation_deg": 30, "split": "test"}])
    run = [f"--config={ROOT / 'configs' / 'visionforce.yaml'}", f"--data.manifest={manifest}", "--data.cache_dir=null",
           "--data.progress=false", f"--trainer.default_root_dir={tmp_path / 'run'}", "--trainer.accelerator=cpu",
           "--trainer.enable_progress_bar=false"]
    cli = _fit([*run, "--trainer.max_epochs=1"])
    assert cli.trainer.current_epoch == 1
    warned = [line for line in capsys.readouterr().err.splitlines() if line.startswith("train.py: warning: ")]
    assert len(warned) == 1 and "judged doubtful: b (end);" in warned[0]

    best = best_checkpoint(tmp_path / "run" / "checkpoints")
    state = torch.load(best, weights_only=True)
    assert state["force_model"]["symmetry_turns"] == 1 and state["force_model"]["init_args"]["in_features"] == 12
    assert state["datamodule_hyper_parameters"]["spec"]["features"] == "polar_z_disp_vel"
    assert state["ForceDataModule"] == {"tracker": "klt", "recordings": {"train": ["a"], "val": ["b"]},
                                        "doubtful": {"b": ["end"]}}
    card = read_model_card(tmp_path / "run")  # what `vfdata model-info` prints of it
    assert card["file"] == str(best) and card["training"]["recordings"] == {"train": ["a"], "val": ["b"]}
    assert card["band"]["frames"] == 20 and card["inputs"]["tracker"] == "klt"
    assert card["training"]["doubtful"] == {"b": ["end"]}

    train.main(["test", *run, f"--ckpt_path={best}"])
    logged = (tmp_path / "run" / "csv" / "version_1" / "metrics.csv").read_text().splitlines()
    header, values = logged[0].split(","), logged[-1].split(",")
    test = dict(zip(header, values, strict=True))
    regressor = ForceRegressor.load(best)
    spec = cli.datamodule.spec
    data = ForceClipDataset.from_manifest(manifest, "test", spec, progress=False)
    items = [data[i] for i in range(len(data))]
    with torch.no_grad():
        pred = torch.cat([regressor.predict_forces({"tokens": i["tokens"][None], "valid": i["valid"][None]})
                          for i in items]).reshape(-1, 3).numpy()
    true = torch.cat([i["force"] for i in items]).numpy()
    position = np.tile(np.arange(spec.clip_frames), len(items))
    keep = latest_clip_frames(np.array(["c"] * len(true)), torch.cat([i["frame_time_ns"] for i in items]).numpy(),
                              position)
    rmse = np.sqrt(((pred[keep] - true[keep]) ** 2).mean(axis=0))
    assert len(keep) == 20 and float(test["test/rmse"]) == pytest.approx(rmse.mean(), rel=1e-5)
    assert float(test["test/rmse_fz"]) == pytest.approx(rmse[2], rel=1e-5)


@pytest.mark.slow
def test_fast_dev_run_on_the_mini_preset(tmp_path):
    """The whole chain on the simulator's `mini` preset (shortened): synth, convert, process with the
    ground-truth tracker, then fit through the CLI with the proposed model's config."""
    from vfdata.cli import main as vfdata_main
    from vfdata.sim import synthesize

    manifest = synthesize("mini", tmp_path / "mini", frames=20, progress=False)
    from vfdata.manifest import load_manifest

    for e in load_manifest(manifest):
        assert vfdata_main(["convert", str(e.raw), str(e.mcap), "--quiet"]) == 0
        assert vfdata_main(["process", str(e.mcap), "--depth", "recorded", "--tracker", "groundtruth", "--quiet"]) == 0
    train.main(["fit", f"--config={ROOT / 'configs' / 'proposed.yaml'}", f"--data.manifest={manifest}",
                "--data.cache_dir=null", f"--trainer.default_root_dir={tmp_path / 'run'}",
                "--trainer.fast_dev_run=true", "--trainer.enable_progress_bar=false", "--trainer.accelerator=cpu"])


class _RunsCode:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        import os
        return (os.system, (f"touch {self.marker}",))


def _bad_checkpoints(tmp_path: Path) -> dict[str, str]:
    """Checkpoint files that must end `train.py test` in one line naming them (file name -> problem)."""
    marker = tmp_path / "ran"
    (tmp_path / "empty.ckpt").write_bytes(b"")
    (tmp_path / "text.ckpt").write_text("hello")
    good = {"state_dict": {"w": torch.zeros(3)}, "hyper_parameters": {"lr": 1e-3}}
    torch.save(good, tmp_path / "whole.ckpt")
    (tmp_path / "truncated.ckpt").write_bytes((tmp_path / "whole.ckpt").read_bytes()[:300])
    torch.save({"state_dict": {"w": _RunsCode(marker)}}, tmp_path / "pickled_code.ckpt")
    torch.save({"state_dict": {}, "hyper_parameters": {"model": {"class_path": "subprocess.Popen",
                "init_args": {"args": f"touch {marker}", "shell": True}}}}, tmp_path / "hparams_class.ckpt")
    torch.save({"state_dict": {}, "hyper_parameters": {"_class_path": "subprocess.getoutput",
                "cmd": f"touch {marker}"}}, tmp_path / "hparams_class_path.ckpt")
    torch.save([1, 2, 3], tmp_path / "list.ckpt")
    return {"missing.ckpt": "checkpoint not found", "empty.ckpt": "not a readable checkpoint",
            "text.ckpt": "not a readable checkpoint", "truncated.ckpt": "not a readable checkpoint",
            "pickled_code.ckpt": "holds pickled code (posix.system)", "hparams_class.ckpt": "'model'",
            "hparams_class_path.ckpt": "'_class_path'", "list.ckpt": "not a checkpoint"}


def test_bad_checkpoints_are_one_line_errors_and_run_nothing(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["train.py"])  # as from a shell: Lightning warns about pytest's own argv
    for name, problem in _bad_checkpoints(tmp_path).items():
        with pytest.raises(SystemExit) as exit_info:
            train.main(["test", *SYNTHETIC, f"--trainer.default_root_dir={tmp_path / 'run'}",
                        f"--ckpt_path={tmp_path / name}"])
        err = capsys.readouterr().err.strip()
        assert exit_info.value.code == 1, name
        assert err.startswith(f"train.py: error: {tmp_path / name}: ") and problem in err, err
        assert "\n" not in err and "Traceback" not in err, err
    assert not (tmp_path / "ran").exists()


def test_a_checkpoint_of_another_model_than_the_config_is_one_line_naming_both(tmp_path, capfd, monkeypatch):
    """E.g. a point-cloud checkpoint under proposed.yaml: which model the checkpoint holds and which the
    --config builds, not Lightning's `Error(s) in loading state_dict for ForceRegressor`; said before
    the trainer starts, so no line of Lightning's comes with it."""
    monkeypatch.setattr(sys, "argv", ["train.py"])
    train.main(["fit", *SYNTHETIC, "--model.model.dim=16", "--model.model.lstm_hidden=32",
                f"--trainer.default_root_dir={tmp_path / 'small'}", "--trainer.max_epochs=1"])
    ckpt = tmp_path / "small" / "checkpoints" / "last.ckpt"
    capfd.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        train.main(["test", *SYNTHETIC, f"--trainer.default_root_dir={tmp_path / 'default'}", f"--ckpt_path={ckpt}"])
    err = capfd.readouterr().err.strip()
    assert exit_info.value.code == 1 and len(err.splitlines()) == 1, err
    assert err.startswith(f"train.py: error: {ckpt}: ") and "state_dict" not in err, err
    assert "SetTransformerLSTM" in err and "dim=16" in err and "dim=64" in err and "lstm_hidden=32" in err, err
    assert "in_features" not in err, err  # only what differs


def test_missing_and_malformed_manifests_are_one_line_errors(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["train.py"])
    (tmp_path / "bad.yaml").write_text("entries: [")
    for manifest, problem in ((tmp_path / "none.yaml", "dataset manifest not found"),
                              (tmp_path / "bad.yaml", "not a valid YAML manifest")):
        with pytest.raises(SystemExit) as exit_info:
            train.main(["fit", f"--config={ROOT / 'configs' / 'visionforce.yaml'}", f"--data.manifest={manifest}",
                        "--trainer.accelerator=cpu", f"--trainer.default_root_dir={tmp_path / 'run'}"])
        err = capsys.readouterr().err.strip()
        assert exit_info.value.code == 1
        assert err.startswith(f"train.py: error: {manifest}: {problem}") and "\n" not in err, err


def test_debug_shows_the_traceback(tmp_path):
    with pytest.raises(InputError):
        train.main(["test", *SYNTHETIC, f"--trainer.default_root_dir={tmp_path}",
                    f"--ckpt_path={tmp_path / 'missing.ckpt'}", "--debug"])


def test_early_stopping_and_the_closing_line(tmp_path, capsys):
    """With lr = 0 the validation loss never improves after epoch 0: patience 2 stops after epoch 2, and
    the closing line names the best checkpoint (epoch 0) and a test command that finds it."""
    root = tmp_path / "run"
    train.main(["fit", *SYNTHETIC, f"--trainer.default_root_dir={root}", "--trainer.max_epochs=30",
                "--early_stopping.patience=2", "--model.lr=0"])
    assert torch.load(root / "checkpoints" / "last.ckpt", weights_only=True)["epoch"] == 2
    best = best_checkpoint(root / "checkpoints")
    out = capsys.readouterr().out
    assert str(best) in out and "epoch 0" in out
    command = next(line for line in out.splitlines() if "train.py test" in line).split("train.py ", 1)[1]
    train.main(command.split())  # the printed command runs as is and tests the best checkpoint


def test_patience_null_runs_every_epoch(tmp_path):
    train.main(["fit", *SYNTHETIC, f"--trainer.default_root_dir={tmp_path}", "--trainer.max_epochs=4",
                "--early_stopping.patience=null", "--model.lr=0"])
    assert torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True)["epoch"] == 3


@pytest.mark.parametrize("config, enabled", [("proposed.yaml", True), ("visionforce.yaml", False)])
def test_early_stopping_follows_the_checkpoint_monitor(config, enabled, tmp_path):
    """visionforce keeps its last averaged weights (no monitor): it runs every epoch; proposed stops early."""
    from vfmodels.training.early_stopping import ValidationEarlyStopping
    from vfmodels.training.train import make_cli

    cli = make_cli([f"--config={ROOT / 'configs' / config}", f"--trainer.default_root_dir={tmp_path}",
                    "--trainer.accelerator=cpu", "--data.manifest=datasets/mini.manifest.yaml"], run=False)
    stoppers = [c for c in cli.trainer.callbacks if isinstance(c, ValidationEarlyStopping)]
    assert len(stoppers) == 1 and stoppers[0].enabled is enabled


def test_a_failed_fit_leaves_no_empty_run_folders(tmp_path):
    """A fit that fails before its first step (here: the model expects 5 features, the clips have 6)
    removes the log versions and folders it created."""
    root = tmp_path / "run"
    with pytest.raises(SystemExit):
        train.main(["fit", *SYNTHETIC[:1], "--model.model.in_features=5", *SYNTHETIC[2:],
                    f"--trainer.default_root_dir={root}", "--trainer.max_epochs=1"])
    assert not root.exists()


def test_run_eta():
    from vfmodels.training.progress import format_seconds, run_eta

    assert run_eta(10.0, 1, 0.0, 4) == pytest.approx(30.0)
    assert run_eta(15.0, 1, 0.5, 4) == pytest.approx(25.0)
    assert run_eta(0.0, 0, 0.0, 4) is None
    assert [format_seconds(s) for s in (7.4, 125, 3725)] == ["7s", "2m05s", "1h02m"]


@pytest.mark.parametrize("argv, option", [
    (["--data.spec.frame", "objct"], "--data.spec.frame"),
    (["--data.batch_sizee", "3"], "--data.batch_sizee"),
    (["--model.lr", "abc"], "--model.lr"),
])
def test_option_errors_are_one_line_naming_the_option(argv, option, capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["train.py"])
    with pytest.raises(SystemExit) as exit_info:
        train.main(["fit", f"--config={ROOT / 'configs' / 'proposed.yaml'}", *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and err[0].startswith(f"train.py fit: error: {option}:"), err
    assert len(err) == 2 and "Traceback" not in err[0]  # the line, then where the help is


def test_help_describes_the_project_and_finds_the_data_options(capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["train.py"])
    for argv in (["--help"], ["fit", "--data.help", "ForceDataModule"], ["fit", "--model.model.help",
                                                                          "SetTransformerLSTM"]):
        with pytest.raises(SystemExit) as exit_info:
            train.main(argv)
        assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert "VisionForce" in out and "Lightning Trainer command line tool" not in out
    assert "--data.spec.frame {object,camera}" in out and "--model.model.in_features" in out


@pytest.mark.slow
def test_ddp_on_two_cpu_processes(tmp_path):
    """`train.py fit --trainer.strategy=ddp --trainer.devices=2` on CPU (gloo) on a short `mini`: both
    ranks train, one closing line names the best checkpoint, and the checkpoint's normalisation
    statistics are the training split's alone."""
    import subprocess

    from vfdata.cli import main as vfdata_main
    from vfdata.clips.dataset import ForceClipDataset
    from vfdata.clips.spec import ClipSpec
    from vfdata.manifest import load_manifest
    from vfdata.sim import synthesize

    manifest = synthesize("mini", tmp_path / "mini", frames=40, progress=False)
    for e in load_manifest(manifest):
        assert vfdata_main(["convert", str(e.raw), str(e.mcap), "--quiet"]) == 0
        assert vfdata_main(["process", str(e.mcap), "--depth", "recorded", "--tracker", "groundtruth", "--quiet"]) == 0
    run = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    config = ROOT / "configs" / "proposed.yaml"
    done = subprocess.run([sys.executable, str(ROOT / "train.py"), "fit", f"--config={config}",
                           f"--data.manifest={manifest}", "--data.cache_dir=null", "--data.progress=false",
                           "--trainer.strategy=ddp", "--trainer.devices=2", "--trainer.accelerator=cpu",
                           "--trainer.max_epochs=2", "--trainer.enable_progress_bar=false",
                           f"--trainer.default_root_dir={run}"], capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    closing = [line for line in done.stdout.splitlines() if line.startswith("best checkpoint")]
    assert len(closing) == 1, done.stdout[-3000:]
    best = best_checkpoint(run / "checkpoints")
    assert str(best) in closing[0]
    state = torch.load(best, weights_only=True)
    train = ForceClipDataset.from_manifest(manifest, split="train", spec=ClipSpec(), progress=False)
    train_stats = train.normalisation()
    for key in ("force_mean", "force_std", "input_mean", "input_std"):
        torch.testing.assert_close(state["state_dict"][key], train_stats[key])
