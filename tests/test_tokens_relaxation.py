"""The relaxation channels of `polar_z_disp_relax_vel`: each point's displacement less its causal average
over `RELAX_TAU_S`, stepped the same way over a whole recording and frame by frame."""

from __future__ import annotations

import numpy as np
import pytest

from vfdata.clips.spec import FEATURE_CHANNELS, ClipSpec
from vfdata.clips.tokens import (
    RELAX_TAU_S,
    displacement_averages,
    point_features,
    relaxation_step,
    relaxation_weight,
    tilt_about,
    tilt_tokens,
    track_tokens,
)
from vfdata.errors import VisionForceError

FPS = 30.0


def _step_then_hold(frames: int = 300, jump_at: int = 30, jump_mm: float = 4.0) -> np.ndarray:
    """Two points on a tube, the first pulled 4 mm along Z at frame 30 and held there."""
    points = np.zeros((frames, 2, 3))
    points[:, :, 0] = 10.0  # 10 mm above the axis
    points[:, 1, 2] = 40.0
    points[jump_at:, 0, 2] += jump_mm
    return points


def test_a_held_pull_relaxes_with_the_time_constant():
    points = _step_then_hold()
    tokens, ok = point_features(points, np.ones(points.shape[:2], bool), [(0, len(points))], FPS,
                                "polar_z_disp_relax_vel")
    assert tokens.shape == (300, 2, FEATURE_CHANNELS["polar_z_disp_relax_vel"])
    relax = tokens[:, 0, 9:12]
    np.testing.assert_allclose(tokens[:, 0, 6:9][:, 2][30:], 4.0, atol=1e-6)  # the displacement stays
    assert relax[29, 2] == 0 and relax[30, 2] == pytest.approx(4.0 * (1 - relaxation_weight(FPS)), rel=1e-6)
    # after one time constant, e^-1 of the pull is left; the still point has none
    held = 30 + int(RELAX_TAU_S * FPS)
    assert relax[held, 2] == pytest.approx(4.0 * np.exp(-1.0), rel=0.02)
    assert relax[-1, 2] < 0.1 and np.abs(tokens[:, 1, 9:12]).max() == 0


def test_a_point_first_seen_late_starts_from_no_relaxation():
    points = _step_then_hold()
    visible = np.ones(points.shape[:2], bool)
    visible[:100, 0] = False  # seen only after the pull
    tokens, ok = point_features(points, visible, [(0, len(points))], FPS, "polar_z_disp_relax_vel")
    assert not ok[:100, 0].any() and np.abs(tokens[100:, 0, 9:12]).max() == 0


def test_an_unseen_stretch_keeps_the_average_and_steps_match_the_whole_recording():
    rng = np.random.default_rng(0)
    disp = rng.normal(0, 1, (50, 4, 3))
    ok = rng.random((50, 4)) > 0.3
    whole = displacement_averages(disp, ok, FPS)
    avg, weight = None, relaxation_weight(FPS)
    for i in range(50):  # as the live estimator steps it
        avg = relaxation_step(avg, disp[i], ok[i], weight)
        np.testing.assert_array_equal(avg, whole[i])
    k = int(np.flatnonzero(~ok[1:, 0] & ok[:-1, 0])[0]) + 1  # a frame where point 0 is lost
    np.testing.assert_array_equal(whole[k, 0], whole[k - 1, 0])


def test_stream_averages_give_the_recording_tokens():
    """A stream passes the averages it stepped; a recording's are stepped inside: the same tokens."""
    spec = ClipSpec(features="polar_z_disp_relax_vel", canonical_side=True)
    points = _step_then_hold(frames=60)
    points[:, :, 1] = -5.0  # the y < 0 flank: mirrored to the canonical side
    visible = np.ones(points.shape[:2], bool)
    whole, _, side = track_tokens(spec, points, visible)
    assert side == -1.0
    reference = points[0]
    averages = displacement_averages(points - reference, visible, FPS)
    last3, _, _ = track_tokens(spec, points[-3:], visible[-3:], first=(points[0], visible[0]), fps=FPS,
                               reference_mm=reference, average_mm=averages[-3:])
    np.testing.assert_allclose(last3[1], whole[-2], atol=1e-6)


def test_tilting_turns_the_relaxation_like_the_displacement():
    points = _step_then_hold(frames=60)
    tokens, _ = point_features(points, np.ones(points.shape[:2], bool), [(0, 60)], FPS, "polar_z_disp_relax_vel")
    rotation = tilt_about(0.3, np.radians(10))
    tilted = tilt_tokens(tokens, "polar_z_disp_relax_vel", rotation)
    np.testing.assert_allclose(tilted[..., 9:12], tokens[..., 9:12] @ rotation.astype(np.float32), atol=1e-5)
    np.testing.assert_allclose(tilted[..., 6:9], tokens[..., 6:9] @ rotation.astype(np.float32), atol=1e-5)


def test_the_relaxation_is_a_known_feature_set():
    assert ClipSpec(features="polar_z_disp_relax_vel").channels == 15
    with pytest.raises(VisionForceError):
        ClipSpec(features="polar_z_relax")
