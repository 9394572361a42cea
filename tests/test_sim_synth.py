"""`vfdata synth` end to end on the mini preset (few frames): the raw layout `vfdata convert` reads,
the ground truth, the manifest, and byte-identical output whatever the number of workers."""

from __future__ import annotations

import filecmp
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from vfdata.calibration import StereoCalibration
from vfdata.cli import main
from vfdata.errors import OutputExistsError
from vfdata.sim import synthesize
from vfdata.sim.presets import PRESETS

FRAMES = 4
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def mini(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("mini")
    synthesize("mini", out, seed=0, workers=1, progress=False, frames=FRAMES)
    return out


def _same_tree(a: Path, b: Path) -> bool:
    files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    if files_a != files_b:
        return False
    return all(filecmp.cmp(a / f, b / f, shallow=False) for f in files_a)


def test_manifest_matches_the_committed_ones(mini):
    written = yaml.safe_load((mini / "mini.manifest.yaml").read_text())
    assert written["name"] == "mini" and written["root"] == "."
    for name in PRESETS:
        committed = yaml.safe_load((REPO / "datasets" / f"{name}.manifest.yaml").read_text())
        assert committed["root"] == f"../data/{name}"
        from vfdata.sim.synthesize import manifest
        assert committed["recordings"] == manifest(PRESETS[name], ".")["recordings"]
    committed = yaml.safe_load((REPO / "datasets" / "mini.manifest.yaml").read_text())
    assert committed["recordings"] == written["recordings"]
    splits = {r["split"] for r in written["recordings"]}
    assert splits == {"train", "val", "test"}
    test_orient = {r["orientation_deg"] for r in written["recordings"] if r["split"] == "test"}
    assert test_orient and 0 not in test_orient


def test_raw_layout(mini):
    rec = mini / "mini_000"
    left = sorted((rec / "left").iterdir())
    assert [p.name for p in left] == [f"{i:06d}.jpg" for i in range(FRAMES)]
    assert sorted(p.name for p in (rec / "right").iterdir()) == [p.name for p in left]
    assert left[0].read_bytes()[:3] == b"\xff\xd8\xff"  # JPEG
    img = cv2.imread(str(left[0]), cv2.IMREAD_UNCHANGED)
    assert img.shape == (512, 640, 3) and img.dtype == np.uint8

    frames = np.loadtxt(rec / "frames.csv", delimiter=",", skiprows=1, dtype=np.int64)
    assert (rec / "frames.csv").read_text().splitlines()[0] == "frame,timestamp_ns"
    np.testing.assert_array_equal(frames[:, 0], np.arange(FRAMES))
    np.testing.assert_allclose(np.diff(frames[:, 1]), 1e9 / 30, atol=1)

    assert (rec / "force.csv").read_text().splitlines()[0] == "timestamp_ns,fx,fy,fz,tx,ty,tz"
    force = np.loadtxt(rec / "force.csv", delimiter=",", skiprows=1)
    stamps = force[:, 0].astype(np.int64)
    assert (np.diff(stamps) > 0).all()
    assert abs(np.median(np.diff(stamps)) - 1e6) < 2e4  # 1 kHz
    assert stamps[0] < frames[0, 1] and stamps[-1] > frames[-1, 1]  # covers the video
    offset = abs(stamps - frames[0, 1]).min()
    assert offset > 0  # the sensor has its own clock

    pose = np.loadtxt(rec / "ecm_pose.csv", delimiter=",", skiprows=1)
    assert (rec / "ecm_pose.csv").read_text().splitlines()[0] == "timestamp_ns,x,y,z,qx,qy,qz,qw"
    assert pose.shape == (FRAMES, 8)
    np.testing.assert_allclose(np.linalg.norm(pose[:, 4:], axis=1), 1, atol=1e-6)
    assert (np.abs(pose[:, 1:4]) < 1).all()  # metres

    calib = StereoCalibration.load(rec / "calibration.yaml")
    assert calib.is_rectified
    assert 4 <= calib.rectified.baseline_mm <= 5
    assert (calib.width, calib.height) == (640, 512)

    meta = yaml.safe_load((rec / "meta.yaml").read_text())
    assert meta["study"] == "glove" and meta["split"] == "train" and meta["orientation_deg"] == 0
    x0, y0, x1, y1 = meta["prompt_box"]
    mask0 = cv2.imread(str(rec / "ground_truth/mask/000000.png"), cv2.IMREAD_UNCHANGED)
    ys, xs = np.nonzero(mask0)
    assert (x0, y0, x1, y1) == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)


def test_ground_truth(mini):
    gt = mini / "mini_000" / "ground_truth"
    mask = cv2.imread(str(gt / "mask/000001.png"), cv2.IMREAD_UNCHANGED)
    depth = cv2.imread(str(gt / "depth/000001.png"), cv2.IMREAD_UNCHANGED)
    assert mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255} and (mask == 255).sum() > 3000
    assert depth.dtype == np.uint16 and depth.shape == (512, 640)
    tube_depth_mm = depth[mask == 255] / 10.0
    assert 40 < np.median(tube_depth_mm) < 150

    points = np.load(gt / "points.npy")
    normals = np.load(gt / "normals.npy")
    visible = np.load(gt / "visible.npy")
    force = np.load(gt / "force.npy")
    assert points.shape == (FRAMES, 2000, 3) and points.dtype == np.float32
    assert normals.shape == points.shape and visible.shape == (FRAMES, 2000) and visible.dtype == bool
    assert force.shape == (FRAMES, 3)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=2), 1, atol=1e-4)
    assert 0.2 < visible.mean() < 0.7
    # Visible points project inside the mask at their ground-truth depth.
    calib = StereoCalibration.load(gt.parent / "calibration.yaml")
    cam = calib.rectified.left
    inside = cam.in_mask(points[1][visible[1]], mask > 0)
    assert inside.mean() > 0.98

    frame = json.loads((gt / "object_frame.json").read_text())
    r = np.array(frame["rotation"])
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-6)
    np.testing.assert_allclose(np.cross(r[:, 2], r[:, 0]), r[:, 1], atol=1e-6)  # Y = Z x X
    # X is up: the world's +Z seen from the camera (ECM pose) is the object frame's X.
    pose = np.loadtxt(gt.parent / "ecm_pose.csv", delimiter=",", skiprows=1)[0]
    qx, qy, qz, qw = pose[4:]
    r_wc = np.array([
        [1 - 2 * (qy**2 + qz**2), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
        [2 * (qx * qy + qz * qw), 1 - 2 * (qx**2 + qz**2), 2 * (qy * qz - qx * qw)],
        [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx**2 + qy**2)],
    ])
    np.testing.assert_allclose(r_wc.T @ [0, 0, 1], r[:, 0], atol=1e-6)
    # The material points start near the tube axis, within the tube's reach along Z.
    local = (points[0] - np.array(frame["origin_mm"])) @ r
    params = json.loads((gt / "params.json").read_text())
    assert local[:, 2].min() > 0 and local[:, 2].max() < params["tube"]["length_mm"] + 1
    assert np.abs(local[:, :2]).max() < params["tube"]["base_radius_mm"] + 2
    assert "sensor" in frame and len(frame["sensor"]["origin_mm"]) == 3


def test_deterministic_whatever_the_workers(mini, tmp_path):
    synthesize("mini", tmp_path, seed=0, workers=2, progress=False, frames=FRAMES)
    assert _same_tree(mini, tmp_path)


def test_seed_changes_the_data(mini, tmp_path):
    synthesize("mini", tmp_path, seed=1, workers=1, progress=False, frames=2)
    a = (mini / "mini_000/left/000000.jpg").read_bytes()
    b = (tmp_path / "mini_000/left/000000.jpg").read_bytes()
    assert a != b


def test_png_frames_on_request_are_the_lossless_originals(mini, tmp_path):
    """--image-format png writes the very frames the JPEGs compress; the ground truth is the same."""
    synthesize("mini", tmp_path, seed=0, workers=1, progress=False, frames=2, image_format="png")
    rec, jpeg_rec = tmp_path / "mini_001", mini / "mini_001"
    assert sorted(p.name for p in (rec / "left").iterdir()) == ["000000.png", "000001.png"]
    png = cv2.imread(str(rec / "left/000001.png"))
    jpeg = cv2.imread(str(jpeg_rec / "left/000001.jpg"))
    assert not np.array_equal(png, jpeg)
    assert np.abs(png.astype(int) - jpeg).mean() < 2.0  # quality 95: close to the original
    for gt in ("mask/000001.png", "depth/000001.png"):
        assert (rec / "ground_truth" / gt).read_bytes() == (jpeg_rec / "ground_truth" / gt).read_bytes()
    # A folder made with the other format is not mistaken for a finished one.
    with pytest.raises(OutputExistsError):
        synthesize("mini", tmp_path, seed=0, workers=1, progress=False, frames=2)


def test_existing_output_is_kept_or_refused(mini, tmp_path, capsys):
    # Same settings: nothing to redo. Other settings: refused without --overwrite.
    synthesize("mini", mini, seed=0, workers=1, progress=False, frames=FRAMES)
    with pytest.raises(OutputExistsError):
        synthesize("mini", mini, seed=5, workers=1, progress=False, frames=FRAMES)
    assert main(["synth", "--preset", "mini", str(mini), "--seed", "5", "--frames", "2"]) == 1
    assert "output exists" in capsys.readouterr().err


def test_cli_writes_the_manifest(tmp_path, capsys):
    assert main(["synth", "--preset", "mini", str(tmp_path / "d"), "--frames", "1"]) == 0
    assert capsys.readouterr().out.strip().endswith("mini.manifest.yaml")
    assert (tmp_path / "d" / "mini_002" / "left" / "000000.jpg").is_file()
    assert main(["synth", "--preset", "mini", str(tmp_path / "p"), "--frames", "1", "--image-format", "png"]) == 0
    assert (tmp_path / "p" / "mini_002" / "left" / "000000.png").is_file()


def test_test_orientations_spread_over_the_test_recordings():
    from vfdata.errors import VisionForceError
    from vfdata.sim.presets import with_test_orientations

    glove = PRESETS["glove"]
    # The preset's own orientations are this very spread.
    assert with_test_orientations(glove, [90, 180]) == glove
    turned = with_test_orientations(glove, [0, 60, 120])
    assert [(r.id, r.orientation_deg) for r in turned.recordings if r.split == "test"] == [
        ("glove_016", 0.0), ("glove_017", 0.0), ("glove_018", 60.0), ("glove_019", 120.0)]
    # Only the test recordings turn; their number, ids and lengths stay.
    for before, after in zip(glove.recordings, turned.recordings, strict=True):
        assert (before.id, before.split, before.frames) == (after.id, after.split, after.frames)
        assert before.split == "test" or before.orientation_deg == after.orientation_deg
    # More orientations than test recordings: one more recording of the same length per extra angle.
    colon = with_test_orientations(PRESETS["colon"], [60, 135, 270])
    tests = [(r.id, r.orientation_deg, r.frames) for r in colon.recordings if r.split == "test"]
    assert tests == [("colon_006", 60.0, 398), ("colon_007", 135.0, 398), ("colon_008", 270.0, 398)]
    assert len({r.index for r in colon.recordings}) == len(colon.recordings)
    with pytest.raises(VisionForceError, match="at least one"):
        with_test_orientations(glove, [])


def test_a_turned_test_recording_is_seen_from_elsewhere():
    from dataclasses import replace

    from vfdata.sim.simulation import build_recording

    plan = PRESETS["mini"].recordings[2]
    at = {deg: build_recording(replace(plan, orientation_deg=deg), seed=0, frames=2) for deg in (0.0, 60.0)}
    # The scope looks from the same side of the room, at another point: along the turned tissue.
    assert not np.allclose(at[0.0].spec.cam.position_w_mm, at[60.0].spec.cam.position_w_mm)
    r_co = {deg: rec.spec.object_to_camera()[0] for deg, rec in at.items()}
    assert not np.allclose(r_co[0.0], r_co[60.0])  # the tissue lies otherwise in the image


def test_cli_test_orientations_reach_the_manifest_and_the_metadata(tmp_path, capsys):
    out = tmp_path / "turned"
    assert main(["synth", "--preset", "mini", str(out), "--frames", "1", "--test-orientations", "60"]) == 0
    manifest = yaml.safe_load((out / "mini.manifest.yaml").read_text())
    assert [(r["id"], r["orientation_deg"]) for r in manifest["recordings"]] == [
        ("mini_000", 0), ("mini_001", 0), ("mini_002", 60)]
    meta = yaml.safe_load((out / "mini_002" / "meta.yaml").read_text())
    assert meta["orientation_deg"] == 60 and "--test-orientations 60" in meta["source"]
    assert json.loads((out / "mini_002/ground_truth/params.json").read_text())["orientation_deg"] == 60
    # The same folder at the preset's orientation is another recording: refused, not kept.
    assert main(["synth", "--preset", "mini", str(out), "--frames", "1"]) == 1
    assert "mini_002: output exists" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["synth", "--preset", "mini", str(out), "--test-orientations", "ninety"])
    assert "not a comma-separated list of degrees" in capsys.readouterr().err


def test_train_recordings_add_or_drop_tissues_and_keep_the_rest():
    from vfdata.errors import VisionForceError
    from vfdata.sim.presets import get_preset, with_train_recordings

    colon = PRESETS["colon"]
    more = with_train_recordings(colon, 8)
    trains = [(r.id, r.index, r.orientation_deg, r.frames) for r in more.recordings if r.split == "train"]
    # The preset's five, then three new ones after every other recording, each its own index (its draws).
    assert trains == [(f"colon_{k:03d}", k, 0.0, 742) for k in range(5)] + \
        [(f"colon_{k:03d}", k, 0.0, 742) for k in (8, 9, 10)]
    # Validation and test recordings are the very same plans.
    assert [r for r in more.recordings if r.split != "train"] == [r for r in colon.recordings if r.split != "train"]
    fewer = with_train_recordings(colon, 2)
    assert [r.id for r in fewer.recordings] == ["colon_000", "colon_001", "colon_005", "colon_006", "colon_007"]
    assert with_train_recordings(colon, 5) == colon
    # With test orientations that add test recordings, new tissues come after those.
    both = get_preset("colon", [60, 135, 270], {"train": 6})
    assert [r.id for r in both.recordings][-2:] == ["colon_008", "colon_009"]
    assert both.recordings[-1].split == "train"
    for bad in (0, -1, 2.5, True):
        with pytest.raises(VisionForceError, match="number of recordings"):
            with_train_recordings(colon, bad)
    # Validation tissues likewise, after the new training ones.
    three = get_preset("colon", None, {"train": 6, "val": 3})
    assert [(r.id, r.split) for r in three.recordings][-3:] == [
        ("colon_008", "train"), ("colon_009", "val"), ("colon_010", "val")]
    assert [r for r in three.recordings if r.split == "test"] == [r for r in colon.recordings if r.split == "test"]


def test_cli_train_recordings_reach_the_manifest_and_the_metadata(tmp_path, capsys):
    out = tmp_path / "more"
    assert main(["synth", "--preset", "mini", str(out), "--frames", "1", "--train-recordings", "2",
                 "--val-recordings", "2"]) == 0
    manifest = yaml.safe_load((out / "mini.manifest.yaml").read_text())
    assert [(r["id"], r["split"]) for r in manifest["recordings"]] == [
        ("mini_000", "train"), ("mini_001", "val"), ("mini_002", "test"), ("mini_003", "train"), ("mini_004", "val")]
    meta = yaml.safe_load((out / "mini_003" / "meta.yaml").read_text())
    assert meta["split"] == "train" and "--train-recordings 2 --val-recordings 2" in meta["source"]
    params = {k: json.loads((out / f"mini_00{k}/ground_truth/params.json").read_text()) for k in (0, 3)}
    assert params[3]["material"] != params[0]["material"]  # another tissue, not a copy
    with pytest.raises(SystemExit):
        main(["synth", "--preset", "mini", str(out), "--train-recordings", "0"])
    assert "not a number of recordings >= 1" in capsys.readouterr().err
