"""ROS 1 and ROS 2 bags -> recording MCAP. The bags are written here with `rosbags` (dVRK topic names,
both ECM pose types, raw and compressed images) and the converted file is checked topic by topic,
value by value, through `vfdata.Recording`."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest
from bagfixtures import (
    FRAME_NS,
    LEFT,
    RIGHT,
    T0_NS,
    BagSpec,
    check_recording,
    write_bag,
)
from convert_fixtures import chunk_messages, out_of_order_chunks
from mcap.reader import make_reader
from rawfixtures import calibration
from rosbags.rosbag2 import CompressionMode, StoragePlugin

from vfdata.cli import main
from vfdata.commands.inspect_bag import inspect_bag_text
from vfdata.conversion import bag_scan, bag_topics, bags, ros_images
from vfdata.conversion.bag_topics import BagTopics
from vfdata.conversion.bags import convert_bag
from vfdata.conversion.raw_folder import ConvertOptions
from vfdata.errors import InputError, OutputExistsError
from vfdata.mcap_io.cdr import CdrError
from vfdata.recording import layout
from vfdata.recording.inspect import check_file
from vfdata.recording.messages import (
    PoseStamped,
    WrenchStamped,
    decode_stamped_batch,
    encode_stamped_batch,
)
from vfdata.recording.reader import Recording

PNG = ConvertOptions(image_format="png", progress=False)


@pytest.mark.parametrize("ros2, storage, pose_type, lz4", [
    (False, None, "PoseStamped", False),
    (False, None, "TransformStamped", True),
    (True, StoragePlugin.SQLITE3, "TransformStamped", False),
    (True, StoragePlugin.MCAP, "PoseStamped", False),
])
def test_raw_bgr8_bag_converts_value_by_value(tmp_path, ros2, storage, pose_type, lz4):
    spec = BagSpec(ros2=ros2, storage=storage or StoragePlugin.SQLITE3, pose_type=pose_type, lz4=lz4)
    bag = tmp_path / ("rec" if ros2 else "rec.bag")
    write_bag(bag, spec)
    before = sorted((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in tmp_path.rglob("*"))
    out = convert_bag(bag, tmp_path / "rec.mcap", options=PNG)
    rec = check_recording(out, spec)
    assert rec.metadata.extra["bag_left_topic"] == LEFT
    assert rec.metadata.extra["bag_pose_topic"] == "/ECM/measured_cp"
    assert rec.metadata.extra["pair_max_offset_ns"] == "2000000"
    after = sorted((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in tmp_path.rglob("*") if p != out)
    assert after == before  # the bag is not modified


@pytest.mark.parametrize("ros2", [False, True])
def test_every_chunk_is_in_log_time_order(tmp_path, ros2):
    """Force (1 kHz) and pose (15 Hz): every chunk in log-time order, never the pose series after the
    force series in one chunk (`mcap doctor`: NON_MONOTONIC_LOG_TIME); each series in chunks of its own."""
    spec = write_bag(tmp_path / ("b" if ros2 else "b.bag"), BagSpec(ros2=ros2, frames=40))
    out = convert_bag(tmp_path / ("b" if ros2 else "b.bag"), tmp_path / "out.mcap", options=PNG)
    assert out_of_order_chunks(out) == []

    with open(out, "rb") as stream:
        ids = {c.topic: c.id for c in make_reader(stream).get_summary().channels.values()}
    series = {ids[layout.WRENCH], ids[layout.ECM_POSE]}
    chunks = [{c for c, _ in chunk} for chunk in chunk_messages(out)]
    assert all(len(c) == 1 for c in chunks if c & series)  # each series in chunks of its own
    counts = {cid: sum(1 for chunk in chunk_messages(out) for c, _ in chunk if c == cid) for cid in series}
    assert counts == {ids[layout.WRENCH]: len(spec.force_ns), ids[layout.ECM_POSE]: len(spec.pose_ns)}
    check_recording(out, spec)


@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP], ids=["sqlite3", "mcap"])
@pytest.mark.parametrize("mode", [CompressionMode.FILE, CompressionMode.MESSAGE], ids=["file", "message"])
def test_compressed_ros2_bags_convert_value_by_value(tmp_path, storage, mode):
    """`ros2 bag record --compression-mode file|message --compression-format zstd`: streamed through
    rosbags, which decompresses them."""
    spec = write_bag(tmp_path / "z", BagSpec(ros2=True, storage=storage, compression_mode=mode, frames=4))
    assert any(p.suffix == ".zstd" for p in (tmp_path / "z").iterdir()) == (mode == CompressionMode.FILE)
    assert "reading: streaming through rosbags" in inspect_bag_text(tmp_path / "z")
    check_recording(convert_bag(tmp_path / "z", tmp_path / "z.mcap", options=PNG), spec)


@pytest.mark.parametrize("ros2", [False, True])
def test_compressed_jpeg_bag_is_copied_not_reencoded(tmp_path, ros2):
    spec = write_bag(tmp_path / ("c" if ros2 else "c.bag"), BagSpec(
        ros2=ros2, encoding="compressed", left=LEFT + "/compressed", right=RIGHT + "/compressed"))
    out = convert_bag(tmp_path / ("c" if ros2 else "c.bag"), tmp_path / "c.mcap",
                      options=ConvertOptions(progress=False))
    jpegs = [[cv2.imencode(".jpg", image)[1] for image in pair] for pair in spec.images]
    spec.images = [[cv2.imdecode(data, cv2.IMREAD_COLOR) for data in pair] for pair in jpegs]
    rec = check_recording(out, spec)
    for i in range(spec.frames):
        left, right = rec.frame_images(i)
        assert left.format == right.format == "jpeg"
        assert (left.data, right.data) == (jpegs[i][0].tobytes(), jpegs[i][1].tobytes())


def test_compressed_png_to_png_is_exact(tmp_path):
    spec = write_bag(tmp_path / "p.bag", BagSpec(encoding="compressed_png", left=LEFT + "/compressed",
                                                 right=RIGHT + "/compressed"))
    check_recording(convert_bag(tmp_path / "p.bag", tmp_path / "p.mcap", options=PNG), spec)


@pytest.mark.parametrize("encoding", ["rgb8", "mono8"])
def test_other_raw_encodings(tmp_path, encoding):
    spec = write_bag(tmp_path / "e.bag", BagSpec(encoding=encoding, frames=3))
    check_recording(convert_bag(tmp_path / "e.bag", tmp_path / "e.mcap", options=PNG), spec)


def test_raw_image_decoding():
    rng = np.random.default_rng(3)
    bgr = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    # row padding (step > width * channels) is dropped
    padded = np.zeros((6, 8 * 3 + 5), np.uint8)
    padded[:, :24] = bgr.reshape(6, 24)
    assert np.array_equal(ros_images.raw_image_to_bgr(6, 8, "bgr8", 0, 29, padded.ravel()), bgr)
    assert np.array_equal(ros_images.raw_image_to_bgr(6, 8, "rgba8", 0, 32, np.dstack([bgr[..., ::-1], bgr[..., :1]])),
                          bgr)
    # 16-bit: full range scaled to 8 bits, either byte order
    mono16 = np.array([[0, 257, 65535, 32896]], np.uint16)
    expect = np.repeat(np.array([[0, 1, 255, 128]], np.uint8)[..., None], 3, axis=2)
    assert np.array_equal(ros_images.raw_image_to_bgr(1, 4, "mono16", 0, 8, mono16.astype("<u2").tobytes()), expect)
    assert np.array_equal(ros_images.raw_image_to_bgr(1, 4, "16UC1", 1, 8, mono16.astype(">u2").tobytes()), expect)
    # Bayer: a flat colour mosaiced in each ROS pattern demosaics back to that colour
    b, g, r = 40, 120, 220
    for pattern_name, layout_2x2 in (("rggb", [[r, g], [g, b]]), ("bggr", [[b, g], [g, r]]),
                                     ("gbrg", [[g, b], [r, g]]), ("grbg", [[g, r], [b, g]])):
        mosaic = np.tile(np.array(layout_2x2, np.uint8), (4, 4))
        out = ros_images.raw_image_to_bgr(8, 8, f"bayer_{pattern_name}8", 0, 8, mosaic)
        assert out[2:6, 2:6].reshape(-1, 3).tolist() == [[b, g, r]] * 16, pattern_name
        out16 = ros_images.raw_image_to_bgr(8, 8, f"bayer_{pattern_name}16", 0, 16, (mosaic.astype(np.uint16) * 257))
        assert out16[2:6, 2:6].reshape(-1, 3).tolist() == [[b, g, r]] * 16, pattern_name
    with pytest.raises(ros_images.UnsupportedImage, match="32FC1"):
        ros_images.raw_image_to_bgr(1, 1, "32FC1", 0, 4, b"\0\0\0\0")
    with pytest.raises(ros_images.UnsupportedImage, match="step"):
        ros_images.raw_image_to_bgr(2, 4, "bgr8", 0, 12, b"\0" * 20)
    with pytest.raises(ros_images.UnsupportedImage, match="compressedDepth"):
        ros_images.compressed_format("16UC1; compressedDepth png")


def test_stamped_batch_codec_matches_message_encoding():
    """The numpy batch codec, both ways, against the one-message CDR encoder (the converters write with
    it, the reader and the bag scan read with it)."""
    rng = np.random.default_rng(1)
    stamps = np.array([1_700_000_000_123_456_789, 5, 3 * 10**9 + 7])
    for frame_id in ("", "a", "ati_sensor", "abcdefg", "world"):
        for cls, width in ((WrenchStamped, 6), (PoseStamped, 7)):
            values = rng.normal(size=(3, width))
            table = encode_stamped_batch(stamps, frame_id, values)
            assert [row.tobytes() for row in table] == [
                cls(int(t), frame_id, tuple(v[:3]), tuple(v[3:])).encode() for t, v in zip(stamps, values, strict=True)]
            got_stamps, got_values = decode_stamped_batch(table, width)
            assert got_stamps.tolist() == stamps.tolist() and np.array_equal(got_values, values)
    with pytest.raises(CdrError, match="frame_id length"):
        decode_stamped_batch(encode_stamped_batch(stamps, "ati", rng.normal(size=(3, 7))), 6)


def test_pair_stamps_mutual_nearest_within_tolerance():
    left = np.array([100, 200, 300, 400, 400, 500])
    right = np.array([505, 102, 199, 330, 401, 260])  # unsorted; 260 sits between two left frames
    li, ri = bags.pair_stamps(left, right, tolerance_ns=20)
    assert [(int(left[i]), int(right[j])) for i, j in zip(li, ri, strict=True)] == [
        (100, 102), (200, 199), (400, 401), (500, 505)]
    assert bags.default_pair_tolerance_ns(np.array([0, 30, 60, 100, 120])) == 15
    li, ri = bags.pair_stamps(left, np.array([10_000]), 20)
    assert len(li) == len(ri) == 0


def test_unpaired_frames_are_reported_and_left_out(tmp_path, caplog):
    extra = (T0_NS + FRAME_NS // 2, T0_NS + 3 * FRAME_NS + FRAME_NS // 2)  # right frames half a period off
    spec = write_bag(tmp_path / "u.bag", BagSpec(extra_right_ns=extra))
    with caplog.at_level(logging.WARNING):
        out = convert_bag(tmp_path / "u.bag", tmp_path / "u.mcap", options=PNG)
    assert "0 left and 2 right frames have no partner within 16.7 ms" in caplog.text
    rec = check_recording(out, spec)
    assert rec.metadata.extra["unpaired_right_frames"] == "2"


def test_zero_header_stamps_fall_back_to_receive_time(tmp_path, caplog):
    spec = write_bag(tmp_path / "z.bag", BagSpec(zero_stamps=True, right_offset_ns=0))
    with caplog.at_level(logging.WARNING):
        out = convert_bag(tmp_path / "z.bag", tmp_path / "z.mcap", options=PNG)
    assert "8 of 8 messages have header.stamp 0; using the bag receive time" in caplog.text
    rec = Recording.open(out)
    assert np.array_equal(rec.frame_times_ns, spec.frame_ns + 5_000_000)  # receive = stamp + 5 ms in write_bag


def test_remapped_topics_and_calibration_file(tmp_path):
    spec = write_bag(tmp_path / "r.bag", BagSpec(left="/cam/l/image", right="/cam/r/image", camera_info=False,
                                                 force_topics=("/my_ft",), pose_type="TransformStamped"))
    calib = calibration(spec.width, spec.height)
    calib.save(tmp_path / "calibration.yaml")
    topics = BagTopics(left="/cam/l/image", right="/cam/r/image", force="/my_ft")
    out = convert_bag(tmp_path / "r.bag", tmp_path / "r.mcap", options=PNG, topics=topics,
                      calibration=tmp_path / "calibration.yaml")
    rec = Recording.open(out)
    assert np.array_equal(rec.force.wrench, spec.wrench)
    assert rec.stereo.baseline_mm == pytest.approx(4.5)
    assert rec.camera.fx == pytest.approx(200.0)
    assert rec.metadata.extra["bag_force_topic"] == "/my_ft"
    # without the calibration, the missing camera_info is named
    with pytest.raises(InputError, match=r"no left camera_info topic .* --calibration"):
        convert_bag(tmp_path / "r.bag", tmp_path / "r2.mcap", options=PNG, topics=topics)


def test_force_auto_detection(tmp_path):
    # not a default name, but the only WrenchStamped beside dVRK arm estimates ("spatial" is not "ati")
    arms = ("/PSM1/body/measured_cf", "/PSM1/spatial/measured_cf")
    spec = write_bag(tmp_path / "a.bag", BagSpec(force_topics=("/sensor/wrench", *arms), frames=3))
    out = convert_bag(tmp_path / "a.bag", tmp_path / "a.mcap", options=PNG)
    assert Recording.open(out).metadata.extra["bag_force_topic"] == "/sensor/wrench"
    assert np.array_equal(Recording.open(out).force.times_ns, spec.force_ns)
    write_bag(tmp_path / "b.bag", BagSpec(force_topics=("/ft1", "/ft2"), frames=3))
    with pytest.raises(InputError, match=r"several WrenchStamped topics .*/ft1, /ft2.* --force-topic"):
        convert_bag(tmp_path / "b.bag", tmp_path / "b.mcap", options=PNG)


def test_image_topic_auto_detection(tmp_path):
    write_bag(tmp_path / "i.bag", BagSpec(left="/stereo/left/image_mono", right="/stereo/right/image_mono",
                                          camera_info=False, frames=3))
    with bag_scan.open_bag(tmp_path / "i.bag") as reader:
        choice = bag_topics.choose_topics(tmp_path / "i.bag", bag_topics.topic_types(reader), BagTopics(),
                                          use_camera_info=False)
    assert (choice.left, choice.right) == ("/stereo/left/image_mono", "/stereo/right/image_mono")
    assert choice.how["left"] == "auto-detected"


def error_of(tmp_path, spec: BagSpec, **kwargs) -> str:
    tmp_path.mkdir()
    bag = tmp_path / "bad.bag"
    write_bag(bag, spec)
    out = tmp_path / "bad.mcap"
    with pytest.raises(InputError) as info:
        convert_bag(bag, out, options=PNG, **kwargs)
    assert not out.exists() and not list(tmp_path.glob(".bad.mcap*"))
    assert "\n" not in str(info.value) and str(info.value).startswith(str(bag))
    return info.value.problem


def test_errors(tmp_path):
    assert "no image topic found" in error_of(tmp_path / "0", BagSpec(with_images=False))
    assert "no left/right image topic pair found among /a, /b" in error_of(tmp_path / "1", BagSpec(left="/a",
                                                                                                   right="/b"))
    assert "left and right images never pair within 16.7 ms" in error_of(
        tmp_path / "2", BagSpec(right_offset_ns=10**10))
    assert "force starts" in error_of(tmp_path / "3", BagSpec(force_shift_ns=120_000_000))
    assert "lie outside the video span" in error_of(tmp_path / "4", BagSpec(force_shift_ns=-10**10))
    assert "unsupported image encoding '32FC1'" in error_of(tmp_path / "5", BagSpec(encoding="32FC1", frames=2))
    assert "no force topic" in error_of(tmp_path / "6", BagSpec(force_topics=()))
    assert "--left-topic /nope: no such topic" in error_of(tmp_path / "7", BagSpec(), topics=BagTopics(left="/nope"))


def test_output_exists_and_not_a_bag(tmp_path):
    write_bag(tmp_path / "o.bag", BagSpec(frames=2))
    (tmp_path / "o.mcap").write_bytes(b"keep")
    with pytest.raises(OutputExistsError):
        convert_bag(tmp_path / "o.bag", tmp_path / "o.mcap", options=PNG)
    assert (tmp_path / "o.mcap").read_bytes() == b"keep"
    (tmp_path / "x.bag").write_bytes(b"not a bag")
    with pytest.raises(InputError, match="cannot read the bag"):
        convert_bag(tmp_path / "x.bag", tmp_path / "x.mcap", options=PNG)
    with pytest.raises(InputError, match="not a ROS bag"):
        convert_bag(tmp_path, tmp_path / "y.mcap", options=PNG)


def test_unfinished_recordings_say_what_to_do(tmp_path):
    """What a recorder leaves when it is killed: a ROS 1 `.bag.active` without its index, a ROS 2 folder
    without metadata.yaml, an MCAP storage file without its end. Each gets its own error and remedy
    (before: "recording folder not found", "calibration file not found", "File end magic is invalid")."""
    write_bag(tmp_path / "r.bag", BagSpec(frames=2))
    (tmp_path / "r.bag").rename(tmp_path / "r.bag.active")
    with pytest.raises(InputError, match=r"unfinished ROS 1 bag .*rosbag reindex"):
        convert_bag(tmp_path / "r.bag.active", tmp_path / "r.mcap", options=PNG)
    spec = write_bag(tmp_path / "r2", BagSpec(ros2=True, frames=2))
    (tmp_path / "r2" / "metadata.yaml").unlink()
    (db3,) = (tmp_path / "r2").glob("*.db3")
    assert bag_scan.is_bag(tmp_path / "r2")
    with pytest.raises(InputError, match=rf"without metadata.yaml .*ros2 bag reindex.* \({db3.name}\)"):
        convert_bag(tmp_path / "r2", tmp_path / "r2.mcap", options=PNG)
    assert main(["convert", "--quiet", str(tmp_path / "r2"), str(tmp_path / "r2.mcap")]) == 1
    assert not (tmp_path / "r2.mcap").exists()
    check_recording(convert_bag(db3, tmp_path / "alone.mcap", options=PNG), spec)  # the remedy works
    mcap = write_bag(tmp_path / "m", BagSpec(ros2=True, storage=StoragePlugin.MCAP, frames=2))
    (file,) = (tmp_path / "m").glob("*.mcap")
    check_recording(convert_bag(tmp_path / "m", tmp_path / "m.mcap", options=PNG), mcap)
    file.write_bytes(file.read_bytes()[:-100])  # the recorder killed before the summary and footer
    for given in (tmp_path / "m", file):
        with pytest.raises(InputError, match=r"m.mcap: the MCAP file stops before its end .*mcap recover"):
            convert_bag(given, tmp_path / "m2.mcap", options=PNG)
    raw_folder_with_an_output_inside = tmp_path / "raw"
    raw_folder_with_an_output_inside.mkdir()
    (raw_folder_with_an_output_inside / "frames.csv").write_text("frame,timestamp_ns\n")
    (raw_folder_with_an_output_inside / "out.mcap").write_bytes(b"")
    assert not bag_scan.is_bag(raw_folder_with_an_output_inside)


def test_inspect_bag(tmp_path, capsys):
    write_bag(tmp_path / "s.bag", BagSpec(force_topics=("/netft_data", "/PSM1/body/measured_cf")))
    text = inspect_bag_text(tmp_path / "s.bag")
    lines = {line.split()[0]: line for line in text.splitlines() if line.startswith("/")}
    assert "sensor_msgs/msg/Image" in lines[LEFT] and " 8 " in lines[LEFT]
    assert "left images (dVRK default)" in lines[LEFT]
    assert "30.00" in lines[LEFT]  # Hz
    assert "force (default)" in lines["/netft_data"] and "1000.00" in lines["/netft_data"]
    assert "used as" not in lines["/PSM1/body/measured_cf"] and lines["/PSM1/body/measured_cf"].split()[-1] != "force"
    assert "ECM pose (dVRK default)" in lines["/ECM/measured_cp"]
    assert "stereo pairs: 8 within 16.7 ms" in text and "ready to convert" in text
    assert "reading: random access: ROS 1 chunks, memory-mapped" in text
    # how each storage is read
    for name, spec, reading in (
            ("lz4.bag", BagSpec(lz4=True, frames=2), "streaming through rosbags"),
            ("sq", BagSpec(ros2=True, frames=2), "random access: sqlite3 rows"),
            ("mc", BagSpec(ros2=True, storage=StoragePlugin.MCAP, frames=2), "random access: MCAP chunks"),
            ("zs", BagSpec(ros2=True, storage=StoragePlugin.MCAP, zstd=True, frames=2), "streaming through rosbags")):
        write_bag(tmp_path / name, spec)
        assert f"reading: {reading}" in inspect_bag_text(tmp_path / name), name
    assert main(["inspect-bag", str(tmp_path / "s.bag"), "--quiet"]) == 0
    assert "ready to convert" in capsys.readouterr().out
    # a bag that cannot be converted is still listed, with the reason, and exits 1 saying it in one line
    write_bag(tmp_path / "n.bag", BagSpec(with_images=False, frames=2))
    assert main(["inspect-bag", str(tmp_path / "n.bag"), "--quiet"]) == 1
    captured = capsys.readouterr()
    assert "/netft_data " in captured.out and "cannot convert: no image topic found" in captured.out
    assert captured.err.strip().startswith(f"vfdata inspect-bag: error: {tmp_path / 'n.bag'}: cannot convert: no "
                                           "image topic found"), captured.err
    assert len(captured.err.strip().splitlines()) == 1, captured.err
    # ... also when the problem shows only while reading the messages
    write_bag(tmp_path / "f.bag", BagSpec(encoding="32FC1", frames=2))
    text = inspect_bag_text(tmp_path / "f.bag")
    assert "left images (dVRK default)" in text
    assert "cannot convert: /jhu_daVinci/left/image_raw: message 0: unsupported image encoding '32FC1'" in text
    assert main(["inspect-bag", str(tmp_path / "f.bag"), "--quiet"]) == 1
    assert "unsupported image encoding '32FC1'" in capsys.readouterr().err


def test_cli_convert_bag(tmp_path, capsys):
    spec = write_bag(tmp_path / "cli", BagSpec(ros2=True, storage=StoragePlugin.MCAP, pose_type="TransformStamped",
                                               frames=4))
    out = tmp_path / "cli.mcap"
    assert main(["convert", str(tmp_path / "cli"), str(out), "--format", "png", "--quiet"]) == 0
    check_recording(out, spec)
    assert main(["convert", str(tmp_path / "cli"), str(out), "--quiet", "--overwrite", "--force-topic", "/nope"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"vfdata convert: error: {tmp_path / 'cli'}: --force-topic /nope: no such topic in the bag"
    assert check_file(out) == []  # the earlier output is untouched
    # one storage file of a ROS 2 bag, given alone
    storage_file = next((tmp_path / "cli").glob("*.mcap"))
    assert bag_scan.is_bag(storage_file)
    assert main(["convert", str(storage_file), str(tmp_path / "file.mcap"), "--format", "png", "--quiet"]) == 0
    check_recording(tmp_path / "file.mcap", spec)
