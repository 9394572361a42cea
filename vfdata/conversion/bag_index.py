"""Random access to the raw messages of a bag, for the storages where it is cheap: ROS 1 bags and
ROS 2 bags in MCAP storage whose chunks are uncompressed (the files are memory-mapped; a message is a
slice of them, copied by nobody), and ROS 2 sqlite3 bags (a message is a row, read as a blob, its
first bytes alone when that is enough: `bag_sqlite`). The interface they share is `bag_access.IndexedBag`.

`rosbags` still opens the bag, checks it and deserialises the messages; this module only replaces
its message iterator where the conversion needs more than an iterator gives:
- the stamp, encoding and size of every image without reading the pixels (the scan);
- the two images of a stereo pair fetched directly, in pair order, once (the convert pass);
- a 1 kHz force series as a few blocks of equal-length payloads, decoded with numpy, instead of one
  Python object per message.

`open_indexed_bag` returns None for every other storage (ROS 1 bags with bz2/lz4 chunks, MCAP
storage with zstd/lz4 chunks or without a summary, compressed ROS 2 bags) and for anything that does
not look exactly as expected; the converter then reads the bag through `rosbags`' iterator, which
also gives the clear errors for a damaged bag."""

from __future__ import annotations

import mmap
import sqlite3
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import yaml
from mcap.exceptions import McapError
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from vfdata.conversion.bag_access import BLOCK, HEAD_BYTES, INDEX_BLOCK, IndexedBag, in_bag_order
from vfdata.conversion.bag_sqlite import SqliteBag
from vfdata.errors import InputError
from vfdata.mcap_io.records import (
    CHUNK_FIELDS,
    INDEX_PAIR,
    MESSAGE_FIELDS,
    MESSAGE_HEAD,
    MESSAGE_HEAD_DTYPE,
    MESSAGE_INDEX_HEAD,
    MESSAGE_INDEX_HEAD_DTYPE,
    RECORD_HEAD,
    Opcode,
    chunk_head_size,
    crc32,
)
from vfdata.recording.messages import NS_PER_S

_U32 = struct.Struct("<I")


def open_indexed_bag(reader: AnyReader, path: Path, topics: set[str]) -> IndexedBag | None:
    """Random access to `topics` of an open bag, or None where the storage does not allow it cheaply
    (see the module docstring)."""
    try:
        if not reader.is2:
            return _Ros1Bag.open(reader, topics)
        storage = ros2_storage(path)
        if storage is None:
            return None
        kind, files = storage
        return SqliteBag.open(files, topics) if kind == "sqlite3" else _McapBag.open(files, topics)
    except (OSError, ValueError, IndexError, KeyError, struct.error, sqlite3.Error, yaml.YAMLError, McapError):
        return None


# ROS 1 bag format 2.0 (wiki.ros.org/Bags/Format/2.0): a record is a uint32 header length, the header
# (fields `uint32 length, name=value`), a uint32 data length and the data. A chunk record (op 5)
# holds message records (op 2), whose positions the bag's index gives as chunk + offset.
_OP_MSG_DATA, _OP_CHUNK = 2, 5


def _record_fields(buf: mmap.mmap, pos: int) -> tuple[dict[bytes, tuple[int, int]], int, int]:
    """The record at `pos` -> ({field name: (value position, value length)}, data position, data length)."""
    header_len = _U32.unpack_from(buf, pos)[0]
    cursor, end = pos + 4, pos + 4 + header_len
    fields = {}
    while cursor < end:
        field_len = _U32.unpack_from(buf, cursor)[0]
        field = buf[cursor + 4:cursor + 4 + field_len]
        name, sep, _ = field.partition(b"=")
        if not sep or cursor + 4 + field_len > end:
            raise ValueError("malformed record header")
        fields[name] = (cursor + 4 + len(name) + 1, field_len - len(name) - 1)
        cursor += 4 + field_len
    return fields, end + 4, _U32.unpack_from(buf, end)[0]


def _gather(data: np.ndarray, starts: np.ndarray, width: int) -> np.ndarray:
    """(n, width) uint8: `width` bytes of `data` from each start."""
    return data[starts[:, None] + np.arange(width)]


def _u32_at(data: np.ndarray, starts: np.ndarray) -> np.ndarray:
    return _gather(data, starts, 4).view("<u4").ravel().astype(np.int64)


class _MappedBag(IndexedBag):
    """Messages as slices of memory-mapped files. As with any mapped file, a bag truncated by another
    program during the conversion would stop the process with SIGBUS instead of an error message; bags
    are not written while they are converted."""

    def __init__(self, buffers: list[mmap.mmap], refs: dict[str, tuple[np.ndarray, ...]]):
        self._buffers = buffers
        self._data = [np.frombuffer(buffer, np.uint8) for buffer in buffers]
        self._refs = refs  # topic -> (receive ns, file index, data position, data length), in bag order

    def receive_ns(self, topic: str) -> np.ndarray:
        return self._refs[topic][0]

    def message(self, topic: str, i: int) -> memoryview:
        _, file, pos, length = self._refs[topic]
        return memoryview(self._buffers[file[i]])[pos[i]:pos[i] + length[i]]

    def head(self, topic: str, i: int) -> memoryview:
        _, file, pos, length = self._refs[topic]
        return memoryview(self._buffers[file[i]])[pos[i]:pos[i] + min(int(length[i]), HEAD_BYTES)]

    def payload_blocks(self, topic: str) -> Iterator[tuple[np.ndarray, np.ndarray | list[bytes]]]:
        receive, file, pos, length = self._refs[topic]
        for start in range(0, len(receive), BLOCK):
            block = slice(start, start + BLOCK)
            files, lengths = file[block], length[block]
            if (lengths == lengths[0]).all() and (files == files[0]).all():
                yield receive[block], _gather(self._data[files[0]], pos[block], int(lengths[0]))
            else:
                yield receive[block], [self._buffers[f][p:p + n] for f, p, n in zip(files, pos[block], lengths,
                                                                                     strict=True)]

    def close(self) -> None:
        del self._data
        _close_all(self._buffers)


def _map(file: Path) -> mmap.mmap:
    with open(file, "rb") as stream:
        return mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ)  # stays open after the file


class _Ros1Bag(_MappedBag):
    """A ROS 1 bag whose chunks are all uncompressed. The index `rosbags` read on opening (per
    connection: receive time, chunk, offset) locates every message; the record headers of the topics
    asked for are checked in bulk against it (op, connection, time) before anything is used."""

    reading = "random access: ROS 1 chunks, memory-mapped"

    @classmethod
    def open(cls, reader: AnyReader, topics: set[str]) -> _Ros1Bag | None:
        (bag,) = reader.readers
        buffer = _map(bag.path)
        try:
            refs = _ros1_index(buffer, bag, reader.connections, topics)
        except BaseException:
            _close_quietly(buffer)
            raise
        if refs is None:
            _close_quietly(buffer)
            return None
        return cls([buffer], {topic: (receive, np.zeros_like(pos), pos, length)
                              for topic, (receive, pos, length) in refs.items()})


def _close_quietly(buffer: mmap.mmap) -> None:
    try:
        buffer.close()
    except BufferError:
        pass  # a message still refers to the mapping; it is unmapped when the last one is gone


def _close_all(buffers: list[mmap.mmap]) -> None:
    for buffer in buffers:
        _close_quietly(buffer)


def _field(buffer: mmap.mmap, fields: dict[bytes, tuple[int, int]], name: bytes) -> bytes | None:
    if name not in fields:
        return None
    pos, length = fields[name]
    return buffer[pos:pos + length]


def _ros1_index(buffer: mmap.mmap, bag, connections: list, topics: set[str],
                ) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] | None:
    """Per topic (receive ns, data position, data length) of its messages; None unless every chunk is
    uncompressed and inside the file."""
    chunk_pos, chunk_data, chunk_end = [], [], []
    for pos in sorted(bag.chunks):
        fields, data_pos, data_len = _record_fields(buffer, pos)
        if _field(buffer, fields, b"op") != bytes([_OP_CHUNK]) or _field(buffer, fields, b"compression") != b"none":
            return None
        chunk_pos.append(pos)
        chunk_data.append(data_pos)
        chunk_end.append(data_pos + data_len)
    if chunk_end and max(chunk_end) > len(buffer):
        return None
    chunks = (np.array(chunk_pos, np.int64), np.array(chunk_data, np.int64), np.array(chunk_end, np.int64))
    data = np.frombuffer(buffer, np.uint8)
    refs = {}
    for topic in topics:
        found = _ros1_refs(buffer, data, chunks, [c for c in connections if c.topic == topic], bag.indexes)
        if found is None:
            return None
        refs[topic] = found
    return refs


def _ros1_refs(buffer: mmap.mmap, data: np.ndarray, chunks: tuple[np.ndarray, np.ndarray, np.ndarray],
               connections: list, indexes: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(receive ns, data position, data length) of every message of these connections, in bag order;
    None unless every record is a message record of its connection at its index time."""
    entries = [(e.time, e.chunk_pos, e.offset, c.id) for c in connections for e in indexes[c.id]]
    if not entries:
        empty = np.zeros(0, np.int64)
        return empty, empty, empty
    table = np.array(entries, np.int64)
    table = table[np.lexsort((table[:, 2], table[:, 1], table[:, 0]))]  # rosbags' merge order
    receive, chunk_at, offset, conn = table.T
    chunk_pos, chunk_data, chunk_end = chunks
    which = np.searchsorted(chunk_pos, chunk_at)
    if (which >= len(chunk_pos)).any() or (chunk_pos[np.minimum(which, len(chunk_pos) - 1)] != chunk_at).any():
        return None
    record = chunk_data[which] + offset
    positions, lengths = np.empty_like(record), np.empty_like(record)
    # The header layout of the first record; every other one must have the same field names in the
    # same order, with only the connection and time values differing.
    fields, _, _ = _record_fields(buffer, int(record[0]))
    layout = {name: fields.get(name) for name in (b"op", b"conn", b"time")}
    if None in layout.values() or [v[1] for v in layout.values()] != [1, 4, 8]:
        return None
    header_len = _U32.unpack_from(buffer, int(record[0]))[0]
    first = int(record[0]) + 4
    template = data[first:first + header_len]
    op_at, conn_at, time_at = (layout[name][0] - first for name in (b"op", b"conn", b"time"))
    fixed = np.ones(header_len, bool)  # the header bytes every record shares: all but conn and time
    fixed[conn_at:conn_at + 4] = fixed[time_at:time_at + 8] = False
    for start in range(0, len(record), BLOCK):
        block = slice(start, start + BLOCK)
        rec = record[block]
        if (rec + 8 + header_len > chunk_end[which[block]]).any() or (_u32_at(data, rec) != header_len).any():
            return None
        headers = _gather(data, rec + 4, header_len)
        sec = headers[:, time_at:time_at + 4].copy().view("<u4").ravel().astype(np.int64)
        nsec = headers[:, time_at + 4:time_at + 8].copy().view("<u4").ravel().astype(np.int64)
        if not ((headers[:, fixed] == template[fixed]).all() and (headers[:, op_at] == _OP_MSG_DATA).all()
                and (headers[:, conn_at:conn_at + 4].copy().view("<u4").ravel() == conn[block]).all()
                and (sec * NS_PER_S + nsec == receive[block]).all()):
            return None
        positions[block] = rec + 8 + header_len
        lengths[block] = _u32_at(data, rec + 4 + header_len)
        if (positions[block] + lengths[block] > chunk_end[which[block]]).any():
            return None
    return receive, positions, lengths


def ros2_storage(path: Path) -> tuple[str, list[Path]] | None:
    """("sqlite3" or "mcap", the storage files) of a ROS 2 bag (a folder, or one .db3 or .mcap file given
    alone); None for other storages and for compressed bags (`ros2 bag record --compression-mode`)."""
    if path.is_file():
        kind = {".db3": "sqlite3", ".mcap": "mcap"}.get(path.suffix)
        return None if kind is None else (kind, [path])
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml: the topics' QoS make the file long
    info = yaml.load((path / "metadata.yaml").read_text(), Loader=loader)["rosbag2_bagfile_information"]
    kind = info.get("storage_identifier")
    if kind not in ("sqlite3", "mcap") or (info.get("compression_mode") or "none").lower() != "none":
        return None
    return kind, [path / Path(name).name for name in info["relative_file_paths"]]


# MCAP: the record layout is `vfdata.mcap_io.records`' (one definition, checked against
# `mcap.records`). Only uncompressed chunks are read here, whose records follow a head of fixed size.
_MCAP_CHUNK_FIXED = chunk_head_size("")
_MCAP_MESSAGE_FIXED = MESSAGE_FIELDS  # a message record's fields before its data


class _McapBag(_MappedBag):
    """A ROS 2 bag in MCAP storage (rosbag2's default from Iron on) whose chunks holding the topics
    asked for are uncompressed (rosbag2's default). The summary's chunk and message indexes locate
    every message; the message records are checked in bulk against them (op, length, channel, log
    time) before anything is used."""

    reading = "random access: MCAP chunks, memory-mapped"

    @classmethod
    def open(cls, files: list[Path], topics: set[str]) -> _McapBag | None:
        buffers: list[mmap.mmap] = []
        parts: dict[str, list[np.ndarray]] = {topic: [] for topic in topics}
        try:
            for index, file in enumerate(files):
                buffers.append(_map(file))
                found = _mcap_refs(file, buffers[-1], topics)
                if found is None:
                    _close_all(buffers)
                    return None
                for topic, table in found.items():
                    parts[topic].append(np.column_stack([table[:, 0], np.full(len(table), index), table[:, 1:]]))
        except BaseException:
            _close_all(buffers)
            raise
        return cls(buffers, in_bag_order(parts, 4))


def _check_chunk_crc(file: Path, buffer: mmap.mmap, chunk_at: int, records: int, records_end: int) -> None:
    """An InputError naming the bag when a chunk's records fail the CRC its chunk record holds (0: none
    written). ISA-L's CRC-32 runs at several GB/s: the whole bag's worth is a small part of a conversion."""
    crc = CHUNK_FIELDS.unpack_from(buffer, chunk_at + RECORD_HEAD.size)[3]
    if crc and crc32(memoryview(buffer)[records:records_end]) != crc:
        raise InputError(file, f"the chunk at byte {chunk_at} fails its CRC: the bag is damaged (its messages "
                               "would be converted altered); convert an intact copy")


def _mcap_refs(file: Path, buffer: mmap.mmap, topics: set[str]) -> dict[str, np.ndarray] | None:
    """Per topic an (N, 3) array of (log time ns, data position, data length) for one MCAP file; None
    without a summary and its statistics, with a compressed chunk holding a topic asked for, when a
    record does not match its index, or when the indexes miss messages the statistics count. Only the
    loop over the summary's chunk indexes is Python; the index and message records are read and
    checked with numpy (a chunk a message: an hour of stereo is 100k chunks)."""
    with open(file, "rb") as stream:
        summary = make_reader(stream).get_summary()
    # Without chunk indexes (unchunked) or statistics (nothing to check the message indexes against:
    # a writer may leave them out) only a full read finds every message.
    if summary is None or not summary.chunk_indexes or summary.statistics is None:
        return None
    channels = {cid: channel.topic for cid, channel in summary.channels.items() if channel.topic in topics}
    indexes = []  # (message index record position, channel id, chunk records start, chunk records end)
    for chunk in summary.chunk_indexes:
        wanted = [(cid, at) for cid, at in chunk.message_index_offsets.items() if cid in channels]
        if not wanted:
            continue
        if chunk.compression:
            return None
        records = chunk.chunk_start_offset + _MCAP_CHUNK_FIXED
        records_end = chunk.chunk_start_offset + chunk.chunk_length
        if records_end != records + chunk.uncompressed_size or records_end > len(buffer):
            return None
        _check_chunk_crc(file, buffer, chunk.chunk_start_offset, records, records_end)
        indexes.extend((at, cid, records, records_end) for cid, at in wanted)
    expected = summary.statistics.channel_message_counts
    refs = {topic: np.zeros((0, 3), np.int64) for topic in topics}
    if not indexes:
        return refs if not any(expected.get(cid, 0) for cid in channels) else None
    index_at, index_channel, records, records_end = np.array(indexes, np.int64).T
    data = np.frombuffer(buffer, np.uint8)
    if records_end.max() > len(data) or (index_at + MESSAGE_INDEX_HEAD.size > len(data)).any():
        return None
    heads = _gather(data, index_at, MESSAGE_INDEX_HEAD.size).view(MESSAGE_INDEX_HEAD_DTYPE).ravel()
    if (heads["opcode"] != Opcode.MESSAGE_INDEX).any() or (heads["channel"] != index_channel).any():
        return None
    counts = heads["nbytes"].astype(np.int64) // INDEX_PAIR
    # Entry k of index record r: its (log time, offset) pair is 16 bytes at its pairs' start + 16 k.
    owner = np.repeat(np.arange(len(index_at)), counts)
    entry = np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)
    pair_at = index_at[owner] + MESSAGE_INDEX_HEAD.size + INDEX_PAIR * entry
    if len(pair_at) and pair_at.max() + INDEX_PAIR > len(data):
        return None
    tables = []
    for start in range(0, len(owner), INDEX_BLOCK):  # bounded temporaries for a long 1 kHz series
        block = slice(start, start + INDEX_BLOCK)
        own, at = owner[block], pair_at[block]
        log_time = _gather(data, at, 8).view("<u8").ravel().astype(np.int64)
        record = records[own] + _gather(data, at + 8, 8).view("<u8").ravel().astype(np.int64)
        end, channel = records_end[own], index_channel[own]
        if (record + MESSAGE_HEAD.size > end).any():
            return None
        message = _gather(data, record, MESSAGE_HEAD.size).view(MESSAGE_HEAD_DTYPE).ravel()
        length = message["length"].astype(np.int64)
        if not ((message["opcode"] == Opcode.MESSAGE).all() and (record + RECORD_HEAD.size + length <= end).all()
                and (length >= MESSAGE_FIELDS).all() and (message["channel"] == channel).all()
                and (message["log_time"].astype(np.int64) == log_time).all()):
            return None
        tables.append(np.column_stack([log_time, record + MESSAGE_HEAD.size, length - MESSAGE_FIELDS, channel]))
    del data
    table = np.concatenate(tables)
    found, count = np.unique(table[:, 3], return_counts=True)
    if dict(zip(found.tolist(), count.tolist(), strict=True)) != {cid: n for cid in channels
                                                                  if (n := expected.get(cid, 0))}:
        return None
    for topic in topics:
        mine = np.isin(table[:, 3], [cid for cid, name in channels.items() if name == topic])
        refs[topic] = table[mine, :3]
    return refs
