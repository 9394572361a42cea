"""ROS 1 and ROS 2 bags -> recording MCAP. The bags are written here with `rosbags` (dVRK topic names,
both ECM pose types, raw and compressed images) and the converted file is checked topic by topic,
value by value, through `vfdata.Recording`."""

from __future__ import annotations

import logging
import shutil
import sqlite3
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from bagfixtures import (
    BASELINE_M,
    CX,
    CY,
    FORCE_NS,
    FRAME_NS,
    FX,
    LEFT,
    RIGHT,
    T0_NS,
    BagSpec,
    write_bag,
)
from convert_fixtures import chunk_messages, out_of_order_chunks
from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType
from mcap.writer import Writer as McapFileWriter
from rawfixtures import calibration
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import CompressionMode, StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from vfdata.cli import main
from vfdata.commands.inspect_bag import inspect_bag_text
from vfdata.conversion import bag_index, bag_scan, bag_topics, bags, image_messages, ros_images, write_recording
from vfdata.conversion.bag_topics import BagTopics
from vfdata.conversion.bags import convert_bag
from vfdata.conversion.raw_folder import ConvertOptions
from vfdata.errors import InputError, OutputExistsError
from vfdata.recording import layout
from vfdata.recording.cdr import CdrError
from vfdata.recording.inspect import check_file
from vfdata.recording.messages import (
    CameraInfo,
    CompressedImage,
    PoseStamped,
    WrenchStamped,
    decode_stamped_batch,
    encode_stamped_batch,
)
from vfdata.recording.reader import Recording
from vfdata.recording.writer import McapWriter

PNG = ConvertOptions(image_format="png", progress=False)


def check_recording(out: Path, spec: BagSpec) -> Recording:
    assert check_file(out) == []  # what `vfdata check` runs: layout, stamps, CRCs
    rec = Recording.open(out)
    n = spec.frames
    # frames: the left stamps, both images carry them; pixels exact for PNG output
    assert np.array_equal(rec.frame_times_ns, spec.frame_ns)
    assert np.array_equal(rec.log_times_ns(layout.RIGHT_IMAGE), spec.frame_ns)
    for i in range(n):
        frame = rec.frame(i)
        left, right = spec.images[i]
        if spec.encoding == "mono8":
            left, right = (cv2.cvtColor(img[..., 1], cv2.COLOR_GRAY2BGR) for img in (left, right))
        assert np.array_equal(frame.left, left) and np.array_equal(frame.right, right)
    # camera info every frame, with the bag's K, D, P and the layout's frame ids
    assert rec.topics[layout.LEFT_INFO].count == n and rec.topics[layout.RIGHT_INFO].count == n
    info_l, info_r = rec.camera_infos
    assert (info_l.frame_id, info_r.frame_id) == (layout.LEFT_FRAME, layout.RIGHT_FRAME)
    assert (info_l.width, info_l.height) == (spec.width, spec.height)
    assert np.array_equal(info_l.k, [[FX, 0, CX], [0, FX, CY], [0, 0, 1]])
    assert np.array_equal(info_l.d, [0.01, -0.02, 0.0, 0.0, 0.001])
    assert info_r.p[0, 3] == -FX * BASELINE_M
    assert rec.stereo.baseline_mm == pytest.approx(BASELINE_M * 1000)
    tf = rec.message(layout.TF_STATIC, 0).transforms[0]
    assert (tf.frame_id, tf.child_frame_id) == (layout.LEFT_FRAME, layout.RIGHT_FRAME)
    assert tf.translation == pytest.approx((BASELINE_M, 0.0, 0.0))
    # force: every sample, stamps and values exact
    force = rec.force
    assert np.array_equal(force.times_ns, spec.force_ns)
    assert np.array_equal(force.wrench, spec.wrench)
    assert force.frame_id == "ati_sensor"
    # pose, as PoseStamped whatever the bag had
    if spec.pose_type:
        pose = rec.ecm_pose
        assert np.array_equal(pose.times_ns, spec.pose_ns)
        assert np.allclose(pose.position_m, spec.pose[:, :3], atol=1e-15)
        assert np.allclose(pose.quaternion_xyzw, spec.pose[:, 3:], atol=1e-15)
        assert rec.topics[layout.ECM_POSE].msgtype == "geometry_msgs/msg/PoseStamped"
    else:
        assert not rec.has(layout.ECM_POSE)
    # the file is in time order
    assert rec.metadata.converter.startswith("vfdata convert (ROS")
    return rec


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
    from mcap.reader import make_reader

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
    # a bag that cannot be converted is still listed, with the reason
    write_bag(tmp_path / "n.bag", BagSpec(with_images=False, frames=2))
    assert main(["inspect-bag", str(tmp_path / "n.bag"), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "/netft_data " in out and "cannot convert: no image topic found" in out
    # ... also when the problem shows only while reading the messages
    write_bag(tmp_path / "f.bag", BagSpec(encoding="32FC1", frames=2))
    text = inspect_bag_text(tmp_path / "f.bag")
    assert "left images (dVRK default)" in text
    assert "cannot convert: /jhu_daVinci/left/image_raw: message 0: unsupported image encoding '32FC1'" in text


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


# -- random access (bag_index), bulk decoding and bulk writing ----------------------------------------
def bag_with_every_shape(path: Path, ros2: bool, lz4: bool = False,
                         storage: StoragePlugin = StoragePlugin.SQLITE3) -> None:
    """A small bag with Image and CompressedImage messages whose frame_id and encoding lengths cover
    every CDR alignment, force from two publishers of one topic (ROS 1), and both pose types."""
    ts = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    T = ts.types
    serialize = ts.serialize_cdr if ros2 else ts.serialize_ros1

    def header(stamp: int, frame: str):
        time = T["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
        return T["std_msgs/msg/Header"](stamp=time, frame_id=frame) if ros2 else T["std_msgs/msg/Header"](
            seq=7, stamp=time, frame_id=frame)

    vec = T["geometry_msgs/msg/Vector3"]
    quat = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.6, w=0.8)
    writer = Writer2(path, version=9, storage_plugin=storage) if ros2 else Writer1(path)
    if lz4:
        writer.set_compression(Writer1.CompressionFormat.LZ4)
    with writer:
        image = writer.add_connection("/cam/image", "sensor_msgs/msg/Image", typestore=ts)
        compressed = writer.add_connection("/cam/compressed", "sensor_msgs/msg/CompressedImage", typestore=ts)
        kw = {} if ros2 else {"callerid": "/netft_a"}
        forces = [writer.add_connection("/netft_data", "geometry_msgs/msg/WrenchStamped", typestore=ts, **kw)]
        if not ros2:
            forces.append(writer.add_connection("/netft_data", "geometry_msgs/msg/WrenchStamped", typestore=ts,
                                                callerid="/netft_b"))
        poses = writer.add_connection("/pose", "geometry_msgs/msg/PoseStamped", typestore=ts)
        transforms = writer.add_connection("/tf_pose", "geometry_msgs/msg/TransformStamped", typestore=ts)
        for i in range(9):
            stamp = T0_NS + i * FRAME_NS
            frame, encoding = "f" * i, ("mono8", "bgr8", "rgb8", "bayer_rggb8")[i % 4]
            pixels = np.arange(4 * 6 * 3, dtype=np.uint8) + i
            writer.write(image, stamp + 1, serialize(T["sensor_msgs/msg/Image"](
                header=header(stamp, frame), height=4, width=6, encoding=encoding, is_bigendian=0, step=18,
                data=pixels), "sensor_msgs/msg/Image"))
            writer.write(compressed, stamp + 2, serialize(T["sensor_msgs/msg/CompressedImage"](
                header=header(stamp, frame), format="jpeg"[: 1 + i % 4], data=pixels[: 5 + i]),
                "sensor_msgs/msg/CompressedImage"))
            for j in range(20):
                t = stamp + j * FORCE_NS
                writer.write(forces[j % len(forces)], t + 3, serialize(T["geometry_msgs/msg/WrenchStamped"](
                    header=header(t, "ati" if i < 5 else "ati_2"), wrench=T["geometry_msgs/msg/Wrench"](
                        force=vec(x=t % 7 + 0.5, y=-1.25, z=j / 3), torque=vec(x=1e-3, y=i / 7, z=-j))),
                    "geometry_msgs/msg/WrenchStamped"))
            point = T["geometry_msgs/msg/Point"](x=0.1 * i, y=0.2, z=0.3)
            writer.write(poses, stamp + 4, serialize(T["geometry_msgs/msg/PoseStamped"](
                header=header(stamp, "ECM_base"), pose=T["geometry_msgs/msg/Pose"](position=point, orientation=quat)),
                "geometry_msgs/msg/PoseStamped"))
            writer.write(transforms, stamp + 5, serialize(T["geometry_msgs/msg/TransformStamped"](
                header=header(stamp, "ECM_base"), child_frame_id="ECM"[: i % 4], transform=T[
                    "geometry_msgs/msg/Transform"](translation=vec(x=0.1, y=0.2, z=0.1 * i), rotation=quat)),
                "geometry_msgs/msg/TransformStamped"))


def iterated(reader, topic: str) -> list[tuple[int, bytes]]:
    connections = [c for c in reader.connections if c.topic == topic]
    return [(t, bytes(raw)) for _, t, raw in reader.messages(connections=connections)]


INDEXED = [(False, StoragePlugin.SQLITE3), (True, StoragePlugin.SQLITE3), (True, StoragePlugin.MCAP)]
INDEXED_IDS = ["ros1", "ros2-sqlite3", "ros2-mcap"]


@pytest.mark.parametrize("ros2, storage", INDEXED, ids=INDEXED_IDS)
def test_indexed_access_matches_rosbags_iterator(tmp_path, ros2, storage):
    bag = tmp_path / ("b" if ros2 else "b.bag")
    bag_with_every_shape(bag, ros2, storage=storage)
    with bag_scan.open_bag(bag) as reader:
        topics = set(reader.topics)
        indexed = bag_index.open_indexed_bag(reader, bag, topics)
        assert indexed is not None
        try:
            for topic in topics:
                expect = iterated(reader, topic)
                assert indexed.receive_ns(topic).tolist() == [t for t, _ in expect], topic
                assert [bytes(indexed.message(topic, i)) for i in range(len(expect))] == [m for _, m in expect]
                assert [bytes(indexed.head(topic, i)) for i in range(len(expect))] == [
                    m[:bag_index.HEAD_BYTES] for _, m in expect]
                blocks = list(indexed.payload_blocks(topic))
                assert np.concatenate([r for r, _ in blocks]).tolist() == [t for t, _ in expect]
                assert [bytes(p) for _, payloads in blocks for p in payloads] == [m for _, m in expect]
            assert isinstance(next(indexed.payload_blocks("/pose"))[1], np.ndarray)  # one payload length
            assert isinstance(next(indexed.payload_blocks("/netft_data"))[1], list)  # two frame_id lengths
        finally:
            indexed.close()


@pytest.mark.parametrize("ros2, storage", INDEXED, ids=INDEXED_IDS)
def test_indexed_access_from_several_threads(tmp_path, ros2, storage):
    """The encoding threads fetch their images themselves: from two threads at once every message
    comes back whole (a sqlite3 bag gives each thread its own connections, which sqlite would
    otherwise take in turns), and closing the bag closes them all."""
    bag = tmp_path / ("b" if ros2 else "b.bag")
    bag_with_every_shape(bag, ros2, storage=storage)
    with bag_scan.open_bag(bag) as reader:
        topics = set(reader.topics)
        expect = {topic: iterated(reader, topic) for topic in topics}
        indexed = bag_index.open_indexed_bag(reader, bag, topics)
        jobs = [(topic, i) for topic in sorted(topics) for i in range(len(expect[topic]))] * 4
        with ThreadPoolExecutor(2) as pool:
            got = list(pool.map(lambda job: bytes(indexed.message(*job)), jobs))
            assert got == [expect[topic][i][1] for topic, i in jobs]
            indexed.close()
            if storage == StoragePlugin.SQLITE3 and ros2:  # closed for the threads that read, and after
                for thread in (pool, ThreadPoolExecutor(1)):
                    with pytest.raises(sqlite3.ProgrammingError):
                        thread.submit(indexed.message, *jobs[0]).result()


def test_indexed_access_only_where_cheap(tmp_path):
    bag_with_every_shape(tmp_path / "lz4.bag", ros2=False, lz4=True)
    write_bag(tmp_path / "zstd", BagSpec(ros2=True, storage=StoragePlugin.MCAP, zstd=True, frames=2))
    for bag in (tmp_path / "lz4.bag", tmp_path / "zstd"):
        with bag_scan.open_bag(bag) as reader:
            assert bag_index.open_indexed_bag(reader, bag, set(reader.topics)) is None


@pytest.mark.parametrize("ros2", [False, True])
def test_image_heads_and_messages_match_deserialisation(tmp_path, ros2):
    bag = tmp_path / ("b" if ros2 else "b.bag")
    bag_with_every_shape(bag, ros2)
    with bag_scan.open_bag(bag) as reader:
        for topic, msgtype in (("/cam/image", bag_topics.IMAGE), ("/cam/compressed", bag_topics.COMPRESSED_IMAGE)):
            for _, raw in iterated(reader, topic):
                msg = reader.deserialize(raw, msgtype)
                head = image_messages.image_head(raw[:bag_index.HEAD_BYTES], msgtype, ros2)
                assert head == bag_scan._head_of(msg)
                assert head.stamp_ns == bag_scan.header_stamp_ns(msg) and head.stamp_ns >= T0_NS
                # cut before the last field it needs: no head, the caller deserialises the message
                assert image_messages.image_head(raw[:head_length(raw, msgtype, ros2) - 1], msgtype, ros2) is None
                # the whole message, its data a view into the serialised bytes
                whole = image_messages.image_message(raw, msgtype, ros2)
                assert whole.head == head and bytes(whole.data) == msg.data.tobytes()
                if msgtype == bag_topics.IMAGE:
                    assert (whole.is_bigendian, whole.step) == (msg.is_bigendian, msg.step) == (0, 18)
                from_rosbags = bag_scan.image_message_of(msg)
                assert (from_rosbags.head, bytes(from_rosbags.data), from_rosbags.step) == (
                    whole.head, bytes(whole.data), whole.step)
                assert image_messages.image_message(raw[:-4 if ros2 else -1], msgtype, ros2) is None  # data cut short
    big_endian = b"\x00\x00\x00\x00" + bytes(40)  # a CDR encapsulation header saying big-endian
    assert image_messages.image_head(big_endian, bag_topics.IMAGE, ros2=True) is None


def head_length(raw: bytes, msgtype: str, ros2: bool) -> int:
    """Bytes up to the end of the last field `image_head` reads (found by growing the prefix)."""
    return next(n for n in range(len(raw) + 1) if image_messages.image_head(raw[:n], msgtype, ros2) is not None)


@pytest.mark.parametrize("ros2", [False, True])
def test_bulk_series_decoding_matches_deserialisation(tmp_path, ros2):
    bag = tmp_path / ("b" if ros2 else "b.bag")
    bag_with_every_shape(bag, ros2)
    with bag_scan.open_bag(bag) as reader:
        for topic, width in (("/netft_data", 6), ("/pose", 7)):
            raws = [m for _, m in iterated(reader, topic)]
            first_frame = raws[:100]  # frame "ati" (WrenchStamped) / "ECM_base" (PoseStamped) only
            stamps, values, frame_id = bag_scan._decode_fixed_batch(first_frame, width, ros2)
            messages = [reader.deserialize(raw, reader.topics[topic].msgtype) for raw in first_frame]
            assert stamps.tolist() == [bag_scan.header_stamp_ns(m) for m in messages]
            assert frame_id == messages[0].header.frame_id == ("ati" if width == 6 else "ECM_base")
            fields = [(m.wrench.force, m.wrench.torque) if width == 6 else bag_scan._pose_fields(m) for m in messages]
            expect = [[v.x, v.y, v.z] + ([v.w] if hasattr(v, "w") else []) for f in fields for v in f]
            assert values.ravel().tolist() == [x for row in expect for x in row]
            table = np.frombuffer(b"".join(first_frame), np.uint8).reshape(len(first_frame), -1)
            assert np.array_equal(bag_scan._decode_fixed_batch(table, width, ros2)[1], values)
        # two frame ids in one block: not decoded in bulk (the caller goes message by message)
        assert bag_scan._decode_fixed_batch([m for _, m in iterated(reader, "/netft_data")], 6, ros2) is None
        series = bag_scan._SeriesReader(reader, bag, "/netft_data", 6)
        connection = next(c for c in reader.connections if c.topic == "/netft_data")
        for receive_ns, raw in iterated(reader, "/netft_data"):
            series.add(connection, receive_ns, raw)
        result = series.result()
        assert len(result.stamps_ns) == 9 * 20 and result.frame_id == ""  # two frame ids: none kept


@pytest.mark.parametrize("ros2, storage", INDEXED, ids=INDEXED_IDS)
def test_indexed_and_streamed_conversions_are_identical(tmp_path, ros2, storage):
    """The random-access path and rosbags' iterator (used for lz4 ROS 1 chunks and zstd MCAP chunks)
    give the same recording, message by message."""
    fast, slow = tmp_path / ("fast" if ros2 else "fast.bag"), tmp_path / ("slow" if ros2 else "slow.bag")
    spec = BagSpec(ros2=ros2, storage=storage, extra_right_ns=(T0_NS + FRAME_NS // 2,), pose_type="TransformStamped")
    write_bag(fast, spec)
    write_bag(slow, BagSpec(ros2=ros2, storage=StoragePlugin.MCAP, lz4=not ros2, zstd=ros2,
                            extra_right_ns=spec.extra_right_ns, pose_type="TransformStamped"))
    with bag_scan.open_bag(fast) as reader:
        assert bag_index.open_indexed_bag(reader, fast, set(reader.topics)) is not None
    with bag_scan.open_bag(slow) as reader:
        assert bag_index.open_indexed_bag(reader, slow, set(reader.topics)) is None
    contents = [raw_messages(convert_bag(bag, tmp_path / f"{bag.stem}.mcap", options=PNG)) for bag in (fast, slow)]
    check_recording(tmp_path / "fast.mcap", spec)
    assert contents[0] == contents[1]


def split_bag(src: Path, dst: Path, storage: StoragePlugin) -> None:
    """`src` rewritten as a ROS 2 bag of two storage files, as `ros2 bag record --max-bag-size` makes:
    the first half of the messages in one file, the rest in the other, one metadata.yaml for both."""
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    with AnyReader([src]) as reader:
        messages = [(c.topic, c.msgtype, t, bytes(raw)) for c, t, raw in reader.messages()]
    dst.mkdir()
    infos = []
    for k, part_messages in enumerate((messages[:len(messages) // 2], messages[len(messages) // 2:])):
        part = dst.parent / f"{dst.name}_part{k}"
        with Writer2(part, version=9, storage_plugin=storage) as writer:
            connections = {}
            for topic, msgtype, t, raw in part_messages:
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
                writer.write(connections[topic], t, raw)
        info = yaml.safe_load((part / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        (name,) = info["relative_file_paths"]
        renamed = f"{dst.name}_{k}{Path(name).suffix}"
        shutil.move(part / name, dst / renamed)
        shutil.rmtree(part)
        for file in info["files"]:
            file["path"] = renamed
        infos.append(info)
    merged = infos[0]
    merged["relative_file_paths"] = [info["files"][0]["path"] for info in infos]
    merged["files"] = [file for info in infos for file in info["files"]]
    merged["message_count"] = sum(info["message_count"] for info in infos)
    topics: dict[str, dict] = {}
    for info in infos:
        for entry in info["topics_with_message_count"]:
            name = entry["topic_metadata"]["name"]
            if name in topics:
                topics[name]["message_count"] += entry["message_count"]
            else:
                topics[name] = entry
    merged["topics_with_message_count"] = list(topics.values())
    end = max(info["starting_time"]["nanoseconds_since_epoch"] + info["duration"]["nanoseconds"] for info in infos)
    merged["duration"]["nanoseconds"] = end - merged["starting_time"]["nanoseconds_since_epoch"]
    (dst / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": merged}))


@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP], ids=["sqlite3", "mcap"])
def test_split_ros2_bag_converts_like_the_whole(tmp_path, storage):
    """A bag recorded in two storage files is read file by file through the random-access path and
    gives the recording the single-file bag gives."""
    whole, split = tmp_path / "whole", tmp_path / "split"
    spec = write_bag(whole, BagSpec(ros2=True, storage=storage))
    split_bag(whole, split, storage)
    assert len(list(split.glob("split_*"))) == 2
    with bag_scan.open_bag(split) as reader:
        indexed = bag_index.open_indexed_bag(reader, split, set(reader.topics))
        assert indexed is not None
        try:
            for topic in reader.topics:
                assert bytes(indexed.message(topic, len(iterated(reader, topic)) - 1)) == iterated(reader, topic)[-1][1]
        finally:
            indexed.close()
    contents = [raw_messages(convert_bag(bag, tmp_path / f"{bag.name}.mcap", options=PNG)) for bag in (whole, split)]
    check_recording(tmp_path / "split.mcap", spec)
    assert contents[0] == contents[1]


def test_leftover_write_ahead_log_is_reported_and_the_db3_read_as_it_is(tmp_path, caplog):
    """A ROS 2 bag whose recorder was killed while writing through sqlite's write-ahead log (the
    resilient preset) has its last messages only in `<file>.db3-wal`: the conversion says so, and
    reads the .db3 as it is, as `rosbags` does."""
    bag, crashed = tmp_path / "bag", tmp_path / "crashed"
    write_bag(bag, BagSpec(ros2=True))
    clean = raw_messages(convert_bag(bag, tmp_path / "clean.mcap", options=PNG))
    (db3,) = bag.glob("*.db3")
    recorder = sqlite3.connect(db3)
    try:
        recorder.execute("PRAGMA journal_mode = WAL")
        recorder.execute("PRAGMA wal_autocheckpoint = 0")  # the last batch stays in the log
        recorder.execute("INSERT INTO messages (topic_id, timestamp, data) SELECT topic_id, timestamp + 1, data "
                         "FROM messages WHERE id = (SELECT max(id) FROM messages)")
        recorder.commit()
        shutil.copytree(bag, crashed)  # what the disk holds if the recorder is killed now
    finally:
        recorder.close()
    assert (crashed / f"{db3.name}-wal").stat().st_size > 0
    assert not (bag / f"{db3.name}-wal").exists()  # closed cleanly: sqlite removed it
    with caplog.at_level(logging.WARNING):
        out = convert_bag(crashed, tmp_path / "crashed.mcap", options=PNG)
    assert f"{db3.name}-wal is left beside it (the recording did not end cleanly)" in caplog.text
    assert raw_messages(out) == clean


def raw_messages(path: Path) -> dict[str, list[tuple[int, bytes]]]:
    """Topic -> (log time, payload) of every message, read with the `mcap` package."""
    topics: dict[str, list[tuple[int, bytes]]] = {}
    with open(path, "rb") as stream:
        for _schema, channel, message in make_reader(stream).iter_messages(log_time_order=True):
            topics.setdefault(channel.topic, []).append((message.log_time, bytes(message.data)))
    return topics


def test_damaged_record_falls_back_to_rosbags_and_its_error(tmp_path):
    bag = tmp_path / "d.bag"
    write_bag(bag, BagSpec(frames=3))
    with bag_scan.open_bag(bag) as reader:
        indexed = bag_index.open_indexed_bag(reader, bag, {"/netft_data"})
        position = int(indexed._refs["/netft_data"][2][10])  # data of the 11th force message
        indexed.close()
    data = bytearray(bag.read_bytes())
    record = data.rfind(b"op=\x02", 0, position)  # its record header's op field
    data[record + 3] = 6  # a chunk-info op where a message should be
    bag.write_bytes(bytes(data))
    with bag_scan.open_bag(bag) as reader:
        assert bag_index.open_indexed_bag(reader, bag, {"/netft_data"}) is None
    with pytest.raises(InputError, match="damaged bag"):
        convert_bag(bag, tmp_path / "d.mcap", options=PNG)


def test_mcap_record_that_disagrees_with_its_index_falls_back_to_rosbags(tmp_path):
    bag = tmp_path / "m"
    spec = write_bag(bag, BagSpec(ros2=True, storage=StoragePlugin.MCAP, frames=3))
    with bag_scan.open_bag(bag) as reader:
        indexed = bag_index.open_indexed_bag(reader, bag, {"/netft_data"})
        assert isinstance(indexed, bag_index._McapBag)
        position = int(indexed._refs["/netft_data"][2][10])  # data of the 11th force message
        indexed.close()
    (file,) = bag.glob("*.mcap")
    data = bytearray(file.read_bytes())
    channel_at = position - bag_index._MCAP_MESSAGE_FIXED  # channel id, then sequence and the two times
    data[channel_at] ^= 0x7F
    file.write_bytes(bytes(data))
    with bag_scan.open_bag(bag) as reader:
        assert bag_index.open_indexed_bag(reader, bag, {"/netft_data"}) is None
        assert bag_index.open_indexed_bag(reader, bag, {spec.left}) is not None  # only the topics asked for


def _rewrite_mcap_bag(file: Path, index_types: IndexType = IndexType.ALL) -> None:
    """The bag's MCAP file written again by the `mcap` package (chunk CRCs, as rosbag2's C++ writer
    writes them; rosbags writes none)."""
    with open(file, "rb") as stream:
        messages = list(make_reader(stream).iter_messages())
    with open(file, "wb") as stream:
        writer = McapFileWriter(stream, compression=CompressionType.NONE, index_types=index_types)
        writer.start(profile="ros2")
        schemas, channels = {}, {}
        for schema, channel, message in messages:
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas[schema.id], channel.metadata)
            writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time)
        writer.finish()


def test_mcap_without_message_indexes_falls_back(tmp_path):
    """A writer may leave out the message indexes (the chunk indexes then point at none): the
    statistics still count the messages, so the missing ones are noticed and the bag is streamed."""
    bag = tmp_path / "m"
    write_bag(bag, BagSpec(ros2=True, storage=StoragePlugin.MCAP, frames=3))
    (file,) = bag.glob("*.mcap")
    _rewrite_mcap_bag(file, IndexType.CHUNK)
    with bag_scan.open_bag(bag) as reader:
        assert bag_index.open_indexed_bag(reader, bag, {"/netft_data"}) is None


def test_mcap_bag_chunk_failing_its_crc_is_refused(tmp_path):
    bag = tmp_path / "m"
    write_bag(bag, BagSpec(ros2=True, storage=StoragePlugin.MCAP, frames=3))
    (file,) = bag.glob("*.mcap")
    _rewrite_mcap_bag(file)
    clean = raw_messages(convert_bag(bag, tmp_path / "clean.mcap", options=PNG))
    with bag_scan.open_bag(bag) as reader:
        indexed = bag_index.open_indexed_bag(reader, bag, {"/netft_data"})
        assert isinstance(indexed, bag_index._McapBag)  # random access, the path that checks the CRCs
        position = int(indexed._refs["/netft_data"][2][10])  # data of the 11th force message
        indexed.close()
    data = bytearray(file.read_bytes())
    data[position + 30] ^= 0x10  # a bit of a force value: the records still match their indexes
    file.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"the chunk at byte \d+ fails its CRC: the bag is damaged"):
        convert_bag(bag, tmp_path / "damaged.mcap", options=PNG)
    assert not (tmp_path / "damaged.mcap").exists() and clean


def test_bit_flips_in_a_ros1_bag_end_in_its_data_or_one_line(tmp_path, capsys):
    """rosbags fails on a damaged ROS 1 chunk in many ways (AssertionError, IndexError, LZ4's
    RuntimeError): each must be a one-line error naming the bag. ROS 1 bags have no checksums, so a
    flip inside a value cannot be noticed; it must not crash."""
    bag = tmp_path / "x.bag"
    write_bag(bag, BagSpec(frames=4, lz4=True))
    pristine = bag.read_bytes()
    for at in range(0, len(pristine), len(pristine) // 60):
        damaged = bytearray(pristine)
        damaged[at] ^= 0x24
        bag.write_bytes(bytes(damaged))
        out = tmp_path / "out.mcap"
        code = main(["convert", "--quiet", "--format", "png", "--overwrite", str(bag), str(out)])
        err = capsys.readouterr().err.strip()
        assert code in (0, 1) and "internal error" not in err, (at, err)
        assert code == 0 or (len(err.splitlines()) == 1 and str(bag) in err), (at, err)


def test_payload_helpers_match_message_encoding():
    info = CameraInfo(5, layout.LEFT_FRAME, 48, 64, "plumb_bob", np.zeros(5), np.eye(3), np.eye(3),
                      np.hstack([np.eye(3), np.ones((3, 1))]), 0, 0, (0, 0, 0, 0, False))
    stamp = 1_700_000_000_987_654_321
    expect = CameraInfo(**{**info.__dict__, "stamp_ns": stamp}).encode()
    assert write_recording.restamped(info.encode(), stamp) == expect
    for frame in ("", "a", "stereo_left_optical"):
        for fmt in ("jpeg", "png"):
            data = np.arange(11, dtype=np.uint8).reshape(-1, 1)  # cv2.imencode's shape
            assert write_recording.compressed_image_payload(stamp, frame, fmt, data) == CompressedImage(
                stamp, frame, fmt, data.tobytes()).encode()


def test_write_payloads_equals_one_write_per_message(tmp_path):
    """`McapWriter.write_payloads` (used for the force and pose series) writes the same bytes as one
    `write_payload` per message, chunk boundaries included."""
    rng = np.random.default_rng(0)
    stamps = np.sort(rng.integers(10**18, 2 * 10**18, 700))
    table = encode_stamped_batch(stamps, "ati", rng.normal(size=(700, 6)))
    for kwargs in ({"separate_topics": ("/f",), "separate_batch": 64}, {"chunk_size": 5000}):
        for name, bulk in (("one.mcap", False), ("bulk.mcap", True)):
            with McapWriter(tmp_path / name, overwrite=True, **kwargs) as writer:
                writer.write_payload("/img", CompressedImage.msgtype, int(stamps[0]), b"x" * 1000)
                for part in np.array_split(np.arange(700), [5, 6, 300]):
                    if bulk:
                        writer.write_payloads("/f", WrenchStamped.msgtype, stamps[part], table[part])
                    else:
                        for i in part:
                            writer.write_payload("/f", WrenchStamped.msgtype, int(stamps[i]), table[i].tobytes())
        assert (tmp_path / "one.mcap").read_bytes() == (tmp_path / "bulk.mcap").read_bytes()
        force = raw_messages(tmp_path / "bulk.mcap")["/f"]
        assert force == [(int(t), row.tobytes()) for t, row in zip(stamps, table, strict=True)]


def test_ros2_camera_info_read_without_rosbags_matches_it(tmp_path):
    write_bag(tmp_path / "b", BagSpec(ros2=True, frames=2))
    with bag_scan.open_bag(tmp_path / "b") as reader:
        connection = next(c for c in reader.connections if c.topic == "/jhu_daVinci/right/camera_info")
        raw = iterated(reader, connection.topic)[0][1]
        ours = bag_scan._first_camera_info(reader, tmp_path / "b", raw, connection)
        theirs = reader.deserialize(raw, connection.msgtype)
        assert isinstance(ours, CameraInfo) and not isinstance(theirs, CameraInfo)
        a, b = (bags.bag_camera_info(tmp_path / "b", connection.topic, m, layout.RIGHT_FRAME) for m in (ours, theirs))
        for name in ("frame_id", "height", "width", "distortion_model", "binning_x", "binning_y", "roi"):
            assert getattr(a, name) == getattr(b, name), name
        for name in ("d", "k", "r", "p"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert a.p[0, 3] == -FX * BASELINE_M
