"""The stereo lift of the `klt` tracker: a tracked point's own match in the right image, triangulated,
recovers a known depth far better than a noisy depth map, and where the match is rejected the point is
the depth map's."""

from __future__ import annotations

import numpy as np
import pytest

from vfdata.calibration import PinholeCamera
from vfdata.errors import BackendError, InputError
from vfdata.tracking import FrameInputs, make_tracker
from vfdata.tracking.flow import to_gray
from vfdata.tracking.lifting import lift_pixels
from vfdata.tracking.stereo_lift import StereoLift

CAMERA = PinholeCamera(fx=560.0, fy=560.0, cx=159.5, cy=119.5, width=320, height=240)
BASELINE_MM = 4.6
DEPTH_NOISE_MM = 1.5  # per pixel of the depth map, about what SGBM leaves along the line of sight


def texture(x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
    """A tissue-like texture (grey 0-255) on the plane, as a sum of sinusoids, so a view of it at any
    sub-pixel shift is exact, not interpolated."""
    rng = np.random.default_rng(7)
    out = np.full(x_mm.shape, 128.0)
    for _ in range(40):
        freq = rng.uniform(0.15, 0.9)  # cycles per mm: 4-25 px at 150 mm
        angle, phase = rng.uniform(0, np.pi), rng.uniform(0, 2 * np.pi)
        out += 9.0 * np.sin(2 * np.pi * freq * (np.cos(angle) * x_mm + np.sin(angle) * y_mm) + phase)
    return out


def pair(z_mm: float, shift_mm: float = 0.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Left and right rectified BGR views of a fronto-parallel textured plane at depth `z_mm`, moved
    `shift_mm` along x; grey-level noise as a sensor's."""
    v, u = np.mgrid[0:CAMERA.height, 0:CAMERA.width].astype(np.float64)
    y = (v - CAMERA.cy) * z_mm / CAMERA.fy
    x_left = (u - CAMERA.cx) * z_mm / CAMERA.fx - shift_mm
    rng = np.random.default_rng(seed)
    views = []
    for x in (x_left, x_left + BASELINE_MM):  # the right camera sits BASELINE_MM along +x
        grey = np.clip(texture(x, y) + rng.normal(0, 1.5, x.shape), 0, 255).astype(np.uint8)
        views.append(np.repeat(grey[..., None], 3, axis=2))
    return views[0], views[1]


def noisy_depth(z_mm: float, seed: int) -> np.ndarray:
    return (z_mm + np.random.default_rng(seed).normal(0, DEPTH_NOISE_MM, (CAMERA.height, CAMERA.width))
            ).astype(np.float32)


def grid(step: int = 16, margin: int = 40) -> np.ndarray:
    v, u = np.mgrid[margin:CAMERA.height - margin:step, margin:CAMERA.width - margin:step]
    return np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64) + 0.3  # off the pixel grid


def test_the_stereo_match_recovers_a_known_disparity_better_than_a_noisy_depth_map():
    z = 150.0
    disparity = CAMERA.fx * BASELINE_MM / z  # 17.17 px: not a whole number
    left, right = pair(z)
    uv = grid()
    fallback = lift_pixels(uv, noisy_depth(z, 1), CAMERA)
    lift = StereoLift(CAMERA, BASELINE_MM, (40.0, 300.0), len(uv))
    points, stereo = lift.lift(uv, to_gray(left), to_gray(right), fallback)
    assert stereo.all()
    stereo_error = np.sqrt(np.mean((points[:, 2] - z) ** 2))
    depth_error = np.sqrt(np.mean((fallback[:, 2] - z) ** 2))
    assert depth_error > 1.2
    assert stereo_error < 0.1 * depth_error
    # 0.3 mm at 150 mm is 0.035 px of disparity
    assert stereo_error < 0.3, f"{stereo_error:.3f} mm ({disparity:.2f} px disparity)"
    # The points lie on the rays of their pixels.
    np.testing.assert_allclose(CAMERA.project(points), uv, atol=1e-6)


def test_rejected_matches_fall_back_to_the_depth_map():
    z = 150.0
    left, right = pair(z)
    right = right.copy()
    right[:, 200:] = pair(z, shift_mm=7.3, seed=5)[1][:, 200:]  # another surface in the right view there
    uv = np.concatenate([grid(), [[8.4, 120.2]]])  # the last one's match would lie left of the image
    fallback = lift_pixels(uv, noisy_depth(z, 2), CAMERA)
    points, stereo = StereoLift(CAMERA, BASELINE_MM, (40.0, 300.0), len(uv)).lift(
        uv, to_gray(left), to_gray(right), fallback)
    matched_in = uv[:, 0] - CAMERA.fx * BASELINE_MM / z
    occluded = matched_in > 215  # well inside the changed part of the right view
    assert occluded.sum() > 20 and not stereo[-1]
    assert stereo[matched_in < 185].mean() > 0.95
    assert stereo[occluded].mean() < 0.2
    np.testing.assert_array_equal(points[~stereo], fallback[~stereo])
    clear = stereo & (matched_in < 185)  # the window wholly on the plane in both views
    assert np.abs(points[clear, 2] - z).max() < 1.0
    # A working range that leaves this plane out rejects every match.
    far_only = StereoLift(CAMERA, BASELINE_MM, (200.0, 300.0), len(uv))
    points, stereo = far_only.lift(uv, to_gray(left), to_gray(right), fallback)
    assert not stereo.any()
    np.testing.assert_array_equal(points, fallback)


def frame(index: int, z_mm: float, shift_mm: float, stereo: bool = True) -> FrameInputs:
    left, right = pair(z_mm, shift_mm, seed=index)
    depth = noisy_depth(z_mm, 10 + index)
    mask = np.zeros(depth.shape, bool)
    mask[40:-40, 40:-40] = True  # the reference points away from the image's edges
    return FrameInputs(index=index, camera=CAMERA, image_bgr=left, depth_mm=depth, mask=mask,
                       cloud_mm=CAMERA.backproject(depth, mask), right_bgr=right if stereo else None,
                       baseline_mm=BASELINE_MM if stereo else None, working_range_mm=(40.0, 300.0))


def test_klt_with_the_stereo_lift_follows_a_plane_moving_in_depth():
    """The plane comes 2 mm nearer and moves sideways: the stereo lift's tracked depth change is the
    true one within 0.3 mm; the depth map's is lost in its noise."""
    depths, shifts = [150.0, 149.0, 148.0], [0.0, 0.4, 0.8]
    frames = [frame(i, z, s) for i, (z, s) in enumerate(zip(depths, shifts, strict=True))]
    trackers = {lift: make_tracker("klt", frames[0], num_points=64, seed=1, lift=lift) for lift in ("depth", "stereo")}
    assert {"right_bgr", "baseline_mm"} <= trackers["stereo"].inputs
    assert "right_bgr" not in trackers["depth"].inputs
    start = {lift: tracker.points for lift, tracker in trackers.items()}
    for f in frames[1:]:
        moved = {lift: tracker.update(f) for lift, tracker in trackers.items()}
    seen = moved["stereo"][1] & moved["depth"][1]  # the same points: both lifts follow the same 2D tracks
    np.testing.assert_array_equal(moved["stereo"][1], moved["depth"][1])
    assert seen.mean() > 0.6
    change = {lift: moved[lift][0][seen, 2] - start[lift][seen, 2] for lift in trackers}
    truth = depths[-1] - depths[0]
    stereo_error = np.sqrt(np.mean((change["stereo"] - truth) ** 2))
    depth_error = np.sqrt(np.mean((change["depth"] - truth) ** 2))
    assert stereo_error < 0.3 and depth_error > 1.5, (stereo_error, depth_error)  # 0.3 mm: 0.035 px


def test_the_stereo_lift_needs_a_right_view():
    with pytest.raises(BackendError, match="needs baseline_mm, right_bgr of frame 0"):
        make_tracker("klt", frame(0, 150.0, 0.0, stereo=False), num_points=16, lift="stereo")
    tracker = make_tracker("klt", frame(0, 150.0, 0.0), num_points=16, lift="stereo")
    with pytest.raises(BackendError, match="needs baseline_mm, right_bgr of frame 1"):
        tracker.update(frame(1, 150.0, 0.0, stereo=False))
    with pytest.raises(InputError, match="lift 'sideways' is not one of depth, stereo"):
        make_tracker("klt", frame(0, 150.0, 0.0), num_points=16, lift="sideways")
