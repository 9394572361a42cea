"""Random access into ROS 1 and ROS 2 bags (`vfdata.conversion.bag_index`), bulk decoding and bulk
writing, and the falls back to `rosbags` when a bag's index or records cannot be trusted; the bags are
written here with `rosbags` and every fast path is checked against its plain iterator."""

from __future__ import annotations

import logging
import shutil
import sqlite3
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import yaml
from bagfixtures import (
    BASELINE_M,
    FORCE_NS,
    FRAME_NS,
    FX,
    T0_NS,
    BagSpec,
    check_recording,
    write_bag,
)
from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType
from mcap.writer import Writer as McapFileWriter
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from vfdata.cli import main
from vfdata.conversion import bag_index, bag_scan, bag_topics, bags, image_messages, write_recording
from vfdata.conversion.bags import convert_bag
from vfdata.conversion.raw_folder import ConvertOptions
from vfdata.errors import InputError
from vfdata.recording import layout
from vfdata.recording.messages import (
    CameraInfo,
    CompressedImage,
    WrenchStamped,
    encode_stamped_batch,
)
from vfdata.recording.writer import McapWriter

PNG = ConvertOptions(image_format="png", progress=False)


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
