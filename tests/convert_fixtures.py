"""Helpers of the conversion tests: the order of the messages in each chunk of an MCAP file, as a
streaming reader (and `mcap doctor`'s NON_MONOTONIC_LOG_TIME check) sees it."""

from __future__ import annotations

from pathlib import Path

from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk


def chunk_messages(path: Path) -> list[list[tuple[int, int]]]:
    """For each chunk of the file, in file order: its messages' (channel id, log time) in record order."""
    chunks = []
    with open(path, "rb") as stream:
        for record in StreamReader(stream, emit_chunks=True).records:
            if isinstance(record, Chunk):
                chunks.append([(r.channel_id, r.log_time) for r in breakup_chunk(record) if isinstance(r, Message)])
    return chunks


def out_of_order_chunks(path: Path) -> list[int]:
    """Indices of the chunks whose messages do not come in non-decreasing log time."""
    return [i for i, messages in enumerate(chunk_messages(path))
            if any(b[1] < a[1] for a, b in zip(messages, messages[1:], strict=False))]
