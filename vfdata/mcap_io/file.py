"""Random access to the messages of an MCAP file, through its index (`index_builder`).

One frame costs one chunk read (cached), and a whole force series is a numpy gather over a few
chunks instead of a per-message decode. Every chunk is checked the first time it is read: its record
against its chunk index, its CRC, and its message index against its records (an index that points at
the wrong records is corrected from the records themselves). A chunk that fails is refused with a
`CorruptChunkError` unless the file was opened with `damaged="skip"` (every chunk is checked on
opening and the damaged ones are left out) or `damaged="serve"` (likewise, but chunks that fail only
their CRC are served as they are)."""

from __future__ import annotations

import os
from collections import OrderedDict
from pathlib import Path

import numpy as np
import zstandard

from vfdata.errors import FormatError
from vfdata.mcap_io.index import Chunk, MessageLocations, merge_locations
from vfdata.mcap_io.index_builder import build_index, scan_chunk_records
from vfdata.mcap_io.records import (
    CHUNK_FIELDS,
    MESSAGE_FIELDS,
    MESSAGE_HEAD,
    MESSAGE_HEAD_DTYPE,
    RECORD_HEAD,
    Opcode,
    crc32,
)

DAMAGED = ("error", "skip", "serve")


class CorruptChunkError(FormatError):
    """A chunk whose messages are refused: it cannot be read, fails its CRC check, or its message
    index disagrees with its records in log times or counts."""

    def __init__(self, path: str | Path, chunk_offset: int, topics: list[str], problem: str):
        self.chunk_offset = chunk_offset
        self.topics = topics
        super().__init__(path, f"chunk at byte {chunk_offset} ({', '.join(topics) or 'no known topic'}) {problem}: "
                               "its messages are refused (open with damaged='skip' to read the rest of the file, "
                               "'serve' to read them as they are; `vfdata check` lists the damage)")


class McapFile:
    """An MCAP file opened for indexed reading. Opened lazily and re-opened after a fork, so an
    instance can be handed to DataLoader workers."""

    def __init__(self, path: str | Path, chunk_cache: int = 4, damaged: str = "error"):
        if damaged not in DAMAGED:
            raise ValueError(f"damaged must be one of {DAMAGED}, not {damaged!r}")
        self.path = Path(path)
        if not self.path.is_file():
            raise FormatError(self.path, "file not found")
        self.damaged = damaged
        self._file = None
        self._pid = None
        self._cache: OrderedDict[int, bytes | memoryview] = OrderedDict()
        self._cache_size = chunk_cache
        self._zstd = zstandard.ZstdDecompressor()
        self.size = self.path.stat().st_size
        self.index = build_index(self)
        if damaged != "error":
            self.verify_all()
            self._leave_out_damaged()

    # -- file access -------------------------------------------------------------------------
    def _handle(self):
        if self._file is None or self._pid != os.getpid():
            self._file = open(self.path, "rb")  # noqa: SIM115 - kept for the reader's lifetime
            self._pid = os.getpid()
            self._cache.clear()
        return self._file

    def read_at(self, offset: int, size: int) -> bytes:
        """`size` bytes at `offset`; a range outside the file (a damaged length or offset) is a
        FormatError, never a read of that size."""
        if offset < 0 or size < 0 or offset + size > self.size:
            raise FormatError(self.path, f"a record points at bytes {offset}..{offset + size}, past the end of "
                                         f"the file ({self.size} bytes)")
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
    def read_chunk(self, chunk: Chunk, problems: list[str]) -> bytes | memoryview:
        """A chunk's records, decompressed (uncompressed: a view of one read, no copy). On its first
        read the chunk record is checked against the index and the records against the CRC, setting
        `chunk.status` and noting what fails in `problems`; FormatError when it cannot be read."""
        where = f"chunk at byte {chunk.record_offset}"
        head = chunk.data_offset - chunk.record_offset
        raw = memoryview(self.read_at(chunk.record_offset, head + chunk.compressed_size))
        first = not chunk.status
        if first and not self._head_agrees(chunk, raw):
            problems.append(f"{where}: its record disagrees with its chunk index")
        try:
            data = self._decompress(chunk, raw[head:])
        except FormatError as exc:
            chunk.status = "unreadable"
            problems.append(exc.problem)
            raise
        if first:
            crc = chunk.uncompressed_crc
            chunk.status = "bad-crc" if crc and crc32(data) != crc else "ok"
            if chunk.status == "bad-crc":
                problems.append(f"{where}: CRC mismatch (the chunk is damaged)")
        return data

    def _head_agrees(self, chunk: Chunk, raw: memoryview) -> bool:
        opcode, length = RECORD_HEAD.unpack_from(raw)
        start, end, uncompressed_size, crc = CHUNK_FIELDS.unpack_from(raw, RECORD_HEAD.size)
        if chunk.uncompressed_crc is None:
            chunk.uncompressed_crc = crc  # the CRC is only in the chunk record
        head = chunk.data_offset - chunk.record_offset
        name = bytes(raw[RECORD_HEAD.size + CHUNK_FIELDS.size + 4:head - 8])
        name_length = int.from_bytes(raw[RECORD_HEAD.size + CHUNK_FIELDS.size:RECORD_HEAD.size + CHUNK_FIELDS.size + 4],
                                     "little")
        records_length = int.from_bytes(raw[head - 8:head], "little")
        return (opcode == Opcode.CHUNK and length == chunk.record_length - RECORD_HEAD.size
                and (start, end, uncompressed_size) == (chunk.start_ns, chunk.end_ns, chunk.uncompressed_size)
                and name_length == len(name) and name == chunk.compression.encode()
                and records_length == chunk.compressed_size and crc == chunk.uncompressed_crc)

    def _decompress(self, chunk: Chunk, raw: memoryview) -> bytes | memoryview:
        """The records of a chunk, never more than its stated size (a damaged size or frame header
        gives a FormatError, not a huge allocation)."""
        size = chunk.uncompressed_size
        where = f"chunk at byte {chunk.record_offset}"
        try:
            if chunk.compression == "":
                data = raw
            elif chunk.compression == "zstd":
                content = zstandard.frame_content_size(raw)
                if content == size:
                    data = self._zstd.decompress(raw)
                elif content == -1:  # no size in the frame: read at most one byte past the stated size
                    data = self._zstd.stream_reader(raw).read(size + 1)
                else:
                    raise FormatError(self.path, f"{where} decompresses to {content} bytes, its index says {size}")
            elif chunk.compression == "lz4":
                import lz4.frame  # a dependency of `mcap`; only files written by others use it

                data = lz4.frame.LZ4FrameDecompressor().decompress(raw, max_length=size + 1)
            else:
                raise FormatError(self.path, f"{where}: unsupported compression '{chunk.compression}'")
        except (zstandard.ZstdError, RuntimeError, ValueError, MemoryError) as exc:
            raise FormatError(self.path, f"{where} cannot be decompressed ({type(exc).__name__}: {exc})") from None
        if len(data) != size:
            raise FormatError(self.path, f"{where} decompresses to a wrong size")
        return data

    def chunk_records(self, chunk_id: int) -> bytes | memoryview:
        """The decompressed records of a chunk (cached); CorruptChunkError for a damaged chunk."""
        if chunk_id in self._cache:
            self._cache.move_to_end(chunk_id)
            return self._cache[chunk_id]
        chunk = self.index.chunks[chunk_id]
        if chunk.status == "unreadable":
            raise self._refused(chunk, "cannot be read")
        first = not chunk.status
        try:
            data = self.read_chunk(chunk, self.index.problems)
        except FormatError as exc:
            raise self._refused(chunk, f"cannot be read ({exc.problem})") from None
        if first and chunk.status == "ok":
            self._verify_message_index(chunk_id, data)
        if chunk.status == "bad-crc" and self.damaged != "serve":
            raise self._refused(chunk, "fails its CRC check")
        if chunk.status == "bad-index":
            raise self._refused(chunk, "has a message index that disagrees with its records in log times or counts "
                                       "(its records may be intact: damaged='skip' indexes them from the records)")
        self._cache[chunk_id] = data
        if len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return data

    def _refused(self, chunk: Chunk, problem: str) -> CorruptChunkError:
        topics = sorted(self.index.channels[c].topic for c in chunk.channels if c in self.index.channels)
        return CorruptChunkError(self.path, chunk.record_offset, topics, problem)

    def _verify_message_index(self, chunk_id: int, records: bytes | memoryview) -> None:
        """Check that the index's entries for this chunk point at message records of their channel and
        log time. Where they do not, the chunk's records are walked: offsets that were wrong are
        corrected (noted); log times or counts that disagree make the chunk 'bad-index'."""
        chunk = self.index.chunks[chunk_id]
        if all(_heads_match(records, self.index.messages[c], chunk_id, c) for c in chunk.channels
               if c in self.index.messages):
            return
        where = f"chunk at byte {chunk.record_offset}"
        found, problem = scan_chunk_records(records, self.path, where)
        indexed = {c: self.index.messages[c] for c in chunk.channels | set(found) if c in self.index.messages}
        same = problem is None and set(found) <= set(indexed) and all(
            np.array_equal(np.sort(loc.log_time_ns[loc.in_chunk(chunk_id)]), np.sort(found.get(c, ([], []))[0]))
            for c, loc in indexed.items())
        if same:
            for c, loc in indexed.items():
                times, offsets = (np.asarray(v, np.int64) for v in found.get(c, ([], [])))
                loc.offset[loc.in_chunk(chunk_id)] = offsets[np.lexsort((offsets, times))]
            self.index.problems.append(f"{where}: its message index points at the wrong records (the messages "
                                       "are intact and were located from the chunk's records)")
        else:
            chunk.status = "bad-index"
            self.index.problems.append(f"{where}: its message index disagrees with its records")

    def verify_all(self) -> list[str]:
        """Read and check every chunk not read yet (see `read_chunk`); the file's problems."""
        for chunk_id, chunk in enumerate(self.index.chunks):
            if chunk.status:
                continue
            try:
                data = self.read_chunk(chunk, self.index.problems)
            except FormatError:
                continue
            if chunk.status == "ok":
                self._verify_message_index(chunk_id, data)
        return self.index.problems

    def _leave_out_damaged(self) -> None:
        """damaged='skip'/'serve': the index lists only what can be served; a chunk whose message index
        disagrees with its records is indexed from its records."""
        for chunk_id, chunk in enumerate(self.index.chunks):
            if chunk.status == "bad-index":
                records = self.read_chunk(chunk, [])
                found, _ = scan_chunk_records(records, self.path, "")
                self._replace_entries(chunk_id, found)
                chunk.status = "ok"
            elif chunk.status == "unreadable" or (chunk.status == "bad-crc" and self.damaged == "skip"):
                self._replace_entries(chunk_id, {})

    def _replace_entries(self, chunk_id: int, found: dict[int, tuple[list[int], list[int]]]) -> None:
        chunk = self.index.chunks[chunk_id]
        for channel_id in chunk.channels | set(found):
            loc = self.index.messages.get(channel_id)
            if loc is None:
                continue
            keep = loc.chunk != chunk_id
            times, offsets = found.get(channel_id, ([], []))
            self.index.messages[channel_id] = merge_locations(
                np.concatenate([loc.log_time_ns[keep], np.asarray(times, np.int64)]),
                np.concatenate([loc.chunk[keep], np.full(len(times), chunk_id, np.int32)]),
                np.concatenate([loc.offset[keep], np.asarray(offsets, np.int64)]))
        chunk.channels = {c for c in found if c in self.index.messages}

    # -- messages ------------------------------------------------------------------------------
    def payload(self, channel_id: int, i: int) -> bytes | memoryview:
        """The payload of the i-th message (in log-time order) of a channel: a view into the cached
        chunk (no copy), or bytes for a message outside any chunk."""
        loc = self.index.messages[channel_id]
        chunk, offset = int(loc.chunk[i]), int(loc.offset[i])
        if chunk < 0:
            length = RECORD_HEAD.unpack(self.read_at(offset, RECORD_HEAD.size))[1]
            return self.read_at(offset + MESSAGE_HEAD.size, length - MESSAGE_FIELDS)
        records = self.chunk_records(chunk)
        length = RECORD_HEAD.unpack_from(records, offset)[1]
        return memoryview(records)[offset + MESSAGE_HEAD.size:offset + RECORD_HEAD.size + length]

    def iter_payload_matrices(self, channel_id: int):
        """A channel's payloads as (N_i, L_i) uint8 matrices, chunk by chunk and one per distinct
        payload length (in practice one): for fixed-size messages (wrench, pose), decoded with numpy
        one chunk at a time so that memory stays at one chunk's worth."""
        loc = self.index.messages[channel_id]
        for chunk, sel in loc.groups().items():
            if chunk < 0:
                for i in sel:
                    yield np.frombuffer(bytes(self.payload(channel_id, int(i))), dtype=np.uint8)[None]
                continue
            records = self.chunk_records(chunk)
            offsets = loc.offset[sel]
            heads = message_heads(records, offsets)
            if heads is None:
                raise FormatError(self.path, "a message runs past the end of its chunk")
            payload_len = heads["length"].astype(np.int64) - MESSAGE_FIELDS
            for length in np.unique(payload_len):
                starts = offsets[payload_len == length] + MESSAGE_HEAD.size
                if length < 0 or starts.max() + length > len(records):
                    raise FormatError(self.path, "a message runs past the end of its chunk")
                yield _rows(records, starts, int(length))

    def iter_payloads(self, channel_id: int, start: int = 0, stop: int | None = None):
        """(log_time_ns, payload) of a channel's messages in log-time order."""
        loc = self.index.messages[channel_id]
        for i in range(start, len(loc) if stop is None else stop):
            yield int(loc.log_time_ns[i]), self.payload(channel_id, i)


def message_heads(records: bytes | memoryview, offsets: np.ndarray) -> np.ndarray | None:
    """The message record heads (MESSAGE_HEAD_DTYPE) at `offsets` in a chunk's records; None where one
    runs past the end. Records of equal length back to back (a series) are a strided view, no copy."""
    size = len(records)
    if not len(offsets):
        return np.zeros(0, MESSAGE_HEAD_DTYPE)
    if offsets.min() < 0 or offsets.max() + MESSAGE_HEAD.size > size:
        return None
    stride = int(offsets[1] - offsets[0]) if len(offsets) > 1 else MESSAGE_HEAD.size
    if stride >= MESSAGE_HEAD.size and (np.diff(offsets) == stride).all():
        return np.ndarray((len(offsets),), MESSAGE_HEAD_DTYPE, records, int(offsets[0]), (stride,))
    data = np.frombuffer(records, np.uint8)
    return data[offsets[:, None] + np.arange(MESSAGE_HEAD.size)].view(MESSAGE_HEAD_DTYPE).ravel()


def _rows(records: bytes | memoryview, starts: np.ndarray, length: int) -> np.ndarray:
    """(n, length) uint8 of the bytes at each start: a strided view when the starts are evenly spaced."""
    stride = int(starts[1] - starts[0]) if len(starts) > 1 else length
    if stride >= length and (np.diff(starts) == stride).all():
        return np.ndarray((len(starts), length), np.uint8, records, int(starts[0]), (stride, 1))
    return np.frombuffer(records, np.uint8)[starts[:, None] + np.arange(length)]


def _heads_match(records: bytes | memoryview, loc: MessageLocations, chunk_id: int, channel_id: int) -> bool:
    """Whether the entries of `loc` in this chunk point at message records of `channel_id` with their
    log times, each inside the chunk."""
    sel = loc.in_chunk(chunk_id)
    offsets = loc.offset[sel]
    heads = message_heads(records, offsets)
    if heads is None:
        return False
    length = heads["length"]
    return bool(((heads["opcode"] == Opcode.MESSAGE) & (heads["channel"] == channel_id)
                 & (heads["log_time"] == loc.log_time_ns[sel].astype(np.uint64)) & (length >= MESSAGE_FIELDS)
                 & (length <= len(records) - offsets - RECORD_HEAD.size)).all())
