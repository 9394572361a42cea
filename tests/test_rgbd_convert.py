"""RGB-D raw folders -> recording MCAP (docs/raw_layout.md, "RGB-D recordings"): topics, depth kept
exactly in mm, info/check, one-line errors with nothing left behind."""

from __future__ import annotations

import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest

from tests.rgbd_fixtures import COLOR_SIZE, DEPTH_SIZE, make_rgbd
from vfdata.conversion.options import ConvertOptions
from vfdata.conversion.raw_rgbd import convert_rgbd_folder
from vfdata.errors import InputError
from vfdata.recording import Recording, layout
from vfdata.recording.inspect import check_file, info_text

QUIET = ConvertOptions(progress=False, workers=2)


def test_rgbd_folder_converts_with_realsense_topics_and_exact_depth(tmp_path):
    src = make_rgbd(tmp_path / "rec", n=6)
    out = convert_rgbd_folder(src, tmp_path / "rec.mcap", options=QUIET)
    rec = Recording.open(out)
    assert rec.is_rgbd and rec.num_frames == 6
    assert set(rec.topics) == {layout.DEPTH_IMAGE, layout.DEPTH_INFO, layout.COLOR_IMAGE, layout.COLOR_INFO,
                               layout.WRENCH, layout.TF_STATIC}
    assert rec.topics[layout.DEPTH_IMAGE].msgtype == "sensor_msgs/msg/Image"
    stored = cv2.imread(str(src / "depth" / "000003.png"), cv2.IMREAD_UNCHANGED).astype(np.float32)
    depth = rec.depth_mm(3)
    assert depth.shape == (DEPTH_SIZE, DEPTH_SIZE)
    np.testing.assert_array_equal(np.isnan(depth), stored == 0)
    np.testing.assert_array_equal(depth[stored > 0], stored[stored > 0])
    assert rec.color_image(3).shape == (COLOR_SIZE, COLOR_SIZE, 3)
    assert rec.camera == rec.depth_camera and rec.camera.cx == pytest.approx((DEPTH_SIZE - 1) / 2)
    assert rec.metadata.extra["depth_color_registered"] == "false"
    assert rec.message(layout.TF_STATIC, 0).transforms == []  # not registered: no transform claimed
    assert check_file(out) == []
    assert "layout: RGB-D (depth-to-colour transform unknown)" in info_text(out)


def test_depth_only_folder_and_a_known_transform(tmp_path):
    src = make_rgbd(tmp_path / "rec", n=4, color=False)
    with open(src / "rgbd_calibration.yaml", "a") as f:
        f.write("depth_to_color: {R: [[1, 0, 0], [0, 1, 0], [0, 0, 1]], T: [25.0, 0.7, -0.3]}\n")
    rec = Recording.open(convert_rgbd_folder(src, tmp_path / "rec.mcap", options=QUIET))
    assert not rec.has(layout.COLOR_IMAGE) and rec.num_frames == 4
    (tf,) = rec.message(layout.TF_STATIC, 0).transforms
    assert (tf.frame_id, tf.child_frame_id) == (layout.DEPTH_FRAME, layout.COLOR_FRAME)
    np.testing.assert_allclose(tf.translation, (-0.025, -0.0007, 0.0003))  # colour origin in depth coordinates
    assert check_file(tmp_path / "rec.mcap") == []


def _broken(tmp_path, how):
    src = make_rgbd(tmp_path / "rec", n=4)
    if how == "8bit":
        cv2.imwrite(str(src / "depth" / "000002.png"), np.zeros((DEPTH_SIZE, DEPTH_SIZE), np.uint8))
    elif how == "size":
        cv2.imwrite(str(src / "depth" / "000001.png"), np.ones((10, 12), np.uint16))
    elif how == "count":
        (src / "color" / "000003.png").unlink()
    elif how == "calibration":
        (src / "rgbd_calibration.yaml").unlink()
    elif how == "focal":
        text = (src / "rgbd_calibration.yaml").read_text().replace("fx: 80.0", "fx: -80.0", 1)
        (src / "rgbd_calibration.yaml").write_text(text)
    elif how == "frames":
        shutil.copy(src / "depth" / "000000.png", src / "depth" / "000009.png")
        shutil.copy(src / "color" / "000000.png", src / "color" / "000009.png")
    return src


@pytest.mark.parametrize(("how", "names", "says"), [
    ("8bit", "depth/000002.png", "16-bit single-channel"),
    ("size", "rgbd_calibration.yaml", "depth size 64x64 differs from depth/000001.png (12x10)"),
    ("count", "color", "3 frames but depth/ has 4"),
    ("calibration", "rgbd_calibration.yaml", "calibration file not found"),
    ("focal", "rgbd_calibration.yaml", "focal lengths"),
    ("frames", "frames.csv", "4 rows but the recording has 5 frames"),
])
def test_bad_rgbd_folders_are_one_line_errors_with_no_output(tmp_path, how, names, says):
    src = _broken(tmp_path, how)
    with pytest.raises(InputError) as err:
        convert_rgbd_folder(src, tmp_path / "out.mcap", options=QUIET)
    assert names in str(err.value) and says in str(err.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]


def test_cli_converts_with_calibration_and_meta_from_elsewhere(tmp_path):
    src = make_rgbd(tmp_path / "rec", n=3)
    (tmp_path / "cal.yaml").write_bytes((src / "rgbd_calibration.yaml").read_bytes())
    (src / "rgbd_calibration.yaml").unlink()
    (tmp_path / "meta.yaml").write_text("id: other_id\nstudy: elsewhere\n")
    before = sorted(p.name for p in src.rglob("*"))
    run = subprocess.run([sys.executable, "-m", "vfdata", "convert", str(src), str(tmp_path / "o.mcap"), "--quiet",
                          "--calibration", str(tmp_path / "cal.yaml"), "--meta", str(tmp_path / "meta.yaml")],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert sorted(p.name for p in src.rglob("*")) == before
    meta = Recording.open(tmp_path / "o.mcap").metadata
    assert (meta.recording_id, meta.study) == ("other_id", "elsewhere")
    bad = subprocess.run([sys.executable, "-m", "vfdata", "convert", str(src), str(tmp_path / "p.mcap"), "--quiet"],
                         capture_output=True, text=True)
    assert bad.returncode == 1 and len(bad.stderr.strip().splitlines()) == 1
    assert "rgbd_calibration.yaml: RGB-D calibration file not found" in bad.stderr
