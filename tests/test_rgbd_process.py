"""Processing RGB-D recordings: the board plane, the plane mask, the board frame, and `vfdata process`
on a converted RGB-D folder (recorded depth, no stereo matching)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.rgbd_fixtures import DEPTH_SIZE, DOME_CENTRE, DOME_MM, DOME_RADIUS_PX, FX, depth_frame, make_rgbd
from vfdata.calibration import PinholeCamera
from vfdata.conversion.options import ConvertOptions
from vfdata.conversion.raw_rgbd import convert_rgbd_folder
from vfdata.errors import InputError
from vfdata.processing import ProcessOptions, process_recording
from vfdata.recon.plane import PlaneSegmenter, board_frame, fit_board_plane
from vfdata.recon.prompt import Prompt
from vfdata.recording import Recording, layout
from vfdata.recording.derived import DerivedRecording

CAMERA = PinholeCamera(FX, FX, (DEPTH_SIZE - 1) / 2, (DEPTH_SIZE - 1) / 2, DEPTH_SIZE, DEPTH_SIZE)


def _dome() -> np.ndarray:
    v, u = np.mgrid[0:DEPTH_SIZE, 0:DEPTH_SIZE]
    return np.hypot(u - DOME_CENTRE[0], v - DOME_CENTRE[1]) < DOME_RADIUS_PX


def test_board_plane_fitted_under_the_tissue():
    depth = depth_frame(0)
    plane = fit_board_plane(depth)
    board = ~_dome()
    assert np.abs(plane.depth_mm(depth.shape)[board] - depth[board]).max() < 1e-6
    # under the dome the plane continues the board, the tissue's full height above it
    centre = int(DOME_CENTRE[1]), int(DOME_CENTRE[0])
    assert plane.depth_mm(depth.shape)[centre] - depth[centre] == pytest.approx(DOME_MM, abs=0.5)


def test_plane_mask_is_the_tissue_and_follows_it():
    segmenter = PlaneSegmenter(min_height_mm=6.0)
    prompt = Prompt.from_box([8, 10, 56, 58])
    blank = np.zeros((DEPTH_SIZE, DEPTH_SIZE, 3), np.uint8)
    mask = segmenter.start(blank, prompt, np.rint(depth_frame(0)))
    dome = _dome()
    iou = (mask & dome).sum() / (mask | dome).sum()
    assert iou > 0.7 and not mask[~dome].any()
    later = segmenter.track(blank, np.rint(depth_frame(25)))  # the middle pressed 20 mm: below 6 mm stays out
    assert later.sum() < mask.sum() and not later[int(DOME_CENTRE[1]), int(DOME_CENTRE[0])]


def test_board_frame_z_is_height_above_the_board():
    depth = depth_frame(0)
    plane = fit_board_plane(depth)
    v, u = np.nonzero(_dome())
    z = depth[v, u]
    cloud = np.stack([(u - CAMERA.cx) * z / FX, (v - CAMERA.cy) * z / FX, z], axis=1)
    frame = board_frame(plane, CAMERA, cloud)
    heights = frame.to_object(cloud)[:, 2]
    assert heights.max() == pytest.approx(DOME_MM, abs=2.0) and heights.min() > -1.0
    assert frame.diagnostics["kind"] == "board_plane"
    np.testing.assert_allclose(frame.rotation.T @ frame.rotation, np.eye(3), atol=1e-9)
    assert frame.rotation[:, 2] @ -frame.origin > 0  # Z (up) points to the camera's side


def test_process_rgbd_uses_recorded_depth_board_frame_and_tracks_the_press(tmp_path):
    src = make_rgbd(tmp_path / "rec", n=10, holes=False)
    rec = convert_rgbd_folder(src, tmp_path / "rec.mcap", options=ConvertOptions(progress=False, workers=1))
    options = ProcessOptions(progress=False, tracker="geometry", num_points=64)
    out = process_recording(rec, options=options)
    with DerivedRecording.open(out) as derived:
        meta = derived.meta
        assert (meta.get("depth"), meta.get("segment"), meta.get("object_frame_kind")) == ("sensor", "plane",
                                                                                            "board_plane")
        assert derived.num_frames == 10
        assert json.loads(meta.get("tracker_parameters"))["lambda_anchor"] == 1.0
        np.testing.assert_allclose(derived.depth_mm(3), np.rint(depth_frame(3)), atol=0.5)
        tracks = derived.tracks()
    assert tracks.points_object_mm.shape == (10, 64, 3)
    top = np.argsort(tracks.points_object_mm[0, :, 2])[-5:]  # the dome's top, where it is pressed
    # the pressed middle sinks towards the board (7 mm at its centre): its points' heights go down
    sink = tracks.points_object_mm[0, top, 2] - tracks.points_object_mm[-1, top, 2]
    uv = CAMERA.project(tracks.points_camera_mm(0)[top])
    true_sink = np.array([depth_frame(9)[int(round(v)), int(round(u))] - depth_frame(0)[int(round(v)), int(round(u))]
                          for u, v in uv]) * abs(tracks.frame.rotation[2, 2])  # along the ray -> along the normal
    edge = np.argsort(tracks.points_object_mm[0, :, 2])[:20]  # the rim: not pressed
    # The geometry tracker follows a fraction of this narrow press (of 4.6 mm: 1.5 without the anchor, 0.9
    # with the RGB-D default lambda_anchor 1, measured): its local-shape terms and the anchor hold the
    # surface back; the direction and the contrast with the rim are what is checked.
    assert true_sink.mean() > 3.0 and sink.mean() > 0.5
    assert np.abs(tracks.points_object_mm[-1, edge, 2] - tracks.points_object_mm[0, edge, 2]).mean() < 1.0
    assert (tmp_path / "rec.processed.png").is_file()
    # ROS tf: the object frame, the mask and the depth hang off the depth camera that saw them
    with Recording.open(out) as derived_file:
        _, tf = next(derived_file.messages(layout.TF_STATIC))
        assert tf.transforms[0].frame_id == layout.DEPTH_FRAME == meta.get("camera_frame_id")
        assert {next(derived_file.messages(topic))[1].frame_id
                for topic in (layout.TISSUE_MASK, layout.TISSUE_DEPTH)} == {layout.DEPTH_FRAME}


def test_process_rgbd_refuses_stereo_depth_and_the_tube_frame(tmp_path):
    src = make_rgbd(tmp_path / "rec", n=3)
    rec = convert_rgbd_folder(src, tmp_path / "rec.mcap", options=ConvertOptions(progress=False, workers=1))
    with pytest.raises(InputError, match="brings its depth"):
        process_recording(rec, options=ProcessOptions(progress=False, depth="stereoanyvideo"))
    with pytest.raises(InputError, match="does not apply to an RGB-D recording"):
        process_recording(rec, options=ProcessOptions(progress=False, object_frame="tissue"))
    with pytest.raises(InputError, match="has no right image: klt's lift 'stereo' does not apply"):
        process_recording(rec, options=ProcessOptions(progress=False, tracker="klt",
                                                      tracker_options={"lift": "stereo"}))
    assert not (tmp_path / "rec.processed.mcap").exists()


def test_an_image_tracker_on_rgbd_is_warned_about(tmp_path, caplog):
    # the image an RGB-D recording's trackers see is its depth drawn as grey: KLT would follow the press
    src = make_rgbd(tmp_path / "rec", n=3, holes=False)
    rec = convert_rgbd_folder(src, tmp_path / "rec.mcap", options=ConvertOptions(progress=False, workers=1))
    with caplog.at_level("WARNING"):
        process_recording(rec, options=ProcessOptions(progress=False, tracker="geometry", num_points=32))
    assert "depth drawn as grey" not in caplog.text
    with caplog.at_level("WARNING"):
        process_recording(rec, tmp_path / "klt.mcap", ProcessOptions(progress=False, tracker="klt", num_points=32))
    assert "tracker 'klt' follows the image" in caplog.text and "rec.mcap" in caplog.text


def test_a_glitched_depth_frame_gets_no_mask_and_is_listed():
    segmenter = PlaneSegmenter()
    blank = np.zeros((DEPTH_SIZE, DEPTH_SIZE, 3), np.uint8)
    segmenter.start(blank, Prompt.from_box([8, 10, 56, 58]), depth_frame(0))
    shifted = np.roll(depth_frame(1), 9, axis=0) + 40.0  # another view of the scene: the board is elsewhere
    assert not segmenter.track(blank, shifted).any()
    assert segmenter.track(blank, depth_frame(2)).sum() > 500
    assert segmenter.glitched_frames == [1] and segmenter.parameters()["glitched_frames"] == [1]


def test_the_anchor_holds_points_that_the_cloud_would_drag_along():
    from vfdata.tracking.geometry import GeometryTracker

    rng = np.random.default_rng(0)
    cloud = np.column_stack([rng.uniform(-30, 30, (2000, 2)), np.full(2000, 500.0)])
    slid = cloud + [0.0, 0.0, -3.0]  # the surface comes 3 mm closer
    moved = {}
    for anchor in (0.0, 1000.0):
        tracker = GeometryTracker(cloud, CAMERA, 64, 0, lambda_anchor=anchor, iterations=30)
        for _ in range(10):
            points, _ = tracker.update(slid)
        moved[anchor] = float(np.abs(points[:, 2] - 500.0).mean())
    assert moved[0.0] > 1.5 and moved[1000.0] < 0.5 * moved[0.0]
