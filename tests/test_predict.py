"""Prediction: overlay drawing, token building, windowed causal inference, streaming = offline, the
checkpoint's clip spec, and the /force/estimate MCAP."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from vfdata.clips.spec import ClipSpec
from vfdata.clips.tokens import point_tokens, recording_side, top_bottom, track_tokens
from vfdata.errors import InputError, VisionForceError
from vfdata.recon.object_frame import ObjectFrame
from vfdata.recording import Recording, layout
from vfdata.recording.derived import (
    Tracks,
    read_force_band,
    read_force_estimate,
    read_force_unlike,
    read_tracks,
    write_force_estimate,
)
from vfmodels import ForceRegressor, SetTransformerLSTM
from vfmodels.inference import overlay, predict
from vfmodels.inference.live import StreamingForceEstimator, StreamingForceModel
from vfmodels.inference.trained_model import TrainedModel
from vfmodels.reports.figures import plot_force_series

IDENTITY = ObjectFrame(np.eye(3), np.zeros(3), False, float("nan"))


def test_force_to_camera_uses_the_object_axes():
    rotation = Rotation.from_euler("xyz", [20, -35, 110], degrees=True).as_matrix()
    f_obj = np.array([[1.0, 0.0, 0.0], [0.3, -2.0, 0.5]])
    f_cam = overlay.force_to_camera(f_obj, rotation)
    np.testing.assert_allclose(f_cam[0], rotation[:, 0])
    np.testing.assert_allclose(f_cam[1] @ rotation, f_obj[1], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(f_cam, axis=1), np.linalg.norm(f_obj, axis=1))


def _changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (np.abs(a.astype(int) - b.astype(int)).sum(axis=2) > 30)


def test_overlay_arrow_points_along_the_in_plane_force():
    image = np.full((200, 200, 3), 40, np.uint8)
    out = overlay.draw_force_overlay(image, (100, 100), np.array([1.0, 0.0, 0.0]), px_per_n=50, legend=False)
    changed = _changed(out, image)
    assert changed[100, 130:148].all()  # along +x (right)
    assert not changed[100, 30:80].any() and not changed[20:80, 100].any()
    out = overlay.draw_force_overlay(image, (100, 100), np.array([0.0, -1.0, 0.0]), px_per_n=50, legend=False)
    assert _changed(out, image)[55:85, 100].all()  # -y is up in the image


def test_overlay_circle_radius_and_colour_follow_the_depth_component():
    image = np.zeros((200, 200, 3), np.uint8)
    away = overlay.draw_force_overlay(image, (100, 100), np.array([0.0, 0.0, 1.2]), px_per_n=50, legend=False)
    ring = _changed(away, image)
    assert ring[100, 160] and ring[100, 40] and not ring[100, 150]  # radius 60
    assert away[100, 160, 1] > away[100, 160, 2]  # green: into the scene
    toward = overlay.draw_force_overlay(image, (100, 100), np.array([0.0, 0.0, -1.2]), px_per_n=50, legend=False)
    assert toward[100, 160, 2] > toward[100, 160, 1]  # red: toward the camera
    nothing = overlay.draw_force_overlay(image, (100, 100), np.full(3, np.nan), px_per_n=50, legend=False)
    rows, cols = np.nonzero(_changed(nothing, image))
    assert np.abs(rows - 100).max() <= 6 and np.abs(cols - 100).max() <= 6  # the origin marker only


def test_overlay_legend_and_measured_force():
    image = np.zeros((400, 640, 3), np.uint8)
    plain = overlay.draw_force_overlay(image, (320, 100), np.array([1.0, 0.0, 0.0]), px_per_n=50, legend=False)
    full = overlay.draw_force_overlay(image, (320, 100), np.array([1.0, 0.0, 0.0]), px_per_n=50,
                                      measured_camera_n=np.array([0.0, 1.0, 0.0]))
    assert _changed(full, plain)[300:, :300].any()  # legend and scale bar bottom left
    assert _changed(full, plain)[130:148, 320].all()  # the measured force: down (+y)


def test_overlay_scale_fits_the_largest_force():
    force = np.zeros((100, 3))
    force[:, 0] = np.linspace(0, 2.0, 100)
    assert overlay.overlay_scale(force, 640) * np.percentile(force[:, 0], 99) == pytest.approx(128.0)
    assert overlay.overlay_scale(np.zeros((5, 3)), 640) == 40.0


def test_overlay_video_writes_a_readable_mp4(tmp_path):
    path = tmp_path / "o.mp4"
    with overlay.OverlayVideo(path, fps=15) as video:
        for k in range(12):
            video.write(np.full((96, 128, 3), 20 * k, np.uint8))
    capture = cv2.VideoCapture(str(path))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == 12
    ok, frame = capture.read()
    assert ok and frame.shape == (96, 128, 3)
    assert not list(tmp_path.glob("*.partial*"))


def test_overlay_label_says_how_sure():
    force = np.array([3.0, 0.0, 4.0])
    assert predict.overlay_label(7, force, None, False, False) == "frame 7  |F| = 5.00 N"
    assert predict.overlay_label(7, force, np.array([0.41, 1.0, 2.25]), True, True) == \
        "frame 7  |F| = 5.00 N  band +-0.4/1.0/2.2 N  BEYOND TRAINING  UNLIKE TRAINING"
    assert predict.overlay_label(0, force, np.full(3, np.nan), False, True) == "frame 0  |F| = 5.00 N  UNLIKE TRAINING"


def test_force_series_plot(tmp_path):
    t = np.arange(50)
    force = np.stack([np.sin(t / 5), np.cos(t / 5), t / 50], axis=1)
    path = plot_force_series(force, tmp_path / "f.png", measured_n=force + 0.1)
    assert cv2.imread(str(path)).shape[0] > 100
    beyond = np.zeros_like(force)
    beyond[40:, 2] = 0.3
    shaded = plot_force_series(force, tmp_path / "band.png", measured_n=force + 0.1, band_n=np.full_like(force, 0.4),
                               beyond_n=beyond, coverage=0.9)
    assert _grey_pixels(cv2.imread(str(shaded))) > 3 * _grey_pixels(cv2.imread(str(path)))  # the band: grey shading


def _grey_pixels(image: np.ndarray) -> int:
    """Pixels of a BGR image that are grey (not white, not coloured)."""
    colourless = np.ptp(image.astype(int), axis=2) < 6
    return int((colourless & (image.min(axis=2) < 240)).sum())


def test_point_tokens_are_positions_and_central_difference_velocities():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(6, 50, 3))
    visible = rng.random((6, 50)) > 0.2
    rotation = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    origin = np.array([1.0, 2.0, 50.0])
    tokens, valid = point_tokens(ClipSpec(fps=10.0), points, visible)
    assert tokens.shape == (6, 50, 6) and tokens.dtype == np.float32
    # Written out by hand: a velocity needs its point seen on both neighbours (one-sided at the ends).
    seen_before = np.vstack([visible[:1], visible[:-1]])
    seen_after = np.vstack([visible[1:], visible[-1:]])
    np.testing.assert_array_equal(valid, visible & seen_before & seen_after)
    np.testing.assert_allclose(tokens[..., :3][valid], points[valid], rtol=1e-6)
    central = 0.5 * 10.0 * (points[2:] - points[:-2])
    np.testing.assert_allclose(tokens[1:-1, :, 3:][valid[1:-1]], central[valid[1:-1]], rtol=1e-5)
    np.testing.assert_allclose(tokens[0, :, 3:][valid[0]], (10.0 * (points[1] - points[0]))[valid[0]], rtol=1e-5)
    assert (tokens[~valid] == 0).all()
    # Uniform motion: the velocity is the same at every frame, the ends included.
    moving = np.arange(6)[:, None, None] * np.array([2.0, -1.0, 0.0]) + np.zeros((1, 4, 3))
    vel, _ = point_tokens(ClipSpec(features="vel", fps=30.0), moving, np.ones((6, 4), bool))
    np.testing.assert_allclose(vel[..., :2], np.broadcast_to([60.0, -30.0], (6, 4, 2)))
    cam, _ = point_tokens(ClipSpec(frame="camera", features="pos"), points, np.ones((6, 50), bool),
                          object_frame=(rotation, origin))
    np.testing.assert_allclose(cam, points @ rotation.T + origin, rtol=1e-6)
    sub, sub_valid = point_tokens(ClipSpec(subset="top_bottom_20"), points, visible)
    keep = top_bottom(points[0])
    assert sub.shape == (6, 20, 6)
    z = points[0, :, 2]
    assert set(keep) == set(np.argsort(z)[:10]) | set(np.argsort(z)[-10:])
    np.testing.assert_allclose(sub[..., :3][sub_valid], points[:, keep][sub_valid], rtol=1e-6)
    with pytest.raises(VisionForceError, match="object frame"):
        point_tokens(ClipSpec(frame="camera"), points, visible)


def test_the_token_recipe_of_a_stream_is_the_recordings():
    """`track_tokens` on the last three frames of a stream, given the first frame and each point's first
    position, gives the whole recording's tokens of the middle frame (mirror, subset, displacements, the place
    along Z from the free end, when a point first seen later lies beyond it)."""
    points, visible = _tracks(frames=12)
    points = points - np.array([0.0, 30.0, 0.0])  # the y < 0 flank: mirrored with canonical_side
    visible[:3, :4] = False
    times = np.arange(12) * 33_333_333
    points[3:, 5, 2] = points[:, :, 2].max() + 20.0  # first seen on frame 3, beyond the first frame's free end
    visible[:3, 5], visible[3:, 5] = False, True
    for spec in (ClipSpec(canonical_side=True, features="disp_vel"), ClipSpec(subset="top_bottom_20"),
                 ClipSpec(features="polar_disp_vel", radius="tissue"), ClipSpec(features="polar_z_disp_vel")):
        whole, whole_valid, side = track_tokens(spec, points, visible, times)
        assert side == (-1.0 if spec.canonical_side else 1.0)
        for t in range(1, 11):
            seen = visible[:t + 1] & np.isfinite(points[:t + 1]).all(axis=-1)
            first = np.argmax(seen, axis=0)
            reference = np.where(seen.any(axis=0)[:, None], points[first, np.arange(points.shape[1])], np.nan)
            tokens, valid, _ = track_tokens(spec, points[t - 1:t + 2], visible[t - 1:t + 2], times[t - 1:t + 2],
                                            first=(points[0], visible[0]), fps=30.0, reference_mm=reference)
            np.testing.assert_array_equal(valid[1], whole_valid[t])
            np.testing.assert_allclose(tokens[1], whole[t], rtol=1e-5, atol=1e-5)


def _regressor(seed: int = 0, in_features: int = 6, symmetry_turns: int = 1) -> ForceRegressor:
    """A small untrained regressor, tested as `visionforce` is: the mean of each clip and its mirror."""
    torch.manual_seed(seed)
    reg = ForceRegressor(SetTransformerLSTM(in_features=in_features, dim=32, heads=4, inducing_points=8,
                                            lstm_hidden=48), symmetry_turns=symmetry_turns)
    reg.set_normalisation(torch.zeros(in_features), torch.full((in_features,), 10.0), torch.tensor([0.1, -0.2, 0.5]),
                          torch.tensor([1.0, 2.0, 0.5]))
    return reg.eval()


def _tracks(frames: int = 40, n: int = 64, seed: int = 0):
    rng = np.random.default_rng(seed)
    base = rng.normal(scale=10.0, size=(n, 3))
    t = np.arange(frames)[:, None, None] / 30.0
    points = base + np.sin(2 * np.pi * t) * np.array([2.0, 0.0, -1.0]) * np.exp(-np.abs(base[:, :1]) / 10)
    visible = rng.random((frames, n)) > 0.1
    return points, visible


def _as_tracks(points: np.ndarray, visible: np.ndarray) -> Tracks:
    return Tracks(np.arange(len(points), dtype=np.int64) * 33_333_333, points, visible, IDENTITY)


def _forces(reg, spec, points, visible, window=None) -> np.ndarray:
    return predict.estimate_from_tracks(reg, spec, _as_tracks(points, visible), window)[0].force_n


def test_windowed_forces_equal_the_model_on_each_causal_window():
    reg = _regressor()
    points, visible = _tracks()
    spec = ClipSpec()
    forces = _forces(reg, spec, points, visible, window=8)
    tokens, valid = point_tokens(spec, points, visible)
    with torch.no_grad():
        for t in (0, 3, 7, 8, 25, 39):
            lo = max(0, t - 7)
            batch = {"tokens": torch.from_numpy(tokens[lo:t + 1])[None],
                     "valid": torch.from_numpy(valid[lo:t + 1])[None]}
            expected = reg.predict_forces(batch)[0, -1].numpy()
            np.testing.assert_allclose(forces[t], expected, rtol=1e-4, atol=1e-5)
        full = reg.predict_forces({"tokens": torch.from_numpy(tokens)[None], "valid": torch.from_numpy(valid)[None]})
    carried = _forces(reg, spec, points, visible, window=0)
    np.testing.assert_allclose(carried, full[0].numpy(), rtol=1e-4, atol=1e-5)
    # A later frame never changes an earlier estimate (causality).
    shorter = _forces(reg, spec, points[:30], visible[:30], window=8)
    np.testing.assert_allclose(shorter[:29], forces[:29], rtol=1e-4, atol=1e-5)
    # The default history is the clip length of the checkpoint's spec.
    np.testing.assert_allclose(_forces(reg, ClipSpec(clip_frames=8), points, visible), forces, rtol=1e-6)
    # The symmetry views count: the same weights without them give other forces.
    plain = _regressor(symmetry_turns=0)
    plain.load_state_dict(reg.state_dict())
    assert np.abs(_forces(plain, spec, points, visible, window=8) - forces).max() > 1e-3


def test_a_model_that_cannot_run_frame_by_frame_is_refused_in_one_line(tmp_path, monkeypatch):
    class WholeClip(torch.nn.Module):  # a token model with forward alone (as a 3D convolution would be)
        input_key, channel_dim, config = "tokens", -1, {}

        def forward(self, tokens, valid=None):
            return tokens.mean(dim=2)[..., :3]

    ckpt = _save_checkpoint(_regressor(), tmp_path / "c.ckpt", {"spec": {"input": "tracks"}})
    assert TrainedModel.load(ckpt).regressor.causal
    monkeypatch.setattr(ForceRegressor, "load", classmethod(lambda cls, path, checkpoint=None:
                                                            ForceRegressor(WholeClip())))
    with pytest.raises(InputError, match="c.ckpt: WholeClip does not run frame by frame"):
        TrainedModel.load(ckpt)


def test_canonical_side_mirrors_the_tracks_in_and_the_force_back_out():
    """A model trained with canonical_side sees a recording shown from its y < 0 flank mirrored, and
    its Fy is turned back: the same as mirroring the tracks by hand, running the plain spec and
    mirroring the force. (With the mirror among the symmetry views the mirror changes nothing.)"""
    reg = _regressor(2, symmetry_turns=0)
    points, visible = _tracks()
    points = points - np.array([0.0, 30.0, 0.0])  # the first frame shows the y < 0 flank
    canonical = ClipSpec(canonical_side=True)
    assert recording_side(canonical, points[0], visible[0]) == -1.0
    assert recording_side(ClipSpec(), points[0], visible[0]) == 1.0
    got = _forces(reg, canonical, points, visible)
    by_hand = _forces(reg, ClipSpec(), points * [1, -1, 1], visible) * [1, -1, 1]
    np.testing.assert_allclose(got, by_hand, rtol=1e-5, atol=1e-6)
    assert not np.allclose(got, _forces(reg, ClipSpec(), points, visible), atol=1e-3)
    mirrored = _regressor(2, symmetry_turns=1)
    np.testing.assert_allclose(_forces(mirrored, canonical, points, visible),
                               _forces(mirrored, ClipSpec(), points, visible), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("window", [8, 0])
@pytest.mark.parametrize("subset", ["all", "top_bottom_20", "canonical_side", "disp_vel", "ref_disp_vel"])
def test_streaming_model_reproduces_the_offline_forces(window, subset):
    reg = _regressor(1, in_features=9 if subset == "ref_disp_vel" else 6)
    points, visible = _tracks(frames=25)
    visible[0, :5] = False  # points first seen later: displacements start where each is first seen
    if subset == "canonical_side":
        points = points - np.array([0.0, 30.0, 0.0])
    spec = (ClipSpec(canonical_side=True) if subset == "canonical_side" else
            ClipSpec(features=subset) if "disp" in subset else ClipSpec(subset=subset))
    offline = _forces(reg, spec, points, visible, window=window)
    stream = StreamingForceModel(reg, spec, np.eye(3), np.zeros(3), window=window)
    stamps = np.arange(25) * 33_333_333
    results = [stream.push(s, p, v) for s, p, v in zip(stamps, points, visible, strict=True)]
    assert results[0] is None
    results = results[1:] + [stream.flush()]
    assert [r[0] for r in results] == list(stamps)
    np.testing.assert_allclose(np.stack([r[1] for r in results]), offline, rtol=1e-4, atol=1e-5)


def test_the_stream_stretches_and_marks_as_offline():
    """With an embedding reference and a calibration that stretches the band: the stream's band and
    distances are the offline ones, and both mark the same frames unlike training."""
    from vfmodels.evaluation.band import BandCalibration, unfamiliar

    reg = _regressor(3)
    points, visible = _tracks(frames=25)
    tokens = torch.from_numpy(np.stack([points, np.zeros_like(points)], axis=-1).reshape(1, 25, -1, 6)[:, :10])
    with torch.no_grad():
        z = reg.model.encode_frames(reg.normalise_input(tokens.float()))
    frames = z.reshape(-1, z.shape[-1]).repeat(10, 1)  # the first 10 frames' embeddings, spread a little
    reg.set_embedding_reference(frames + 0.1 * torch.randn(frames.shape, generator=torch.Generator().manual_seed(0)))
    offline, _side = predict.estimate_from_tracks(reg, ClipSpec(), _as_tracks(points, visible), 8)
    limit = float(np.median(offline.distance))
    reg.band_calibration = BandCalibration((0.5, 0.5, 0.5), (0.0, 0.0, 0.0), distance_ref=limit / 2,
                                           distance_limit=limit)
    offline, _side = predict.estimate_from_tracks(reg, ClipSpec(), _as_tracks(points, visible), 8)
    assert np.isfinite(offline.distance).all() and (offline.band_n > 0.5).any()
    stream = StreamingForceModel(reg, ClipSpec(), np.eye(3), np.zeros(3), window=8)
    stamps = np.arange(25) * 33_333_333
    results = [stream.push(s, p, v) for s, p, v in zip(stamps, points, visible, strict=True)][1:] + [stream.flush()]
    np.testing.assert_allclose(np.stack([r[2] for r in results]), offline.band_n, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose([r[3] for r in results], offline.distance, rtol=1e-4)
    marks = unfamiliar(np.array([r[3] for r in results]), reg.band_calibration)
    assert marks.tolist() == unfamiliar(offline.distance, reg.band_calibration).tolist() and 0 < marks.sum() < 25


def test_streaming_model_cuts_velocities_at_dropped_frames_as_offline():
    """A camera that drops a frame now and then (a Kinect's 70 ms of 30): over the recording the
    velocities are one-sided at each gap, as in training; the stream does the same, judging gaps
    against its usual period rather than the few frames it holds."""
    reg = _regressor(2)
    points, visible = _tracks(frames=30)
    period = 33_333_333
    stamps = np.arange(30) * period + np.where(np.arange(30) >= 9, period, 0) + np.where(np.arange(30) >= 20, period, 0)
    offline = predict.estimate_from_tracks(reg, ClipSpec(), Tracks(stamps, points, visible, IDENTITY), 8)[0].force_n
    stream = StreamingForceModel(reg, ClipSpec(), np.eye(3), np.zeros(3), window=8)
    results = [stream.push(s, p, v) for s, p, v in zip(stamps, points, visible, strict=True)][1:] + [stream.flush()]
    np.testing.assert_allclose(np.stack([r[1] for r in results]), offline, rtol=1e-4, atol=1e-5)


def _save_checkpoint(reg: ForceRegressor, path, datamodule_hp: dict | None = None):
    checkpoint = {"state_dict": reg.state_dict(), "hyper_parameters": dict(reg.hparams)}
    reg.on_save_checkpoint(checkpoint)
    if datamodule_hp is not None:
        checkpoint["datamodule_hyper_parameters"] = datamodule_hp
    torch.save(checkpoint, path)
    return path


def test_canonical_side_is_read_from_the_checkpoint_and_needs_the_object_frame(tmp_path):
    ckpt = _save_checkpoint(_regressor(), tmp_path / "c.ckpt", {"spec": {"canonical_side": True, "frame": "object"}})
    assert TrainedModel.load(ckpt).spec.canonical_side is True
    with pytest.raises(VisionForceError, match="object frame"):
        ClipSpec(frame="camera", canonical_side=True)


def test_predict_step_turns_a_mirrored_clip_back():
    reg = _regressor(3)
    points, visible = _tracks(frames=16)
    tokens, valid = point_tokens(ClipSpec(), points, visible)
    batch = {"tokens": torch.from_numpy(tokens)[None].repeat(2, 1, 1, 1),
             "valid": torch.from_numpy(valid)[None].repeat(2, 1, 1), "side": torch.tensor([1.0, -1.0])}
    with torch.no_grad():
        out = reg.predict_step(batch, 0)["force_n"]
        raw = reg.predict_forces(batch)
    torch.testing.assert_close(out[0], raw[0])
    torch.testing.assert_close(out[1], raw[1] * torch.tensor([1.0, -1.0, 1.0]))


def test_a_trained_model_reads_the_clip_spec_and_checks_features(tmp_path):
    reg = _regressor()
    ckpt = _save_checkpoint(reg, tmp_path / "m.ckpt", {"spec": {"frame": "camera", "fps": 25.0}})
    model = TrainedModel.load(ckpt)
    loaded, spec = model.regressor, model.spec
    assert spec.frame == "camera" and spec.fps == 25.0 and spec.features == "pos_vel"
    points, visible = _tracks(frames=10)
    np.testing.assert_allclose(_forces(loaded, ClipSpec(), points, visible), _forces(reg, ClipSpec(), points, visible),
                               rtol=1e-5)
    # checkpoints written before ClipSpec kept the options flat
    old = _save_checkpoint(reg, tmp_path / "old.ckpt", {"frame": "camera", "fps": 25.0, "batch_size": 32})
    assert TrainedModel.load(old).spec == spec
    mismatch = _save_checkpoint(reg, tmp_path / "pos.ckpt", {"spec": {"features": "pos"}})
    with pytest.raises(InputError, match="features per point"):
        TrainedModel.load(mismatch)
    with pytest.raises(InputError, match="checkpoint not found"):
        TrainedModel.load(tmp_path / "missing.ckpt")


@pytest.mark.parametrize("class_path", ["vfmodels.set_transformer.SetTransformerLSTM", "vfmodels.SetTransformerLSTM"])
def test_checkpoints_saved_before_the_subpackages_still_load(tmp_path, class_path):
    """Checkpoints name their model by class path; those saved when the networks sat at vfmodels' top
    (`vfmodels.set_transformer`) load as they did, with the same forces."""
    reg = _regressor()
    ckpt = _save_checkpoint(reg, tmp_path / "old.ckpt")
    state = torch.load(ckpt, weights_only=True)
    assert state["force_model"]["class_path"] == "vfmodels.networks.set_transformer.SetTransformerLSTM"
    state["force_model"]["class_path"] = class_path
    torch.save(state, ckpt)
    loaded = TrainedModel.load(ckpt).regressor
    points, visible = _tracks(frames=10)
    np.testing.assert_allclose(_forces(loaded, ClipSpec(), points, visible), _forces(reg, ClipSpec(), points, visible),
                               rtol=1e-5)


@pytest.mark.parametrize("class_path, init_args", [
    ("subprocess.getoutput", {"cmd": "touch {marker}"}),
    ("vfmodels.SetTransformerLSTM", {"in_features": 6, "evil": "x"}),
    ("os.system", {}),
])
def test_a_checkpoint_cannot_choose_code_to_run(tmp_path, class_path, init_args):
    marker = tmp_path / "ran"
    ckpt = _save_checkpoint(_regressor(), tmp_path / "evil.ckpt")
    state = torch.load(ckpt, weights_only=True)
    state["force_model"] = {"class_path": class_path,
                            "init_args": {k: str(v).format(marker=marker) for k, v in init_args.items()}}
    torch.save(state, ckpt)
    with pytest.raises(InputError, match="evil.ckpt"):
        TrainedModel.load(ckpt)
    assert not marker.exists()


def test_damaged_checkpoints_are_one_line_errors(tmp_path):
    good = _save_checkpoint(_regressor(), tmp_path / "good.ckpt").read_bytes()
    for name, data in (("empty.ckpt", b""), ("half.ckpt", good[: len(good) // 2]), ("text.ckpt", b"hello")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputError, match=name):
            TrainedModel.load(tmp_path / name)
    torch.save([1, 2, 3], tmp_path / "list.ckpt")
    with pytest.raises(InputError, match="list.ckpt"):
        TrainedModel.load(tmp_path / "list.ckpt")


def test_force_mcap_round_trip(tmp_path):
    times = 1_700_000_000_000_000_000 + np.arange(5, dtype=np.int64) * 33_333_333
    force = np.arange(15, dtype=np.float64).reshape(5, 3) / 7
    frame = ObjectFrame(Rotation.from_euler("y", 30, degrees=True).as_matrix(), np.array([1.0, 2.0, 80.0]), True, 1.0)
    path = write_force_estimate(tmp_path / "x.force.mcap", times, force, frame, {"x_axis": "arbitrary"})
    t, f = read_force_estimate(path)
    np.testing.assert_array_equal(t, times)
    np.testing.assert_allclose(f, force)
    with Recording.open(path) as rec:
        _, msg = next(rec.messages(layout.FORCE_ESTIMATE))
        assert msg.frame_id == layout.OBJECT_FRAME and np.all(np.asarray(msg.torque) == 0.0)
        _, tf = next(rec.messages(layout.TF_STATIC))
        assert tf.transforms[0].child_frame_id == layout.OBJECT_FRAME
        np.testing.assert_allclose(tf.transforms[0].translation, [0.001, 0.002, 0.08])
        meta = rec.metadata_records[layout.DERIVED_METADATA]
        assert meta["x_axis"] == "arbitrary" and meta["torque_estimated"] == "false"
    assert read_force_band(path) is None  # written without a band: none to read

    band, beyond = force / 10 + 0.5, np.zeros_like(force)
    band[0] = np.nan  # a frame without a calibrated band stays NaN
    beyond[3] = [0.0, -1.5, 2.0]
    path = write_force_estimate(tmp_path / "b.force.mcap", times, force, frame, {}, band_n=band, beyond_n=beyond)
    np.testing.assert_allclose(read_force_estimate(path)[1], force)
    t, b, o = read_force_band(path)
    np.testing.assert_array_equal(t, times)
    np.testing.assert_allclose(b, band)
    np.testing.assert_allclose(o, beyond)
    with Recording.open(path) as rec:
        assert rec.topics[layout.FORCE_BAND].msgtype == "geometry_msgs/msg/WrenchStamped"
    assert read_force_unlike(path) is None  # written without it: none to read

    unlike = np.linspace(0.2, 1.8, len(times))
    unlike[1] = np.nan  # a frame whose distance is unknown
    path = write_force_estimate(tmp_path / "u.force.mcap", times, force, frame, {}, band_n=band, beyond_n=beyond,
                                unlike=unlike)
    t, u = read_force_unlike(path)
    np.testing.assert_array_equal(t, times)  # logged at its estimate's stamp
    np.testing.assert_array_equal(u, unlike)
    with Recording.open(path) as rec:
        info = rec.topics[layout.FORCE_UNLIKE]
        assert info.msgtype == "std_msgs/msg/Float64" and info.count == len(times)
        payload = next(rec.payloads(layout.FORCE_UNLIKE))[1]
    # ROS 2's own definition reads the same number (rosbags' typestore), and so does the mcap package's
    # ROS 2 decoder from the schema the file carries
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.typesys import Stores, get_typestore
    assert get_typestore(Stores.ROS2_HUMBLE).deserialize_cdr(bytes(payload), "std_msgs/msg/Float64").data == unlike[0]
    with open(path, "rb") as f:
        decoded = [(m.log_time, d.data) for _, _, m, d in make_reader(f, decoder_factories=[DecoderFactory()])
                   .iter_decoded_messages(topics=[layout.FORCE_UNLIKE])]
    np.testing.assert_array_equal([t for t, _ in decoded], times)
    np.testing.assert_array_equal([v for _, v in decoded], unlike)


@pytest.mark.slow
def test_predict_recording_and_streaming_agree_on_a_simulated_recording(tmp_path):
    """The whole offline pipeline (processing, model, MCAP, plot, video) on a simulated recording
    without using its force, then the live estimator (serial and pipelined) on the same frames."""
    from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder
    from vfdata.rig import StereoRig, camera_up
    from vfdata.sim import synthesize

    manifest = synthesize("mini", tmp_path / "data", seed=0, workers=1, progress=False, frames=20)
    recording = convert_raw_folder(manifest.parent / "mini_002", tmp_path / "mini_002.mcap",
                                   options=ConvertOptions(progress=False))
    ckpt = _save_checkpoint(_regressor(), tmp_path / "m.ckpt", {"spec": {"input": "tracks", "fps": 30.0}})
    # The colortrack mask (GrabCut) draws from OpenCV's global RNG: the same seed for both runs.
    cv2.setRNGSeed(0)
    result = predict.predict_recording(recording, ckpt, tmp_path / "out", window=8, progress=False)
    times, force = read_force_estimate(result.force_mcap)
    assert len(times) == result.frames == 20 and np.isfinite(force).all()
    capture = cv2.VideoCapture(str(result.video))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == 20
    assert cv2.imread(str(result.plot)) is not None
    tracks = read_tracks(result.processed)
    with pytest.raises(Exception, match="exists"):  # outputs are kept unless overwrite
        predict.predict_recording(recording, ckpt, tmp_path / "out", window=8, progress=False)
    np.testing.assert_array_equal(tracks.times_ns, times)

    with Recording.open(recording) as rec:
        frames = [rec.rectified_frame(i) for i in range(rec.num_frames)]
        camera, baseline, up = rec.camera, rec.stereo.baseline_mm, camera_up(rec)
        prompt = "box:" + ",".join(str(int(round(float(v)))) for v in
                                   rec.metadata.extra["prompt_box"].strip("[]").split(","))
    for pipelined in (False, True):
        cv2.setRNGSeed(0)
        rig = StereoRig(recording, camera=camera, baseline_mm=baseline, up=up)
        live = StreamingForceEstimator(ckpt, rig, prompt, window=8, pipelined=pipelined)
        estimates = [e for f in frames if (e := live.push(f.left, f.right, f.stamp_ns)) is not None]
        assert len(estimates) == 20 - (2 if pipelined else 1)
        estimates += live.flush()
        live.close()
        assert [e.stamp_ns for e in estimates] == list(times)
        np.testing.assert_allclose(np.stack([e.force_n for e in estimates]), force, rtol=1e-3, atol=1e-3)
        assert set(live.stage_seconds) >= {"depth", "mask", "cloud", "tracking", "force"}

    # A model trained on other tracks (vfdata predict --tracker klt): the geometry tracks of the run
    # above are not reused for it, they are redone with KLT.
    from vfdata.processing import ProcessOptions

    klt = predict.predict_recording(recording, ckpt, tmp_path / "out", ProcessOptions(tracker="klt"), window=8,
                                    video=False, progress=False, overwrite=True)
    assert read_tracks(klt.processed).metadata.values["tracker"] == "klt"


def test_displacement_tokens_and_the_mirror():
    points, visible = _tracks(frames=6, n=10)
    visible[:2, 0] = False
    tokens, valid = point_tokens(ClipSpec(features="ref_disp_vel"), points, visible)
    np.testing.assert_allclose(tokens[3, 1:, 3:6][valid[3, 1:]], (points[3, 1:] - points[0, 1:])[valid[3, 1:]],
                               rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(tokens[4, 0, :3], points[2, 0], rtol=1e-5)  # point 0 is first seen at frame 2
    from vfdata.clips.tokens import mirror_tokens

    flipped = mirror_tokens(tokens)
    np.testing.assert_allclose(flipped[..., 1::3], -tokens[..., 1::3])
    np.testing.assert_allclose(flipped[..., 0::3], tokens[..., 0::3])
    with pytest.raises(VisionForceError, match="mirror_augment"):
        ClipSpec(frame="camera", mirror_augment=True)


def test_the_trained_tracker_is_read_from_the_checkpoint_as_a_known_name(tmp_path):
    path = _save_checkpoint(_regressor(), tmp_path / "k.ckpt")
    assert TrainedModel.load(path).tracker is None  # an older checkpoint does not say: the caller's default
    checkpoint = torch.load(path, weights_only=True)
    checkpoint["ForceDataModule"] = {"tracker": "klt"}
    torch.save(checkpoint, path)
    assert TrainedModel.load(path).tracker == "klt"
    checkpoint["ForceDataModule"] = {"tracker": "rm -rf /"}
    torch.save(checkpoint, path)
    with pytest.raises(InputError, match="unknown tracker"):
        TrainedModel.load(path)


@pytest.mark.parametrize("kind, up_known, says", [
    ("tissue", True, "gravity up"), ("tissue", False, "arbitrary"),
    ("board_plane", False, "the image's right"), ("camera", False, "the image's right")])
def test_the_x_axis_is_described_by_the_frames_kind(kind, up_known, says):
    from vfdata.recon.object_frame import x_axis_meaning

    assert x_axis_meaning(kind, up_known).split(":")[0] == says


def test_predict_on_an_rgbd_recording_says_its_board_frame(tmp_path):
    """No ECM pose on an RGB-D recording, yet the board frame's X is not arbitrary: the output says what it is."""
    from tests.rgbd_fixtures import make_rgbd
    from vfdata.conversion.raw_folder import ConvertOptions
    from vfdata.conversion.raw_rgbd import convert_rgbd_folder
    from vfdata.processing import ProcessOptions

    src = make_rgbd(tmp_path / "rec", n=6, holes=False)
    recording = convert_rgbd_folder(src, tmp_path / "rec.mcap", options=ConvertOptions(progress=False, workers=1))
    ckpt = _save_checkpoint(_regressor(), tmp_path / "m.ckpt", {"spec": {"input": "tracks", "fps": 30.0}})
    result = predict.predict_recording(recording, ckpt, tmp_path / "out", ProcessOptions(), window=4,
                                       video=False, progress=False)
    assert not result.up_known and result.x_axis.startswith("the image's right")
    # frame by frame (`--stream`, what `vfdata live` runs): the same forces, said the same way
    from vfdata.cli import main

    assert main(["predict", str(recording), "--ckpt", str(ckpt), "--out", str(tmp_path / "stream"), "--stream",
                 "--window", "4", "--quiet"]) == 0
    offline, stream = result.force_mcap, tmp_path / "stream" / "rec.force.mcap"
    for path in (offline, stream):
        with Recording.open(path) as rec:
            assert rec.metadata_records[layout.DERIVED_METADATA]["x_axis"] == result.x_axis
            _, tf = next(rec.messages(layout.TF_STATIC))  # the object frame hangs off the depth camera
            assert tf.transforms[0].frame_id == layout.DEPTH_FRAME
    (times, forces), (stream_times, stream_forces) = read_force_estimate(offline), read_force_estimate(stream)
    assert len(times) == 6 and np.array_equal(times, stream_times)
    np.testing.assert_allclose(stream_forces, forces, rtol=1e-4, atol=1e-4)


def test_the_training_tissues_lean_is_read_from_the_checkpoint(tmp_path):
    path = _save_checkpoint(_regressor(), tmp_path / "k.ckpt")
    assert TrainedModel.load(path).lean_deg is None  # an older checkpoint does not say: no note
    checkpoint = torch.load(path, weights_only=True)
    checkpoint["ForceDataModule"] = {"tracker": "klt", "tissue_lean_deg": [4.5, 7.25]}
    torch.save(checkpoint, path)
    assert TrainedModel.load(path).lean_deg == [4.5, 7.25]
    checkpoint["ForceDataModule"] = {"tissue_lean_deg": "low"}
    torch.save(checkpoint, path)
    with pytest.raises(InputError, match="not a range of two angles"):
        TrainedModel.load(path)


@pytest.fixture(scope="module")
def mini_recording(tmp_path_factory):
    """A six-frame simulated recording (mini seed 0's test recording), converted."""
    from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder
    from vfdata.sim import synthesize

    root = tmp_path_factory.mktemp("mini")
    manifest = synthesize("mini", root / "data", seed=0, workers=1, progress=False, frames=6)
    return convert_raw_folder(manifest.parent / "mini_002", root / "mini_002.mcap",
                              options=ConvertOptions(progress=False))


def test_predict_records_how_the_tissue_hangs_against_the_training_tissues(tmp_path, mini_recording):
    """A model whose training tissues hung 20-25 deg below level: the recording's tissue hangs outside their
    range, which the result and the force file's metadata record; within the range, they do not."""
    from vfdata.tissue_lean import read_lean, unlike_training

    recording = mini_recording
    ckpt = _save_checkpoint(_regressor(), tmp_path / "m.ckpt", {"spec": {"input": "tracks", "fps": 30.0}})
    checkpoint = torch.load(ckpt, weights_only=True)
    checkpoint["ForceDataModule"] = {"tissue_lean_deg": [20.0, 25.0]}
    torch.save(checkpoint, ckpt)
    result = predict.predict_recording(recording, ckpt, tmp_path / "out", window=4, video=False, progress=False)
    lean = read_lean(result.processed, recording)
    assert lean is not None and lean < 19.0
    assert result.lean_note == unlike_training(lean, [20.0, 25.0])
    assert result.lean_note.endswith(", outside the training tissues' 20.0 to 25.0 deg below level")
    with Recording.open(result.force_mcap) as rec:
        said = json.loads(next(m["tissue_lean"] for m in rec.metadata_records.values() if "tissue_lean" in m))
    assert said == {"lean_deg": round(lean, 2), "training_deg": [20.0, 25.0], "unlike_training": result.lean_note}

    checkpoint["ForceDataModule"] = {"tissue_lean_deg": [lean - 2.0, lean + 2.0]}
    torch.save(checkpoint, ckpt)
    again = predict.predict_recording(recording, ckpt, tmp_path / "out", window=4, video=False, progress=False,
                                      overwrite=True)
    assert again.lean_note is None


def test_a_run_folder_is_its_best_checkpoint_and_predict_reads_it_once(tmp_path, mini_recording, monkeypatch,
                                                                       capsys):
    """`--ckpt` takes a run folder (its best checkpoint by validation loss), and `vfdata predict` reads the
    checkpoint once, handing the loaded model down (`TrainedModel`), however many of its facts it asks."""
    from vfdata.cli import main
    from vfmodels.training import checkpoint as checkpoint_module

    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    spec = {"spec": {"input": "tracks", "fps": 30.0}}
    best = _save_checkpoint(_regressor(1), run / "checkpoints" / "epoch003-val_loss0.50000.ckpt", spec)
    _save_checkpoint(_regressor(2), run / "checkpoints" / "epoch001-val_loss0.90000.ckpt", spec)
    assert TrainedModel.load(run).path == best
    assert TrainedModel.load(run / "checkpoints").path == best

    recording = mini_recording
    reads = []
    load_weights = checkpoint_module.load_weights
    monkeypatch.setattr(checkpoint_module, "load_weights", lambda path, what: reads.append(path) or
                        load_weights(path, what))
    assert main(["predict", str(recording), "--ckpt", str(best), "--out", str(tmp_path / "out"), "--window", "4",
                 "--tracker", "klt", "--no-video", "--quiet"]) == 0
    assert reads == [best]
    with Recording.open(tmp_path / "out" / "mini_002.force.mcap") as rec:
        meta = rec.metadata_records[layout.DERIVED_METADATA]
    assert meta["checkpoint"] == str(best.resolve())
    assert "RMSE against the recording's force sensor" in capsys.readouterr().out
