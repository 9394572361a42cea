"""The index of an MCAP file: its channels, its chunks and where every message is (built by
`index_builder`, read through by `McapFile`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

COMPRESSIONS = ("", "zstd", "lz4")


@dataclass
class Channel:
    id: int
    topic: str
    msgtype: str  # the schema's name ('' for a channel without a schema)
    message_encoding: str
    schema_encoding: str
    schema: bytes


@dataclass
class Chunk:
    record_offset: int  # file offset of the chunk record
    data_offset: int  # file offset of its (compressed) records
    compressed_size: int
    uncompressed_size: int
    uncompressed_crc: int | None  # None until the chunk record is read (the chunk index lacks it)
    compression: str
    start_ns: int
    end_ns: int
    record_length: int  # the whole record, head included
    channels: set[int] = field(default_factory=set)  # the channels with messages in it
    # '' not read yet; 'ok'; 'bad-crc' (decompresses, fails its CRC); 'unreadable'; 'bad-index' (its
    # message index disagrees with its records in log times or counts)
    status: str = ""


@dataclass
class MessageLocations:
    """Where one channel's messages are, sorted by log time (file order breaks ties). `chunk` is -1
    for a message outside any chunk, whose `offset` is then its record's offset in the file, else the
    offset of its record in its chunk's records."""

    log_time_ns: np.ndarray
    chunk: np.ndarray
    offset: np.ndarray
    _groups: dict[int, np.ndarray] | None = field(default=None, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.log_time_ns)

    def in_chunk(self, chunk_id: int) -> np.ndarray:
        """Positions (ascending) of the messages in chunk `chunk_id`."""
        return self.groups().get(chunk_id, np.zeros(0, np.int64))

    def groups(self) -> dict[int, np.ndarray]:
        """Chunk id -> positions (ascending) of its messages, in chunk order. Grouped once, in O(N)
        when the chunks follow one another in time (the usual case), else with one stable sort."""
        if self._groups is None:
            chunk = self.chunk
            order = (np.arange(len(chunk)) if (np.diff(chunk) >= 0).all()
                     else np.argsort(chunk, kind="stable"))
            ids, starts = np.unique(chunk[order], return_index=True)
            ends = np.append(starts[1:], len(order))
            self._groups = {int(c): order[s:e] for c, s, e in zip(ids, starts, ends, strict=True)}
        return self._groups


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
    data_end_offset: int | None = None  # the DataEnd record, where the data-section CRC stops
    data_section_crc: int = 0


def merge_locations(times, chunks, offsets) -> MessageLocations:
    times = np.asarray(times, np.int64)
    chunks = np.asarray(chunks, np.int32)
    offsets = np.asarray(offsets, np.int64)
    # Chunks may overlap in time; file order breaks ties so equal stamps keep their write order. Found
    # in file order, a series written in time order is sorted already (a 1 kHz hour: 0.4 s of lexsort).
    if not (np.diff(times) > 0).all():
        order = np.lexsort((offsets, chunks, times))
        times, chunks, offsets = times[order], chunks[order], offsets[order]
    return MessageLocations(times, chunks, offsets)
