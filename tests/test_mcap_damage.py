"""Damaged recordings: truncations at every 5 % and single-bit flips in every region of a small
recording (header, definitions, metadata, image chunks, force and pose chunks, message indexes, data
end, summary, footer). Each case must end in the original data, a named error (FormatError), or, for
a truncated file, a part of the original data with the damage listed in `problems`: never altered
data served silently, nor another exception (MemoryError, IndexError, ...), nor a hang. And `vfdata
check` agrees with the reader: a file it finds sound reads exactly as the original."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pytest
import zstandard
from mcap.opcode import Opcode
from mcap.writer import Writer
from rawfixtures import FRAME_NS, T0_NS, calibration, frames

from vfdata.conversion.raw_folder import camera_infos, stereo_tf
from vfdata.errors import FormatError
from vfdata.mcap_io.records import FOOTER_SIZE, MAGIC, RECORD_HEAD, iter_records
from vfdata.recording import CorruptChunkError, McapWriter, Recording, layout
from vfdata.recording.inspect import check_file
from vfdata.recording.messages import CompressedImage, PoseStamped, WrenchStamped

pytestmark = pytest.mark.timeout(60)


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    return write_pristine(tmp_path_factory.mktemp("damage") / "rec.mcap")


def write_pristine(path: Path) -> Path:
    """12 stereo JPEG frames in 8 kB chunks, 1 kHz force in chunks of 100 samples, 100 Hz pose in
    one chunk (also the base of bench/adversarial.py)."""
    calib = calibration()
    rng = np.random.default_rng(0)
    n_force, n_pose = 400, 40
    with McapWriter(path, chunk_size=8 * 1024, separate_topics=(layout.WRENCH, layout.ECM_POSE),
                    separate_batch=100, chunk_level=None) as writer:
        writer.add_metadata(layout.RECORDING_METADATA, layout.RecordingMeta(recording_id="damage").to_record())
        writer.write(layout.TF_STATIC, stereo_tf(calib, T0_NS))
        force = rng.normal(size=(n_force, 6))
        pose_i = force_i = 0
        for i, (left, right) in enumerate(frames(12, 160, 128)):
            stamp = T0_NS + i * FRAME_NS
            while force_i < n_force and T0_NS + force_i * 1_000_000 <= stamp:
                writer.write(layout.WRENCH, WrenchStamped(T0_NS + force_i * 1_000_000, layout.SENSOR_FRAME,
                                                          tuple(force[force_i, :3]), tuple(force[force_i, 3:])))
                force_i += 1
            while pose_i < n_pose and T0_NS + pose_i * 10_000_000 <= stamp:
                writer.write(layout.ECM_POSE, PoseStamped(T0_NS + pose_i * 10_000_000, layout.WORLD_FRAME,
                                                          (0.1 * pose_i, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
                pose_i += 1
            info_l, info_r = camera_infos(calib, stamp)
            writer.write(layout.LEFT_INFO, info_l)
            writer.write(layout.RIGHT_INFO, info_r)
            for topic, frame_id, image in ((layout.LEFT_IMAGE, layout.LEFT_FRAME, left),
                                           (layout.RIGHT_IMAGE, layout.RIGHT_FRAME, right)):
                data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 60])[1].tobytes()
                writer.write(topic, CompressedImage(stamp, frame_id, "jpeg", data))
    assert check_file(path) == []
    return path


def read_all(path: Path, damaged: str = "error") -> dict:
    """Everything a user reads from a recording: every topic's (log time, payload), the decoded force
    and pose series, the metadata, and the problems listed."""
    rec = Recording.open(path, damaged=damaged)
    view = {topic: [(t, bytes(p)) for t, p in rec.payloads(topic)] for topic in rec.topics}
    if rec.has(layout.WRENCH):
        view["force"] = [(int(t), tuple(w)) for t, w in zip(rec.force.times_ns, rec.force.wrench, strict=True)]
    if rec.has(layout.ECM_POSE):
        view["pose"] = [(int(t), tuple(p)) for t, p in zip(rec.ecm_pose.times_ns, rec.ecm_pose.position_m,
                                                           strict=True)]
    if rec.num_frames:
        rec.frame(0)
    view["metadata"] = sorted((k, tuple(sorted(v.items()))) for k, v in rec.metadata_records.items())
    return {"view": view, "problems": rec.problems}


def outcome(path: Path, reference: dict, damaged: str = "error") -> str:
    """'exact', 'error' (a named one), 'partial' (a part of the original, the damage listed), or what
    went wrong: 'altered' (data that differs from the original, or missing without a problem listed)
    or 'crash: <exception>'."""
    try:
        got = read_all(path, damaged)
    except FormatError:
        return "error"
    except Exception as exc:  # noqa: BLE001 - any other exception is the failure this test looks for
        return f"crash: {type(exc).__name__}: {exc}"
    view, problems = got["view"], got["problems"]
    if view == reference:
        return "exact"
    subset = all(key in reference and not (Counter(items) - Counter(reference[key])) for key, items in view.items())
    return "partial" if subset and problems else "altered"


def regions(data: bytes) -> dict[str, list[tuple[int, int]]]:
    """Byte ranges of each region of a file written by McapWriter (chunks told apart by their topic)."""
    found: dict[str, list[tuple[int, int]]] = {}
    rec_topics = {}

    def add(name: str, start: int, end: int) -> None:
        found.setdefault(name, []).append((start, end))

    add("magic", 0, len(MAGIC))
    footer_at = len(data) - len(MAGIC) - FOOTER_SIZE
    summary_start = int.from_bytes(data[footer_at + 9:footer_at + 17], "little")
    for pos, opcode, body in iter_records(data, Path("x"), "data", len(MAGIC), summary_start):
        end = pos + RECORD_HEAD.size + len(body)
        if opcode == Opcode.CHUNK:
            name_length = int.from_bytes(body[28:32], "little")
            records = body[40 + name_length:]
            if bytes(body[32:32 + name_length]) == b"zstd":
                records = zstandard.ZstdDecompressor().decompress(records)
            channels = {int.from_bytes(b[:2], "little") for _, op, b in iter_records(records, Path("x"), "c")
                        if op == Opcode.MESSAGE}
            topics = {rec_topics[c] for c in channels}
            kind = ("force chunk" if topics == {layout.WRENCH} else "pose chunk" if topics == {layout.ECM_POSE}
                    else "image chunk")
            head = RECORD_HEAD.size + 40 + name_length
            add(kind + " head", pos, pos + head)
            add(kind + " records", pos + head, end)
        elif opcode == Opcode.CHANNEL:
            topic_length = int.from_bytes(body[4:8], "little")
            rec_topics[int.from_bytes(body[:2], "little")] = bytes(body[8:8 + topic_length]).decode()
            add("definitions", pos, end)
        else:
            add({Opcode.HEADER: "header", Opcode.SCHEMA: "definitions", Opcode.METADATA: "metadata",
                 Opcode.MESSAGE_INDEX: "message index", Opcode.DATA_END: "data end"}[opcode], pos, end)
    add("summary", summary_start, footer_at)
    add("footer", footer_at, len(data))
    return found


FLIPS_PER_REGION = 12


def damaged_cases(data: bytes) -> list[tuple[str, bytes]]:
    cases = [(f"truncated to {p}%", data[:len(data) * p // 100]) for p in range(0, 100, 5)]
    cases.append(("last byte missing", data[:-1]))
    rng = np.random.default_rng(20)
    for region, ranges in regions(data).items():
        sizes = np.array([end - start for start, end in ranges])
        for _ in range(FLIPS_PER_REGION):
            which = rng.choice(len(ranges), p=sizes / sizes.sum())
            at = int(rng.integers(*ranges[which]))
            bit = int(rng.integers(8))
            flipped = bytearray(data)
            flipped[at] ^= 1 << bit
            cases.append((f"{region}: bit {bit} of byte {at}", bytes(flipped)))
    return cases


def test_every_damage_ends_in_the_data_or_a_named_error(pristine, tmp_path):
    """The one exception: a metadata record's text has no CRC of its own (MCAP gives it none); the
    data-section CRC covers it, and `vfdata check` verifies that, but the reader cannot without
    reading the whole file. Such flips must be caught by `check`."""
    data = pristine.read_bytes()
    reference = read_all(pristine)["view"]
    assert len(regions(data)) == 14
    results = Counter()
    failures = []
    path = tmp_path / "damaged.mcap"
    for name, damaged in damaged_cases(data):
        region = name.split(":")[0].split(" to ")[0]
        path.write_bytes(damaged)
        result = outcome(path, reference)
        problems = check_file(path)
        if result == "altered" and region == "metadata" and any("data section CRC" in p for p in problems):
            result = "altered, check finds it"
        elif result.startswith(("crash", "altered")):
            failures.append(f"{name}: {result}")
        elif not problems and result != "exact":
            failures.append(f"{name}: check finds nothing, the reader gives {result}")
        skipping = outcome(path, reference, damaged="skip")
        if skipping.startswith("crash") or skipping == "altered" and region != "metadata":
            failures.append(f"{name}, damaged='skip': {skipping}")
        results[region, result] += 1
    print("\n" + "\n".join(f"{k[0]:22} {k[1]:24} {n}" for k, n in sorted(results.items())))
    assert failures == []
    assert sum(results.values()) == 21 + 14 * FLIPS_PER_REGION


def test_a_damaged_image_chunk_is_refused_by_name_and_the_rest_reads(pristine, tmp_path):
    rec = Recording.open(pristine)
    chunk = next(c for c in rec._mcap.index.chunks if c.compressed_size > 4000)
    data = bytearray(pristine.read_bytes())
    data[chunk.data_offset + chunk.compressed_size // 2] ^= 0x04
    path = tmp_path / "flipped.mcap"
    path.write_bytes(bytes(data))
    rec = Recording.open(path)
    refused = []
    for i in range(rec.num_frames):
        try:
            rec.frame_images(i)
        except CorruptChunkError as exc:
            refused.append(i)
            message, topics, offset = str(exc), exc.topics, exc.chunk_offset
    assert refused and len(refused) < rec.num_frames
    assert offset == chunk.record_offset and layout.LEFT_IMAGE in topics
    assert f"chunk at byte {chunk.record_offset}" in message and "CRC" in message and layout.LEFT_IMAGE in message
    skipped = Recording.open(path, damaged="skip")
    assert skipped.num_frames < 12 and any("CRC mismatch" in p for p in skipped.problems)
    served = Recording.open(path, damaged="serve")
    assert served.num_frames == 12 and served.frame_images(refused[0])
    assert any("CRC mismatch" in p for p in check_file(path))


def test_a_message_index_pointing_at_the_wrong_record_is_read_from_the_chunk(pristine, tmp_path):
    """An offset that stays inside its chunk is only noticed on reading the chunk: the chunk's records
    then locate the message, which reads as the original."""
    rec = Recording.open(pristine)
    data = bytearray(pristine.read_bytes())
    channel = rec._by_topic[layout.WRENCH].id
    chunk_id = int(rec._mcap.index.messages[channel].chunk[150])
    chunk = rec._mcap.index.chunks[chunk_id]
    index_at = chunk.record_offset + chunk.record_length  # the chunk's message index records follow it
    opcode, length = RECORD_HEAD.unpack_from(data, index_at)
    assert opcode == Opcode.MESSAGE_INDEX
    data[index_at + 15 + 16 * 3 + 8] ^= 0x08  # the offset of its 4th entry, a few bytes off
    path = tmp_path / "offset.mcap"
    path.write_bytes(bytes(data))
    assert read_all(path)["view"] == read_all(pristine)["view"]
    assert any("points at the wrong records" in p for p in Recording.open(path, damaged="skip").problems)


@pytest.mark.parametrize("summary_crc", [True, False], ids=["with-summary-crc", "without"])
def test_a_flipped_summary_length_is_a_named_problem_not_a_memory_error(pristine, tmp_path, summary_crc):
    """The top byte of a chunk index's record length flipped (2**62 bytes): with the summary CRC the
    CRC notices, without it the length is bounded by the summary; either way the data section is
    scanned and reads as the original."""
    data = bytearray(pristine.read_bytes())
    footer_at = len(data) - len(MAGIC) - FOOTER_SIZE
    summary_start = int.from_bytes(data[footer_at + 9:footer_at + 17], "little")
    for pos, opcode, _body in iter_records(bytes(data), Path("x"), "s", summary_start, footer_at):
        if opcode == Opcode.CHUNK_INDEX:
            data[pos + 1 + 7] ^= 0x40
            break
    if not summary_crc:
        data[footer_at + 25:footer_at + 29] = bytes(4)  # "not computed"
    path = tmp_path / "summary.mcap"
    path.write_bytes(bytes(data))
    rec = Recording.open(path)
    assert any("summary" in p for p in rec.problems)
    assert read_all(path)["view"] == read_all(pristine)["view"]
    assert any("summary" in p for p in check_file(path))


def _foreign_file(path: Path, channels: list[tuple[str, str, str, bytes]]) -> Path:
    """A file written by `mcap`'s writer: (topic, schema name, message encoding, payload) each."""
    with open(path, "wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2")
        for topic, schema, encoding, payload in channels:
            schema_id = writer.register_schema(schema, "ros2msg", b"")
            writer.add_message(writer.register_channel(topic, encoding, schema_id), T0_NS, payload, T0_NS)
        writer.finish()
    return path


def test_wrong_payloads_on_our_topics_are_named_errors(tmp_path):
    rec = Recording.open(_foreign_file(tmp_path / "wrong.mcap", [
        (layout.WRENCH, WrenchStamped.msgtype, "json", b'{"fx": 1.0}'),
        (layout.LEFT_INFO, "sensor_msgs/msg/CameraInfo", "cdr", b"\x00\x01\x00\x00\x05"),
        (layout.ECM_POSE, "std_msgs/msg/String", "cdr", b"\x00\x01\x00\x00\x01\x00\x00\x00\x00"),
        (layout.LEFT_IMAGE, CompressedImage.msgtype, "cdr", b"\x00\x01\x00\x00\xff\xff\xff\xff"),
    ]))
    with pytest.raises(FormatError, match=r"wrong.mcap: /force_sensor/wrench has message encoding 'json'"):
        rec.force  # noqa: B018
    with pytest.raises(FormatError, match=r"wrong.mcap: /stereo/left/camera_info: message 0 is not a valid"):
        rec.camera  # noqa: B018
    with pytest.raises(FormatError, match=r"/ecm/measured_cp has type 'std_msgs/msg/String', expected"):
        rec.ecm_pose  # noqa: B018
    with pytest.raises(FormatError, match=r"/stereo/left/image/compressed: message 0 is not a valid"):
        rec.frame_images(0)
    assert any("/force_sensor/wrench" in p for p in check_file(rec.path))
    short = Recording.open(_foreign_file(tmp_path / "short.mcap", [
        (layout.WRENCH, WrenchStamped.msgtype, "cdr", b"\x00\x01\x00\x00" + bytes(20))]))
    with pytest.raises(FormatError, match=r"short.mcap: /force_sensor/wrench: messages are not valid"):
        short.force  # noqa: B018
