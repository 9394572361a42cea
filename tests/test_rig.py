"""The rig (`vfdata.rig`): a stereo recording, an RGB-D recording and a live camera as the engine's
input: the frames, the stage defaults, the images and the live view of each kind, and that no other
module outside the recording layer asks which kind an input is."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from tests.rawfixtures import make_raw
from tests.rgbd_fixtures import make_rgbd
from vfdata.conversion.options import ConvertOptions
from vfdata.conversion.raw_folder import convert_raw_folder
from vfdata.conversion.raw_rgbd import convert_rgbd_folder
from vfdata.engine import EngineOptions
from vfdata.errors import InputError
from vfdata.recording import Recording, layout
from vfdata.rig import Frame, RgbdRig, StereoRig, rig_for

ROOT = Path(__file__).resolve().parents[1]
# Where an input's kind may be asked (`Recording.is_rgbd`): the recording layer, which reads and writes
# each kind, and the rig, which is the one place the rest of the code learns it from.
KIND_LAYER = ("vfdata/recording/", "vfdata/conversion/", "vfdata/lerobot/", "vfdata/rig.py")
NEVER = lambda topic: False  # noqa: E731  (a viewer that wants no image)


@pytest.fixture(scope="module")
def stereo(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("stereo")
    raw = make_raw(root / "raw", n=4)
    (raw / "meta.yaml").write_text("study: test\ntissue: glove\norientation_deg: 0\nprompt_box: [20, 16, 140, 110]\n")
    return convert_raw_folder(raw, root / "stereo.mcap", options=ConvertOptions(progress=False))


@pytest.fixture(scope="module")
def rgbd(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("rgbd")
    src = make_rgbd(root / "raw", n=5)
    return convert_rgbd_folder(src, root / "rgbd.mcap", options=ConvertOptions(progress=False, workers=1))


def test_a_stereo_recording_gives_rectified_pairs_and_the_tubes_defaults(stereo):
    with Recording.open(stereo) as rec:
        rig = rig_for(rec, stereo)
        assert isinstance(rig, StereoRig) and rig.kind == "stereo" and not rig.depth_only
        assert rig.camera == rec.stereo.left and rig.baseline_mm == rec.stereo.baseline_mm > 0
        assert rig.up is not None and rig.camera_frame_id == layout.LEFT_FRAME
        frames = list(rig.frames())
        assert len(frames) == 4 and len(list(rig.frames(2))) == 2
        for i, frame in enumerate(frames):
            expected = rec.rectified_frame(i)
            assert isinstance(frame, Frame) and frame.depth_mm is None and frame.stamp_ns == expected.stamp_ns
            np.testing.assert_array_equal(frame.left, expected.left)
            np.testing.assert_array_equal(frame.right, expected.right)
            np.testing.assert_array_equal(rig.image(i), expected.left)  # what processing saw
            np.testing.assert_array_equal(rig.motion_image(i), rec.left_image(i))  # as recorded
        assert rig.prompt(None).box == (20, 16, 140, 110) and rig.prompt("box:1,2,30,40").box == (1, 2, 30, 40)

        options = rig.stage_options(EngineOptions())
        assert (options.object_frame, options.depth, options.segment) == ("tissue", "sgbm", "colortrack")
        assert rig.stage_options(EngineOptions(object_frame="camera")).object_frame == "camera"
        with pytest.raises(InputError, match="RGB-D camera's own"):  # a pair has no sensor depth
            rig.stage_options(EngineOptions(depth="sensor"))
        engine = rig.engine(options, rig.prompt(None), look_ahead=4)
        assert (engine.camera, engine.baseline_mm) == (rig.camera, rig.baseline_mm)
        np.testing.assert_array_equal(engine.up, rig.up)
        ahead = engine.look_ahead  # the motion scan's left images, and any frame's rectified pair
        assert ahead.frames == 4 and len(list(ahead.scan_images())) == len(ahead.scan_indices) >= 1
        pair = ahead.pair(3)
        np.testing.assert_array_equal(pair[0], frames[3].left)
        np.testing.assert_array_equal(pair[1], frames[3].right)
        assert rig.engine(options, rig.prompt(None)).look_ahead is None

        shown = rig.view_messages(frames[0].stamp_ns, frames[0].left, None, lambda topic: True)
        assert [topic for topic, _ in shown] == [layout.LEFT_IMAGE, layout.LEFT_INFO]
        assert [topic for topic, _ in rig.view_messages(0, frames[0].left, None, NEVER)] == [layout.LEFT_INFO]
        np.testing.assert_allclose(np.asarray(shown[1][1].k).reshape(3, 3), rig.camera.K)


def test_an_rgbd_recording_gives_its_depth_drawn_grey_and_the_boards_defaults(rgbd):
    with Recording.open(rgbd) as rec:
        rig = rig_for(rec)
        assert isinstance(rig, RgbdRig) and rig.kind == "rgbd" and rig.depth_only and rig.path == rgbd
        assert rig.camera == rec.depth_camera and rig.baseline_mm == 0.0 and rig.up is None
        assert rig.camera_frame_id == layout.DEPTH_FRAME
        frames = list(rig.frames())
        assert len(frames) == 5
        first = rec.depth_mm(0)
        near, far = np.percentile(first[np.isfinite(first)], [1, 99])
        for i, frame in enumerate(frames):
            assert frame.right is None and frame.stamp_ns == rec.frame_times_ns[i]
            np.testing.assert_array_equal(frame.depth_mm, rec.depth_mm(i))
            assert frame.left.shape == (*frame.depth_mm.shape, 3) and frame.left.dtype == np.uint8
            np.testing.assert_array_equal(rig.image(i), frame.left)  # the preview's image is the engine's
            # near bright, far dark, on the first frame's scale for every frame
            grey = frame.left[..., 0].astype(float)
            known = np.isfinite(frame.depth_mm)
            assert np.corrcoef(grey[known], frame.depth_mm[known])[0, 1] < -0.9
            assert (grey[frame.depth_mm <= near] == 255).all() and (grey[frame.depth_mm >= far] == 0).all()
            assert (grey[~known] == 0).all()
        np.testing.assert_array_equal(rig.motion_image(2), rec.color_image(2))  # the colour view, where there is one

        options = rig.stage_options(EngineOptions())
        assert (options.depth, options.segment, options.object_frame) == ("sensor", "plane", "board")
        assert options.tracker_options == {"lambda_anchor": 1.0}
        assert rig.stage_options(EngineOptions(segment="sam2", object_frame="camera")).segment == "sam2"
        with pytest.raises(InputError, match="does not apply"):
            rig.stage_options(EngineOptions(object_frame="tissue"))
        with pytest.raises(InputError, match="brings its depth"):
            rig.stage_options(EngineOptions(depth="stereoanyvideo"))
        with pytest.raises(InputError, match="no right image"):
            rig.stage_options(EngineOptions(tracker="klt", tracker_options={"lift": "stereo"}))

        shown = rig.view_messages(frames[0].stamp_ns, frames[0].left, frames[0].depth_mm, lambda topic: True)
        assert [topic for topic, _ in shown] == [layout.DEPTH_IMAGE, layout.DEPTH_INFO]
        assert shown[1][1].frame_id == layout.DEPTH_FRAME


def test_running_and_stepping_a_rig_give_the_same_frames(rgbd):
    """One way to run a recording and one to step a frame, for either kind (here: a depth camera's)."""
    with Recording.open(rgbd) as rec:
        rig = rig_for(rec)
        options = rig.stage_options(EngineOptions(tracker="static", num_points=16))
        ran = list(rig.engine(options, rig.prompt(None)).run(rig.frames()))
        engine = rig.engine(options, rig.prompt(None))
        stepped = [engine.step(i, *frame) for i, frame in enumerate(rig.frames())]
    assert len(ran) == len(stepped) == 5
    for a, b in zip(ran, stepped, strict=True):
        assert a.stamp_ns == b.stamp_ns and a.mask.any()
        np.testing.assert_array_equal(a.mask, b.mask)
        np.testing.assert_array_equal(a.cloud_mm, b.cloud_mm)
        np.testing.assert_array_equal(a.points_mm, b.points_mm)


def test_a_camera_rig_has_no_recording_behind_it(stereo):
    with Recording.open(stereo) as rec:
        camera, baseline = rec.stereo.left, rec.stereo.baseline_mm
    rig = StereoRig("0", camera=camera, baseline_mm=baseline)
    assert (rig.camera, rig.baseline_mm, rig.up, rig.ground_truth(None)) == (camera, baseline, None, None)
    with pytest.raises(InputError, match="needs --prompt"):
        rig.prompt(None)
    engine = rig.engine(rig.stage_options(EngineOptions()), rig.prompt("box:20,16,140,110"), look_ahead=10)
    assert engine.look_ahead is None and engine.baseline_mm == baseline  # no frames to look ahead at
    with pytest.raises(InputError, match="camera model"):
        RgbdRig("camera")


def test_an_rgbd_recording_is_refused_where_a_stereo_one_is_needed(rgbd):
    with Recording.open(rgbd) as rec:
        with pytest.raises(InputError, match="not a stereo recording"):
            StereoRig(rgbd, rec).check()
        rig_for(rec).check()


def test_no_module_outside_the_recording_layer_and_the_rig_asks_an_inputs_kind():
    """A new kind of input is a rig (docs/architecture.md): the rest of the code asks the rig, never
    `is_rgbd` (a raw folder's `is_rgbd_folder`, for conversion, is another question)."""
    asked = []
    for path in sorted([*ROOT.glob("vfdata/**/*.py"), *ROOT.glob("vfmodels/**/*.py"), *ROOT.glob("bench/*.py")]):
        name = path.relative_to(ROOT).as_posix()
        if name.startswith(KIND_LAYER):
            continue
        asked += [f"{name}:{n}" for n, line in enumerate(path.read_text().splitlines(), 1)
                  if re.search(r"\bis_rgbd\b", line)]
    assert asked == []
    assert re.search(r"\bis_rgbd\b", (ROOT / "vfdata/rig.py").read_text())  # the test reads the real tree
