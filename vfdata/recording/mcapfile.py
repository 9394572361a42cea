"""Random access to the messages of an MCAP file, through its standard indexes.

The summary's chunk indexes and the message index records that follow each chunk give, per channel,
every message's log time and its offset inside its decompressed chunk. With those, one frame costs
one chunk decompression (cached), and a whole force series is a numpy gather over a few chunks
instead of a per-message decode. A file without a usable summary (truncated, damaged, written
without one) is indexed by a linear scan up to the first damage; `problems` says what was found."""

from __future__ import annotations

import os
import struct
import zlib
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zstandard

from vfdata.errors import FormatError

MAGIC = b"\x89MCAP0\r\n"

OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
OP_CHUNK_INDEX = 0x08
OP_METADATA = 0x0C
OP_METADATA_INDEX = 0x0D
OP_DATA_END = 0x0F

_RECORD_HEAD = struct.Struct("<BQ")
_FOOTER_SIZE = 1 + 8 + 8 + 8 + 4
# opcode, length, channel id, sequence, log time, publish time
_MESSAGE_HEAD = 1 + 8 + 2 + 4 + 8 + 8


@dataclass
class Channel:
    id: int
    topic: str
    msgtype: str
    message_encoding: str
    schema_encoding: str
    schema: bytes


@dataclass
class Chunk:
    record_offset: int  # file offset of the chunk record
    data_offset: int  # file offset of its (compressed) records
    compressed_size: int
    uncompressed_size: int
    uncompressed_crc: int
    compression: str
    start_ns: int
    end_ns: int


@dataclass
class MessageLocations:
    """Where one channel's messages are, sorted by log time. `chunk` is -1 for a message outside any
    chunk, whose `offset` is then its absolute record offset in the file."""

    log_time_ns: np.ndarray
    chunk: np.ndarray
    offset: np.ndarray

    def __len__(self) -> int:
        return len(self.log_time_ns)


@dataclass
class McapIndex:
    channels: dict[int, Channel] = field(default_factory=dict)
    chunks: list[Chunk] = field(default_factory=list)
    messages: dict[int, MessageLocations] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    profile: str = ""
    library: str = ""
    from_summary: bool = False
    problems: list[str] = field(default_factory=list)
    data_end_offset: int | None = None
    data_section_crc: int | None = None


class _Buffer:
    """Little-endian field reader over bytes, with bounds checks that raise FormatError."""

    def __init__(self, data: bytes | memoryview, path: Path, what: str):
        self.data = memoryview(data)
        self.pos = 0
        self.path = path
        self.what = what

    def take(self, size: int) -> memoryview:
        end = self.pos + size
        if end > len(self.data):
            raise FormatError(self.path, f"{self.what} record is truncated")
        view = self.data[self.pos:end]
        self.pos = end
        return view

    def u16(self) -> int:
        return struct.unpack("<H", self.take(2))[0]

    def u32(self) -> int:
        return struct.unpack("<I", self.take(4))[0]

    def u64(self) -> int:
        return struct.unpack("<Q", self.take(8))[0]

    def string(self) -> str:
        return bytes(self.take(self.u32())).decode("utf-8", errors="replace")

    def prefixed_bytes(self) -> bytes:
        return bytes(self.take(self.u32()))

    def string_map(self) -> dict[str, str]:
        end = self.pos + 4 + self.u32()
        result = {}
        while self.pos < end:
            key = self.string()
            result[key] = self.string()
        return result


class McapFile:
    """An MCAP file opened for indexed reading. Opened lazily and re-opened after a fork, so an
    instance can be handed to DataLoader workers."""

    def __init__(self, path: str | Path, chunk_cache: int = 4):
        self.path = Path(path)
        if not self.path.is_file():
            raise FormatError(self.path, "file not found")
        self._file = None
        self._pid = None
        self._cache: OrderedDict[int, bytes] = OrderedDict()
        self._cache_size = chunk_cache
        self._schemas: dict[int, tuple[str, str, bytes]] = {}
        self._zstd = zstandard.ZstdDecompressor()
        self.size = self.path.stat().st_size
        self.index = self._build_index()

    # -- file access -------------------------------------------------------------------------
    def _handle(self):
        if self._file is None or self._pid != os.getpid():
            self._file = open(self.path, "rb")  # noqa: SIM115 - kept for the reader's lifetime
            self._pid = os.getpid()
            self._cache.clear()
        return self._file

    def read_at(self, offset: int, size: int) -> bytes:
        handle = self._handle()
        handle.seek(offset)
        data = handle.read(size)
        if len(data) != size:
            raise FormatError(self.path, f"unexpected end of file at byte {offset + len(data)}")
        return data

    def close(self) -> None:
        if self._file is not None and self._pid == os.getpid():
            self._file.close()
        self._file = None
        self._cache.clear()

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_file"] = None
        state["_pid"] = None
        state["_cache"] = OrderedDict()
        del state["_zstd"]
        return state

    def __setstate__(self, state) -> None:
        self.__dict__.update(state)
        self._zstd = zstandard.ZstdDecompressor()

    # -- chunks --------------------------------------------------------------------------------
    def chunk_records(self, chunk_id: int) -> bytes:
        """The decompressed records of a chunk (cached)."""
        if chunk_id in self._cache:
            self._cache.move_to_end(chunk_id)
            return self._cache[chunk_id]
        chunk = self.index.chunks[chunk_id]
        raw = self.read_at(chunk.data_offset, chunk.compressed_size)
        data = self._decompress(chunk, raw)
        self._cache[chunk_id] = data
        if len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return data

    def _decompress(self, chunk: Chunk, raw: bytes) -> bytes:
        try:
            if chunk.compression == "zstd":
                data = self._zstd.decompress(raw, max_output_size=chunk.uncompressed_size)
            elif chunk.compression == "lz4":
                import lz4.frame

                data = lz4.frame.decompress(raw)
            elif chunk.compression == "":
                data = raw
            else:
                raise FormatError(self.path, f"unsupported chunk compression '{chunk.compression}'")
        except (zstandard.ZstdError, RuntimeError) as exc:
            raise FormatError(self.path, f"chunk at byte {chunk.record_offset} cannot be decompressed: {exc}") from None
        if len(data) != chunk.uncompressed_size:
            raise FormatError(self.path, f"chunk at byte {chunk.record_offset} decompresses to a wrong size")
        return data

    def chunk_crc_ok(self, chunk_id: int) -> bool:
        chunk = self.index.chunks[chunk_id]
        return chunk.uncompressed_crc == 0 or zlib.crc32(self.chunk_records(chunk_id)) == chunk.uncompressed_crc

    # -- messages ------------------------------------------------------------------------------
    def payload(self, channel_id: int, i: int) -> bytes | memoryview:
        """The CDR payload of the i-th message (in log-time order) of a channel: a view into the
        cached chunk (no copy), or bytes for a message outside any chunk."""
        loc = self.index.messages[channel_id]
        chunk, offset = int(loc.chunk[i]), int(loc.offset[i])
        if chunk < 0:
            head = self.read_at(offset, 9)
            length = _RECORD_HEAD.unpack(head)[1]
            return self.read_at(offset + _MESSAGE_HEAD, length - (_MESSAGE_HEAD - 9))
        records = self.chunk_records(chunk)
        length = struct.unpack_from("<Q", records, offset + 1)[0]
        return memoryview(records)[offset + _MESSAGE_HEAD: offset + 9 + length]

    def iter_payload_matrices(self, channel_id: int):
        """A channel's payloads as (N_i, L_i) uint8 matrices, chunk by chunk and one per distinct
        payload length (in practice one): for fixed-size messages (wrench, pose), decoded with numpy
        one chunk at a time so that memory stays at one chunk's worth."""
        loc = self.index.messages[channel_id]
        for chunk in np.unique(loc.chunk):
            sel = np.nonzero(loc.chunk == chunk)[0]
            if chunk < 0:
                for i in sel:
                    yield np.frombuffer(bytes(self.payload(channel_id, int(i))), dtype=np.uint8)[None]
                continue
            records = np.frombuffer(self.chunk_records(int(chunk)), dtype=np.uint8)
            offsets = loc.offset[sel]
            length_bytes = records[(offsets + 1)[:, None] + np.arange(8)]
            payload_len = length_bytes.copy().view("<u8").ravel().astype(np.int64) - (_MESSAGE_HEAD - 9)
            for length in np.unique(payload_len):
                starts = offsets[payload_len == length] + _MESSAGE_HEAD
                if starts.max() + length > len(records):
                    raise FormatError(self.path, "message runs past the end of its chunk")
                yield records[starts[:, None] + np.arange(length)]

    def iter_payloads(self, channel_id: int, start: int = 0, stop: int | None = None):
        """(log_time_ns, payload) of a channel's messages in log-time order."""
        loc = self.index.messages[channel_id]
        for i in range(start, len(loc) if stop is None else stop):
            yield int(loc.log_time_ns[i]), self.payload(channel_id, i)

    # -- index construction --------------------------------------------------------------------
    def _build_index(self) -> McapIndex:
        if self.size < len(MAGIC) * 2 or self.read_at(0, len(MAGIC)) != MAGIC:
            raise FormatError(self.path, "not an MCAP file (bad magic)")
        index = McapIndex()
        if self.size >= len(MAGIC) * 2 + _FOOTER_SIZE and self.read_at(self.size - len(MAGIC), len(MAGIC)) == MAGIC:
            try:
                self._read_summary(index)
            except FormatError as exc:
                index = McapIndex(problems=[f"summary unusable ({exc.problem}); scanned the data section instead"])
        else:
            index.problems.append("file is truncated (no footer); scanned the data section up to the damage")
        if not index.from_summary:
            self._scan(index)
        self._read_header(index)
        return index

    def _read_header(self, index: McapIndex) -> None:
        opcode, length = _RECORD_HEAD.unpack(self.read_at(len(MAGIC), 9))
        if opcode != OP_HEADER:
            raise FormatError(self.path, "first record is not an MCAP header")
        buf = _Buffer(self.read_at(len(MAGIC) + 9, min(length, self.size - len(MAGIC) - 9)), self.path, "header")
        index.profile = buf.string()
        index.library = buf.string()

    def _read_summary(self, index: McapIndex) -> None:
        footer_at = self.size - len(MAGIC) - _FOOTER_SIZE
        opcode, length = _RECORD_HEAD.unpack(self.read_at(footer_at, 9))
        if opcode != OP_FOOTER:
            raise FormatError(self.path, "footer record not found")
        summary_start, _summary_offset_start, _crc = struct.unpack("<QQI", self.read_at(footer_at + 9, 20))
        if summary_start == 0:
            raise FormatError(self.path, "file has no summary section")
        if not (len(MAGIC) < summary_start <= footer_at):
            raise FormatError(self.path, "footer points outside the file")
        summary = self.read_at(summary_start, footer_at - summary_start)
        chunk_indexes = []
        metadata_offsets = []
        pos = 0
        while pos < len(summary):
            opcode, length = _RECORD_HEAD.unpack_from(summary, pos)
            body = _Buffer(memoryview(summary)[pos + 9: pos + 9 + length], self.path, "summary")
            if pos + 9 + length > len(summary):
                raise FormatError(self.path, "summary record runs past the footer")
            if opcode == OP_SCHEMA:
                self._parse_schema(body)
            elif opcode == OP_CHANNEL:
                self._parse_channel(body, index)
            elif opcode == OP_CHUNK_INDEX:
                chunk_indexes.append(self._parse_chunk_index(body))
            elif opcode == OP_METADATA_INDEX:
                offset = body.u64()
                body.u64()
                metadata_offsets.append(offset)
            pos += 9 + length
        if not index.channels:
            raise FormatError(self.path, "summary lists no channels")
        per_channel: dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
        for chunk_id, (chunk, index_offsets, index_length) in enumerate(chunk_indexes):
            index.chunks.append(chunk)
            if not index_offsets:
                continue
            first = min(index_offsets.values())
            block = self.read_at(first, index_length)
            for channel_id, offset in index_offsets.items():
                times, offsets = self._parse_message_index(block, offset - first)
                per_channel.setdefault(channel_id, []).append(
                    (times, np.full(len(times), chunk_id, dtype=np.int32), offsets)
                )
        for channel_id in index.channels:
            index.messages[channel_id] = _merge_locations(per_channel.get(channel_id, []))
        for offset in metadata_offsets:
            opcode, length = _RECORD_HEAD.unpack(self.read_at(offset, 9))
            if opcode != OP_METADATA:
                raise FormatError(self.path, "metadata index points at something else")
            body = _Buffer(self.read_at(offset + 9, length), self.path, "metadata")
            name = body.string()
            index.metadata[name] = body.string_map()
        index.from_summary = True

    def _parse_message_index(self, block: bytes, pos: int) -> tuple[np.ndarray, np.ndarray]:
        opcode, length = _RECORD_HEAD.unpack_from(block, pos)
        if opcode != OP_MESSAGE_INDEX:
            raise FormatError(self.path, "message index offset points at something else")
        (count_bytes,) = struct.unpack_from("<I", block, pos + 9 + 2)
        pairs = np.frombuffer(block, dtype="<u8", count=count_bytes // 8, offset=pos + 9 + 2 + 4).reshape(-1, 2)
        return pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)

    def _parse_chunk_index(self, body: _Buffer) -> tuple[Chunk, dict[int, int], int]:
        start_ns, end_ns, record_offset, record_length = body.u64(), body.u64(), body.u64(), body.u64()
        map_end = body.pos + 4 + body.u32()
        offsets = {}
        while body.pos < map_end:
            channel_id = body.u16()
            offsets[channel_id] = body.u64()
        index_length = body.u64()
        compression = body.string()
        compressed_size, uncompressed_size = body.u64(), body.u64()
        if record_offset + record_length > self.size:
            raise FormatError(self.path, "a chunk index points past the end of the file")
        # Chunk record: opcode, length, start, end, uncompressed size, crc, compression, records length.
        head = self.read_at(record_offset + 9 + 24, 4)
        (crc,) = struct.unpack("<I", head)
        data_offset = record_offset + 9 + 24 + 4 + 4 + len(compression.encode()) + 8
        chunk = Chunk(record_offset, data_offset, compressed_size, uncompressed_size, crc, compression, start_ns,
                      end_ns)
        return chunk, offsets, index_length

    def _parse_schema(self, body: _Buffer) -> None:
        schema_id = body.u16()
        name = body.string()
        encoding = body.string()
        self._schemas[schema_id] = (name, encoding, body.prefixed_bytes())

    def _parse_channel(self, body: _Buffer, index: McapIndex) -> None:
        channel_id = body.u16()
        schema_id = body.u16()
        topic = body.string()
        message_encoding = body.string()
        name, encoding, data = self._schemas.get(schema_id, ("", "", b""))
        index.channels[channel_id] = Channel(channel_id, topic, name, message_encoding, encoding, data)

    def _scan(self, index: McapIndex) -> None:
        """Index by walking the records from the start, decompressing chunks, up to the first damage."""
        per_channel: dict[int, list[tuple[int, int, int]]] = {}
        pos = len(MAGIC)
        while pos < self.size:
            if pos + 9 > self.size:
                index.problems.append(f"record header at byte {pos} is cut off")
                break
            opcode, length = _RECORD_HEAD.unpack(self.read_at(pos, 9))
            if pos + 9 + length > self.size:
                index.problems.append(f"record (opcode 0x{opcode:02x}) at byte {pos} is cut off")
                break
            if opcode == OP_DATA_END:
                index.data_end_offset = pos
                break
            if opcode in (OP_SCHEMA, OP_CHANNEL, OP_METADATA, OP_MESSAGE, OP_CHUNK):
                body = _Buffer(self.read_at(pos + 9, length), self.path, f"0x{opcode:02x}")
                try:
                    if opcode == OP_SCHEMA:
                        self._parse_schema(body)
                    elif opcode == OP_CHANNEL:
                        self._parse_channel(body, index)
                    elif opcode == OP_METADATA:
                        name = body.string()
                        index.metadata[name] = body.string_map()
                    elif opcode == OP_MESSAGE:
                        channel_id = body.u16()
                        body.u32()
                        per_channel.setdefault(channel_id, []).append((body.u64(), -1, pos))
                    else:
                        self._scan_chunk(body, pos, index, per_channel)
                except FormatError as exc:
                    index.problems.append(f"record at byte {pos}: {exc.problem}")
                    break
            pos += 9 + length
        for channel_id in index.channels:
            rows = per_channel.get(channel_id, [])
            arr = np.array(rows, dtype=np.int64).reshape(-1, 3)
            index.messages[channel_id] = _merge_locations(
                [(arr[:, 0], arr[:, 1].astype(np.int32), arr[:, 2])]
            )

    def _scan_chunk(self, body: _Buffer, pos: int, index: McapIndex, per_channel) -> None:
        start_ns, end_ns, uncompressed_size = body.u64(), body.u64(), body.u64()
        crc = body.u32()
        compression = body.string()
        compressed_size = body.u64()
        chunk = Chunk(pos, pos + 9 + body.pos, compressed_size, uncompressed_size, crc, compression, start_ns, end_ns)
        records = self._decompress(chunk, bytes(body.take(compressed_size)))
        chunk_id = len(index.chunks)
        index.chunks.append(chunk)
        if crc and zlib.crc32(records) != crc:
            index.problems.append(f"chunk at byte {pos}: CRC mismatch")
        inner = 0
        while inner + 9 <= len(records):
            opcode, length = _RECORD_HEAD.unpack_from(records, inner)
            rec = _Buffer(memoryview(records)[inner + 9: inner + 9 + length], self.path, "chunk")
            if opcode == OP_SCHEMA:
                self._parse_schema(rec)
            elif opcode == OP_CHANNEL:
                self._parse_channel(rec, index)
            elif opcode == OP_MESSAGE:
                channel_id = rec.u16()
                rec.u32()
                per_channel.setdefault(channel_id, []).append((rec.u64(), chunk_id, inner))
            inner += 9 + length


def _merge_locations(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> MessageLocations:
    if not parts:
        empty = np.zeros(0, dtype=np.int64)
        return MessageLocations(empty, np.zeros(0, dtype=np.int32), empty)
    times = np.concatenate([p[0] for p in parts])
    chunks = np.concatenate([p[1] for p in parts])
    offsets = np.concatenate([p[2] for p in parts])
    # Chunks may overlap in time; file order breaks ties so equal stamps keep their write order.
    order = np.lexsort((offsets, chunks, times))
    return MessageLocations(times[order], chunks[order], offsets[order])
