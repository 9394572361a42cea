"""The recording layer: raw folder -> MCAP -> reader, checked against the inputs and an independent
reader (rosbags), plus every bad input the converter must refuse and damaged files."""

from __future__ import annotations

import csv
import hashlib
import multiprocessing
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import zstandard
from rawfixtures import FRAME_NS, T0_NS, make_raw

from vfdata.calibration import StereoCalibration
from vfdata.cli import main
from vfdata.conversion.raw_folder import ConvertOptions, convert_raw_folder, jpeg_colour_size, read_force_csv
from vfdata.errors import FormatError
from vfdata.recording import Recording, layout
from vfdata.recording.inspect import check_file, info_text

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _convert(src: Path, out: Path, **kw) -> Path:
    return convert_raw_folder(src, out, options=ConvertOptions(progress=False, **kw))


def _tree_digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def raw(tmp_path_factory) -> Path:
    return make_raw(tmp_path_factory.mktemp("raw") / "rec", n=12)


@pytest.fixture(scope="module")
def converted_png(raw, tmp_path_factory) -> Path:
    # Small chunks, so that damage in one leaves the others readable.
    return _convert(raw, tmp_path_factory.mktemp("out") / "rec.mcap", image_format="png", chunk_size=64 * 1024)


def test_png_round_trip_is_exact(raw, converted_png):
    rec = Recording.open(converted_png)
    assert rec.num_frames == 12
    np.testing.assert_array_equal(rec.frame_times_ns, T0_NS + np.arange(12) * FRAME_NS)
    for i in (0, 5, 11):
        frame = rec.frame(i)
        np.testing.assert_array_equal(frame.left, cv2.imread(str(raw / "left" / f"{i:06d}.png")))
        np.testing.assert_array_equal(frame.right, cv2.imread(str(raw / "right" / f"{i:06d}.png")))
    rows = _read_csv(raw / "force.csv")
    force = rec.force
    np.testing.assert_array_equal(force.times_ns, [int(r["timestamp_ns"]) for r in rows])
    np.testing.assert_array_equal(force.wrench, [[float(r[k]) for k in ("fx", "fy", "fz", "tx", "ty", "tz")]
                                                 for r in rows])
    pose = rec.ecm_pose
    rows = _read_csv(raw / "ecm_pose.csv")
    np.testing.assert_allclose(pose.position_m, [[float(r[k]) for k in "xyz"] for r in rows])
    assert rec.metadata.orientation_deg == 90.0 and rec.metadata.split == "test" and rec.metadata.study == "test"
    assert rec.stereo.baseline_mm == pytest.approx(4.5)
    assert rec.camera.fx == pytest.approx(200.0) and rec.camera.width == 160
    assert check_file(converted_png) == []


def test_jpeg_is_default_and_close(raw, tmp_path):
    rec = Recording.open(_convert(raw, tmp_path / "rec.mcap"))
    left, _ = rec.frame_images(3)
    assert left.format == "jpeg"
    error = np.abs(rec.frame(3).left.astype(int) - cv2.imread(str(raw / "left" / "000003.png")).astype(int)).mean()
    assert error < 10.0  # noise-like test texture is the worst case for JPEG


def test_jpeg_frames_are_stored_as_they_are(tmp_path):
    src = make_raw(tmp_path / "rec", n=6, suffix=".jpg")
    rec = Recording.open(_convert(src, tmp_path / "rec.mcap"))
    for i in (0, 5):
        left, right = rec.frame_images(i)
        assert left.data == (src / "left" / f"{i:06d}.jpg").read_bytes()
        assert right.data == (src / "right" / f"{i:06d}.jpg").read_bytes()
    again = tmp_path / "again.mcap"
    assert main(["convert", "--quiet", "--reencode", "--quality", "60", str(src), str(again)]) == 0
    left, _ = Recording.open(again).frame_images(0)
    assert left.data != (src / "left" / "000000.jpg").read_bytes()


def test_encoding_threads_default_to_one_per_core(monkeypatch, tmp_path):
    from vfdata.commands import convert as convert_command

    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {0, 1, 2}, raising=False)
    assert ConvertOptions().workers == 3
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: set(range(32)), raising=False)
    assert ConvertOptions().workers == 8  # more would wait on the main thread
    used = []
    monkeypatch.setattr(convert_command, "convert_raw_folder", lambda src, out, overwrite, options: used.append(
        options.workers) or out)
    main(["convert", "--quiet", str(tmp_path / "src"), str(tmp_path / "a.mcap")])
    main(["convert", "--quiet", "--workers", "5", str(tmp_path / "src"), str(tmp_path / "b.mcap")])
    assert used == [8, 5]


def test_grayscale_jpeg_is_stored_in_colour(tmp_path):
    src = make_raw(tmp_path / "rec", n=4, suffix=".jpg")
    for path in (src / "left").iterdir():
        cv2.imwrite(str(path), cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
    assert jpeg_colour_size((src / "left" / "000000.jpg").read_bytes()) is None
    assert jpeg_colour_size((src / "right" / "000000.jpg").read_bytes()) == (160, 128)
    rec = Recording.open(_convert(src, tmp_path / "rec.mcap"))
    assert rec.frame(2).left.shape == (128, 160, 3)


@pytest.mark.parametrize("video", ["pair", "sbs"])
def test_video_sources(tmp_path, video):
    src = make_raw(tmp_path / "rec", n=10, video=video)
    rec = Recording.open(_convert(src, tmp_path / "rec.mcap"))
    assert rec.num_frames == 10
    assert rec.frame(9).left.shape == (128, 160, 3)
    assert check_file(rec.path) == []


def test_independent_reader_rosbags(raw, converted_png):
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    expected = {**{t: layout.RECORDING_TOPICS[t] for t in layout.RECORDING_TOPICS}}
    with Reader(converted_png) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == expected
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts[layout.LEFT_IMAGE] == 12 and counts[layout.WRENCH] == len(_read_csv(raw / "force.csv"))
        wrench_rows = _read_csv(raw / "force.csv")
        k = 0
        for connection, timestamp, data in reader.messages():
            msg = typestore.deserialize_cdr(data, connection.msgtype)
            if connection.topic == layout.WRENCH:
                row = wrench_rows[k]
                stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                assert stamp == timestamp == int(row["timestamp_ns"])
                assert msg.wrench.force.x == float(row["fx"]) and msg.wrench.torque.z == float(row["tz"])
                k += 1
            elif connection.topic == layout.LEFT_IMAGE:
                stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                assert stamp == timestamp and msg.format == "png"
                i = (stamp - T0_NS) // FRAME_NS
                image = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
                np.testing.assert_array_equal(image, cv2.imread(str(raw / "left" / f"{i:06d}.png")))
            elif connection.topic == layout.RIGHT_INFO:
                assert msg.p[3] == pytest.approx(-200.0 * 4.5e-3)
            elif connection.topic == layout.TF_STATIC:
                assert msg.transforms[0].child_frame_id == layout.RIGHT_FRAME
                assert msg.transforms[0].transform.translation.x == pytest.approx(4.5e-3)
        assert k == len(wrench_rows)


def test_mcap_library_reads_and_validates_ours(raw, converted_png):
    from mcap.reader import make_reader
    from mcap.stream_reader import StreamReader

    with open(converted_png, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary.statistics.message_count == sum(
            summary.statistics.channel_message_counts.values())
        assert {c.topic for c in summary.channels.values()} == set(layout.RECORDING_TOPICS)
        # images stored as they are (JPEG/PNG do not compress), the force and pose series in zstd
        assert {i.compression for i in summary.chunk_indexes} == {"", "zstd"}
        times = [m.log_time for _, c, m in reader.iter_messages(topics=[layout.WRENCH])]
        assert times == [int(r["timestamp_ns"]) for r in _read_csv(raw / "force.csv")]
        assert reader.get_header().profile == "ros2"
        assert list(reader.iter_metadata())[0].name == layout.RECORDING_METADATA
    with open(converted_png, "rb") as f:
        records = list(StreamReader(f, validate_crcs=True).records)
    assert sum(type(r).__name__ == "Message" for r in records) == summary.statistics.message_count


def test_writer_takes_payloads_as_views_and_arrays(tmp_path):
    """A record's length is that of the bytes written, whatever object carries them (len() of a
    float64 view or a 2-D array counts items, not bytes), and a buffer reused after the call does not
    change what was written."""
    from mcap.reader import make_reader

    from vfdata.recording.writer import McapWriter

    values = np.arange(10, dtype=np.float64)
    table = np.arange(24, dtype=np.uint8).reshape(4, 6)
    buffer = bytearray(b"abcdef")
    payloads = [memoryview(values), table, buffer, b"plain"]
    expected = [values.tobytes(), table.tobytes(), b"abcdef", b"plain"]
    out = tmp_path / "views.mcap"
    with McapWriter(out) as writer:
        for i, payload in enumerate(payloads):
            writer.write_payload("/test", "sensor_msgs/msg/CompressedImage", 1_000 + i, payload)
        buffer[:] = b"XXXXXX"
    with open(out, "rb") as f:
        got = [m.data for _, _, m in make_reader(f, validate_crcs=True).iter_messages()]
    assert got == expected


def test_force_at_interpolates_and_respects_gaps(converted_png):
    rec = Recording.open(converted_png)
    t = rec.force.times_ns
    mid = (t[10] + t[11]) // 2
    np.testing.assert_allclose(rec.force_at([mid])[0], (rec.force.wrench[10] + rec.force.wrench[11]) / 2)
    np.testing.assert_array_equal(rec.force_at([t[7]])[0], rec.force.wrench[7])
    assert np.isnan(rec.force_at([t[0] - 1, t[-1] + 1])).all()
    assert np.isnan(rec.force_at([mid], max_gap_ns=100)).all()


def test_ecm_pose_slerp(converted_png):
    rec = Recording.open(converted_png)
    times = rec.ecm_pose.times_ns
    position, quat = rec.ecm_pose_at([(times[2] + times[3]) // 2])
    angle = 2 * np.arctan2(quat[0, 0], quat[0, 3])
    assert angle == pytest.approx(0.025, abs=1e-6)
    assert position[0, 1] == pytest.approx(0.2025)


def test_reader_works_in_forked_workers(converted_png):
    rec = Recording.open(converted_png)
    rec.frame(0)  # open the file in the parent before forking
    ctx = multiprocessing.get_context("fork")
    with ctx.Pool(2) as pool:
        sums = pool.map(_frame_sum, [(rec, i) for i in range(6)])
    assert sums == [int(rec.frame(i).left.sum()) for i in range(6)]


def _frame_sum(args) -> int:
    rec, i = args
    return int(rec.frame(i).left.sum())


def test_unrectified_calibration_gets_rectification(tmp_path):
    src = make_raw(tmp_path / "rec", n=3, rectified=False)
    rec = Recording.open(_convert(src, tmp_path / "rec.mcap"))
    left, right = rec.camera_infos
    assert left.distortion_model == "plumb_bob" and left.d[0] == pytest.approx(-0.1)
    assert not np.allclose(left.r, np.eye(3))
    assert rec.stereo.baseline_mm == pytest.approx(np.linalg.norm([4.5, 0.05, 0.1]), rel=1e-3)
    assert not rec.is_rectified
    assert Recording.open(_convert(make_raw(tmp_path / "r2", n=2), tmp_path / "r2.mcap")).is_rectified
    calib = StereoCalibration.load(src / "calibration.yaml")
    frame = rec.frame(1)
    expected = calib.rectify_pair(frame.left, frame.right)
    rectified = rec.rectified_frame(1)
    assert np.abs(rectified.left.astype(int) - expected[0].astype(int)).mean() < 1.0
    assert np.abs(rectified.left.astype(int) - frame.left.astype(int)).mean() > 1.0


def test_rostopic_force_export(tmp_path):
    src = make_raw(tmp_path / "rec", n=4, rostopic=True)
    rec = Recording.open(_convert(src, tmp_path / "rec.mcap"))
    assert rec.force.frame_id == "ati_sensor"
    rows = _read_csv(src / "force.csv")
    np.testing.assert_array_equal(rec.force.times_ns, [int(r["field.header.stamp"]) for r in rows])


@pytest.mark.skipif(not (SHARED / "gao2018" / "1-1-force.csv").exists(), reason="../shared not present")
def test_real_rostopic_force_log():
    stamps, wrench, frame_id = read_force_csv(SHARED / "gao2018" / "1-1-force.csv")
    assert len(stamps) == 3467 and frame_id == "optoforce_0"
    assert stamps[0] == 1519700447392580032
    assert 0.0 <= np.median(wrench[:, 2]) <= 4.5 and (wrench[:, 3:] == 0).all()


# -- bad inputs --------------------------------------------------------------------------------------
def _rewrite_csv(path: Path, edit) -> None:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    edit(rows)
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows(rows)


def _break_missing_folder(src: Path) -> str:
    shutil.rmtree(src)
    return "recording folder not found"


def _break_missing_calibration(src: Path) -> str:
    (src / "calibration.yaml").unlink()
    return "calibration.yaml: calibration file not found"


def _break_frame_count(src: Path) -> str:
    sorted((src / "right").iterdir())[-1].unlink()
    return "right: 11 frames but left/ has 12"


def _break_frames_rows(src: Path) -> str:
    _rewrite_csv(src / "frames.csv", lambda rows: rows.pop())
    return "frames.csv: 11 rows but the recording has 12 frames"


def _break_backwards(src: Path) -> str:
    def edit(rows):
        rows[5][1] = str(int(rows[3][1]))
    _rewrite_csv(src / "frames.csv", edit)
    return "goes backwards"


def _break_repeat(src: Path) -> str:
    def edit(rows):
        rows[5][1] = rows[4][1]
    _rewrite_csv(src / "frames.csv", edit)
    return "repeats"


def _break_force_nan(src: Path) -> str:
    def edit(rows):
        rows[40][2] = "nan"
    _rewrite_csv(src / "force.csv", edit)
    return "force.csv: line 41: NaN or inf value"


def _break_pose_inf(src: Path) -> str:
    def edit(rows):
        rows[2][1] = "inf"
    _rewrite_csv(src / "ecm_pose.csv", edit)
    return "ecm_pose.csv: line 3: NaN or inf value"


def _break_force_gap(src: Path) -> str:
    def edit(rows):
        del rows[100:200]
    _rewrite_csv(src / "force.csv", edit)
    return "gap of 101.0 ms in the force stream"


def _break_force_short(src: Path) -> str:
    def edit(rows):
        del rows[200:]
    _rewrite_csv(src / "force.csv", edit)
    return "force ends"


def _break_undecodable_image(src: Path) -> str:
    (src / "left" / "000007.png").write_bytes(b"not a png at all")
    return "000007.png: image cannot be decoded"


def _break_calibration_size(src: Path) -> str:
    text = (src / "calibration.yaml").read_text().replace("image_width: 160", "image_width: 320")
    (src / "calibration.yaml").write_text(text)
    return "calibration.yaml: image size 320x128 differs from left/000000.png (160x128)"


def _break_damaged_jpeg(src: Path) -> str:
    for side in ("left", "right"):
        for path in (src / side).iterdir():
            cv2.imwrite(str(path.with_suffix(".jpg")), cv2.imread(str(path)))
            path.unlink()
    path = src / "right" / "000004.jpg"
    path.write_bytes(path.read_bytes()[:2] + b"\x00" * 64)
    return "000004.jpg: image cannot be decoded"


def _break_jpeg_size(src: Path) -> str:
    _break_damaged_jpeg(src)
    cv2.imwrite(str(src / "right" / "000004.jpg"), np.zeros((128, 150, 3), np.uint8))
    return "calibration.yaml: image size 160x128 differs from right/000004.jpg (150x128)"


BREAKERS = [
    _break_missing_folder, _break_missing_calibration, _break_frame_count, _break_frames_rows, _break_backwards,
    _break_repeat, _break_force_nan, _break_pose_inf, _break_force_gap, _break_force_short,
    _break_undecodable_image, _break_calibration_size, _break_damaged_jpeg, _break_jpeg_size,
]


@pytest.mark.parametrize("breaker", BREAKERS, ids=lambda f: f.__name__.removeprefix("_break_"))
def test_bad_input_is_refused_cleanly(tmp_path, capsys, breaker):
    src = make_raw(tmp_path / "rec", n=12)
    expected = breaker(src)
    before = _tree_digest(src) if src.exists() else {}
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    code = main(["convert", "--quiet", str(src), str(out_dir / "rec.mcap")])
    err = capsys.readouterr().err.strip()
    assert code == 1
    assert len(err.splitlines()) == 1 and expected in err, err
    assert "Traceback" not in err
    assert list(out_dir.iterdir()) == []  # no output, no temporary file
    assert (_tree_digest(src) if src.exists() else {}) == before


def test_existing_output_needs_overwrite(raw, tmp_path, capsys):
    out = tmp_path / "rec.mcap"
    out.write_bytes(b"precious")
    assert main(["convert", "--quiet", str(raw), str(out)]) == 1
    assert "output exists" in capsys.readouterr().err and out.read_bytes() == b"precious"
    assert main(["convert", "--quiet", "--overwrite", str(raw), str(out)]) == 0
    assert Recording.open(out).num_frames == 12


# -- damaged files -----------------------------------------------------------------------------------
def test_truncated_file_gives_what_precedes_the_damage(converted_png, tmp_path, capsys):
    data = converted_png.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    rec = Recording.open(cut)
    assert rec.problems and "truncated" in rec.problems[0]
    assert 0 < rec.num_frames < 12
    np.testing.assert_array_equal(rec.frame(0).left, Recording.open(converted_png).frame(0).left)
    assert main(["check", str(cut)]) == 1
    assert "truncated" in capsys.readouterr().err
    assert main(["info", str(cut)]) == 0
    assert "damaged:" in capsys.readouterr().out


def test_bit_flip_is_detected(converted_png, tmp_path, capsys):
    data = bytearray(converted_png.read_bytes())
    rec = Recording.open(converted_png)
    chunk = rec._mcap.index.chunks[1]
    data[chunk.data_offset + chunk.compressed_size // 2] ^= 0x10
    flipped = tmp_path / "flipped.mcap"
    flipped.write_bytes(bytes(data))
    problems = check_file(flipped)
    assert any("CRC mismatch" in p or "cannot be decompressed" in p for p in problems), problems
    assert main(["check", str(flipped)]) == 1
    capsys.readouterr()


def test_not_an_mcap(tmp_path, capsys):
    path = tmp_path / "x.mcap"
    path.write_bytes(b"hello world, not an mcap file")
    with pytest.raises(FormatError, match="bad magic"):
        Recording.open(path)
    assert main(["info", str(path)]) == 1
    assert "not an MCAP file" in capsys.readouterr().err


@pytest.mark.parametrize("content", [b"hello world, not an mcap file", None])
def test_check_names_the_file_once(tmp_path, capsys, content):
    path = tmp_path / "x.mcap"
    if content is not None:
        path.write_bytes(content)
    assert main(["check", str(path)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.count(str(path)) == 1, err
    assert err.endswith("not an MCAP file (bad magic)" if content else "file not found"), err


def test_info_reports_rates_and_sync(converted_png):
    text = info_text(converted_png)
    assert "/force_sensor/wrench" in text and "1000.00" in text and "force-to-frame sync" in text


# -- the writer's records ------------------------------------------------------------------------------
def test_every_record_written_is_the_mcap_librarys_own(raw, tmp_path):
    """Each record of a converted file, read by `mcap`'s StreamReader and written again by the library's
    record builders, gives the file's bytes, the chunks' records included (the writer packs message
    records, chunk heads and message indexes itself)."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader, breakup_chunk

    from vfdata.mcap_io.records import MAGIC, record_bytes

    out = _convert(raw, tmp_path / "rec.mcap", chunk_size=16 * 1024)
    data = out.read_bytes()
    pos, kinds = len(MAGIC), set()
    for record in StreamReader(str(out), emit_chunks=True, validate_crcs=True).records:
        written = record_bytes(record)
        assert data[pos:pos + len(written)] == written, type(record).__name__
        pos += len(written)
        kinds.add(type(record).__name__)
        if isinstance(record, Chunk):
            records = breakup_chunk(record, validate_crc=True)
            inner = b"".join(record_bytes(r) for r in records)
            chunk_data = record.data if not record.compression else zstandard.decompress(record.data)
            assert inner == chunk_data
    assert data[pos:] == MAGIC
    assert kinds >= {"Header", "Schema", "Channel", "Metadata", "Chunk", "MessageIndex", "DataEnd", "Statistics",
                     "ChunkIndex", "MetadataIndex", "SummaryOffset", "Footer"}


def test_each_series_has_chunks_of_its_own_in_log_time_order(tmp_path):
    """Force and pose batches written one after the other (as the bag converter does) land in chunks of
    their own topic, each in log-time order; the data-section CRC holds (validated by `mcap`)."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader, breakup_chunk

    from vfdata.recording.messages import PoseStamped, WrenchStamped
    from vfdata.recording.writer import McapWriter

    out = tmp_path / "series.mcap"
    stamps = T0_NS + np.arange(300) * 1_000_000
    with McapWriter(out, separate_topics=(layout.WRENCH, layout.ECM_POSE), separate_batch=64) as writer:
        for lo in range(0, 300, 100):
            for t in stamps[lo:lo + 100]:
                writer.write(layout.WRENCH, WrenchStamped(int(t), "ati", (1.0, 2.0, 3.0), (0.0, 0.0, 0.0)))
            for t in stamps[lo:lo + 100]:
                writer.write(layout.ECM_POSE, PoseStamped(int(t), "world", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    chunks = [r for r in StreamReader(str(out), emit_chunks=True, validate_crcs=True).records if isinstance(r, Chunk)]
    assert len(chunks) == 10
    for chunk in chunks:
        messages = [m for m in breakup_chunk(chunk) if type(m).__name__ == "Message"]
        assert len({m.channel_id for m in messages}) == 1
        times = [m.log_time for m in messages]
        assert times == sorted(times)
    rec = Recording.open(out)
    np.testing.assert_array_equal(rec.force.times_ns, stamps)
    np.testing.assert_array_equal(rec.ecm_pose.times_ns, stamps)
    assert rec._mcap.index.data_section_crc != 0


def test_metadata_stays_a_string_map(tmp_path):
    from mcap.reader import make_reader

    from vfdata.recording.writer import McapWriter

    out = tmp_path / "meta.mcap"
    with McapWriter(out) as writer:
        writer.add_metadata("x", {"flag": True, "n": 3, "text": "a"})
    with open(out, "rb") as f:
        (record,) = make_reader(f).iter_metadata()
    assert record.metadata == {"flag": "True", "n": "3", "text": "a"}
    assert Recording.open(out).metadata_records == {"x": {"flag": "True", "n": "3", "text": "a"}}
