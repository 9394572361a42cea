"""Serving the live pipeline's output over the Foxglove WebSocket protocol (the `foxglove-sdk`
package, the optional extra `live`), with the topics and ROS 2 schemas of the files
(`vfdata.recording.layout`): CDR payloads with `ros2msg` schemas, so Foxglove's app decodes them as it
decodes our MCAPs, and the layout in docs/ shows them.

    server = FoxgloveServer(port=8765, record="live.mcap")
    server.publish(layout.FORCE_ESTIMATE, WrenchStamped(...))
    server.close({"stage": "live"})     # the recording appears under its name only now

A message is encoded only when someone takes it (a subscribed client or the recording): `wants(topic)`.
With `record`, everything served is also written to an MCAP of our layout (atomically: nothing under
that name if the session fails)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

from vfdata.errors import OutputError, VisionForceError
from vfdata.recording import layout
from vfdata.recording.schemas import schema_text
from vfdata.recording.writer import McapWriter

# The server sends from its own queues; stopping it drops what is still queued. A subscribed client
# gets this long to receive the last messages (the flush's forces) before the connection closes.
DRAIN_S = 0.5

def import_foxglove():
    try:  # the optional extra 'live', imported when a server starts
        import foxglove
    except ImportError:
        raise VisionForceError("the live view needs the foxglove-sdk package: pip install 'visionforce[live]'"
                               ) from None
    return foxglove


class _Subscriptions:
    """The server's listener: which topics have at least one subscriber (for `wait_for_subscriber`)."""

    def __init__(self):
        self.topics: dict[str, int] = {}
        self.changed = threading.Condition()

    def on_subscribe(self, client, channel) -> None:
        with self.changed:
            self.topics[channel.topic] = self.topics.get(channel.topic, 0) + 1
            self.changed.notify_all()

    def on_unsubscribe(self, client, channel) -> None:
        with self.changed:
            self.topics[channel.topic] = max(0, self.topics.get(channel.topic, 0) - 1)
            self.changed.notify_all()


class FoxgloveServer:
    """A Foxglove WebSocket server on `host:port` (port 0: any free port, see `.port`) advertising
    `layout.LIVE_TOPICS`; `record`: also write what is served to this MCAP."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, record: str | Path | None = None,
                 overwrite: bool = False, name: str = "visionforce"):
        foxglove = import_foxglove()
        # The recording's output is checked before the port is taken: a refused output leaves nothing open.
        self.recorder = McapWriter(record, overwrite=overwrite) if record is not None else None
        self.host = host
        self.context = foxglove.Context()
        self.subscriptions = _Subscriptions()
        try:
            self.server = foxglove.start_server(name=name, host=host, port=port, context=self.context,
                                                server_listener=self.subscriptions)
        except Exception as exc:  # the SDK raises its own error types (address in use, bad host)
            if self.recorder is not None:
                self.recorder.abort()
            raise OutputError(Path(f"{host}:{port}"), f"cannot serve the Foxglove WebSocket ({exc})") from None
        self.channels = {
            topic: foxglove.Channel(topic, message_encoding=layout.MESSAGE_ENCODING, context=self.context,
                                    schema=foxglove.Schema(name=msgtype, encoding=layout.SCHEMA_ENCODING,
                                                           data=schema_text(msgtype).encode()))
            for topic, msgtype in layout.LIVE_TOPICS.items()}
        self.published = dict.fromkeys(layout.LIVE_TOPICS, 0)
        self._closed = False

    @property
    def port(self) -> int:
        return self.server.port

    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def wants(self, topic: str) -> bool:
        """Whether a message on `topic` goes anywhere (a subscribed client, or the recording)."""
        return self.recorder is not None or self.channels[topic].has_sinks()

    def publish(self, topic: str, message, log_time_ns: int | None = None) -> None:
        """Send a typed message (`vfdata.recording.messages`) to the subscribers and the recording."""
        if not self.wants(topic):
            return
        stamp = message.stamp_ns if log_time_ns is None else int(log_time_ns)
        payload = message.encode()
        self.channels[topic].log(payload, log_time=stamp)
        if self.recorder is not None:
            self.recorder.write_payload(topic, layout.LIVE_TOPICS[topic], stamp, payload)
        self.published[topic] += 1

    def wait_for_subscriber(self, topic: str, timeout_s: float) -> bool:
        """Block until a client subscribes to `topic` (True), or `timeout_s` passes (False)."""
        with self.subscriptions.changed:
            return self.subscriptions.changed.wait_for(lambda: self.subscriptions.topics.get(topic, 0) > 0,
                                                       timeout=timeout_s)

    def close(self, metadata: dict[str, str] | None = None) -> Path | None:
        """Stop serving; publish the recording (with `metadata` as the `visionforce.derived` record)."""
        if self._closed:
            return None
        self._closed = True
        if any(self.subscriptions.topics.values()):
            time.sleep(DRAIN_S)
        for channel in self.channels.values():
            channel.close()
        self.server.stop()
        if self.recorder is None:
            return None
        self.recorder.add_metadata(layout.DERIVED_METADATA, {k: str(v) for k, v in (metadata or {}).items()})
        self.recorder.close()
        return self.recorder.path

    def abort(self) -> None:
        """Stop serving and leave no recording behind."""
        if self._closed:
            return
        self._closed = True
        self.server.stop()
        if self.recorder is not None:
            self.recorder.abort()
