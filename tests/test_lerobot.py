"""LeRobot datasets in (`vfdata convert DATASET`) and out (`vfdata export --lerobot`), on small
datasets the tests write themselves (tests/lerobot_fixtures.py) and small raw recordings. The check
against LeRobot's own reader is in test_lerobot_slow.py."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
from lerobot_fixtures import FPS, calibration, force, image, level, write_dataset, write_mp4
from rawfixtures import make_raw

from vfdata.cli import main
from vfdata.conversion.lerobot_dataset import convert_lerobot_dataset, parse_splits
from vfdata.conversion.lerobot_episodes import convert_lerobot_episode
from vfdata.conversion.raw_folder import convert_raw_folder
from vfdata.errors import InputError
from vfdata.lerobot import features as names
from vfdata.lerobot.export import ExportOptions, export_lerobot
from vfdata.lerobot.features import choose_features, parse_topics
from vfdata.lerobot.folder import read_dataset
from vfdata.lerobot.video import psnr_db
from vfdata.lerobot.windows import pack_windows, unpack_windows, window_length
from vfdata.manifest import load_manifest
from vfdata.recon.object_frame import ObjectFrame
from vfdata.recording import Recording
from vfdata.recording.derived import DerivedWriter, write_force_estimate
from vfdata.recording.inspect import check_file
from vfmodels.experiment.prepare import convert as prepare_convert

QUIET = dict(progress=False)


def tree_digest(root: Path) -> str:
    digest = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        digest.update(str(path.relative_to(root)).encode() + path.read_bytes())
    return digest.hexdigest()


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".tmp-" in p.name)


# -- windows --------------------------------------------------------------------------------------
def test_force_windows_give_back_every_sample_of_the_span_exactly():
    rng = np.random.default_rng(0)
    frame_ns = 1_000_000_000 + np.cumsum(rng.integers(30_000_000, 36_000_000, 40))
    force_ns = np.sort(rng.integers(frame_ns[0] - 100_000_000, frame_ns[-1] + 100_000_000, 3000))
    force_ns = np.unique(force_ns)
    wrench = rng.normal(size=(len(force_ns), 6))
    period = 33_333_333
    length = window_length(frame_ns, force_ns, period)
    samples, stamps, counts = pack_windows(frame_ns, force_ns, wrench, period, length)
    back_ns, back = unpack_windows(samples, stamps, counts)
    span = (force_ns > frame_ns[0] - period) & (force_ns <= frame_ns[-1])
    assert np.array_equal(back_ns, force_ns[span]) and np.array_equal(back, wrench[span])
    # frame k holds the samples after frame k-1 and up to its own stamp
    k = 10
    mine = stamps[k, : counts[k]]
    assert (mine > frame_ns[k - 1]).all() and (mine <= frame_ns[k]).all()
    assert (samples[k, counts[k]:] == 0).all()


# -- which features -------------------------------------------------------------------------------
def test_features_are_found_by_name_and_open_h_prefers_the_endoscope_pair(tmp_path):
    ds = read_dataset(write_dataset(tmp_path / "a", views=("observation.images.endoscope.left",
                                                           "observation.images.endoscope.right"),
                                    extra_views=("observation.images.wrist.left", "observation.images.wrist.right")))
    choice = choose_features(ds)
    assert (choice.left, choice.right) == ("observation.images.endoscope.left", "observation.images.endoscope.right")
    assert choice.force == names.FORCE and choice.force_columns == (0, 1, 2, 3, 4, 5)
    assert choice.pose == "observation.state" and not choice.samples and choice.stamp is None


def test_two_pairs_without_an_endoscope_are_an_error_listing_both(tmp_path):
    ds = read_dataset(write_dataset(tmp_path / "a", views=("observation.images.cam_left",
                                                           "observation.images.cam_right"),
                                    extra_views=("observation.images.wrist_left", "observation.images.wrist_right")))
    with pytest.raises(InputError, match="several stereo pairs.*cam_left.*wrist_left.*--topics left="):
        choose_features(ds)
    choice = choose_features(ds, parse_topics(["left=observation.images.wrist_left"]))
    assert choice.right == "observation.images.wrist_right"


def test_a_force_named_otherwise_is_found_by_its_names_and_ordered_by_them(tmp_path):
    ds = read_dataset(write_dataset(tmp_path / "a", force_key="observation.wrench",
                                    force_names=["tx", "ty", "tz", "fx", "fy", "fz"]))
    choice = choose_features(ds)
    assert choice.force == "observation.wrench" and choice.force_columns == (3, 4, 5, 0, 1, 2)


def test_without_a_force_the_error_says_how_to_name_one(tmp_path):
    root = write_dataset(tmp_path / "a", force_key="observation.effort", force_names=["a", "b", "c", "d", "e", "f"])
    with pytest.raises(InputError, match="info.json: no observation.meta.force_torque.*--topics force=FEATURE"):
        choose_features(read_dataset(root))


# -- LeRobot in ------------------------------------------------------------------------------------
@pytest.mark.parametrize("version", ["v3.0", "v2.1"])
def test_every_episode_converts_with_its_frames_force_pose_and_a_manifest(tmp_path, version):
    root = write_dataset(tmp_path / "ds", version, episodes=3, frames=8,
                         splits={"train": "0:1", "validation": "1:2", "test": "2:3"})
    before = tree_digest(root)
    manifest = convert_lerobot_dataset(root, tmp_path / "out", options=_options())
    assert tree_digest(root) == before
    entries = load_manifest(manifest).entries
    assert [(e.id, e.split, e.episode) for e in entries] == [("ds_episode_000000", "train", 0),
                                                             ("ds_episode_000001", "val", 1),
                                                             ("ds_episode_000002", "test", 2)]
    for e, entry in enumerate(entries):
        assert check_file(entry.mcap) == []
        with Recording.open(entry.mcap) as rec:
            assert rec.num_frames == 8
            assert np.abs(rec.frame_times_ns - np.arange(8) * 1e9 / FPS).max() < 1000  # the float32 timestamps
            for k in (0, 7):  # the right frames of the right episode (episodes share one MP4 in v3)
                frame = rec.frame(k)
                for view in (frame.left, frame.right):
                    assert abs(float(view[:, 20:44].mean()) - level(e, k)) < 4
                assert frame.left[:, :12, 2].mean() > 200 and frame.right[:, -12:, 2].mean() > 200
            np.testing.assert_allclose(rec.force.wrench, force(e, 8), rtol=1e-6)
            position, quat = rec.ecm_pose_at(rec.frame_times_ns)
            np.testing.assert_allclose(position[:, 2], 0.1 + 0.001 * np.arange(8), atol=1e-6)
            assert rec.stereo.baseline_mm == pytest.approx(4.6)
            assert rec.metadata.extra["lerobot_episode"] == str(e)


def test_one_episode_converts_to_one_file_and_the_cli_says_what_to_give(tmp_path, capsys):
    root = write_dataset(tmp_path / "ds", episodes=2)
    assert main(["convert", str(root), str(tmp_path / "e1.mcap"), "--episode", "1", "--quiet"]) == 0
    with Recording.open(tmp_path / "e1.mcap") as rec:
        assert rec.metadata.recording_id == "ds_episode_000001"
    assert main(["convert", str(root), str(tmp_path / "all.mcap"), "--quiet"]) == 1
    assert "the dataset has 2 episodes: give --episode N" in capsys.readouterr().err
    assert main(["convert", str(root), str(tmp_path / "e9.mcap"), "--episode", "9", "--quiet"]) == 1
    assert "no episode 9 (the dataset has episodes 0..1)" in capsys.readouterr().err


def test_a_clock_offset_moves_the_force_onto_the_video_clock(tmp_path):
    root = write_dataset(tmp_path / "ds", episodes=1)
    assert main(["convert", str(root), str(tmp_path / "plain.mcap"), "--episode", "0", "--quiet"]) == 0
    assert main(["convert", str(root), str(tmp_path / "moved.mcap"), "--episode", "0", "--quiet",
                 "--time-offset-ms=-12.5"]) == 0
    with Recording.open(tmp_path / "plain.mcap") as plain, Recording.open(tmp_path / "moved.mcap") as moved:
        np.testing.assert_array_equal(moved.force.times_ns, plain.force.times_ns + 12_500_000)
        np.testing.assert_array_equal(moved.frame_times_ns, plain.frame_times_ns)


def test_splits_and_meta_from_the_command_line_reach_the_manifest(tmp_path, capsys):
    root = write_dataset(tmp_path / "ds", episodes=3)
    assert main(["convert", str(root), str(tmp_path / "out"), "--splits", "train=0:1,val=1:2,test=2:3",
                 "--meta", "orientation_deg=90", "--meta", "prompt=box:1,1,30,30", "--meta", "2:orientation_deg=180",
                 "--meta", "1-2:prompt_box=2,2,20,20", "--quiet"]) == 0
    assert "note:" not in capsys.readouterr().out
    entries = load_manifest(tmp_path / "out" / "ds.manifest.yaml").entries
    assert [e.split for e in entries] == ["train", "val", "test"]
    assert [e.orientation_deg for e in entries] == [90.0, 90.0, 180.0]
    assert [e.prompt for e in entries] == ["box:1,1,30,30"] * 3  # prompt= wins over prompt_box=, as in process
    with Recording.open(entries[2].mcap) as rec:
        assert rec.metadata.extra["prompt_box"] == "2,2,20,20"
    assert main(["convert", str(root), str(tmp_path / "out2"), "--meta", "5:tissue=x", "--quiet"]) == 1
    assert "--meta: names episode 5, which the dataset does not have" in capsys.readouterr().err
    with pytest.raises(InputError, match="not SPLIT=START:STOP"):
        parse_splits(["train=3:1"])


def test_an_rgbd_dataset_converts_with_depth_in_millimetres(tmp_path):
    for kind in ("image", "array"):
        root = write_dataset(tmp_path / kind, views=("observation.images.color", "unused"), depth=kind, episodes=1)
        out = convert_lerobot_episode(root, 0, tmp_path / f"{kind}.mcap", options=_options())
        assert check_file(out) == []
        with Recording.open(out) as rec:
            assert rec.is_rgbd and rec.num_frames == 8
            assert np.nanmedian(rec.depth_mm(3)) == 530.0
            assert abs(float(rec.color_image(3)[:, 20:44].mean()) - level(0, 3)) < 4


def test_a_deleted_recording_is_converted_again_from_its_manifest_entry(tmp_path):
    root = write_dataset(tmp_path / "ds", episodes=2)
    manifest = convert_lerobot_dataset(root, tmp_path / "out", options=_options())
    entry = load_manifest(manifest).entries[1]
    first = Recording.open(entry.mcap)
    stamps = first.frame_times_ns.copy()
    first.close()
    entry.mcap.unlink()
    prepare_convert(entry)
    with Recording.open(entry.mcap) as rec:
        assert np.array_equal(rec.frame_times_ns, stamps) and rec.metadata.extra["lerobot_episode"] == "1"


@pytest.mark.parametrize("damage, message", [
    ("no_calibration", "no camera calibration: the dataset has no meta/calibration.yaml; give --calibration FILE"),
    ("template", "data_path 'data/{chunk_index.__class__}.parquet' names 'chunk_index.__class__'"),
    ("escape", "path '../outside/file-000.parquet' leaves the dataset folder"),
    ("rows", "episode 1: 7 rows but meta/ says 8 frames"),
    ("timestamp", "episode 0: timestamp of row 4 (0.100000 s) does not come after the row before (0.100000 s)"),
    ("nan_force", "episode 0 row 2: NaN or inf in observation.meta.force_torque"),
    ("video", "file-000.mp4: episode 0 observation.images.left: cannot be decoded (Invalid data"),
    ("no_video", "file-000.mp4: video not found"),
    ("short_video", "file-000.mp4: episode 1 observation.images.left: the video ends before frame 4 of 8"),
    ("version", "codebase_version 'v1.6' is not one this reader knows"),
    ("size", "calibration.yaml: image size 80x48 differs from observation.images.left (64x48)"),
])
def test_a_broken_dataset_is_one_line_naming_the_file_and_leaves_nothing(tmp_path, damage, message):
    root = write_dataset(tmp_path / "ds", episodes=2, calibrate=damage != "no_calibration")
    _damage(root, damage)
    before = tree_digest(root)
    with pytest.raises(InputError, match=re.escape(message)):
        convert_lerobot_dataset(root, tmp_path / "out", options=_options())
    assert not (tmp_path / "out").exists() and leftovers(tmp_path) == []
    assert tree_digest(root) == before


def _damage(root: Path, damage: str) -> None:
    info_path = root / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    data = root / "data" / "chunk-000" / "file-000.parquet"
    if damage == "template":
        info["data_path"] = "data/{chunk_index.__class__}.parquet"
    elif damage == "escape":
        info["data_path"] = "../outside/file-{file_index:03d}.parquet"
    elif damage == "version":
        info["codebase_version"] = "v1.6"
    elif damage in ("rows", "timestamp", "nan_force"):
        table = pq.read_table(data)
        if damage == "rows":
            table = table.slice(0, 15)
        else:
            column = "timestamp" if damage == "timestamp" else names.FORCE
            values = table.column(column).to_pylist()
            if damage == "timestamp":
                values[4] = values[3] = 0.1
            else:
                values[2] = [float("nan")] * 6
            table = table.set_column(table.schema.get_field_index(column), column,
                                     pa.array(values, table.column(column).type))
        pq.write_table(table, data)
    elif damage == "video":
        video = root / "videos" / "observation.images.left" / "chunk-000" / "file-000.mp4"
        payload = bytearray(video.read_bytes())
        video.write_bytes(bytes(payload[: len(payload) // 2]))
    elif damage == "short_video":
        write_mp4(root / "videos" / "observation.images.left" / "chunk-000" / "file-000.mp4",
             [image(e, k) for e in range(2) for k in range(8)][:12])
    elif damage == "no_video":
        (root / "videos" / "observation.images.left" / "chunk-000" / "file-000.mp4").unlink()
    elif damage == "size":
        calibration(80, 48).save(root / "meta" / "calibration.yaml")
    info_path.write_text(json.dumps(info))


def _options():
    from vfdata.conversion.options import ConvertOptions

    return ConvertOptions(progress=False, image_format="png")


# -- LeRobot out, and back ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> list[Path]:
    """Two small recordings (1 kHz force, ECM pose), a train and a test one."""
    folder = tmp_path_factory.mktemp("rec")
    paths = []
    for i, split in enumerate(("test", "train")):
        raw = make_raw(folder / f"r{i}", n=12, seed=i)
        (raw / "meta.yaml").write_text(f"split: {split}\norientation_deg: {90 * i}\nprompt_box: [10, 10, 100, 100]\n"
                                       "tissue: liver\nsession: 3\noperator: '007'\nwhen: 2024-05-01\nscale: 1e3\n"
                                       "sensor_to_object: xyz_deg:0,0,90\n")
        paths.append(convert_raw_folder(raw, folder / f"r{i}.mcap", options=_options()))
    return paths


@pytest.mark.parametrize("version", ["v3.0", "v2.1"])
def test_export_then_convert_gives_back_the_stamps_forces_and_metadata_exactly(tmp_path, recordings, version):
    out = export_lerobot(recordings, tmp_path / "ds", options=ExportOptions(version=version, **QUIET))
    info = json.loads((out / "meta" / "info.json").read_text())
    assert info["codebase_version"] == version and info["fps"] == 30
    assert info["splits"] == {"train": "0:1", "test": "1:2"}  # episodes in split order
    assert info["features"][names.FORCE]["names"] == ["fx", "fy", "fz", "tx", "ty", "tz"]
    manifest = convert_lerobot_dataset(out, tmp_path / "back", options=_options())
    entries = {e.id: e for e in load_manifest(manifest).entries}
    assert {k: (e.split, e.orientation_deg) for k, e in entries.items()} == {"r1": ("train", 90.0),
                                                                             "r0": ("test", 0.0)}
    for original in recordings:
        with Recording.open(original) as a, Recording.open(entries[original.stem].mcap) as b:
            assert np.array_equal(a.frame_times_ns, b.frame_times_ns)
            span = (a.force.times_ns > a.frame_times_ns[0] - round(1e9 / 30)) & \
                   (a.force.times_ns <= a.frame_times_ns[-1])
            assert np.array_equal(a.force.times_ns[span], b.force.times_ns)
            assert np.array_equal(a.force.wrench[span], b.force.wrench)
            provenance = {"source", "converter", "lerobot_dataset", "lerobot_episode", "lerobot_codebase_version",
                          "lerobot_task"}
            assert {k: v for k, v in a.metadata.to_record().items() if k not in provenance} == \
                {k: v for k, v in b.metadata.to_record().items() if k not in provenance}
            assert b.metadata.extra["prompt_box"] == "[10, 10, 100, 100]" and b.metadata.tissue == "liver"
            assert min(psnr_db(a.frame(i).left, b.frame(i).left) for i in range(a.num_frames)) > 25  # blurred noise
            pa_, qa = a.ecm_pose_at(a.frame_times_ns)
            pb, qb = b.ecm_pose_at(b.frame_times_ns)
            np.testing.assert_allclose(pb, pa_, atol=1e-6)
            assert b.stereo.baseline_mm == pytest.approx(a.stereo.baseline_mm)


def test_the_export_has_stats_tasks_and_an_open_h_card(tmp_path, recordings):
    out = export_lerobot(recordings, tmp_path / "ds", options=ExportOptions(**QUIET))
    stats = json.loads((out / "meta" / "stats.json").read_text())
    assert set(stats[names.FORCE]) == {"min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99"}
    assert np.shape(stats[names.LEFT]["mean"]) == (3, 1, 1) and stats[names.FORCE]["count"] == [24]
    tasks = pq.read_table(out / "meta" / "tasks.parquet")
    assert tasks.column("task_index").to_pylist() == [0]
    episodes = pq.read_table(next((out / "meta" / "episodes").glob("*/*.parquet"))).to_pylist()
    assert [e["videos/" + names.LEFT + "/from_timestamp"] for e in episodes] == [0.0, 12 / 30]
    card = (out / "README.md").read_text()
    for section in ("## At a Glance", "## Dataset Overview", "**Total Trajectories** | 2", "## Equipment & Setup",
                    "## Data Synchronization Approach", "## Attribution & Contact", "task_categories:"):
        assert section in card
    assert (out / "meta" / "README.md").read_text() == card


def test_a_failed_export_leaves_nothing_and_recordings_are_untouched(tmp_path, recordings):
    other = make_raw(tmp_path / "big", n=4, width=96, height=64)
    odd = convert_raw_folder(other, tmp_path / "big.mcap", options=_options())
    before = [p.read_bytes() for p in recordings]
    with pytest.raises(InputError, match="96x64 images where r1.mcap has 160x128"):
        export_lerobot([*recordings, odd], tmp_path / "ds", options=ExportOptions(**QUIET))
    assert not (tmp_path / "ds").exists() and leftovers(tmp_path) == []
    assert [p.read_bytes() for p in recordings] == before
    export_lerobot(recordings, tmp_path / "ds", options=ExportOptions(**QUIET))
    with pytest.raises(Exception, match="output exists"):
        export_lerobot(recordings, tmp_path / "ds", options=ExportOptions(**QUIET))
    assert main(["export", "--lerobot", *map(str, recordings), str(tmp_path / "ds"), "--overwrite", "--quiet"]) == 0
    with pytest.raises(InputError, match="not found: the tracks"):
        export_lerobot(recordings, tmp_path / "ds2", options=ExportOptions(tracks=".processed.mcap", **QUIET))


def test_the_tracks_and_the_estimated_force_go_with_the_export(tmp_path, recordings):
    frame = ObjectFrame(np.eye(3), np.array([0.0, 0.0, 80.0]), True, 1.0)
    rng = np.random.default_rng(1)
    written = {}
    for path in recordings:
        with Recording.open(path) as rec:
            times = rec.frame_times_ns
        points = rng.normal(size=(len(times), 5, 3)) * 10
        visible = rng.random((len(times), 5)) > 0.3
        with DerivedWriter(path.with_name(f"{path.stem}.t.mcap"), overwrite=True) as writer:
            writer.object_frame(frame, int(times[0]))
            for t, p, v in zip(times, points, visible, strict=True):
                writer.tracks(int(t), p, v)
            writer.close({"object_frame": json.dumps(frame.to_dict())})
        estimate = rng.normal(size=(len(times) - 3, 3))
        write_force_estimate(path.with_name(f"{path.stem}.e.mcap"), times[3:], estimate, frame, {}, overwrite=True)
        written[path.stem] = (points, visible, estimate)
    out = export_lerobot(recordings, tmp_path / "ds", options=ExportOptions(tracks=".t.mcap", estimate=".e.mcap",
                                                                            **QUIET))
    info = json.loads((out / "meta" / "info.json").read_text())
    assert info["features"][names.TRACKS]["shape"] == [5, 3] and info["features"][names.FORCE_ESTIMATE]["info"] == \
        {"frame": "tissue_object", "units": "N"}
    table = pq.read_table(next((out / "data").glob("*/*.parquet")))
    episode = table.column("episode_index").to_numpy()
    for e, stem in enumerate(("r1", "r0")):  # train first
        points, visible, estimate = written[stem]
        rows = table.filter(pc.equal(table.column("episode_index"), e))
        got = np.array(rows.column(names.TRACKS).to_pylist(), dtype=np.float32)
        np.testing.assert_allclose(got, points.astype(np.float32), rtol=1e-6)
        assert np.array_equal(np.array(rows.column(names.TRACKS_VISIBLE).to_pylist()), visible)
        force = np.array(rows.column(names.FORCE_ESTIMATE).to_pylist(), dtype=np.float64)
        assert np.isnan(force[:3]).all() and np.allclose(force[3:], estimate, rtol=1e-6)
    assert set(episode) == {0, 1}


def test_epoch_seconds_in_the_timestamp_column_need_the_frame_index_clock(tmp_path, capsys):
    """Open-H's dVRK converter passes the kinematics' epoch seconds as `timestamp`; in float32 they
    collapse. The error says so, and --clock frame_index reads the frames at frame_index / fps."""
    root = write_dataset(tmp_path / "ds", "v2.1", episodes=1)
    data = root / "data" / "chunk-000" / "episode_000000.parquet"
    table = pq.read_table(data)
    epoch = pa.array((1.7e9 + np.arange(8) / FPS).astype(np.float32))
    pq.write_table(table.set_column(table.schema.get_field_index("timestamp"), "timestamp", epoch), data)
    assert main(["convert", str(root), str(tmp_path / "a.mcap"), "--quiet"]) == 1
    assert "--clock frame_index times the frames by frame_index / fps" in capsys.readouterr().err
    assert main(["convert", str(root), str(tmp_path / "a.mcap"), "--quiet", "--clock", "frame_index"]) == 0
    with Recording.open(tmp_path / "a.mcap") as rec:
        assert abs(float(rec.frame(7).left[:, 20:44].mean()) - level(0, 7)) < 4
        assert rec.frame_times_ns[1] == round(1e9 / FPS)


def test_episodes_past_the_file_size_limits_start_new_files_that_read_back(tmp_path, recordings, monkeypatch):
    from vfdata.lerobot import writers

    monkeypatch.setattr(writers, "DATA_FILE_MB", 0)
    monkeypatch.setattr(writers, "VIDEO_FILE_MB", 0)
    out = export_lerobot(recordings, tmp_path / "ds", options=ExportOptions(**QUIET))
    assert sorted(p.name for p in (out / "data" / "chunk-000").iterdir()) == ["file-000.parquet", "file-001.parquet"]
    assert len(list((out / "videos" / names.LEFT / "chunk-000").iterdir())) == 2
    manifest = convert_lerobot_dataset(out, tmp_path / "back", options=_options())
    for entry in load_manifest(manifest).entries:
        with Recording.open(entry.mcap) as b, Recording.open(next(p for p in recordings if p.stem == entry.id)) as a:
            assert np.array_equal(a.frame_times_ns, b.frame_times_ns)
            assert psnr_db(a.frame(11).left, b.frame(11).left) > 25


def test_the_export_command_says_what_it_cannot_take(tmp_path, recordings, capsys):
    assert main(["export", "--lerobot", str(recordings[0]), str(tmp_path / "x.mcap")]) == 1
    assert "the last path is the output dataset folder" in capsys.readouterr().err
    assert main(["export", "--lerobot", "--tracks", str(recordings[0]), str(recordings[1]), str(tmp_path / "o")]) == 1
    assert "is not a suffix such as .klt.mcap: give the option after the paths" in capsys.readouterr().err
    assert main(["export", "--lerobot", str(recordings[0]), str(tmp_path / "o"), "--crf", "99"]) == 1
    assert "--crf: must be 0-63" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
