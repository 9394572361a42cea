"""Writing MCAP files of the VisionForce layout (recordings and derived files).

`McapWriter` writes MCAP (https://mcap.dev/spec) directly: profile ros2, CDR messages, ros2msg
schemas, zstd chunks with message indexes and CRCs, and a summary (with its CRC) holding schemas,
channels, statistics, chunk and metadata indexes and summary offsets. Writing the records ourselves
(instead of through `mcap.writer.Writer`) buys two things the converters need:

- per-chunk compression: chunks of JPEG/PNG images do not compress (ratio 1.00003), so the
  converters store them uncompressed (`IMAGE_LEVEL`; zstd's default level cost 2 ms per stereo
  frame and its fastest level still 0.15 ms, on writing and again on every read); the small
  high-rate series (force, pose), which do compress, use zstd level 3;
- small high-rate topics gathered into chunks of their own (`separate_topics`), so a reader gets a
  1 kHz force series without decompressing the video.

The data-section CRC is left at 0 ("not computed", as `mcap.writer.Writer` does by default): every
chunk carries the CRC of its records already, and a second CRC pass over the whole video cost as much
as the compression. The file appears under its name only when `close()` succeeds; on any error nothing is left behind.
Files are read back in the tests by `mcap`'s own reader and by rosbags."""

from __future__ import annotations

import contextlib
import struct
from pathlib import Path
from types import TracebackType

import numpy as np
import zstandard

# ISA-L's CRC-32 (zlib's polynomial and values) runs at ~17 GB/s here, zlib 1.2.13's at 1.7 GB/s: at
# 30 stereo frames/s of JPEGs the chunk CRCs cost 0.26 ms a frame with zlib. Same values either way.
try:
    from isal.isal_zlib import crc32
except ImportError:  # a platform without an isal wheel
    from zlib import crc32

from vfdata import __version__
from vfdata.atomic import atomic_output
from vfdata.recording import layout
from vfdata.recording.mcapfile import (
    MAGIC,
    OP_CHANNEL,
    OP_CHUNK,
    OP_CHUNK_INDEX,
    OP_DATA_END,
    OP_FOOTER,
    OP_HEADER,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_METADATA,
    OP_METADATA_INDEX,
    OP_SCHEMA,
)
from vfdata.recording.schemas import schema_text

OP_STATISTICS = 0x0B
OP_SUMMARY_OFFSET = 0x0E

# Large enough that a stereo JPEG pair and a few hundred force samples share a chunk; small enough
# that reading one frame decompresses little.
CHUNK_SIZE = 4 * 1024 * 1024
FAST_LEVEL = -1  # zstd "fast" level: the default of mixed chunks (derived files: clouds, masks, depth)
IMAGE_LEVEL = None  # no compression: for chunks of already-compressed images (the converters)
SERIES_LEVEL = 3  # zstd default: for the separated small-message series

_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, length, channel, sequence, log time, publish time


def _string(text: str) -> bytes:
    data = text.encode("utf-8")
    return struct.pack("<I", len(data)) + data


def _string_map(items: dict[str, str]) -> bytes:
    body = b"".join(_string(k) + _string(v) for k, v in sorted(items.items()))
    return struct.pack("<I", len(body)) + body


def _record(opcode: int, body: bytes) -> bytes:
    return struct.pack("<BQ", opcode, len(body)) + body


class _Chunk:
    """Messages gathered for one chunk, with their per-channel message index."""

    def __init__(self, level: int | None):
        """`level`: zstd level, or None to store the chunk uncompressed."""
        self.compressor = None if level is None else zstandard.ZstdCompressor(level=level)
        self.compression = "" if level is None else "zstd"
        self.reset()

    def reset(self) -> None:
        # The records as a list of pieces, joined only when compressed: an uncompressed chunk of images
        # goes to the file piece by piece, with no copy of each image into one buffer first.
        self.parts: list[bytes] = []
        self.size = 0
        self.index: dict[int, list[tuple[int, int]]] = {}
        self.start = None
        self.end = None

    def add(self, channel_id: int, sequence: int, log_time: int, payload: bytes | memoryview) -> None:
        offset = self.size
        # bytes are kept as they are; a view or bytearray is copied, its owner may reuse the memory.
        data = payload if type(payload) is bytes else bytes(payload)
        # The length of what is written: len() of a view of float64s or of a 2-D array counts items.
        head = _MESSAGE_HEAD.pack(OP_MESSAGE, 22 + len(data), channel_id, sequence, log_time, log_time)
        self.parts += (head, data)
        self.size += len(head) + len(data)
        self.index.setdefault(channel_id, []).append((log_time, offset))
        self.start = log_time if self.start is None else min(self.start, log_time)
        self.end = log_time if self.end is None else max(self.end, log_time)

    def add_many(self, channel_id: int, first_sequence: int, log_times: np.ndarray, payloads: np.ndarray) -> None:
        """`add` for n messages of one channel at once: payloads an (n, L) uint8 array, one row each.
        The records are built as one numpy table, byte for byte what n `add` calls append."""
        count, length = payloads.shape
        record = np.dtype([("opcode", "u1"), ("length", "<u8"), ("channel", "<u2"), ("sequence", "<u4"),
                           ("log_time", "<u8"), ("publish_time", "<u8"), ("payload", "u1", (length,))])
        table = np.empty(count, record)
        table["opcode"] = OP_MESSAGE
        table["length"] = 22 + length
        table["channel"] = channel_id
        table["sequence"] = np.arange(first_sequence, first_sequence + count)
        table["log_time"] = table["publish_time"] = log_times
        table["payload"] = payloads
        offsets = self.size + record.itemsize * np.arange(count)
        self.parts.append(table.tobytes())
        self.size += table.nbytes
        self.index.setdefault(channel_id, []).extend(zip(log_times.tolist(), offsets.tolist(), strict=True))
        low, high = int(log_times.min()), int(log_times.max())
        self.start = low if self.start is None else min(self.start, low)
        self.end = high if self.end is None else max(self.end, high)


class McapWriter:
    """Usage: `with McapWriter(path) as w: w.write(topic, msg); w.add_metadata(name, dict)`."""

    def __init__(self, path: str | Path, overwrite: bool = False, chunk_size: int = CHUNK_SIZE,
                 separate_topics: tuple[str, ...] = (), separate_batch: int = 2048,
                 chunk_level: int | None = FAST_LEVEL, series_level: int | None = SERIES_LEVEL):
        """`separate_topics`: small high-rate topics (force, pose) whose messages are gathered into
        chunks of their own, `separate_batch` messages at a time. `chunk_level` / `series_level`:
        zstd levels of the mixed chunks and of the separated series' chunks (None: uncompressed)."""
        self.path = Path(path)
        self._atomic = atomic_output(self.path, overwrite)
        self._tmp = self._atomic.__enter__()
        self._stream = open(self._tmp, "wb")  # noqa: SIM115 - closed in close()/abort()
        self._offset = 0
        self._chunk_size = chunk_size
        self._separate = set(separate_topics)
        self._separate_batch = separate_batch
        self._main = _Chunk(chunk_level)
        self._series = _Chunk(series_level)
        self._schemas: dict[str, int] = {}
        self._schema_records: list[bytes] = []
        self._channels: dict[str, tuple[int, str]] = {}
        self._channel_records: list[bytes] = []
        self._sequence: dict[str, int] = {}
        self._message_counts: dict[int, int] = {}
        self._time_range: list[int] = []
        self._chunk_indexes: list[bytes] = []
        self._metadata_indexes: list[bytes] = []
        self._closed = False
        self._emit(MAGIC)
        self._emit(_record(OP_HEADER, _string(layout.PROFILE) + _string(f"visionforce {__version__}")))

    def _emit(self, data: bytes | bytearray) -> None:
        self._stream.write(data)
        self._offset += len(data)

    # -- channels and messages ----------------------------------------------------------------
    def channel(self, topic: str, msgtype: str) -> int:
        """The channel id of `topic`, registering it (and its schema) on first use."""
        if topic in self._channels:
            channel_id, known = self._channels[topic]
            if known != msgtype:
                raise ValueError(f"topic {topic} already has type {known}, not {msgtype}")
            return channel_id
        if msgtype not in self._schemas:
            schema_id = len(self._schemas) + 1
            data = schema_text(msgtype).encode()
            record = _record(OP_SCHEMA, struct.pack("<H", schema_id) + _string(msgtype)
                             + _string(layout.SCHEMA_ENCODING) + struct.pack("<I", len(data)) + data)
            self._schemas[msgtype] = schema_id
            self._schema_records.append(record)
            self._emit(record)
        channel_id = len(self._channels)
        record = _record(OP_CHANNEL, struct.pack("<HH", channel_id, self._schemas[msgtype]) + _string(topic)
                         + _string(layout.MESSAGE_ENCODING) + _string_map({}))
        self._channels[topic] = (channel_id, msgtype)
        self._channel_records.append(record)
        self._sequence[topic] = 0
        self._message_counts[channel_id] = 0
        self._emit(record)
        return channel_id

    def write(self, topic: str, message, log_time_ns: int | None = None) -> None:
        """Write a typed message (vfdata.recording.messages); log time = its stamp unless given."""
        stamp = message.stamp_ns if log_time_ns is None else log_time_ns
        self.write_payload(topic, message.msgtype, stamp, message.encode())

    def write_payload(self, topic: str, msgtype: str, log_time_ns: int, payload: bytes | memoryview) -> None:
        channel_id = self.channel(topic, msgtype)
        sequence = self._sequence[topic]
        self._sequence[topic] = sequence + 1
        self._message_counts[channel_id] += 1
        log_time = int(log_time_ns)
        if topic in self._separate:
            self._series.add(channel_id, sequence, log_time, payload)
            if sum(len(v) for v in self._series.index.values()) >= self._separate_batch:
                self._flush(self._series)
            return
        self._main.add(channel_id, sequence, log_time, payload)
        if self._main.size >= self._chunk_size:
            self._flush(self._main)

    def write_payloads(self, topic: str, msgtype: str, log_times_ns: np.ndarray, payloads: np.ndarray) -> None:
        """Many messages of one topic at once: `payloads` an (n, L) uint8 array (one message a row, all of
        length L, e.g. a force series), `log_times_ns` (n,). The file is byte for byte what n
        `write_payload` calls give (same chunk boundaries), at a fraction of their per-message cost."""
        log_times_ns = np.asarray(log_times_ns, np.int64)
        payloads = np.ascontiguousarray(payloads, np.uint8)
        if len(log_times_ns) != len(payloads) or payloads.ndim != 2:
            raise ValueError("write_payloads needs one log time per payload row")
        channel_id = self.channel(topic, msgtype)
        separate = topic in self._separate
        chunk = self._series if separate else self._main
        record_size = 31 + payloads.shape[1]
        start = 0
        while start < len(payloads):
            # As many messages as `write_payload` would add before its next flush of this chunk.
            if separate:
                room = self._separate_batch - sum(len(v) for v in chunk.index.values())
            else:
                room = -(-(self._chunk_size - chunk.size) // record_size)
            stop = min(len(payloads), start + max(1, room))
            sequence = self._sequence[topic]
            chunk.add_many(channel_id, sequence, log_times_ns[start:stop], payloads[start:stop])
            self._sequence[topic] = sequence + stop - start
            self._message_counts[channel_id] += stop - start
            full = (sum(len(v) for v in chunk.index.values()) >= self._separate_batch if separate
                    else chunk.size >= self._chunk_size)
            if full:
                self._flush(chunk)
            start = stop

    def _flush(self, chunk: _Chunk) -> None:
        if not chunk.index:
            return
        if chunk.compressor is None:
            pieces = chunk.parts
            crc = 0
            for piece in pieces:
                crc = crc32(piece, crc)
        else:
            records = b"".join(chunk.parts)
            crc = crc32(records)
            pieces = [chunk.compressor.compress(records)]
        stored = sum(len(piece) for piece in pieces)
        start_offset = self._offset
        body = (struct.pack("<QQQI", chunk.start, chunk.end, chunk.size, crc)
                + _string(chunk.compression) + struct.pack("<Q", stored))
        self._emit(struct.pack("<BQ", OP_CHUNK, len(body) + stored) + body)
        for piece in pieces:
            self._emit(piece)
        chunk_length = self._offset - start_offset
        index_start = self._offset
        offsets = {}
        for channel_id, entries in sorted(chunk.index.items()):
            offsets[channel_id] = self._offset
            pairs = b"".join(struct.pack("<QQ", t, o) for t, o in entries)
            self._emit(_record(OP_MESSAGE_INDEX, struct.pack("<HI", channel_id, len(pairs)) + pairs))
        offset_map = b"".join(struct.pack("<HQ", c, o) for c, o in offsets.items())
        self._chunk_indexes.append(_record(OP_CHUNK_INDEX, struct.pack(
            "<QQQQ", chunk.start, chunk.end, start_offset, chunk_length) + struct.pack("<I", len(offset_map))
            + offset_map + struct.pack("<Q", self._offset - index_start) + _string(chunk.compression)
            + struct.pack("<QQ", stored, chunk.size)))
        self._time_range += [chunk.start, chunk.end]
        chunk.reset()

    def add_metadata(self, name: str, record: dict[str, str]) -> None:
        offset = self._offset
        data = _record(OP_METADATA, _string(name) + _string_map({str(k): str(v) for k, v in record.items()}))
        self._emit(data)
        self._metadata_indexes.append(_record(OP_METADATA_INDEX, struct.pack("<QQ", offset, len(data))
                                              + _string(name)))

    # -- finishing -------------------------------------------------------------------------------
    def _finish(self) -> None:
        self._flush(self._main)
        self._flush(self._series)
        self._emit(_record(OP_DATA_END, struct.pack("<I", 0)))
        summary_start = self._offset
        summary_crc = 0
        groups = []
        counts = b"".join(struct.pack("<HQ", c, n) for c, n in sorted(self._message_counts.items()))
        statistics = _record(OP_STATISTICS, struct.pack(
            "<QHIIII", sum(self._message_counts.values()), len(self._schemas), len(self._channels), 0,
            len(self._metadata_indexes), len(self._chunk_indexes))
            + struct.pack("<QQ", min(self._time_range, default=0), max(self._time_range, default=0))
            + struct.pack("<I", len(counts)) + counts)
        for opcode, records in ((OP_SCHEMA, self._schema_records), (OP_CHANNEL, self._channel_records),
                                (OP_STATISTICS, [statistics]), (OP_CHUNK_INDEX, self._chunk_indexes),
                                (OP_METADATA_INDEX, self._metadata_indexes)):
            if not records:
                continue
            start = self._offset
            data = b"".join(records)
            self._stream.write(data)
            summary_crc = crc32(data, summary_crc)
            self._offset += len(data)
            groups.append(struct.pack("<BQQ", opcode, start, self._offset - start))
        summary_offset_start = self._offset
        offsets = b"".join(_record(OP_SUMMARY_OFFSET, g) for g in groups)
        self._stream.write(offsets)
        self._offset += len(offsets)
        footer_head = struct.pack("<BQQQ", OP_FOOTER, 20, summary_start, summary_offset_start)
        summary_crc = crc32(footer_head, crc32(offsets, summary_crc))
        self._stream.write(footer_head + struct.pack("<I", summary_crc) + MAGIC)

    def close(self) -> None:
        """Finish the file and move it into place."""
        if self._closed:
            return
        self._closed = True
        try:
            self._finish()
            self._stream.close()
        except BaseException as exc:
            self._stream.close()
            self._atomic.__exit__(type(exc), exc, exc.__traceback__)
            raise
        self._atomic.__exit__(None, None, None)

    def abort(self) -> None:
        """Discard everything written."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(Exception):
            self._stream.close()
        with contextlib.suppress(Exception):
            self._atomic.__exit__(RuntimeError, RuntimeError("aborted"), None)

    def __enter__(self) -> McapWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
