"""One checkpoint, one recording, every way a user runs it: the forces `vfdata experiment` scores (its
test: `trainer.predict` over the test clips), `vfdata predict`, `vfdata predict --stream` and `vfdata live
--record` agree to 1e-4 N wherever they define the same clip, for a model tested as `visionforce` is (the
mean of each clip and its mirror, `symmetry_turns: 1`), and so do the bands beside them
(`/force/estimate/band`) and the marks of forces beyond the training range (`/force/estimate/beyond`).
Along the way: `vfdata process` and `vfdata predict` from the command line (docs/models.md, "What each
path computes")."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

from vfdata.cli import main
from vfdata.clips.datamodule import ForceDataModule
from vfdata.clips.spec import ClipSpec
from vfdata.clips.tokens import clip_starts, segments
from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder
from vfdata.recording import Recording
from vfdata.recording.derived import read_force_band, read_force_estimate, read_force_unlike, read_tracks
from vfdata.sim import synthesize
from vfdata.tissue_lean import level
from vfmodels import ForceRegressor, SetTransformerLSTM
from vfmodels.evaluation.band import BandCalibration
from vfmodels.evaluation.metrics import force_metrics
from vfmodels.experiment.runner import test_predictions as experiment_test

LIMIT = 4.0  # the embedding distance beyond which a frame is unlike training (no stretch: no distance_ref)
FRAMES = 20  # clips of 16 frames every 4: frames 0-15 and 19 are scored from the clip that ends on them
SPEC = {"input": "tracks", "frame": "object", "features": "polar_z_disp_vel", "radius": "tissue", "clip_frames": 16,
        "stride": 4, "mirror_augment": True, "rotate_augment": True, "fps": 30.0}  # configs/visionforce.yaml's
# The scale of each token channel (place, place along Z, displacement, [relaxation,] velocity).
SCALES = {"polar_z_disp_vel": [1, 1, 0.2, 1, 1, 30, 2, 2, 2, 30, 30, 30.0],
          "polar_z_disp_relax_vel": [1, 1, 0.2, 1, 1, 30, 2, 2, 2, 0.5, 0.5, 0.5, 30, 30, 30.0]}


@pytest.fixture(scope="module", params=list(SCALES))
def spec(request) -> dict:
    """Every path, for the tokens without and with the relaxation (stepped through the whole history:
    offline over the recording, live frame by frame)."""
    return {**SPEC, "features": request.param}


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("parity")
    synthesize("mini", root, seed=1, frames=FRAMES, workers=1, progress=False)
    convert_raw_folder(root / "mini_002", root / "mini_002.mcap", options=ConvertOptions(progress=False))
    return root


@pytest.fixture(scope="module")
def ckpt(root, spec) -> Path:
    """An untrained `visionforce`-shaped model, saved as training saves it (spec, tracker, symmetry views,
    a band calibration whose views' weight makes the band follow their spread, and a training range narrow
    enough that some estimates lie beyond it)."""
    torch.manual_seed(0)
    scales = SCALES[spec["features"]]
    model = SetTransformerLSTM(in_features=len(scales), dim=32, heads=4, inducing_points=16, lstm_hidden=64)
    regressor = ForceRegressor(model, symmetry_turns=1)
    regressor.set_normalisation(torch.zeros(len(scales)), torch.tensor(scales),
                                torch.tensor([0.1, -0.2, 0.5]), torch.tensor([1.0, 2.0, 0.5]))
    regressor.band_calibration = BandCalibration((0.3, 0.5, 0.2), (20.0, 10.0, 40.0), (0.0, 0.0, 1.0), 0.9, 500,
                                                 (-0.5, -0.5, 0.46), (0.5, 0.5, 0.47), distance_limit=LIMIT)
    regressor.embedding_reference = (torch.zeros(32, dtype=torch.float64), torch.eye(32, dtype=torch.float64))
    checkpoint = {"state_dict": regressor.state_dict(), "hyper_parameters": dict(regressor.hparams),
                  "datamodule_hyper_parameters": {"spec": spec},
                  # training tissues that hung 30-35 deg below level: far softer than the mini's, which is named
                  "ForceDataModule": {"tracker": "klt", "tissue_lean_deg": [30.0, 35.0]}}
    regressor.on_save_checkpoint(checkpoint)
    path = root / f"visionforce_{spec['features']}.ckpt"
    torch.save(checkpoint, path)
    return path


@pytest.fixture(scope="module")
def processed(root) -> Path:
    cv2.setRNGSeed(0)  # the colortrack mask (GrabCut) draws from OpenCV's RNG: the same seed for every path
    out = root / "mini_002.klt.mcap"
    assert main(["process", str(root / "mini_002.mcap"), str(out), "--tracker", "klt", "--quiet"]) == 0
    return out


def test_process_from_the_command_line_writes_tracks_and_the_first_frame(processed):
    tracks = read_tracks(processed)
    assert tracks.metadata.values["tracker"] == "klt" and len(tracks.times_ns) == FRAMES
    assert tracks.points_object_mm.shape == (FRAMES, 256, 3) and tracks.visible[0].mean() > 0.9
    # tracked tissue: the points sit on the tube, a few mm to tens of mm from its axis, and move between frames
    assert 1.0 < np.nanmedian(np.hypot(*tracks.points_object_mm[0, :, :2].T)) < 60.0
    assert np.nanmax(np.abs(tracks.points_object_mm[-1] - tracks.points_object_mm[0])) > 0.1
    assert cv2.imread(str(processed.with_suffix(".png"))).shape[0] > 100  # the first-frame picture


@pytest.fixture(scope="module")
def scored(root, spec, ckpt, processed) -> dict[str, np.ndarray]:
    """The experiment's test: its test-clip loader and `trainer.predict` (vfmodels.experiment.runner)."""
    manifest = root / "parity.manifest.yaml"
    manifest.write_text(yaml.safe_dump({"name": "parity", "root": str(root), "recordings": [
        {"id": "mini_002", "orientation_deg": 90, "split": "test", "processed": processed.name}]}))
    data = ForceDataModule(str(manifest), ClipSpec.from_dict(spec), batch_size=4, progress=False,
                           cache_dir=None)
    data.setup("test")
    frames, _ = experiment_test(ForceRegressor.load(ckpt), data.test_dataloader())
    return frames


@pytest.fixture(scope="module")
def predicted(root, ckpt, processed) -> tuple[Path, str]:
    """`vfdata predict` (offline) from the command line: its force file and what it printed."""
    cv2.setRNGSeed(0)
    with contextlib.redirect_stdout(io.StringIO()) as out:
        assert main(["predict", str(root / "mini_002.mcap"), "--ckpt", str(ckpt), "--out",
                     str(root / ckpt.stem / "offline"), "--no-video", "--quiet"]) == 0
    return root / ckpt.stem / "offline" / "mini_002.force.mcap", out.getvalue()


def test_vfdata_predict_writes_forces_and_reports_the_rmse_and_band(root, spec, predicted, processed):
    path, _ = predicted
    times, force = read_force_estimate(path)
    assert len(times) == FRAMES and np.isfinite(force).all()
    offline = read_tracks(path.parent / "mini_002.predict.processed.mcap")
    np.testing.assert_array_equal(offline.points_object_mm, read_tracks(processed).points_object_mm)
    assert (path.parent / "mini_002.force.png").is_file()
    with Recording.open(path) as rec:
        meta = rec.metadata_records["visionforce.derived"]
    assert meta["window"] == "16" and json.loads(meta["clip_spec"])["features"] == spec["features"]
    assert json.loads(meta["band"])["scale"] == [0.3, 0.5, 0.2] and int(meta["frames_beyond_training"]) > 0
    assert "band: 90% band on 500 validation frames" in predicted[1]
    assert "band against the force sensor: coverage Fx" in predicted[1]


def test_every_path_gives_the_forces_the_experiment_scored(root, spec, ckpt, scored, predicted):
    offline_times, offline = read_force_estimate(predicted[0])
    root = root / ckpt.stem  # this model's outputs
    cv2.setRNGSeed(0)
    with contextlib.redirect_stdout(io.StringIO()) as streamed:
        assert main(["predict", str(root.parent / "mini_002.mcap"), "--ckpt", str(ckpt), "--out",
                     str(root / "stream"), "--stream", "--quiet"]) == 0
    paths = {"vfdata predict --stream": read_force_estimate(root / "stream" / "mini_002.force.mcap")}
    if _has_foxglove():
        from vfmodels.commands import live

        parser = argparse.ArgumentParser()
        live.register(parser.add_subparsers())
        cv2.setRNGSeed(0)
        record = root / "live.mcap"
        # the whole image's depth, as offline (the live default's region of interest is a measured trade)
        assert live.run(parser.parse_args(["live", str(root.parent / "mini_002.mcap"), "--ckpt", str(ckpt),
                                           "--port", "0", "--speed", "0", "--depth-roi-margin", "0", "--record",
                                           str(record), "--quiet"])) == 0
        paths["vfdata live --record"] = read_force_estimate(record)
    for name, (times, force) in paths.items():
        np.testing.assert_array_equal(times, offline_times, err_msg=name)
        np.testing.assert_allclose(force, offline, rtol=0, atol=1e-4, err_msg=name)
    # the bands and the marks beyond training, too
    _, offline_band, offline_beyond = read_force_band(predicted[0])
    # the untrained model's views disagree on Fy (its mean, -0.2 N, is turned to +0.2 N by the mirror)
    assert np.isfinite(offline_band).all() and (offline_band >= np.array([0.3, 0.5, 0.22]) - 1e-6).all()
    assert offline_band[:, 1].min() > 1.0 and offline_band[:, 1].std() > 0
    # Fz, 0.46-0.48 N, runs out of the training range (0.46-0.47 N, 0.001 N of margin) after its first frames
    # (the untrained model with the relaxation's channels lies beyond it from the start)
    marked = (offline_beyond != 0).any(axis=1).sum()
    assert 0 < marked < FRAMES or (spec["features"] != SPEC["features"] and marked > 0)
    files = {"vfdata predict --stream": root / "stream" / "mini_002.force.mcap"}
    if "vfdata live --record" in paths:
        files["vfdata live --record"] = root / "live.mcap"
    _, offline_unlike = read_force_unlike(predicted[0])
    # the untrained model's embeddings are saturated: each frame lies sqrt(32) from the reference's zero mean
    np.testing.assert_allclose(offline_unlike, np.sqrt(32) / LIMIT, rtol=1e-5)
    # both say so, in their metadata and in the same warnings
    marked = {}
    for name, path in (("offline", predicted[0]), ("stream", root / "stream" / "mini_002.force.mcap")):
        with Recording.open(path) as rec:
            meta = rec.metadata_records["visionforce.derived"]
            marked[name] = (meta["frames_beyond_training"], meta["frames_unlike_training"])
    assert marked["offline"] == marked["stream"] and marked["offline"][1] == str(FRAMES)
    # and of the tissue's lean against the training tissues' (vfdata.tissue_lean): the same record everywhere
    leans = {}
    for name, path in {"offline": predicted[0], **files}.items():
        with Recording.open(path) as rec:
            leans[name] = json.loads(rec.metadata_records["visionforce.derived"]["tissue_lean"])
    offline_lean = leans.pop("offline")
    assert offline_lean["training_deg"] == [30.0, 35.0] and offline_lean["lean_deg"] < 29.0
    assert offline_lean["unlike_training"] == (f"hangs {level(offline_lean['lean_deg'])}, outside the training "
                                               "tissues' 30.0 to 35.0 deg below level")
    for name, lean in leans.items():
        assert lean == offline_lean, name
    for out in (predicted[1], streamed.getvalue()):
        assert f"warning: {FRAMES} of {FRAMES} frames look unlike any training frame" in out
        assert f"warning: {marked['offline'][0]} of {FRAMES} frames have a force beyond the training range" in out
    for name, path in files.items():
        times, band, beyond = read_force_band(path)
        np.testing.assert_array_equal(times, offline_times, err_msg=name)
        np.testing.assert_allclose(band, offline_band, rtol=0, atol=1e-4, err_msg=name)
        np.testing.assert_array_equal(beyond != 0, offline_beyond != 0, err_msg=name)
        times, unlike = read_force_unlike(path)
        np.testing.assert_array_equal(times, offline_times, err_msg=name)
        np.testing.assert_allclose(unlike, offline_unlike, rtol=1e-4, err_msg=name)

    # The test scores each frame once, from the clip it ends latest in; `vfdata predict` runs the latest
    # 16 frames ending at it. Where those are the same clip, the forces are the same.
    np.testing.assert_array_equal(scored["frame_time_ns"], offline_times)
    same = scored_clip_starts(offline_times, 16, 4) == np.maximum(0, np.arange(FRAMES) - 15)
    assert same.sum() == 17 and not same[16:19].any()
    np.testing.assert_allclose(offline[same], scored["pred"][same], rtol=0, atol=1e-4)
    np.testing.assert_allclose(offline_band[same], scored["band"][same], rtol=0, atol=1e-4)
    np.testing.assert_allclose(read_force_unlike(predicted[0])[1][same], scored["distance"][same] / LIMIT, rtol=1e-4)
    # elsewhere the test's clip is shorter: close, not equal
    assert 0 < np.abs(offline[~same] - scored["pred"][~same]).max() < 0.5
    # and the RMSE `vfdata predict` prints is its forces' against the sensor, as the experiment's metric
    assert f"{force_metrics(offline, scored['true'])['rmse']:.3f} N" in predicted[1]


def scored_clip_starts(times_ns: np.ndarray, clip_frames: int, stride: int) -> np.ndarray:
    """Per frame, the first frame of the clip the test scores it from (`latest_clip_frames`: the clip in
    which it has the latest position)."""
    out = np.full(len(times_ns), -1, dtype=np.int64)
    for start in clip_starts(segments(times_ns), clip_frames, stride)[::-1]:  # the smallest start wins
        out[start:start + clip_frames] = start
    return out


def _has_foxglove() -> bool:
    try:
        import foxglove  # noqa: F401
    except ImportError:
        return False
    return True


def test_every_path_says_when_the_recording_is_doubtful(root, ckpt, monkeypatch, capsys):
    """A doubtful recording is said by every path: in its force file's metadata and in one line on stderr.
    Every mask outline is made too little on depth steps (MIN_EDGE_SUPPORT over 1), so each path's own
    verdict must say "mask_edges", and the streams, which judge as they go, reach the offline verdict's
    figures."""
    from vfdata import confidence

    monkeypatch.setattr(confidence, "MIN_EDGE_SUPPORT", 1.01)
    outputs = {}
    for name, extra in (("offline", []), ("stream", ["--stream"])):
        cv2.setRNGSeed(0)
        assert main(["predict", str(root / "mini_002.mcap"), "--ckpt", str(ckpt), "--out",
                     str(root / ckpt.stem / f"doubt_{name}"), "--no-video", "--quiet", *extra]) == 0
        err = capsys.readouterr().err
        assert "doubtful: " in err and "mask: its outline" in err, name
        outputs[name] = root / ckpt.stem / f"doubt_{name}" / "mini_002.force.mcap"
    if _has_foxglove():
        from vfmodels.commands import live

        parser = argparse.ArgumentParser()
        live.register(parser.add_subparsers())
        cv2.setRNGSeed(0)
        outputs["live"] = root / ckpt.stem / "doubt_live.mcap"
        assert live.run(parser.parse_args(["live", str(root / "mini_002.mcap"), "--ckpt", str(ckpt), "--port", "0",
                                           "--speed", "0", "--depth-roi-margin", "0", "--record",
                                           str(outputs["live"]), "--quiet"])) == 0
        assert "warning: live: doubtful from frame stamp" in capsys.readouterr().err
    verdicts = {}
    for name, path in outputs.items():
        with Recording.open(path) as rec:
            meta = rec.metadata_records["visionforce.derived"]
        assert meta["doubtful"] == "true", name
        verdicts[name] = json.loads(meta["confidence"])
        assert "mask_edges" in verdicts[name]["reasons"], name
    for name, verdict in verdicts.items():
        assert verdict["figures"]["tracks_kept"] == verdicts["offline"]["figures"]["tracks_kept"], name
        assert verdict["figures"]["mask_area_change"] == verdicts["offline"]["figures"]["mask_area_change"], name
        assert verdict["figures"]["mask_edge_support"] == verdicts["offline"]["figures"]["mask_edge_support"], name
