"""Random access to the raw messages of a bag: the interface the storages that allow it share
(`bag_index`: ROS 1 and MCAP files, memory-mapped; `bag_sqlite`: sqlite3 rows), and the helpers they
have in common."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

HEAD_BYTES = 256  # enough for the fields before the pixels unless frame_id or encoding are very long
BLOCK = 4096  # messages per block of a series, and per bulk check of ROS 1 record headers
INDEX_BLOCK = 65536  # rows of the sqlite index read at a time


class IndexedBag:
    """The messages of the topics asked for, in bag order (by receive time, as `rosbags` yields them),
    each reachable by its position in its topic."""

    reading = ""  # how the messages are reached, for `vfdata inspect-bag`

    def receive_ns(self, topic: str) -> np.ndarray:
        """Bag receive times (ns) of the messages of `topic`, in bag order."""
        raise NotImplementedError

    def message(self, topic: str, i: int) -> bytes | memoryview:
        """The serialised message i of `topic`."""
        raise NotImplementedError

    def head(self, topic: str, i: int) -> bytes | memoryview:
        """The first bytes (at most HEAD_BYTES) of message i of `topic`."""
        raise NotImplementedError

    def payload_blocks(self, topic: str) -> Iterator[tuple[np.ndarray, np.ndarray | list[bytes]]]:
        """Every message of `topic` in blocks of at most BLOCK: (receive times (n,) ns, payloads), the
        payloads as an (n, L) uint8 array when they all have length L, else a list of bytes."""
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


def as_table(payloads: list[bytes]) -> np.ndarray | list[bytes]:
    length = len(payloads[0])
    if any(len(p) != length for p in payloads):
        return payloads
    return np.frombuffer(b"".join(payloads), np.uint8).reshape(len(payloads), length)


def in_bag_order(parts: dict[str, list[np.ndarray]], columns: int) -> dict[str, tuple[np.ndarray, ...]]:
    """Per topic, its per-file tables of (receive ns, file index, position, ...) joined and sorted by
    receive time, then file, then position (rosbags' merge order), as contiguous columns (a strided
    column would be copied by every `searchsorted`)."""
    refs = {}
    for topic, found in parts.items():
        table = np.concatenate(found) if found else np.zeros((0, columns), np.int64)
        table = table[np.lexsort(table.T[::-1])]  # the last key sorts first
        refs[topic] = tuple(np.ascontiguousarray(column) for column in table.T)
    return refs
