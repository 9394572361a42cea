"""`vfdata process` on a short simulated recording: the derived MCAP's topics and contents against the
simulator's ground truth, provenance, and the errors a user can hit."""

from __future__ import annotations

import errno
import hashlib
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from vfdata.cli import main
from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder
from vfdata.errors import InputError
from vfdata.processing import ProcessOptions, process_recording
from vfdata.recording import Recording, layout
from vfdata.recording.derived import DERIVED_VERSION, DerivedRecording
from vfdata.recording.inspect import check_file
from vfdata.sim import synthesize

FRAMES = 6


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sim")
    synthesize("mini", root, seed=3, frames=FRAMES, progress=False)
    return convert_raw_folder(root / "mini_002", root / "mini_002.mcap", options=ConvertOptions(progress=False))


@pytest.fixture(scope="module")
def processed(recording) -> Path:
    return process_recording(recording, options=ProcessOptions(progress=False))


def test_derived_file_layout_and_provenance(recording, processed):
    assert processed == recording.with_name("mini_002.processed.mcap")
    assert check_file(processed) == []
    rec = Recording.open(processed)
    counts = {topic: info.count for topic, info in rec.topics.items()}
    assert counts == {layout.TISSUE_MASK: FRAMES, layout.TISSUE_DEPTH: FRAMES, layout.TISSUE_POINTS: FRAMES,
                      layout.TRACKING_POINTS: FRAMES, layout.TF_STATIC: 1}
    np.testing.assert_array_equal(rec.log_times_ns(layout.TISSUE_MASK), Recording.open(recording).frame_times_ns)
    meta = rec.metadata_records[layout.DERIVED_METADATA]
    assert meta["source_sha256"] == hashlib.sha256(recording.read_bytes()).hexdigest()
    assert meta["depth"] == "sgbm" and meta["tracker"] == "geometry" and meta["up_known"] == "true"
    assert meta["origin_cut_by_view"] == "false"  # the mini tissue is whole in view
    assert set(json.loads(meta["stage_fps"])) >= {"depth", "mask", "cloud", "tracking"}


def test_mask_depth_and_object_frame_match_ground_truth(recording, processed):
    derived = DerivedRecording.open(processed)
    assert derived.num_frames == FRAMES and derived.meta.version == DERIVED_VERSION
    gt = Path(Recording.open(recording).metadata.source) / "ground_truth"
    for i in (0, FRAMES - 1):
        mask = derived.mask(i)
        true_mask = cv2.imread(str(gt / "mask" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
        assert (mask & true_mask).sum() / (mask | true_mask).sum() > 0.85
        depth = derived.depth_mm(i)
        true_depth = cv2.imread(str(gt / "depth" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED) * 0.1
        inside = true_mask & np.isfinite(depth)
        assert np.median(np.abs(depth[inside] - true_depth[inside]) / true_depth[inside]) < 0.03
    truth = json.loads((gt / "object_frame.json").read_text())
    z, true_z = derived.object_frame.z_axis, np.asarray(truth["rotation"])[:, 2]
    assert np.degrees(np.arccos(np.clip(z @ true_z, -1, 1))) < 5.0


def test_tracks_are_256_points_in_the_object_frame(processed):
    rec = Recording.open(processed)
    tf = rec.message(layout.TF_STATIC, 0).transforms[0]
    assert (tf.frame_id, tf.child_frame_id) == (layout.LEFT_FRAME, layout.OBJECT_FRAME)
    first = rec.message(layout.TRACKING_POINTS, 0)
    assert first.frame_id == layout.OBJECT_FRAME and len(first.points) == 256
    assert set(first.points.dtype.names) == {"x", "y", "z", "visible"}
    assert 0.005 < np.ptp(first.points["z"]) < 0.2  # REP 103: metres (the mini tissue is ~60 mm long)
    tracks = DerivedRecording.open(processed).tracks()
    z = tracks.points_object_mm[0, :, 2]
    assert np.percentile(z, 2) == pytest.approx(0.0, abs=1.0)  # origin at the 2nd percentile along Z
    assert tracks.visible[0].mean() > 0.9
    moved = np.linalg.norm(tracks.points_object_mm[-1] - tracks.points_object_mm[0], axis=1)
    assert np.isfinite(moved).all() and moved.max() < 30.0


def test_depth_is_16uc1_millimetres(processed):
    """REP 118: 16UC1 depth images are millimetres."""
    image = Recording.open(processed).message(layout.TISSUE_DEPTH, 0)
    data = np.frombuffer(image.data, "<u2")
    assert image.encoding == "16UC1" and 40 < np.median(data[data > 0]) < 300  # the mini tissue at ~90 mm


def test_first_frame_preview_beside_the_derived_file(recording, processed):
    """The picture of the first frame's decisions: the left image with the mask tinted green and the
    object frame's axes drawn from its projected origin (Z in blue, toward the narrow end)."""
    preview = cv2.imread(str(processed.with_name("mini_002.processed.png")))
    left = Recording.open(recording).rectified_frame(0).left
    assert preview.shape == left.shape
    mask = DerivedRecording.open(processed).mask(0)
    mask[:50] = False  # the labels' band
    tint = preview[mask].astype(float) - left[mask].astype(float)
    assert tint[:, 1].mean() > 15 and tint[:, 2].mean() < 0  # greener, less red
    frame = DerivedRecording.open(processed).object_frame
    rotation, origin = frame.rotation, frame.origin
    camera = Recording.open(recording).camera
    u, v = camera.project((origin + 0.7 * 20.0 * rotation[:, 2])[None])[0]  # on the Z arrow
    b, g, r = preview[int(round(v)), int(round(u))].astype(int)
    assert b > 150 and b > r + 60, (b, g, r)


def test_source_is_never_modified(recording, processed, tmp_path):
    before = hashlib.sha256(recording.read_bytes()).hexdigest()
    out = tmp_path / "again.processed.mcap"  # not the shared fixture's file, which later tests read whole
    process_recording(recording, out, ProcessOptions(progress=False, tracker="none", max_frames=2))
    assert hashlib.sha256(recording.read_bytes()).hexdigest() == before
    assert layout.TRACKING_POINTS not in Recording.open(out).topics


@pytest.mark.parametrize("argv, message", [
    (["--depth", "nosuch"], "nosuch"),
    (["--segment", "sam2"], "sam2"),
    (["--prompt", "box:10,10,5000,40"], "outside"),
    (["--prompt", "box:2,2,12,12"], "empty"),
])
def test_errors_are_one_line(recording, tmp_path, capsys, argv, message):
    out = tmp_path / "out.mcap"
    code = main(["process", "--quiet", "--max-frames", "2", str(recording), str(out), *argv])
    err = capsys.readouterr().err.strip()
    assert code == 1 and len(err.splitlines()) == 1 and message in err, err
    assert list(tmp_path.iterdir()) == []


def _full_disk_for_png(monkeypatch) -> None:
    """A disk that fills up when the preview PNG is written (the derived MCAP fits)."""
    write_bytes = Path.write_bytes

    def full(self, data):
        if ".png" in self.name:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))
        return write_bytes(self, data)

    monkeypatch.setattr(Path, "write_bytes", full)


def test_a_full_disk_at_the_preview_leaves_neither_output(recording, tmp_path, capsys, monkeypatch):
    """The derived MCAP and its picture are one transaction: no MCAP without its picture, and with
    --overwrite the older pair stays as it was."""
    _full_disk_for_png(monkeypatch)
    out = tmp_path / "x.processed.mcap"
    argv = ["process", "--quiet", "--tracker", "none", "--max-frames", "2", str(recording), str(out)]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"vfdata process: error: {tmp_path / 'x.processed.png'}: no space left on the device (or quota " \
                  "exceeded); nothing was written: free some space or write the output elsewhere", err
    assert list(tmp_path.iterdir()) == []
    out.write_bytes(b"older mcap")
    with open(tmp_path / "x.processed.png", "wb") as picture:  # past the full disk, which only Path.write_bytes has
        picture.write(b"its picture")
    assert main([*argv, "--overwrite"]) == 1
    assert out.read_bytes() == b"older mcap" and (tmp_path / "x.processed.png").read_bytes() == b"its picture"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.processed.mcap", "x.processed.png"]


def test_source_without_images_is_refused(processed, tmp_path, capsys):
    assert main(["process", "--quiet", str(processed), str(tmp_path / "x.mcap")]) == 1
    assert "not a stereo recording" in capsys.readouterr().err


def test_the_source_cannot_be_the_output(recording, tmp_path, capsys):
    before = recording.read_bytes()
    assert main(["process", "--quiet", "--overwrite", "--max-frames", "2", str(recording), str(recording)]) == 1
    assert "input" in capsys.readouterr().err
    assert recording.read_bytes() == before


def test_one_thread_by_default_and_the_callers_counts_restored(recording, processed, tmp_path):
    """The thread policy (vfdata/threads.py): processing runs with one torch thread unless asked for
    another, records the count beside its stage rates and leaves the caller's setting as it was."""
    import torch

    meta = Recording.open(processed).metadata_records[layout.DERIVED_METADATA]
    assert meta["stage_threads"] == "1" and int(meta["stage_cores"]) >= 1 and float(meta["stage_load_1min"]) >= 0
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        out = process_recording(recording, tmp_path / "t.processed.mcap",
                                ProcessOptions(progress=False, threads=2, max_frames=2))
        assert torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(before)
    assert Recording.open(out).metadata_records[layout.DERIVED_METADATA]["stage_threads"] == "2"
    with pytest.raises(SystemExit):
        main(["process", str(recording), str(tmp_path / "u.mcap"), "--threads", "0"])


def test_set_threads_reaches_torch_loaded_before_or_after_and_loads_no_torch_itself():
    """Every command and worker sets its threads through `vfdata.threads.set_threads`: a simulator worker
    that never needs torch must not load it, and torch loaded later takes the count from OMP_NUM_THREADS."""
    import subprocess
    import sys

    code = ("import sys; from vfdata.threads import set_threads; set_threads(1); "
            "loaded = 'torch' in sys.modules; import torch; before = torch.get_num_threads(); "
            "set_threads(2); print(loaded, before, torch.get_num_threads())")
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    assert out.stdout.split() == ["False", "1", "2"]


def test_a_derived_file_reads_like_a_recording(processed):
    """frame(i) holds what the file has for that frame; metadata values come typed."""
    derived = DerivedRecording.open(processed)
    assert derived.num_frames == FRAMES
    last = derived.frame(-1)
    assert last.index == FRAMES - 1 and last.stamp_ns == derived.frame_times_ns[-1]
    np.testing.assert_array_equal(last.mask, derived.mask(FRAMES - 1))
    assert last.points_mm.shape == (256, 3) and last.visible.shape == (256,) and last.cloud_mm.shape[1] == 3
    assert [f.index for f in derived.frames()] == list(range(FRAMES))
    with pytest.raises(IndexError):
        derived.frame(FRAMES)
    assert derived.meta.number("frames") == FRAMES and derived.meta.number("stage_threads") == 1
    assert derived.meta.value("up_known") is True and isinstance(derived.meta.value("stage_fps"), dict)
    assert derived.meta.typed()["depth"] == "sgbm"
    with pytest.raises(InputError):
        derived.meta.number("depth")


def test_the_foxglove_layout_names_what_the_files_hold(recording, processed):
    """docs/foxglove_layout.json (a recording and its derived file opened together) names only topics
    the two files have (and the estimate, its band, its distance beyond training and how unlike training's
    its input is, of a .force.mcap),
    wherever in the layout they appear."""
    layout_file = json.loads((Path(__file__).resolve().parents[1] / "docs" / "foxglove_layout.json").read_text())
    topics = {*Recording.open(recording).topics, *Recording.open(processed).topics, layout.FORCE_ESTIMATE,
              layout.FORCE_BAND, layout.FORCE_BEYOND, layout.FORCE_UNLIKE}
    named = set()

    def walk(node) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                if key == "topics" and isinstance(value, dict):
                    named.update(value)
                elif key in ("imageTopic", "calibrationTopic", "topic") and isinstance(value, str):
                    named.add(value)
                elif key == "value" and isinstance(value, str) and value.startswith("/"):
                    named.add(value.split(".", 1)[0])
                walk(value)
        elif isinstance(node, list):
            for item in node:
                walk(item)

    walk(layout_file)
    assert named and named <= topics, named - topics


def test_timing_says_how_the_rates_were_measured(recording, processed):
    from vfdata.manifest import ManifestEntry
    from vfmodels.experiment.report import rate_conditions

    entry = ManifestEntry("mini_002", 90.0, "test", recording.parent / "mini_002", recording, processed)
    line = rate_conditions([entry], "geometry")
    meta = Recording.open(processed).metadata_records[layout.DERIVED_METADATA]
    assert f"{meta['stage_threads']} torch thread" in line and f"{meta['stage_cores']} core" in line


def test_the_papers_frame_on_request_is_the_papers_search_on_the_first_cloud(recording, processed, tmp_path):
    """`--object-frame paper` reproduces the paper: `estimate_object_frame` on the first frame's cloud,
    which the default (`tissue`) only takes as one of its fits."""
    from vfdata.recon.object_frame import estimate_object_frame

    out = tmp_path / "paper.processed.mcap"
    assert main(["process", str(recording), str(out), "--object-frame", "paper", "--tracker", "none", "--quiet"]) == 0
    derived = DerivedRecording.open(out)
    cloud = derived.frame(0).cloud_mm  # object frame, float32 as written
    expected = estimate_object_frame(derived.object_frame.to_camera(cloud), derived.object_frame.rotation[:, 0])
    np.testing.assert_allclose(derived.object_frame.z_axis, expected.z_axis, atol=1e-3)
    assert "axis_fits" not in derived.meta.json("object_frame_check", {})  # none of the product's checks ran
    assert "axis_fits" in DerivedRecording.open(processed).meta.json("object_frame_check", {})


def test_the_stereo_lift_of_klt_gets_the_right_images(recording, tmp_path):
    """`--tracker klt --tracker-options lift=stereo`: the engine hands each frame's right image to the
    tracker, which lifts the same 2D tracks by their own stereo match (docs/tracking.md)."""
    tracks = {}
    for lift in ("depth", "stereo"):
        out = tmp_path / f"{lift}.processed.mcap"
        assert main(["process", str(recording), str(out), "--tracker", "klt", "--tracker-options", f"lift={lift}",
                     "--points", "64", "--quiet"]) == 0
        derived = DerivedRecording.open(out)
        assert json.loads(derived.meta.get("tracker_parameters"))["lift"] == lift
        written = derived.tracks()
        tracks[lift] = [written.points_camera_mm(i) for i in range(FRAMES)]
    camera = Recording.open(recording).camera
    for f in (0, FRAMES - 1):
        depth, stereo = tracks["depth"][f], tracks["stereo"][f]
        seen = np.isfinite(depth).all(axis=1) & np.isfinite(stereo).all(axis=1)
        assert seen.mean() > 0.8
        # The same 2D tracks (the same rays), lifted to other depths where the stereo match was taken.
        np.testing.assert_allclose(camera.project(stereo[seen]), camera.project(depth[seen]), atol=1e-2)
        assert np.mean(np.abs(stereo[seen, 2] - depth[seen, 2]) > 1e-3) > 0.3
