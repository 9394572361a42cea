"""The MCAP record layout (mcap.dev/spec) in one place, on the `mcap` package.

Records are read and written through `mcap.records` (each record's read and write side by side),
`mcap.opcode` and `mcap.data_stream`. What this module adds is only what the fast paths need to
address bytes directly, and each piece is checked against the library's own record builders when the
module is imported, so that it cannot drift from them:
- the record head (opcode, length) that frames every record;
- a message record's fixed fields before its data: zero-copy payload views, the numpy gather of a
  force series, and message heads packed by the writer;
- a chunk record's fixed fields before its records: a chunk's records read without copying the chunk
  through `Chunk.read`, and written piece by piece;
- a message index record's fixed fields before its (log time, offset) pairs, read and written with
  numpy (`MessageIndex.read` and `.write` loop in Python over the pairs).

Every length read here is bounded by the bytes it claims to describe, so a damaged length gives a
`FormatError` naming the file, never a huge allocation."""

from __future__ import annotations

import io
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Chunk, Footer, McapRecord, Message, MessageIndex
from mcap.writer import MCAP0_MAGIC

from vfdata.errors import FormatError

# The spec's CRC-32 (zlib's polynomial and values). ISA-L's runs at ~13 GB/s here, zlib 1.2.13's at
# 1.9 GB/s: verifying a 4 MB image chunk on its first read costs 0.3 ms instead of 2.2 ms.
try:
    from isal.isal_zlib import crc32  # noqa: F401 - the CRC of every module here
except ImportError:  # a platform without an isal wheel
    from zlib import crc32  # noqa: F401

MAGIC = MCAP0_MAGIC
RECORD_HEAD = struct.Struct("<BQ")  # opcode, length of the record's body
# A message record's head: the record head, then channel id, sequence, log time, publish time.
MESSAGE_HEAD = struct.Struct("<BQHIQQ")
MESSAGE_FIELDS = MESSAGE_HEAD.size - RECORD_HEAD.size  # the body's bytes before the data
# A chunk record's body before the compression string: start, end, uncompressed size, its CRC.
CHUNK_FIELDS = struct.Struct("<QQQI")
# A message index record's head: the record head, channel id, byte length of the (u64, u64) pairs.
MESSAGE_INDEX_HEAD = struct.Struct("<BQHI")
MESSAGE_INDEX_HEAD_DTYPE = np.dtype([("opcode", "u1"), ("length", "<u8"), ("channel", "<u2"), ("nbytes", "<u4")])
INDEX_PAIR = 16
# MESSAGE_HEAD as a numpy record, for many message heads at once (gathered, or built as a table).
MESSAGE_HEAD_DTYPE = np.dtype([("opcode", "u1"), ("length", "<u8"), ("channel", "<u2"), ("sequence", "<u4"),
                               ("log_time", "<u8"), ("publish_time", "<u8")])


def record_bytes(record: McapRecord) -> bytes:
    """A record serialised by the library's own builder."""
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


FOOTER_SIZE = len(record_bytes(Footer(0, 0, 0)))
DATA_END_SIZE = RECORD_HEAD.size + 4


def chunk_head_size(compression: str) -> int:
    """Bytes of a chunk record before its records (the record head included)."""
    return RECORD_HEAD.size + CHUNK_FIELDS.size + 4 + len(compression.encode()) + 8


def _self_check() -> None:
    """The hand-addressed layouts above against `mcap.records`' builders."""
    message = record_bytes(Message(channel_id=0x0102, log_time=3, data=b"xy", publish_time=4, sequence=5))
    chunk = record_bytes(Chunk(compression="zstd", data=b"abc", message_end_time=2, message_start_time=1,
                               uncompressed_crc=7, uncompressed_size=9))
    index = record_bytes(MessageIndex(3, [(11, 12)]))
    ok = (MESSAGE_HEAD.unpack_from(message) == (Opcode.MESSAGE, len(message) - 9, 0x0102, 5, 3, 4)
          and message[MESSAGE_HEAD.size:] == b"xy"
          and CHUNK_FIELDS.unpack_from(chunk, RECORD_HEAD.size) == (1, 2, 9, 7)
          and chunk[chunk_head_size("zstd"):] == b"abc"
          and struct.unpack_from("<Q", chunk, chunk_head_size("zstd") - 8)[0] == 3
          and MESSAGE_HEAD_DTYPE.itemsize == MESSAGE_HEAD.size
          and np.frombuffer(message, MESSAGE_HEAD_DTYPE, 1)[0].tolist() == (Opcode.MESSAGE, len(message) - 9,
                                                                           0x0102, 5, 3, 4)
          and np.frombuffer(index, MESSAGE_INDEX_HEAD_DTYPE, 1)[0].tolist() == (Opcode.MESSAGE_INDEX, len(index) - 9,
                                                                                 3, INDEX_PAIR)
          and MESSAGE_INDEX_HEAD.unpack_from(index) == (Opcode.MESSAGE_INDEX, len(index) - 9, 3, INDEX_PAIR)
          and struct.unpack_from("<QQ", index, MESSAGE_INDEX_HEAD.size) == (11, 12))
    if not ok:
        raise ImportError("vfdata.mcap_io.records disagrees with the installed mcap package's records")


_self_check()

_PARSE_ERRORS = (struct.error, McapError, UnicodeDecodeError, ValueError, KeyError)


def parse(cls: type[McapRecord], body: bytes | memoryview, path: Path, where: str):
    """One record's body parsed by the library (`cls.read`); bounded by the body, so a damaged field
    gives a FormatError instead of a read past it. Extra bytes after the fields (padding) are ignored."""
    try:
        return cls.read(ReadDataStream(io.BytesIO(body)))
    except _PARSE_ERRORS:
        raise FormatError(path, f"{where}: malformed {cls.__name__} record") from None


def iter_records(data: bytes | memoryview, path: Path, where: str, start: int = 0,
                 end: int | None = None) -> Iterator[tuple[int, int, memoryview]]:
    """(offset, opcode, body) of the records packed in data[start:end]. A record that runs past the
    end raises FormatError."""
    view = memoryview(data)
    end = len(view) if end is None else end
    pos = start
    while pos < end:
        if pos + RECORD_HEAD.size > end:
            raise FormatError(path, f"{where}: record head at byte {pos} is cut off")
        opcode, length = RECORD_HEAD.unpack_from(view, pos)
        body_end = pos + RECORD_HEAD.size + length
        if body_end > end:
            raise FormatError(path, f"{where}: record (opcode 0x{opcode:02x}) at byte {pos} runs past its end")
        yield pos, opcode, view[pos + RECORD_HEAD.size:body_end]
        pos = body_end
