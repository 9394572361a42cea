"""Valid MCAP files read correctly whoever wrote them: every feature combination of the foxglove/mcap
conformance suite (`mcap_variants`), and every combination of the `mcap` package's writer options,
checked message by message (channel, log time, bytes), with topics, schemas and metadata, against
what was written and against `mcap`'s own linear reader. Files that are invalid by construction are
reported as problems."""

from __future__ import annotations

import io
import itertools
import json
import os
from pathlib import Path

import pytest
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, IndexType, Writer
from mcap_variants import variants

from vfdata.mcap_io.file import McapFile
from vfdata.recording import Recording

VARIANTS = {v.name: v for v in variants()}


def our_view(path: Path) -> tuple[dict, list, dict, list[str]]:
    """What our index gives: (channels, sorted (channel id, log time, data), metadata, problems)."""
    mcap = McapFile(path)
    index = mcap.index
    topics = {c.id: (c.topic, c.message_encoding, c.msgtype, c.schema_encoding, c.schema)
              for c in index.channels.values()}
    messages = sorted((cid, t, bytes(p)) for cid in index.messages for t, p in mcap.iter_payloads(cid))
    return topics, messages, index.metadata, index.problems


def library_view(data: bytes) -> tuple[dict, list, dict]:
    """The same from `mcap`'s StreamReader, which reads every record in file order (CRCs validated)."""
    schemas, channels, messages, metadata = {}, {}, [], {}
    for record in StreamReader(io.BytesIO(data), validate_crcs=True).records:
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Message):
            messages.append((record.channel_id, record.log_time, bytes(record.data)))
        elif isinstance(record, Metadata):
            metadata[record.name] = record.metadata
    topics = {}
    for cid, c in channels.items():
        s = schemas.get(c.schema_id)
        topics[cid] = (c.topic, c.message_encoding, s.name if s else "", s.encoding if s else "",
                       bytes(s.data) if s else b"")
    return topics, sorted(messages), metadata


def test_the_variants_are_the_suites_416():
    assert len(VARIANTS) == 416
    assert {"NoData", "OneMessage-ch-chx-mx-pad-rch-rsh-st-sum", "TenMessages-ch", "OneMetadata-mdx-pad-st-sum",
            "OneSchemalessMessage-ch-rch-st"} <= set(VARIANTS)


@pytest.mark.parametrize("name", sorted(VARIANTS))
def test_conformance_variant_reads_correctly(tmp_path, name):
    variant = VARIANTS[name]
    data = variant.build()
    path = tmp_path / f"{name}.mcap"
    path.write_bytes(data)
    expected = library_view(data)
    topics, messages, metadata, problems = our_view(path)
    assert (topics, messages, metadata) == expected
    assert problems == []  # a valid file, read by a scan or not, has no damage
    rec = Recording.open(path)
    assert {t: i.count for t, i in rec.topics.items()} == {
        t[0]: sum(m[0] == cid for m in messages) for cid, t in topics.items()}
    assert rec.metadata_records == metadata
    if messages:
        assert [bytes(p) for _, p in rec.payloads("example")] == [m[2] for m in sorted(
            messages, key=lambda m: m[1])]


def _write_with_library(stream, *, chunking: bool, compression: CompressionType, index_types: IndexType,
                        repeat_channels: bool, repeat_schemas: bool, statistics: bool, summary_offsets: bool) -> None:
    writer = Writer(stream, chunk_size=300, compression=compression, index_types=index_types,
                    repeat_channels=repeat_channels, repeat_schemas=repeat_schemas, use_chunking=chunking,
                    use_statistics=statistics, use_summary_offsets=summary_offsets)
    writer.start(profile="ros2", library="test")
    typed = writer.register_schema("pkg/msg/A", "ros2msg", b"int32 a\n")
    untyped = writer.register_schema("", "", b"")  # a schema of encoding '' (allowed, if unusual)
    channels = [writer.register_channel("/a", "cdr", typed), writer.register_channel("/b", "json", 0),
                writer.register_channel("/c", "x", untyped, {"k": "v"})]
    writer.register_channel("/silent", "cdr", typed)  # a channel without messages
    writer.add_metadata("first", {"a": "1"})
    for k, log_time in enumerate([5, 3, 3, 9, 1, 7, 7, 2, 8, 4] * 3):
        writer.add_message(channels[k % 3], log_time, bytes([k]) * (k + 1), log_time, k)
        if k == 12:
            writer.add_attachment(1, 2, "file", "text/plain", b"hello")
    writer.add_metadata("second", {"b": "2", "c": ""})
    writer.finish()


WRITER_OPTIONS = [
    dict(chunking=chunking, compression=compression, index_types=index_types, repeat_channels=rch,
         repeat_schemas=rsh, statistics=st, summary_offsets=sum_)
    for chunking, compression in [(False, CompressionType.NONE), (True, CompressionType.NONE),
                                  (True, CompressionType.ZSTD), (True, CompressionType.LZ4)]
    for index_types in [IndexType.NONE, IndexType.CHUNK, IndexType.CHUNK | IndexType.MESSAGE, IndexType.MESSAGE,
                        IndexType.METADATA, IndexType.ALL, IndexType.ALL & ~IndexType.METADATA]
    for rch, rsh, st, sum_ in itertools.product([False, True], repeat=4)
]


def _option_id(options: dict) -> str:
    return "-".join([("chunked-" + options["compression"].name.lower()) if options["chunking"] else "unchunked",
                     str(options["index_types"]).removeprefix("IndexType.").replace("|", "+")]
                    + [k for k in ("repeat_channels", "repeat_schemas", "statistics", "summary_offsets") if options[k]])


def test_every_writer_option_combination_reads_correctly(tmp_path):
    """Against `mcap`'s own linear reader, for all 448 combinations (one test: a few ms each)."""
    wrong = []
    for options in WRITER_OPTIONS:
        stream = io.BytesIO()
        _write_with_library(stream, **options)
        path = tmp_path / "w.mcap"
        path.write_bytes(stream.getvalue())
        topics, messages, metadata, problems = our_view(path)
        if (topics, messages, metadata) != library_view(stream.getvalue()) or problems:
            wrong.append((_option_id(options), problems))
    assert len(WRITER_OPTIONS) == 448
    assert wrong == []


def test_invalid_files_report_problems(tmp_path):
    """Messages on a channel the file never defines, a channel naming a schema it lacks."""
    stream = io.BytesIO()
    writer = Writer(stream, use_chunking=False)
    writer.start()
    writer.register_channel("/orphan", "cdr", schema_id=7)
    writer.add_message(1, 10, b"a", 10)
    writer.add_message(5, 11, b"b", 11)
    writer.finish()
    path = tmp_path / "invalid.mcap"
    path.write_bytes(stream.getvalue())
    problems = Recording.open(path).problems
    assert any("names schema 7" in p for p in problems) and any("channel 5" in p for p in problems), problems


@pytest.mark.skipif(not os.environ.get("VF_MCAP_CONFORMANCE_DIR"),
                    reason="set VF_MCAP_CONFORMANCE_DIR to a checkout's tests/conformance/data (git lfs pull)")
def test_the_suites_own_files():
    """The suite's generated files with their expected records (.json beside each .mcap)."""
    root = Path(os.environ["VF_MCAP_CONFORMANCE_DIR"])
    wrong = []
    files = sorted(root.rglob("*.mcap"))
    for path in files:
        expected = _expected_from_json(path.with_suffix(".json"))
        topics, messages, metadata, problems = our_view(path)
        if (topics, messages, metadata) != expected or problems:
            wrong.append(path.name)
    assert files and wrong == []


def _expected_from_json(path: Path) -> tuple[dict, list, dict]:
    schemas, channels, messages, metadata = {}, {}, [], {}
    for record in json.loads(path.read_text())["records"]:
        f = dict(record["fields"])
        if record["type"] == "Schema":
            schemas[int(f["id"])] = (f["name"], f["encoding"], bytes(int(x) for x in f["data"]))
        elif record["type"] == "Channel":
            channels[int(f["id"])] = (f["topic"], f["message_encoding"], int(f["schema_id"]))
        elif record["type"] == "Message":
            messages.append((int(f["channel_id"]), int(f["log_time"]), bytes(int(x) for x in f["data"])))
        elif record["type"] == "Metadata":
            metadata[f["name"]] = f["metadata"]
    topics = {cid: (topic, encoding, *schemas.get(sid, ("", "", b""))) for cid, (topic, encoding, sid)
              in channels.items()}
    return topics, sorted(messages), metadata
