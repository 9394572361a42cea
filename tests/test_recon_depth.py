"""Stereo depth stage: accuracy on the real SCARED frame, the backends' contracts and errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from vfdata.calibration import PinholeCamera
from vfdata.errors import BackendError, InputError
from vfdata.recon import make_depth_estimator
from vfdata.recon.depth import fill_disparity_holes

SCARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "scared"


def _scared():
    if not (SCARED / "left.png").is_file():
        pytest.skip(f"SCARED sample frame not found in {SCARED}")
    left = cv2.imread(str(SCARED / "left.png"))
    right = cv2.imread(str(SCARED / "right.png"))
    gt = cv2.imread(str(SCARED / "disparity.tiff"), cv2.IMREAD_UNCHANGED)
    occlusion = cv2.imread(str(SCARED / "occlusion.png"), cv2.IMREAD_UNCHANGED)
    valid = (gt > 0) & (occlusion != 128)
    return left, right, gt, valid


def test_sgbm_on_scared_meets_accuracy_and_density_targets():
    left, right, gt, valid = _scared()
    disp = make_depth_estimator("sgbm").disparity(left, right)
    assert disp.shape == gt.shape and disp.dtype == np.float32
    given = np.isfinite(disp) & (disp > 0)
    density = (given & valid).sum() / valid.sum()
    epe = np.abs(disp - gt)[valid & given].mean()
    assert density == 1.0, f"density {density:.4f}"
    assert epe <= 0.4, f"end-point error {epe:.3f} px"


def test_plain_matching_alone_would_miss_the_target():
    """The refinement and smoothing carry weight: without them the same matcher is worse."""
    left, right, gt, valid = _scared()
    plain = make_depth_estimator("sgbm", refine_window=0, smooth_radius=0).disparity(left, right)
    full = make_depth_estimator("sgbm").disparity(left, right)
    assert np.abs(plain - gt)[valid].mean() > np.abs(full - gt)[valid].mean() + 0.05


def _synthetic_pair(disparity: float = 12.0, h: int = 96, w: int = 128):
    """A textured fronto-parallel plane at a known disparity."""
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (h, w + 64)).astype(np.float32), (0, 0), 1.2)
    texture = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    # x_right = x_left - d: the right view is the texture shifted left by d.
    xs = np.arange(w, dtype=np.float32)[None, :].repeat(h, 0) + 32
    ys = np.arange(h, dtype=np.float32)[:, None].repeat(w, 1)
    left = cv2.remap(texture, xs, ys, cv2.INTER_LINEAR)
    right = cv2.remap(texture, xs + disparity, ys, cv2.INTER_LINEAR)
    return cv2.cvtColor(left, cv2.COLOR_GRAY2BGR), cv2.cvtColor(right, cv2.COLOR_GRAY2BGR)


def test_depth_mm_of_a_plane():
    left, right = _synthetic_pair(12.0)
    cam = PinholeCamera(500.0, 500.0, 64.0, 48.0, 128, 96)
    depth = make_depth_estimator("sgbm", max_disparity=32).depth_mm(left, right, cam, baseline_mm=5.0)
    expected = 500.0 * 5.0 / 12.0
    centre = depth[20:-20, 40:-20]
    assert np.isfinite(depth).all()
    assert abs(np.median(centre) - expected) / expected < 0.01


def test_hole_fill_follows_the_image():
    """A hole next to an edge takes its value from the side whose intensity it shares."""
    disp = np.zeros((4, 10), np.float32)
    disp[:, :5] = 10.0
    disp[:, 5:] = 30.0
    image = np.zeros((4, 10), np.uint8)
    image[:, 5:] = 200  # the edge of the image is at column 5
    valid = np.ones((4, 10), bool)
    valid[:, 3:7] = False  # holes on both sides of the edge
    filled = fill_disparity_holes(disp, valid, image)
    np.testing.assert_allclose(filled[:, 3:5], 10.0, atol=0.01)
    np.testing.assert_allclose(filled[:, 5:7], 30.0, atol=0.01)


def test_recorded_backend_passes_depth_through():
    cam = PinholeCamera(500.0, 500.0, 32.0, 24.0, 64, 48)
    gt = np.full((48, 64), 80.0, np.float32)
    gt[0, 0] = 0.0
    est = make_depth_estimator("recorded", depths=[gt])
    img = np.zeros((48, 64, 3), np.uint8)
    out = est.depth_mm(img, img, cam, 5.0)
    assert np.isnan(out[0, 0]) and np.allclose(out[1:], 80.0)
    with pytest.raises(BackendError, match="no depth map supplied"):
        est.depth_mm(img, img, cam, 5.0)
    est.supply(np.ones((10, 10)))
    with pytest.raises(InputError, match="depth"):
        est.depth_mm(img, img, cam, 5.0)


def test_unknown_backend_lists_the_known_ones():
    with pytest.raises(BackendError, match="sgbm, stereoanyvideo, recorded"):
        make_depth_estimator("raft")


def test_stereoanyvideo_without_code_or_weights_fails_clearly(tmp_path):
    with pytest.raises(BackendError, match="checkpoint"):
        make_depth_estimator("stereoanyvideo")
    with pytest.raises(BackendError, match="not a Stereo Any Video checkout"):
        make_depth_estimator("stereoanyvideo", code=tmp_path, checkpoint=tmp_path / "x.pth")
    code = tmp_path / "stereoanyvideo" / "models" / "core"
    code.mkdir(parents=True)
    (code / "stereoanyvideo.py").write_text("")
    with pytest.raises(BackendError, match="not found"):
        make_depth_estimator(
            "stereoanyvideo", code=tmp_path / "stereoanyvideo", checkpoint=tmp_path / "x.pth"
        )


def test_bad_sgbm_options_and_images():
    with pytest.raises(BackendError, match="unknown option"):
        make_depth_estimator("sgbm", blocksize=5)
    est = make_depth_estimator("sgbm")
    with pytest.raises(InputError, match="differ in size"):
        est.disparity(np.zeros((64, 64, 3), np.uint8), np.zeros((64, 80, 3), np.uint8))


def test_depth_stream_equals_frame_by_frame():
    """The overlapped stream gives exactly the per-frame results, in order."""
    pairs = [_synthetic_pair(d) for d in (8.0, 12.0, 16.0)]
    cam = PinholeCamera(500.0, 500.0, 64.0, 48.0, 128, 96)
    est = make_depth_estimator("sgbm", max_disparity=32)
    streamed = list(est.depth_stream(pairs, cam, 5.0))
    assert len(streamed) == 3
    for (left, right), depth in zip(pairs, streamed, strict=True):
        np.testing.assert_array_equal(depth, est.depth_mm(left, right, cam, 5.0))
    assert list(est.depth_stream([], cam, 5.0)) == []
    recorded = make_depth_estimator("recorded", depths=[np.full((96, 128), 50.0)])
    assert np.allclose(next(recorded.depth_stream(pairs[:1], cam, 5.0)), 50.0)
