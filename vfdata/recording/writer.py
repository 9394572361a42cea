"""Writing MCAP files of the VisionForce layout (recordings and derived files).

`McapWriter` writes profile ros2, CDR messages, ros2msg schemas, chunks with message indexes and
CRCs, the data-section CRC, and a summary (with its CRC) holding schemas, channels, statistics,
chunk and metadata indexes and summary offsets. Records go through `mcap.records`' builders, except
the three the converters write at the rate of their messages, whose bytes are packed here (layout
from `vfdata.mcap_io.records`, checked against the library; tests compare them byte for byte): message records,
chunk record heads and message indexes. What `mcap.writer.Writer` cannot do, and the converters need:

- per-chunk compression: chunks of JPEG/PNG images do not compress (ratio 1.00003), so the
  converters store them uncompressed (`IMAGE_LEVEL`; zstd's default level cost 2 ms per stereo
  frame and its fastest level still 0.15 ms, on writing and again on every read); the small
  high-rate series (force, pose), which do compress, use zstd level 3;
- each small high-rate topic gathered into chunks of its own (`separate_topics`), so a reader gets a
  1 kHz force series without decompressing the video, and every chunk's messages are in log-time
  order (a chunk shared by the force and pose series held one after the other).

The file appears under its name only when `close()` succeeds; on any error nothing is left behind.
Files are read back in the tests by `mcap`'s own reader and by rosbags."""

from __future__ import annotations

import contextlib
import struct
from pathlib import Path
from types import TracebackType

import numpy as np
import zstandard
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from vfdata import __version__
from vfdata.atomic import atomic_output
from vfdata.mcap_io.records import (
    CHUNK_FIELDS,
    MAGIC,
    MESSAGE_FIELDS,
    MESSAGE_HEAD,
    MESSAGE_HEAD_DTYPE,
    MESSAGE_INDEX_HEAD,
    RECORD_HEAD,
    Opcode,
    crc32,
    record_bytes,
)
from vfdata.recording import layout
from vfdata.recording.schemas import schema_text

# Large enough that a stereo JPEG pair and a few hundred force samples share a chunk; small enough
# that reading one frame decompresses little.
CHUNK_SIZE = 4 * 1024 * 1024
FAST_LEVEL = -1  # zstd "fast" level: the default of mixed chunks (derived files: clouds, masks, depth)
IMAGE_LEVEL = None  # no compression: for chunks of already-compressed images (the converters)
SERIES_LEVEL = 3  # zstd default: for the separated small-message series


class _Chunk:
    """Messages gathered for one chunk, with their per-channel message index.

    Message records are packed here rather than by `mcap.records.Message.write`, which copies each
    payload into a BytesIO: 6-54 us per 100 kB image against 0.2 us for the packed head (the image
    itself is kept as it is), 1.3 us against 0.14 us per force message, 0.03 us per message in a
    numpy table (`add_many`) (`bench/bench_recording.py --records`)."""

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
        self.count = 0
        self.index: dict[int, tuple[list[int], list[int]]] = {}  # channel -> (log times, offsets)
        self.start = None
        self.end = None

    def add(self, channel_id: int, sequence: int, log_time: int, payload: bytes | memoryview) -> None:
        offset = self.size
        # bytes are kept as they are; a view or bytearray is copied, its owner may reuse the memory.
        data = payload if type(payload) is bytes else bytes(payload)
        # The length of what is written: len() of a view of float64s or of a 2-D array counts items.
        head = MESSAGE_HEAD.pack(Opcode.MESSAGE, MESSAGE_FIELDS + len(data), channel_id, sequence, log_time, log_time)
        self.parts += (head, data)
        self.size += len(head) + len(data)
        self.count += 1
        times, offsets = self.index.setdefault(channel_id, ([], []))
        times.append(log_time)
        offsets.append(offset)
        self.start = log_time if self.start is None else min(self.start, log_time)
        self.end = log_time if self.end is None else max(self.end, log_time)

    def add_many(self, channel_id: int, first_sequence: int, log_times: np.ndarray, payloads: np.ndarray) -> None:
        """`add` for n messages of one channel at once: payloads an (n, L) uint8 array, one row each.
        The records are built as one numpy table, byte for byte what n `add` calls append."""
        count, length = payloads.shape
        record = np.dtype(MESSAGE_HEAD_DTYPE.descr + [("payload", "u1", (length,))])
        table = np.empty(count, record)
        table["opcode"] = Opcode.MESSAGE
        table["length"] = MESSAGE_FIELDS + length
        table["channel"] = channel_id
        table["sequence"] = np.arange(first_sequence, first_sequence + count)
        table["log_time"] = table["publish_time"] = log_times
        table["payload"] = payloads
        offsets = self.size + record.itemsize * np.arange(count)
        self.parts.append(table.tobytes())
        self.size += table.nbytes
        self.count += count
        times, at = self.index.setdefault(channel_id, ([], []))
        times += log_times.tolist()
        at += offsets.tolist()
        low, high = int(log_times.min()), int(log_times.max())
        self.start = low if self.start is None else min(self.start, low)
        self.end = high if self.end is None else max(self.end, high)


class McapWriter:
    """Usage: `with McapWriter(path) as w: w.write(topic, msg); w.add_metadata(name, dict)`."""

    def __init__(self, path: str | Path, overwrite: bool = False, chunk_size: int = CHUNK_SIZE,
                 separate_topics: tuple[str, ...] = (), separate_batch: int = 2048,
                 chunk_level: int | None = FAST_LEVEL, series_level: int | None = SERIES_LEVEL,
                 inputs: tuple[str | Path, ...] = ()):
        """`separate_topics`: small high-rate topics (force, pose) whose messages are gathered into
        chunks of their own, one topic a chunk, `separate_batch` messages at a time. `chunk_level` /
        `series_level`: zstd levels of the mixed chunks and of the separated series' chunks (None:
        uncompressed)."""
        self.path = Path(path)
        self._atomic = atomic_output(self.path, overwrite, inputs)  # `inputs`: files it is made from
        self._tmp = self._atomic.__enter__()
        self._stream = open(self._tmp, "wb")  # noqa: SIM115 - closed in close()/abort()
        self._offset = 0
        self._data_crc = 0
        self._chunk_size = chunk_size
        self._separate_batch = separate_batch
        self._main = _Chunk(chunk_level)
        self._series = {topic: _Chunk(series_level) for topic in separate_topics}
        self._schemas: dict[str, Schema] = {}
        self._channels: dict[str, Channel] = {}
        self._types: dict[str, str] = {}
        self._sequence: dict[str, int] = {}
        self._message_counts: dict[int, int] = {}
        self._time_range: list[int] = []
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._closed = False
        self._emit(MAGIC)
        self._emit(record_bytes(Header(layout.PROFILE, f"visionforce {__version__}")))

    def _emit(self, data: bytes | bytearray) -> None:
        """Write into the data section (everything before the DataEnd record), whose CRC the DataEnd
        record carries: ISA-L's CRC at ~13 GB/s costs 0.01 ms per stereo pair of 100 kB images."""
        self._stream.write(data)
        self._offset += len(data)
        self._data_crc = crc32(data, self._data_crc)

    # -- channels and messages ----------------------------------------------------------------
    def channel(self, topic: str, msgtype: str) -> int:
        """The channel id of `topic`, registering it (and its schema) on first use."""
        if topic in self._channels:
            known = self._types[topic]
            if known != msgtype:
                raise ValueError(f"topic {topic} already has type {known}, not {msgtype}")
            return self._channels[topic].id
        if msgtype not in self._schemas:
            schema = Schema(id=len(self._schemas) + 1, data=schema_text(msgtype).encode(),
                            encoding=layout.SCHEMA_ENCODING, name=msgtype)
            self._schemas[msgtype] = schema
            self._emit(record_bytes(schema))
        channel = Channel(id=len(self._channels), topic=topic, message_encoding=layout.MESSAGE_ENCODING,
                          metadata={}, schema_id=self._schemas[msgtype].id)
        self._channels[topic] = channel
        self._types[topic] = msgtype
        self._sequence[topic] = 0
        self._message_counts[channel.id] = 0
        self._emit(record_bytes(channel))
        return channel.id

    def write(self, topic: str, message, log_time_ns: int | None = None) -> None:
        """Write a typed message (vfdata.recording.messages); log time = its stamp unless given."""
        stamp = message.stamp_ns if log_time_ns is None else log_time_ns
        self.write_payload(topic, message.msgtype, stamp, message.encode())

    def write_payload(self, topic: str, msgtype: str, log_time_ns: int, payload: bytes | memoryview) -> None:
        channel_id = self.channel(topic, msgtype)
        sequence = self._sequence[topic]
        self._sequence[topic] = sequence + 1
        self._message_counts[channel_id] += 1
        series = self._series.get(topic)
        if series is not None:
            series.add(channel_id, sequence, int(log_time_ns), payload)
            if series.count >= self._separate_batch:
                self._flush(series)
            return
        self._main.add(channel_id, sequence, int(log_time_ns), payload)
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
        series = self._series.get(topic)
        chunk = self._main if series is None else series
        record_size = MESSAGE_HEAD.size + payloads.shape[1]
        start = 0
        while start < len(payloads):
            # As many messages as `write_payload` would add before its next flush of this chunk.
            if series is not None:
                room = self._separate_batch - chunk.count
            else:
                room = -(-(self._chunk_size - chunk.size) // record_size)
            stop = min(len(payloads), start + max(1, room))
            sequence = self._sequence[topic]
            chunk.add_many(channel_id, sequence, log_times_ns[start:stop], payloads[start:stop])
            self._sequence[topic] = sequence + stop - start
            self._message_counts[channel_id] += stop - start
            if (chunk.count >= self._separate_batch) if series is not None else (chunk.size >= self._chunk_size):
                self._flush(chunk)
            start = stop

    def _flush(self, chunk: _Chunk) -> None:
        if not chunk.count:
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
        # The chunk record's head packed here so that its records go to the file piece by piece:
        # `mcap.records.Chunk.write` copies a 4 MB chunk of images twice, 2.8-7 ms (1 us for the head).
        name = chunk.compression.encode()
        body = CHUNK_FIELDS.pack(chunk.start, chunk.end, chunk.size, crc) + struct.pack("<I", len(name)) + name
        body += struct.pack("<Q", stored)
        self._emit(RECORD_HEAD.pack(Opcode.CHUNK, len(body) + stored) + body)
        for piece in pieces:
            self._emit(piece)
        chunk_length = self._offset - start_offset
        index_start = self._offset
        offsets = {}
        for channel_id, (times, at) in sorted(chunk.index.items()):
            offsets[channel_id] = self._offset
            # The pairs as one numpy array: `MessageIndex.write` packs them one by one, 0.9 ms for a
            # chunk of 2048 force messages (0.44 us a message, three times the packed message head),
            # 0.4 ms here.
            pairs = np.column_stack((np.asarray(times, np.int64), np.asarray(at, np.int64))).astype("<u8").tobytes()
            self._emit(MESSAGE_INDEX_HEAD.pack(Opcode.MESSAGE_INDEX, 6 + len(pairs), channel_id, len(pairs)) + pairs)
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=chunk.start, message_end_time=chunk.end, chunk_start_offset=start_offset,
            chunk_length=chunk_length, message_index_offsets=offsets, message_index_length=self._offset - index_start,
            compression=chunk.compression, compressed_size=stored, uncompressed_size=chunk.size))
        self._time_range += [chunk.start, chunk.end]
        chunk.reset()

    def add_metadata(self, name: str, record: dict[str, str]) -> None:
        """A metadata record: a string map (values are written as their str())."""
        offset = self._offset
        data = record_bytes(Metadata(name=name, metadata={str(k): str(v) for k, v in sorted(record.items())}))
        self._emit(data)
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=len(data), name=name))

    # -- finishing -------------------------------------------------------------------------------
    def _finish(self) -> None:
        self._flush(self._main)
        for series in self._series.values():
            self._flush(series)
        self._stream.write(record_bytes(DataEnd(self._data_crc)))
        self._offset += 4 + RECORD_HEAD.size
        summary_start = self._offset
        statistics = Statistics(
            message_count=sum(self._message_counts.values()), schema_count=len(self._schemas),
            channel_count=len(self._channels), attachment_count=0, metadata_count=len(self._metadata_indexes),
            chunk_count=len(self._chunk_indexes), message_start_time=min(self._time_range, default=0),
            message_end_time=max(self._time_range, default=0),
            channel_message_counts=dict(sorted(self._message_counts.items())))
        summary = bytearray()
        offsets = []
        for opcode, records in ((Opcode.SCHEMA, list(self._schemas.values())),
                                (Opcode.CHANNEL, list(self._channels.values())), (Opcode.STATISTICS, [statistics]),
                                (Opcode.CHUNK_INDEX, self._chunk_indexes),
                                (Opcode.METADATA_INDEX, self._metadata_indexes)):
            if records:
                start = summary_start + len(summary)
                for record in records:
                    summary += record_bytes(record)
                offsets.append(SummaryOffset(opcode, start, summary_start + len(summary) - start))
        summary_offset_start = summary_start + len(summary)
        for offset in offsets:
            summary += record_bytes(offset)
        footer = record_bytes(Footer(summary_start, summary_offset_start, 0))
        # The summary CRC covers the summary and the footer up to its CRC field.
        summary_crc = crc32(footer[:-4], crc32(summary))
        self._stream.write(summary)
        self._stream.write(record_bytes(Footer(summary_start, summary_offset_start, summary_crc)) + MAGIC)

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
