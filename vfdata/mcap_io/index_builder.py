"""Building the `McapIndex` of an MCAP file, whoever wrote it.

From the summary when it accounts for everything: its CRC holds, it has statistics, and the chunk and
message indexes list every message the statistics count. The gaps a valid summary may have are filled
from the data section: chunks without message indexes are read, channels and schemas the summary does
not repeat are looked up, metadata without an index is found by walking the top-level records.
Anything else (no summary or no statistics, indexes that miss messages, a damaged summary, a truncated
file) is indexed by a linear scan of the data section, up to the first damage. `problems` says what
was damaged; a valid file read by a scan has none."""

from __future__ import annotations

from array import array
from pathlib import Path
from typing import Protocol

import numpy as np
from mcap.opcode import Opcode
from mcap.records import Channel as ChannelRecord
from mcap.records import ChunkIndex, Footer, Header, Metadata, MetadataIndex, Schema, Statistics

from vfdata.errors import FormatError
from vfdata.mcap_io.index import COMPRESSIONS, Channel, Chunk, McapIndex, MessageLocations, merge_locations
from vfdata.mcap_io.records import (
    CHUNK_FIELDS,
    DATA_END_SIZE,
    FOOTER_SIZE,
    INDEX_PAIR,
    MAGIC,
    MESSAGE_FIELDS,
    MESSAGE_HEAD,
    MESSAGE_INDEX_HEAD,
    RECORD_HEAD,
    chunk_head_size,
    crc32,
    iter_records,
    parse,
)


class McapSource(Protocol):
    """What the index builder reads a file through (`vfdata.mcap_io.file.McapFile` is one): its
    path and size in bytes, bytes at an offset, and a chunk's records checked against its CRC."""

    path: Path
    size: int

    def read_at(self, offset: int, size: int) -> bytes: ...

    def read_chunk(self, chunk: Chunk, problems: list[str]) -> bytes | memoryview: ...


def build_index(file: McapSource) -> McapIndex:
    return _Builder(file).build()


def scan_chunk_records(records: bytes | memoryview, path, where: str, on_definition=None,
                       ) -> tuple[dict[int, tuple[list[int], list[int]]], str | None]:
    """({channel id: (log times, offsets)} of the message records of a chunk in file order, the problem
    that stopped the walk or None); `on_definition(opcode, body, offset)` for its schemas and channels."""
    found: dict[int, tuple[list[int], list[int]]] = {}
    try:
        for pos, opcode, body in iter_records(records, path, where):
            if opcode == Opcode.MESSAGE:
                if len(body) < MESSAGE_FIELDS:
                    raise FormatError(path, f"{where}: message record at byte {pos} is too short")
                channel_id, _sequence, log_time = MESSAGE_HEAD.unpack_from(records, pos)[2:5]
                times, offsets = found.setdefault(channel_id, ([], []))
                times.append(log_time)
                offsets.append(pos)
            elif on_definition is not None and opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
                on_definition(opcode, body, pos)
    except FormatError as exc:
        return found, exc.problem
    return found, None


class _Entries:
    """Per channel (log time, chunk, offset) of the messages found, as compact arrays."""

    def __init__(self) -> None:
        self.by_channel: dict[int, tuple[array, array, array]] = {}

    def _columns(self, channel_id: int) -> tuple[array, array, array]:
        return self.by_channel.setdefault(channel_id, (array("q"), array("q"), array("q")))

    def add(self, channel_id: int, log_time: int, chunk: int, offset: int) -> None:
        times, chunks, offsets = self._columns(channel_id)
        times.append(log_time)
        chunks.append(chunk)
        offsets.append(offset)

    def extend(self, channel_id: int, log_times, chunk: int, offsets) -> None:
        times, chunks, at = self._columns(channel_id)
        times.frombytes(np.asarray(log_times, np.int64).tobytes())
        chunks.frombytes(np.full(len(log_times), chunk, np.int64).tobytes())
        at.frombytes(np.asarray(offsets, np.int64).tobytes())

    def counts(self) -> dict[int, int]:
        return {c: len(v[0]) for c, v in self.by_channel.items() if len(v[0])}

    def locations(self, channel_id: int) -> MessageLocations:
        columns = self.by_channel.get(channel_id, (array("q"), array("q"), array("q")))
        return merge_locations(*(np.frombuffer(c, np.int64) if len(c) else np.zeros(0, np.int64)
                                 for c in columns))


class _Builder:
    def __init__(self, file: McapSource):
        self.file = file
        self.path = file.path
        self.index = McapIndex()
        self.statistics: Statistics | None = None
        self._reset()

    def _reset(self) -> None:
        self.schemas: dict[int, Schema] = {}
        self.channel_records: dict[int, ChannelRecord] = {}
        self.entries = _Entries()
        self.scanned: set[int] = set()
        self.index.chunks = []
        self.index.metadata = {}

    def build(self) -> McapIndex:
        if self.file.size < len(MAGIC) or self.file.read_at(0, len(MAGIC)) != MAGIC:
            raise FormatError(self.path, "not an MCAP file (bad magic)")
        self._read_header()
        try:
            complete = self._from_summary()
        except FormatError as exc:
            self.index.problems.append(f"summary unusable ({exc.problem}); scanned the data section instead")
            complete = False
        if complete:
            self.index.from_summary = True
        else:
            self._reset()
            self._walk(messages=True, definitions=True, metadata=True)
            self._compare_statistics()
        self._finish()
        return self.index

    # -- header and summary ----------------------------------------------------------------------
    def _read_header(self) -> None:
        start = len(MAGIC) + RECORD_HEAD.size
        if self.file.size < start:
            self.index.problems.append("file is truncated (no header)")
            return
        opcode, length = RECORD_HEAD.unpack(self.file.read_at(len(MAGIC), RECORD_HEAD.size))
        try:
            if opcode != Opcode.HEADER or start + length > self.file.size:
                raise FormatError(self.path, "the first record is not an MCAP header")
            header = parse(Header, self.file.read_at(start, length), self.path, "header")
            self.index.profile, self.index.library = header.profile, header.library
        except FormatError as exc:
            self.index.problems.append(exc.problem)

    def _footer(self) -> Footer | None:
        size = self.file.size
        footer_at = size - len(MAGIC) - FOOTER_SIZE
        if footer_at < len(MAGIC) or self.file.read_at(size - len(MAGIC), len(MAGIC)) != MAGIC:
            self.index.problems.append("file is truncated (no footer); scanned the data section up to the damage")
            return None
        head = self.file.read_at(footer_at, FOOTER_SIZE)
        opcode, length = RECORD_HEAD.unpack_from(head)
        if opcode != Opcode.FOOTER or length != FOOTER_SIZE - RECORD_HEAD.size:
            self.index.problems.append("footer record not found; scanned the data section instead")
            return None
        return parse(Footer, head[RECORD_HEAD.size:], self.path, "footer")

    def _from_summary(self) -> bool:
        """Index from the summary; False where only a scan of the data section finds every message."""
        footer = self._footer()
        if footer is None:
            return False
        footer_at = self.file.size - len(MAGIC) - FOOTER_SIZE
        if footer.summary_start == 0:  # a valid file without a summary
            self._find_data_end(footer_at)
            return False
        if not len(MAGIC) < footer.summary_start <= footer_at:
            raise FormatError(self.path, "the footer points outside the file")
        summary = self.file.read_at(footer.summary_start, footer_at - footer.summary_start)
        # The summary CRC covers the summary section and the footer up to the CRC field itself.
        if footer.summary_crc and crc32(self.file.read_at(footer_at, FOOTER_SIZE - 4),
                                        crc32(summary)) != footer.summary_crc:
            raise FormatError(self.path, "the summary section fails its CRC check")
        statistics = None
        chunk_indexes: list[ChunkIndex] = []
        metadata_indexes: list[MetadataIndex] = []
        for pos, opcode, body in iter_records(summary, self.path, "summary"):
            where = f"summary record at byte {footer.summary_start + pos}"
            if opcode == Opcode.SCHEMA:
                schema = parse(Schema, body, self.path, where)
                self.schemas[schema.id] = schema
            elif opcode == Opcode.CHANNEL:
                channel = parse(ChannelRecord, body, self.path, where)
                self.channel_records[channel.id] = channel
            elif opcode == Opcode.STATISTICS:
                statistics = parse(Statistics, body, self.path, where)
            elif opcode == Opcode.CHUNK_INDEX:
                chunk_indexes.append(parse(ChunkIndex, body, self.path, where))
            elif opcode == Opcode.METADATA_INDEX:
                metadata_indexes.append(parse(MetadataIndex, body, self.path, where))
        self._find_data_end(footer.summary_start)
        self.statistics = statistics
        if statistics is None:  # nothing to check the indexes against: only a scan finds every message
            return False
        data_end = self.index.data_end_offset or footer.summary_start
        rescan = []
        for chunk_index in chunk_indexes:
            chunk_id = self._add_indexed_chunk(chunk_index, data_end)
            if not self._read_message_indexes(chunk_id, chunk_index, data_end):
                rescan.append(chunk_id)
        for chunk_id in rescan:
            self._scan_chunk(chunk_id, messages=True)
        if self._missing_definitions():
            self._walk(messages=False, definitions=True, metadata=False)
        self._read_metadata(metadata_indexes, data_end)
        return self._accounts_for(statistics, chunk_indexes, rescan)

    def _find_data_end(self, end: int) -> None:
        """The DataEnd record just before `end` (the summary, or the footer without one)."""
        at = end - DATA_END_SIZE
        if at > len(MAGIC):
            record = self.file.read_at(at, DATA_END_SIZE)
            if RECORD_HEAD.unpack_from(record) == (Opcode.DATA_END, 4):
                self.index.data_end_offset = at
                self.index.data_section_crc = int.from_bytes(record[RECORD_HEAD.size:], "little")

    def _add_indexed_chunk(self, chunk_index: ChunkIndex, data_end: int) -> int:
        start, length, compression = chunk_index.chunk_start_offset, chunk_index.chunk_length, chunk_index.compression
        head = chunk_head_size(compression)
        if not (len(MAGIC) <= start and start + length <= data_end and head + chunk_index.compressed_size <= length
                and (compression or chunk_index.compressed_size == chunk_index.uncompressed_size)):
            raise FormatError(self.path, f"the chunk index of the chunk at byte {start} does not fit the file")
        # The chunk's CRC is only in the chunk record: read when the chunk is.
        chunk = Chunk(start, start + head, chunk_index.compressed_size, chunk_index.uncompressed_size, None,
                      compression, chunk_index.message_start_time, chunk_index.message_end_time, length)
        self.index.chunks.append(chunk)
        if compression not in COMPRESSIONS:
            chunk.status = "unreadable"
            self.index.problems.append(f"chunk at byte {start}: unsupported compression '{compression}'")
        return len(self.index.chunks) - 1

    def _read_message_indexes(self, chunk_id: int, chunk_index: ChunkIndex, data_end: int) -> bool:
        """The chunk's message index records into the entries; False where a valid file left them out
        or they are damaged (noted): the chunk's records are read instead."""
        chunk = self.index.chunks[chunk_id]
        offsets = chunk_index.message_index_offsets
        if chunk.status == "unreadable":
            return True
        if not offsets:
            return False
        block_start = chunk.record_offset + chunk.record_length
        block_end = block_start + chunk_index.message_index_length
        found = []
        try:
            if block_end > data_end or not all(block_start <= o < block_end for o in offsets.values()):
                raise ValueError("points outside the chunk's message index records")
            block = self.file.read_at(block_start, block_end - block_start)
            ordered = sorted(offsets.items(), key=lambda item: item[1])
            for k, (channel_id, offset) in enumerate(ordered):
                rel = offset - block_start
                # A record ends before the next one starts: a longer length is padding only up to there.
                limit = (ordered[k + 1][1] if k + 1 < len(ordered) else block_end) - block_start
                if rel + MESSAGE_INDEX_HEAD.size > limit:
                    raise ValueError("is cut off")
                opcode, length, channel, nbytes = MESSAGE_INDEX_HEAD.unpack_from(block, rel)
                if (opcode != Opcode.MESSAGE_INDEX or channel != channel_id or nbytes % INDEX_PAIR
                        or nbytes + MESSAGE_INDEX_HEAD.size - RECORD_HEAD.size > length
                        or rel + RECORD_HEAD.size + length > limit):
                    raise ValueError(f"record of channel {channel_id} is malformed")
                pairs = np.frombuffer(block, "<u8", nbytes // 8, rel + MESSAGE_INDEX_HEAD.size).reshape(-1, 2)
                times, at = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)
                if len(pairs) and ((at < 0) | (at + MESSAGE_HEAD.size > chunk.uncompressed_size)
                                   | (times < chunk.start_ns) | (times > chunk.end_ns)).any():
                    raise ValueError(f"record of channel {channel_id} points outside its chunk")
                found.append((channel_id, times, at))
        except ValueError as exc:
            self.index.problems.append(f"the message index of the chunk at byte {chunk.record_offset} {exc}; "
                                       "read the chunk's records instead")
            return False
        for channel_id, times, at in found:
            if len(times):
                self.entries.extend(channel_id, times, chunk_id, at)
                chunk.channels.add(channel_id)
        return True

    def _missing_definitions(self) -> bool:
        """Whether channels or schemas that messages use, or that the statistics count, are unknown."""
        used = set(self.entries.by_channel)
        if not used <= set(self.channel_records):
            return True
        if self.statistics is not None and len(self.channel_records) < self.statistics.channel_count:
            return True
        return any(c.schema_id and c.schema_id not in self.schemas for c in self.channel_records.values())

    def _read_metadata(self, metadata_indexes: list[MetadataIndex], data_end: int) -> None:
        walk = len(metadata_indexes) < self.statistics.metadata_count
        for entry in metadata_indexes:
            try:
                if not (len(MAGIC) <= entry.offset and entry.offset + entry.length <= data_end
                        and entry.length >= RECORD_HEAD.size):
                    raise FormatError(self.path, "points outside the data section")
                record = self.file.read_at(entry.offset, entry.length)
                if RECORD_HEAD.unpack_from(record) != (Opcode.METADATA, entry.length - RECORD_HEAD.size):
                    raise FormatError(self.path, "points at something else")
                metadata = parse(Metadata, record[RECORD_HEAD.size:], self.path, f"byte {entry.offset}")
                self.index.metadata[metadata.name] = metadata.metadata
            except FormatError as exc:
                self.index.problems.append(f"the metadata index of '{entry.name}' {exc.problem}; scanned for it")
                walk = True
        if walk:
            self._walk(messages=False, definitions=False, metadata=True)

    def _accounts_for(self, statistics: Statistics, chunk_indexes: list[ChunkIndex], rescan: list[int]) -> bool:
        """Whether the indexes list every message the statistics count."""
        counts = self.entries.counts()
        expected = {c: n for c, n in statistics.channel_message_counts.items() if n}
        total = sum(counts.values())
        if total == statistics.message_count and (not expected or counts == expected):
            return True
        if (chunk_indexes and len(chunk_indexes) == statistics.chunk_count and not rescan
                and all(c.message_index_offsets for c in chunk_indexes)):
            # Every chunk is indexed: a writer's own messages outside chunks aside, the indexes are damaged.
            self.index.problems.append(
                f"the message indexes list {total} messages, the statistics count {statistics.message_count}; "
                "scanned the data section instead")
        return False

    def _compare_statistics(self) -> None:
        if self.statistics is None:
            return
        counts = self.entries.counts()
        expected = {c: n for c, n in self.statistics.channel_message_counts.items() if n}
        if sum(counts.values()) != self.statistics.message_count or (expected and counts != expected):
            self.index.problems.append(f"the statistics count {self.statistics.message_count} messages, the data "
                                       f"section holds {sum(counts.values())}")

    # -- the data section ----------------------------------------------------------------------
    def _walk(self, messages: bool, definitions: bool, metadata: bool) -> None:
        """Walk the top-level records of the data section from its start, up to its end or the first
        damage. Chunks are read when their messages are wanted, or while definitions are missing."""
        size, pos = self.file.size, len(MAGIC)
        known = {chunk.record_offset: i for i, chunk in enumerate(self.index.chunks)}
        while pos < size:
            if definitions and not messages and not metadata and not self._missing_definitions():
                return
            if pos + RECORD_HEAD.size > size:
                self.index.problems.append(f"record head at byte {pos} is cut off")
                return
            opcode, length = RECORD_HEAD.unpack(self.file.read_at(pos, RECORD_HEAD.size))
            end = pos + RECORD_HEAD.size + length
            if end > size:
                self.index.problems.append(f"record (opcode 0x{opcode:02x}) at byte {pos} is cut off")
                return
            if opcode == Opcode.DATA_END:
                if length >= 4:
                    self.index.data_end_offset = pos
                    self.index.data_section_crc = int.from_bytes(self.file.read_at(pos + RECORD_HEAD.size, 4),
                                                                 "little")
                return
            if opcode == Opcode.FOOTER:
                return
            try:
                self._top_level(opcode, pos, length, known, messages, definitions, metadata)
            except FormatError as exc:
                self.index.problems.append(f"record at byte {pos}: {exc.problem}")
                if messages:
                    return
            pos = end

    def _top_level(self, opcode: int, pos: int, length: int, known: dict[int, int], messages: bool,
                   definitions: bool, metadata: bool) -> None:
        if opcode == Opcode.CHUNK and (messages or definitions):
            chunk_id = known.get(pos)
            if chunk_id is None:
                chunk_id = self._add_scanned_chunk(pos, length)
                known[pos] = chunk_id
            self._scan_chunk(chunk_id, messages)
        elif opcode == Opcode.MESSAGE and messages:
            if length < MESSAGE_FIELDS:
                raise FormatError(self.path, "message record is too short")
            channel_id, _sequence, log_time = MESSAGE_HEAD.unpack(self.file.read_at(pos, MESSAGE_HEAD.size))[2:5]
            self.entries.add(channel_id, log_time, -1, pos)
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL) and definitions:
            self._definition(opcode, self.file.read_at(pos + RECORD_HEAD.size, length), pos)
        elif opcode == Opcode.METADATA and metadata:
            record = parse(Metadata, self.file.read_at(pos + RECORD_HEAD.size, length), self.path, "metadata")
            self.index.metadata.setdefault(record.name, record.metadata)

    def _add_scanned_chunk(self, pos: int, length: int) -> int:
        fixed = CHUNK_FIELDS.size + 4
        if length < fixed + 8:
            raise FormatError(self.path, "chunk record is too short")
        body = self.file.read_at(pos + RECORD_HEAD.size, fixed)
        start, end, uncompressed_size, crc = CHUNK_FIELDS.unpack_from(body)
        name_length = int.from_bytes(body[CHUNK_FIELDS.size:], "little")
        if fixed + name_length + 8 > length:
            raise FormatError(self.path, "chunk record is malformed")
        tail = self.file.read_at(pos + RECORD_HEAD.size + fixed, name_length + 8)
        try:
            compression = tail[:name_length].decode()
        except UnicodeDecodeError:
            raise FormatError(self.path, "chunk record is malformed") from None
        compressed_size = int.from_bytes(tail[name_length:], "little")
        head = chunk_head_size(compression)
        if head + compressed_size > RECORD_HEAD.size + length:
            raise FormatError(self.path, "chunk records run past the chunk record")
        if not compression and compressed_size != uncompressed_size:
            raise FormatError(self.path, "uncompressed chunk with two sizes")
        chunk = Chunk(pos, pos + head, compressed_size, uncompressed_size, crc, compression, start, end,
                      RECORD_HEAD.size + length)
        self.index.chunks.append(chunk)
        if compression not in COMPRESSIONS:
            chunk.status = "unreadable"
            self.index.problems.append(f"chunk at byte {pos}: unsupported compression '{compression}'")
        return len(self.index.chunks) - 1

    def _scan_chunk(self, chunk_id: int, messages: bool) -> None:
        """Read a chunk's records: its definitions, and its messages into the entries when `messages`."""
        chunk = self.index.chunks[chunk_id]
        if chunk_id in self.scanned or chunk.status == "unreadable":
            return
        self.scanned.add(chunk_id)
        try:
            records = self.file.read_chunk(chunk, self.index.problems)
        except FormatError:
            return  # noted by read_chunk; its messages stay out of the index
        # Definitions come only from records whose CRC holds: a damaged chunk must not rename a topic.
        found, problem = scan_chunk_records(records, self.path, f"chunk at byte {chunk.record_offset}",
                                            self._definition if chunk.status == "ok" else None)
        if problem and chunk.status == "ok":
            self.index.problems.append(problem)
        if messages:
            for channel_id, (times, offsets) in found.items():
                self.entries.extend(channel_id, times, chunk_id, offsets)
                chunk.channels.add(channel_id)

    def _definition(self, opcode: int, body, pos: int) -> None:
        where = f"record at byte {pos}"
        if opcode == Opcode.SCHEMA:
            schema = parse(Schema, body, self.path, where)
            self.schemas.setdefault(schema.id, schema)
        else:
            channel = parse(ChannelRecord, body, self.path, where)
            self.channel_records.setdefault(channel.id, channel)

    # -- the result ----------------------------------------------------------------------------
    def _finish(self) -> None:
        index = self.index
        for channel_id, record in sorted(self.channel_records.items()):
            schema = self.schemas.get(record.schema_id) if record.schema_id else None
            if record.schema_id and schema is None:
                index.problems.append(f"channel {record.topic} names schema {record.schema_id}, which the file lacks")
            index.channels[channel_id] = Channel(
                channel_id, record.topic, schema.name if schema else "", record.message_encoding,
                schema.encoding if schema else "", bytes(schema.data) if schema else b"")
        for channel_id in sorted(set(self.entries.counts()) - set(index.channels)):
            index.problems.append(f"messages on channel {channel_id}, which the file does not define")
        for channel_id in index.channels:
            index.messages[channel_id] = self.entries.locations(channel_id)
