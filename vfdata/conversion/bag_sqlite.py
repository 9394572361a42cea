"""Random access to a ROS 2 bag in sqlite3 storage: a message is a row, read as a blob, its first bytes
alone when that is enough (see `bag_index`)."""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from vfdata.conversion.bag_access import BLOCK, HEAD_BYTES, INDEX_BLOCK, IndexedBag, as_table, in_bag_order


class SqliteBag(IndexedBag):
    """A ROS 2 bag in sqlite3 storage (one or more .db3 files, not compressed), read through our own
    read-only connections: messages are rows of `messages(id, topic_id, timestamp, data)`.

    Each thread reads through connections of its own: sqlite serialises the calls on one connection,
    so two encoding threads copying images out of one connection took turns."""

    reading = "random access: sqlite3 rows, each image copied out of its blob"

    def __init__(self, files: list[Path], connections: list[sqlite3.Connection],
                 refs: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]):
        self._files = files
        self._refs = refs  # topic -> (receive ns, file index, row id), in bag order
        self._local = threading.local()
        self._local.db = connections
        self._opened = list(connections)  # every thread's, to close
        self._lock = threading.Lock()
        self._closed = False

    @classmethod
    def open(cls, files: list[Path], topics: set[str]) -> SqliteBag:
        connections = []
        try:
            for file in files:
                connections.append(_connect(file))
            # One query per file for all the topics (a query per topic scanned the messages once each).
            parts: dict[str, list[np.ndarray]] = {topic: [] for topic in topics}
            for index, db in enumerate(connections):
                ids = {topic_id: name for topic_id, name in db.execute("SELECT id, name FROM topics")
                       if name in topics}
                if not ids:
                    continue
                cursor = db.execute(f"SELECT timestamp, id, topic_id FROM messages WHERE topic_id IN "
                                    f"({','.join('?' * len(ids))}) ORDER BY timestamp, id", list(ids))
                # Into an array block by block: a list of row tuples costs ~140 bytes a message, i.e.
                # gigabytes for an hour of 1 kHz force and pose; the array costs 24.
                blocks = []
                while rows := cursor.fetchmany(INDEX_BLOCK):
                    blocks.append(np.array(rows, np.int64))
                table = np.concatenate(blocks) if blocks else np.zeros((0, 3), np.int64)
                for topic_id, name in ids.items():
                    mine = table[table[:, 2] == topic_id]
                    parts[name].append(np.column_stack([mine[:, 0], np.full(len(mine), index), mine[:, 1]]))
            refs = in_bag_order(parts, 3)
        except BaseException:
            for db in connections:
                db.close()
            raise
        return cls(files, connections, refs)

    def receive_ns(self, topic: str) -> np.ndarray:
        return self._refs[topic][0]

    def _connections(self) -> list[sqlite3.Connection]:
        mine = getattr(self._local, "db", None)
        if mine is None:
            mine = []
            with self._lock:
                if self._closed:
                    raise sqlite3.ProgrammingError("the bag is closed")
                try:
                    for file in self._files:
                        mine.append(_connect(file))
                finally:
                    self._opened.extend(mine)  # closed with the others, also after a failed connect
            self._local.db = mine
        return mine

    def _blob(self, topic: str, i: int):
        _, file, row = self._refs[topic]
        return self._connections()[int(file[i])].blobopen("messages", "data", int(row[i]), readonly=True)

    def message(self, topic: str, i: int) -> bytes:
        with self._blob(topic, i) as blob:
            return blob.read()

    def head(self, topic: str, i: int) -> bytes:
        with self._blob(topic, i) as blob:
            return blob.read(HEAD_BYTES)

    def payload_blocks(self, topic: str) -> Iterator[tuple[np.ndarray, np.ndarray | list[bytes]]]:
        # File by file: the files of a split bag follow one another in time.
        for db in self._connections():
            cursor = db.execute("SELECT messages.timestamp, messages.data FROM messages JOIN topics ON "
                                "messages.topic_id = topics.id WHERE topics.name = ? "
                                "ORDER BY messages.timestamp, messages.id", (topic,))
            while rows := cursor.fetchmany(BLOCK):
                yield np.array([r[0] for r in rows], np.int64), as_table([r[1] for r in rows])

    def close(self) -> None:
        with self._lock:
            self._closed = True
            for db in self._opened:
                db.close()


def _connect(file: Path) -> sqlite3.Connection:
    db = sqlite3.connect(file.resolve().as_uri() + "?mode=ro&immutable=1", uri=True, check_same_thread=False)
    # Pages through a memory map: an image spans hundreds of pages, one read() each otherwise.
    db.execute("PRAGMA mmap_size = 1099511627776")
    return db
