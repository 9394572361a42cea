"""Writing MCAP files of the VisionForce layout (recordings and derived files).

`McapWriter` is the atomic, typed front of `mcap.writer.Writer`: profile ros2, CDR messages,
ros2msg schemas, zstd chunks, chunk and data CRCs, summary with all indexes. The file appears under
its name only when `close()` succeeds; on any error nothing is left behind."""

from __future__ import annotations

import contextlib
from pathlib import Path
from types import TracebackType

from mcap.writer import CompressionType, Writer

from vfdata import __version__
from vfdata.atomic import atomic_output
from vfdata.recording import layout
from vfdata.recording.schemas import schema_text

# Large enough that a stereo JPEG pair and a few hundred force samples share a chunk; small enough
# that reading one frame decompresses little.
CHUNK_SIZE = 4 * 1024 * 1024


class McapWriter:
    """Usage: `with McapWriter(path) as w: w.write(topic, msg); w.add_metadata(name, dict)`."""

    def __init__(self, path: str | Path, overwrite: bool = False, chunk_size: int = CHUNK_SIZE,
                 separate_topics: tuple[str, ...] = (), separate_batch: int = 2048):
        """`separate_topics`: small high-rate topics (force, pose) whose messages are gathered into
        chunks of their own, `separate_batch` messages at a time, instead of sharing chunks with
        images. Overlapping chunks are standard MCAP; it lets a reader get a 1 kHz force series
        without decompressing the video."""
        self.path = Path(path)
        self._separate = set(separate_topics)
        self._separate_batch = separate_batch
        self._pending: list[tuple[int, int, int, bytes]] = []
        self._atomic = atomic_output(self.path, overwrite)
        self._tmp = self._atomic.__enter__()
        self._stream = open(self._tmp, "wb")  # noqa: SIM115 - closed in close()/abort()
        self._writer = Writer(
            self._stream, chunk_size=chunk_size, compression=CompressionType.ZSTD,
            enable_crcs=True, enable_data_crcs=True,
        )
        self._writer.start(profile=layout.PROFILE, library=f"visionforce {__version__}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self._sequence: dict[str, int] = {}
        self._closed = False

    def channel(self, topic: str, msgtype: str) -> int:
        """The channel id of `topic`, registering it (and its schema) on first use."""
        if topic in self._channels:
            channel_id, known = self._channels[topic]
            if known != msgtype:
                raise ValueError(f"topic {topic} already has type {known}, not {msgtype}")
            return channel_id
        if msgtype not in self._schemas:
            self._schemas[msgtype] = self._writer.register_schema(
                name=msgtype, encoding=layout.SCHEMA_ENCODING, data=schema_text(msgtype).encode()
            )
        channel_id = self._writer.register_channel(
            topic=topic, message_encoding=layout.MESSAGE_ENCODING, schema_id=self._schemas[msgtype]
        )
        self._channels[topic] = (channel_id, msgtype)
        self._sequence[topic] = 0
        return channel_id

    def write(self, topic: str, message, log_time_ns: int | None = None) -> None:
        """Write a typed message (vfdata.recording.messages); log time = its stamp unless given."""
        stamp = message.stamp_ns if log_time_ns is None else log_time_ns
        self.write_payload(topic, message.msgtype, stamp, message.encode())

    def write_payload(self, topic: str, msgtype: str, log_time_ns: int, payload: bytes) -> None:
        channel_id = self.channel(topic, msgtype)
        sequence = self._sequence[topic]
        self._sequence[topic] = sequence + 1
        if topic in self._separate:
            self._pending.append((channel_id, int(log_time_ns), sequence, payload))
            if len(self._pending) >= self._separate_batch:
                self._flush_pending()
            return
        self._writer.add_message(
            channel_id=channel_id, log_time=int(log_time_ns), publish_time=int(log_time_ns),
            data=payload, sequence=sequence,
        )

    def _flush_pending(self) -> None:
        if not self._pending:
            return
        self._writer.flush()  # close the chunk in progress so the batch gets a chunk of its own
        for channel_id, log_time, sequence, payload in self._pending:
            self._writer.add_message(
                channel_id=channel_id, log_time=log_time, publish_time=log_time, data=payload, sequence=sequence
            )
        self._writer.flush()
        self._pending.clear()

    def add_metadata(self, name: str, record: dict[str, str]) -> None:
        self._writer.add_metadata(name, {str(k): str(v) for k, v in record.items()})

    def close(self) -> None:
        """Finish the file and move it into place."""
        if self._closed:
            return
        self._closed = True
        try:
            self._flush_pending()
            self._writer.finish()
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
