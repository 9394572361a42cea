import cv2
import numpy as np

from vfdata.tracking.flow import refine_from_reference, track_lk


def textured(shift_px=(0.0, 0.0), size=(240, 320)):
    """A smooth random texture, translated by `shift_px` (sub-pixel, bilinear)."""
    rng = np.random.default_rng(0)
    noise = cv2.GaussianBlur(rng.uniform(0, 255, size).astype(np.float32), (0, 0), 2.0)
    noise = cv2.normalize(noise, None, 0, 255, cv2.NORM_MINMAX)
    warp = np.float32([[1, 0, shift_px[0]], [0, 1, shift_px[1]]])
    return cv2.warpAffine(noise, warp, (size[1], size[0]), flags=cv2.INTER_LINEAR).astype(np.uint8)


def test_reference_match_removes_the_drift_of_a_guess_and_refuses_far_guesses():
    reference, current = textured(), textured((6.3, -4.2))
    grid = np.stack(np.meshgrid(np.arange(60, 260, 25), np.arange(50, 190, 25)), axis=-1).reshape(-1, 2)
    truth = grid + [6.3, -4.2]
    drifted = truth + [0.8, -0.6]  # where frame-to-frame flow might have got to after many frames
    found, ok = refine_from_reference(reference, current, grid, drifted, max_disagreement_px=2.0)
    assert ok.all()
    assert np.abs(found - truth).max() < 0.2 < np.abs(drifted - truth).min()
    # A guess far from the reference match is left alone rather than trusted.
    _, ok = refine_from_reference(reference, current, grid, truth + [5.0, 0.0], max_disagreement_px=2.0)
    assert not ok.any()


def test_frame_to_frame_flow_follows_a_shift():
    previous, current = textured(), textured((2.5, 1.5))
    uv = np.array([[100.0, 100.0], [200.0, 120.0]])
    new, ok = track_lk(previous, current, uv)
    assert ok.all() and np.abs(new - uv - [2.5, 1.5]).max() < 0.1
