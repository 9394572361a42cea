"""MCAP files of every feature combination the foxglove/mcap conformance suite exercises, built with
the `mcap` package's record builders (the suite's own generator is TypeScript).

The features are the suite's: chunks (ch), message indexes (mx), chunk indexes (chx), statistics
(st), schemas and channels repeated in the summary (rsh, rch), attachment and metadata indexes (ax,
mdx), summary offsets (sum), and padding after the fields of every record that may carry it (pad).
`variants()` yields the combinations that make sense for each input (416, as in the suite), each
with the records it holds, so that a reader's view can be checked against what was written."""

from __future__ import annotations

import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from itertools import combinations

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.writer import MCAP0_MAGIC

FEATURES = ("ch", "mx", "st", "rsh", "rch", "ax", "mdx", "chx", "sum", "pad")
PAD = b"\x01\xff\xff"


def _message(channel_id: int, log_time: int, publish_time: int, sequence: int) -> Message:
    return Message(channel_id=channel_id, log_time=log_time, data=bytes([1, 2, 3]), publish_time=publish_time,
                   sequence=sequence)


_SCHEMA = Schema(id=1, data=bytes([4, 5, 6]), encoding="c", name="Example")
_CHANNEL = Channel(id=1, topic="example", message_encoding="a", metadata={"foo": "bar"}, schema_id=1)

# The suite's inputs: one of each record kind, and ten messages with repeated and unordered log times.
INPUTS: dict[str, list] = {
    "NoData": [],
    "OneSchemalessMessage": [
        Channel(id=1, topic="example", message_encoding="text", metadata={}, schema_id=0),
        _message(1, 2, 1, 10)],
    "OneMessage": [_SCHEMA, _CHANNEL, _message(1, 2, 1, 10)],
    "OneAttachment": [Attachment(create_time=1, log_time=2, name="myFile", media_type="application/octet-stream",
                                 data=bytes([1, 2, 3]))],
    "OneMetadata": [Metadata(name="myMetadata", metadata={"foo": "bar"})],
    "TenMessages": [_SCHEMA, _CHANNEL] + [_message(1, t, t, k) for k, t in enumerate([0, 2, 1, 3, 3, 5, 4, 7, 8, 9])],
}


@dataclass
class Variant:
    name: str
    features: frozenset[str]
    records: list

    def build(self) -> bytes:
        return build_file(self.features, self.records)


def _makes_sense(records: list, features: frozenset[str]) -> bool:
    kinds = {type(r) for r in records}
    if "ax" in features and Attachment not in kinds or "mdx" in features and Metadata not in kinds:
        return False
    if "rsh" in features and Schema not in kinds or "rch" in features and Channel not in kinds:
        return False
    if not kinds & {Message, Channel, Schema} and features & {"ch", "chx", "mx"}:
        return False
    if "sum" in features and not features & {"chx", "rsh", "rch", "mdx", "ax", "st"}:
        return False
    return not (features & {"chx", "mx"} and "ch" not in features)


def variants() -> Iterator[Variant]:
    for base, records in INPUTS.items():
        for n in range(len(FEATURES) + 1):
            for chosen in combinations(FEATURES, n):
                features = frozenset(chosen)
                if _makes_sense(records, features):
                    yield Variant("-".join([base, *sorted(features)]), features, records)


class _Builder(RecordBuilder):
    """A record builder that pads every record it finishes, but messages and footers, which cannot be."""

    def __init__(self, pad: bool):
        super().__init__()
        self.pad = pad

    def start_record(self, opcode: Opcode):
        self._opcode = opcode
        super().start_record(opcode)

    def finish_record(self):
        if self.pad and self._opcode not in (Opcode.MESSAGE, Opcode.FOOTER):
            self.write(PAD)
        super().finish_record()


def build_file(features: frozenset[str], records: list) -> bytes:
    pad = "pad" in features
    out = _Builder(pad)
    out.write(MCAP0_MAGIC)
    Header(profile="", library="").write(out)
    chunk = RecordBuilder() if "ch" in features else None
    entries: dict[int, list[tuple[int, int]]] = {}
    schemas, channels, metadata_indexes, attachment_indexes, chunk_indexes = [], [], [], [], []
    counts: dict[int, int] = {}
    times = []
    for record in records:
        if isinstance(record, (Schema, Channel, Message)):
            if isinstance(record, Schema):
                schemas.append(record)
            elif isinstance(record, Channel):
                channels.append(record)
            else:
                counts[record.channel_id] = counts.get(record.channel_id, 0) + 1
                times.append(record.log_time)
                if chunk is not None:
                    entries.setdefault(record.channel_id, []).append((record.log_time, chunk.count))
            record.write(chunk if chunk is not None else out)
        elif isinstance(record, Attachment):
            offset = out.count
            record.write(out)
            attachment_indexes.append(AttachmentIndex(offset, out.count - offset, record.log_time, record.create_time,
                                                      len(record.data), record.name, record.media_type))
        elif isinstance(record, Metadata):
            offset = out.count
            record.write(out)
            metadata_indexes.append(MetadataIndex(offset, out.count - offset, record.name))
    if chunk is not None and (chunk.count or entries):
        data = chunk.end()
        start = out.count
        Chunk(compression="", data=data, message_end_time=max(times, default=0),
              message_start_time=min(times, default=0), uncompressed_crc=zlib.crc32(data),
              uncompressed_size=len(data)).write(out)
        chunk_length = out.count - start
        offsets = {}
        if "mx" in features:
            for channel_id, pairs in entries.items():
                offsets[channel_id] = out.count
                MessageIndex(channel_id, pairs).write(out)
        chunk_indexes.append(ChunkIndex(chunk_length=chunk_length, chunk_start_offset=start, compression="",
                                        compressed_size=len(data), message_end_time=max(times, default=0),
                                        message_index_length=out.count - start - chunk_length,
                                        message_index_offsets=offsets, message_start_time=min(times, default=0),
                                        uncompressed_size=len(data)))
    head = out.end()
    out = _Builder(pad)
    out.write(head)
    DataEnd(zlib.crc32(head)).write(out)
    summary_start = out.count
    groups = []

    def group(opcode: Opcode, items: list) -> None:
        start = out.count
        for item in items:
            item.write(out)
        if out.count > start:
            groups.append(SummaryOffset(opcode, start, out.count - start))

    group(Opcode.SCHEMA, schemas if "rsh" in features else [])
    group(Opcode.CHANNEL, channels if "rch" in features else [])
    if "st" in features:
        group(Opcode.STATISTICS, [Statistics(
            attachment_count=len(attachment_indexes), channel_count=len(channels), channel_message_counts=counts,
            chunk_count=len(chunk_indexes), message_count=sum(counts.values()), message_end_time=max(times, default=0),
            message_start_time=min(times, default=0), metadata_count=len(metadata_indexes),
            schema_count=len(schemas))])
    group(Opcode.METADATA_INDEX, metadata_indexes if "mdx" in features else [])
    group(Opcode.ATTACHMENT_INDEX, attachment_indexes if "ax" in features else [])
    group(Opcode.CHUNK_INDEX, chunk_indexes if "chx" in features else [])
    has_summary = out.count > summary_start
    summary_offset_start = 0
    if "sum" in features:
        summary_offset_start = out.count
        for offset in groups:
            offset.write(out)
    body = out.end()
    footer_head = RecordBuilder()
    Footer(summary_start if has_summary else 0, summary_offset_start, 0).write(footer_head)
    crc = zlib.crc32(footer_head.end()[:-4], zlib.crc32(body[summary_start:]))
    tail = RecordBuilder()
    Footer(summary_start if has_summary else 0, summary_offset_start, crc).write(tail)
    return body + tail.end() + MCAP0_MAGIC


def expected_view(records: list) -> tuple[dict, list, dict]:
    """(channel id -> (topic, message encoding, schema name, schema encoding, schema data), sorted
    (channel id, log time, data) of every message, metadata name -> map) of what `records` hold."""
    schemas = {r.id: r for r in records if isinstance(r, Schema)}
    topics = {}
    for r in records:
        if isinstance(r, Channel):
            schema = schemas.get(r.schema_id)
            topics[r.id] = (r.topic, r.message_encoding, schema.name if schema else "",
                            schema.encoding if schema else "", bytes(schema.data) if schema else b"")
    messages = sorted((r.channel_id, r.log_time, bytes(r.data)) for r in records if isinstance(r, Message))
    metadata = {r.name: r.metadata for r in records if isinstance(r, Metadata)}
    return topics, messages, metadata
