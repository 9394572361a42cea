"""Object frame: the paper's slicing search on synthetic tubes and the simulator's tissue."""

from __future__ import annotations

import json
import time

import cv2
import numpy as np
import pytest
from recon_fixtures import random_rotation, tapered_tube

from vfdata.errors import InputError
from vfdata.recon import ObjectFrame, estimate_object_frame, up_in_camera
from vfdata.recon.tube_axis import hemisphere_directions


def _angle_deg(a, b):
    return float(
        np.degrees(np.arccos(np.clip(abs(np.dot(a, b)) / np.linalg.norm(a) / np.linalg.norm(b), 0, 1)))
    )


def _side_view_rotation(rng):
    """A random tube pose whose axis is within 60 degrees of the image plane (the tissue seen
    from its side, as in the paper's setup)."""
    while True:
        r = random_rotation(rng)
        if abs(r[2, 2]) < np.sin(np.radians(60)):
            return r


def test_candidates_cover_a_hemisphere():
    dirs = hemisphere_directions()
    assert dirs.shape == (36 * 36, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0)
    assert (dirs[:, 2] >= 0).all()
    # Every direction of the sphere is within a few degrees of a candidate or its opposite.
    rng = np.random.default_rng(0)
    probe = rng.normal(size=(500, 3))
    probe /= np.linalg.norm(probe, axis=1, keepdims=True)
    worst = np.degrees(np.arccos(np.abs(probe @ dirs.T).max(axis=1))).max()
    assert worst < 6.0


@pytest.mark.parametrize("seed", range(4))
def test_tapered_tube_axis_and_wide_end(seed):
    rng = np.random.default_rng(seed)
    rotation = _side_view_rotation(rng)
    points = tapered_tube(rng, rotation)
    frame = estimate_object_frame(points)
    true_z = rotation[:, 2]
    assert _angle_deg(frame.z_axis, true_z) <= 3.0
    assert frame.z_axis @ true_z > 0, "+Z must run from the wide end toward the narrow end"
    # Origin near the wide end of the centreline (2nd percentile along Z).
    wide_centre = np.array([0.0, 0.0, 120.0]) - rotation[:, 2] * 30.0
    assert np.linalg.norm(frame.origin - wide_centre) < 5.0


def test_frame_is_right_handed_and_round_trips():
    rng = np.random.default_rng(7)
    rotation = _side_view_rotation(rng)
    points = tapered_tube(rng, rotation)
    up = np.array([0.2, -1.0, 0.1])
    frame = estimate_object_frame(points, up=up)
    r = frame.rotation
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-9)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(np.cross(r[:, 2], r[:, 0]), r[:, 1], atol=1e-9)
    # X is `up` made perpendicular to Z.
    projected = up - (up @ frame.z_axis) * frame.z_axis
    assert _angle_deg(frame.x_axis, projected) < 1e-6 and frame.x_axis @ projected > 0
    assert frame.up_known
    np.testing.assert_allclose(frame.to_camera(frame.to_object(points)), points, atol=1e-9)
    obj = frame.to_object(points)
    assert np.percentile(obj[:, 2], 2) == pytest.approx(0.0, abs=1e-6)


def test_without_up_x_is_deterministic_and_flagged():
    rng = np.random.default_rng(8)
    points = tapered_tube(rng, _side_view_rotation(rng))
    a = estimate_object_frame(points)
    again = estimate_object_frame(points.copy())
    reordered = estimate_object_frame(points[::-1].copy())
    assert not a.up_known
    np.testing.assert_array_equal(a.rotation, again.rotation)
    assert _angle_deg(a.x_axis, reordered.x_axis) < 1.0 and a.x_axis @ reordered.x_axis > 0
    assert abs(a.x_axis @ a.z_axis) < 1e-9
    # The image's up direction (-y of the camera), made perpendicular to Z.
    assert a.x_axis[1] < 0


def test_shuffled_and_noisier_cloud_gives_the_same_axis():
    rng = np.random.default_rng(9)
    rotation = _side_view_rotation(rng)
    points = tapered_tube(rng, rotation, noise=0.8)
    frame = estimate_object_frame(rng.permutation(points))
    assert _angle_deg(frame.z_axis, rotation[:, 2]) <= 3.0


def test_runs_within_the_time_budget():
    rng = np.random.default_rng(10)
    points = tapered_tube(rng, _side_view_rotation(rng), n=2000)
    start = time.process_time()
    estimate_object_frame(points)
    # CPU time (the machine running the tests may be shared); the target is 2 s per recording.
    assert time.process_time() - start < 4.0


def test_up_in_camera_from_a_pose():
    # Camera looking straight down at the world (z forward = world -Z): camera-to-world rotation
    # maps camera x -> world x, camera y -> world -y, camera z -> world -z (180 deg about x).
    up = up_in_camera(np.array([1.0, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(up, [0.0, 0.0, -1.0], atol=1e-12)
    # Identity orientation: camera axes are the world axes.
    np.testing.assert_allclose(up_in_camera(np.array([0, 0, 0, 1.0])), [0, 0, 1.0])
    with pytest.raises(InputError):
        up_in_camera(np.zeros(4))


def test_bad_inputs():
    with pytest.raises(InputError, match="too few"):
        estimate_object_frame(np.zeros((10, 3)))
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        estimate_object_frame(np.zeros((100, 2)))
    rng = np.random.default_rng(11)
    rotation = _side_view_rotation(rng)
    points = tapered_tube(rng, rotation)
    with pytest.raises(InputError, match="parallel"):
        estimate_object_frame(points, up=rotation[:, 2])


def test_object_frame_to_dict_is_json():
    rng = np.random.default_rng(12)
    frame = estimate_object_frame(tapered_tube(rng, _side_view_rotation(rng)))
    assert isinstance(frame, ObjectFrame)
    data = json.loads(json.dumps(frame.to_dict()))
    np.testing.assert_allclose(data["rotation"], frame.rotation)
    again = ObjectFrame.from_dict(data)
    np.testing.assert_allclose(again.matrix(), frame.matrix())
    assert (again.up_known, again.score_deg) == (frame.up_known, frame.score_deg)


@pytest.mark.parametrize("base_mm, cut", [(51.0, True), (30.0, False)])
def test_origin_cut_by_view_flags_a_tissue_that_runs_out_of_the_image(base_mm, cut):
    """A tube seen from above, running up the image from its base (the origin) at camera y = base_mm:
    at 51 mm (100 mm deep) the base projects onto the bottom row, at 30 mm 100 px above it."""
    from vfdata.calibration import PinholeCamera
    from vfdata.recon.object_frame import origin_cut_by_view

    camera = PinholeCamera(500.0, 500.0, 320.0, 256.0, 640, 512)
    rng = np.random.default_rng(0)
    along = rng.uniform(0.0, 40.0, 2000)  # mm from the base toward the tip
    points = np.stack([rng.uniform(-8, 8, 2000), base_mm - along, np.full(2000, 100.0)], axis=1)
    rotation = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # columns X, Y, Z = -y
    frame = ObjectFrame(rotation, np.array([0.0, base_mm, 100.0]), up_known=True, score_deg=0.0)
    assert origin_cut_by_view(points, frame, camera) is cut


def _occluder_band(rng, rotation, n, length=60.0, r_wide=10.0, distance=120.0, reach=25.0):
    """A sheet of points rising from the tube's upper flank over its wide half toward the camera:
    what an instrument shaft lying over the tissue leaves in a stereo cloud (its depth bled into a
    band of tissue pixels)."""
    z = rng.uniform(0, length / 2, n)
    s = rng.uniform(0, 1, n)
    base = np.outer(z - length / 2, rotation[:, 2]) + r_wide * rotation[:, 0] + np.array([0.0, 0.0, distance])
    toward = -base / np.linalg.norm(base, axis=1, keepdims=True)
    return base + (s * reach)[:, None] * (toward + 0.6 * rotation[:, 0])


@pytest.mark.parametrize("seed", [2, 3, 4])
def test_the_roundest_fit_is_taken_over_one_an_occluder_band_turned(seed):
    """The band is in the whole cloud; a cloud without it (the frontal part) gives the round tube."""
    from vfdata.recon.tissue_frame import chosen_axis

    rng = np.random.default_rng(seed)
    rotation = _side_view_rotation(rng)
    tube = tapered_tube(rng, rotation)
    cloud = np.vstack([tube, _occluder_band(rng, rotation, 1000)])
    true_z = rotation[:, 2]
    assert _angle_deg(estimate_object_frame(cloud).z_axis, true_z) > 15.0, "the band must turn the plain fit"
    axis, diagnostics = chosen_axis({"cloud": cloud, "clean": cloud, "frontal": tube})
    assert _angle_deg(axis.direction, true_z) < 3.0 and diagnostics["axis_from"] == "frontal"
    assert diagnostics["axis_fits"]["cloud"]["deg"] > 15.0 and not diagnostics["axis_doubtful"]
    fits = diagnostics["axis_fits"]
    assert fits["frontal"]["residual"] < fits["cloud"]["residual"]


@pytest.mark.parametrize(("seed", "degrees"), [(2, 20.0), (3, 20.0), (2, 11.5), (3, 11.5)])
def test_a_smaller_cloud_as_round_about_a_turned_axis_makes_the_axis_doubtful(seed, degrees):
    """glove_009 of the sweep: the metal-free cloud (the chosen fit's judge) is a partial tube that a turned
    axis fits roundly, while the metal-free frontal cloud, too small to be chosen, is as round about the
    true axis. Two clouds that each look like a tube about axes 20 degrees apart: the axis is a guess. So
    is it at 11.5 degrees (glove_018 of glove 203: 11.9), beyond the 10 the object frame promises."""
    from vfdata.recon.tissue_frame import chosen_axis

    rng = np.random.default_rng(seed)
    rotation = _side_view_rotation(rng)
    tube = tapered_tube(rng, rotation, n=3000)
    turn = cv2.Rodrigues(np.radians(degrees) * rotation[:, 0])[0]  # about the tube's X
    turned = tapered_tube(rng, turn @ rotation, n=3000)
    share = 0.3 * len(tube) / len(turned)
    rival = turned[: int(share * len(turned))]
    clouds = {"cloud": tube, "clean": tube[: int(0.7 * len(tube))], "frontal": tube[::2]}
    _axis, diagnostics = chosen_axis({**clouds, "clean_frontal": rival})
    assert diagnostics["axis_from"] != "clean_frontal" and diagnostics["axis_fits"]["clean_frontal"]["deg"] > 10.0
    assert diagnostics["axis_doubtful"] and diagnostics["axis_rivals"] == ["clean_frontal"]
    _axis, diagnostics = chosen_axis({**clouds, "clean_frontal": tube[: len(rival)]})
    assert not diagnostics["axis_doubtful"] and diagnostics["axis_rivals"] == []  # the same tube: no rival
    _axis, diagnostics = chosen_axis({**clouds, "clean_frontal": rival[: int(0.2 * len(tube))]})
    assert "clean_frontal" not in diagnostics["axis_fits"] and not diagnostics["axis_doubtful"]  # too little


def test_a_cloud_too_small_to_trust_is_not_fitted_and_a_flat_one_is_doubtful():
    from vfdata.recon.tissue_frame import chosen_axis

    rng = np.random.default_rng(2)
    tube = tapered_tube(rng, _side_view_rotation(rng))
    _axis, diagnostics = chosen_axis({"cloud": tube, "clean": tube[:100], "frontal": tube[::2]})
    assert "clean" not in diagnostics["axis_fits"]  # an instrument over most of the tissue: not judged on it
    sheet = np.stack([rng.uniform(-30, 30, 3000), rng.uniform(-10, 10, 3000), 100 + rng.normal(0, 0.3, 3000)], 1)
    _axis, diagnostics = chosen_axis({"cloud": sheet})
    assert diagnostics["axis_doubtful"]  # the bed, not a tube: no axis fits it


def test_a_tube_a_little_less_round_is_not_doubtful_when_every_fit_agrees():
    """On the colon sweeps four frames were doubtful by the residual alone (0.103-0.119) with their four fits
    within 5 degrees of each other, and 2.4-6.7 degrees from the truth: each cost a training or validation
    tissue. A noisier tube (residual 0.10-0.15) whose fits agree is not doubtful; fitted alone, or rougher
    still, it is."""
    from vfdata.recon.tissue_frame import AXIS_DOUBT_RESIDUAL, chosen_axis

    rng = np.random.default_rng(2)
    rotation = _side_view_rotation(rng)
    rough = tapered_tube(rng, rotation, noise=1.3)
    clouds = {"cloud": rough, "clean": rough[: int(0.7 * len(rough))], "frontal": rough[::2],
              "clean_frontal": rough[1::3]}
    axis, diagnostics = chosen_axis(clouds)
    residual = diagnostics["axis_fits"][diagnostics["axis_from"]]["residual"]
    assert AXIS_DOUBT_RESIDUAL < residual < 1.5 * AXIS_DOUBT_RESIDUAL
    assert not diagnostics["axis_doubtful"] and _angle_deg(axis.direction, rotation[:, 2]) < 3.0
    assert chosen_axis({"cloud": rough})[1]["axis_doubtful"]  # one fit agrees with nothing
    rougher = tapered_tube(rng, rotation, noise=2.5)  # residual over 0.15: far from a tube whatever the fits say
    assert chosen_axis({"cloud": rougher, "clean": rougher[::2], "frontal": rougher[1::2]})[1]["axis_doubtful"]


def test_tube_residual_is_small_about_the_true_axis_and_grows_with_its_tilt():
    from vfdata.recon.tube_axis import TubeAxis, tube_residual

    rng = np.random.default_rng(4)
    rotation = _side_view_rotation(rng)
    tube = tapered_tube(rng, rotation)
    centre = np.array([0.0, 0.0, 120.0])  # the tube's axis passes here (tapered_tube's distance)
    true = tube_residual(tube, TubeAxis(rotation[:, 2], centre, 0.0, len(tube)))
    tilted_z = rotation[:, 2] * np.cos(np.radians(15)) + rotation[:, 0] * np.sin(np.radians(15))
    tilted = tube_residual(tube, TubeAxis(tilted_z, centre, 0.0, len(tube)))
    assert true < 0.05 and tilted > 2 * true


def test_size_points_decide_the_wide_end():
    """The axis from one cloud, the wide end from another's silhouette: a tube tapering the other way
    turns +Z round (and the origin to the other end)."""
    rng = np.random.default_rng(11)
    rotation = _side_view_rotation(rng)
    points = tapered_tube(rng, rotation)
    reversed_taper = tapered_tube(rng, rotation, r_wide=6.0, r_narrow=10.0)
    plain = estimate_object_frame(points)
    turned = estimate_object_frame(points, size_points=reversed_taper)
    assert plain.z_axis @ rotation[:, 2] > 0.99 and turned.z_axis @ rotation[:, 2] < -0.99
    assert np.linalg.norm(turned.origin - plain.origin) > 40.0  # the 60 mm tube's other end
