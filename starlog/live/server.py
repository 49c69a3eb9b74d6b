"""The Foxglove WebSocket server of ``starlog live`` (``foxglove-sdk``).

Every channel a live layer writes, and every channel of the source, is advertised with the schema
its log holds (a protobuf FileDescriptorSet, a JSON Schema) and publishes the bytes written to the
log, as they are written. ``/live/status`` (JSON) says once a second how far behind the source the
processing is; falling behind is also sent as a Foxglove status message (shown by the app).

The Foxglove app connects to ``ws://HOST:PORT`` (*Open connection* → *Foxglove WebSocket*). A client
that reads slower than the messages come loses the oldest of them (the SDK's per-client backlog):
the log on disk, not the WebSocket, is the record.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

from starlog.codecs.schemas import MessageType

__all__ = ["STATUS_SCHEMA", "STATUS_TOPIC", "LiveServer"]

STATUS_TOPIC = "/live/status"

#: The JSON Schema of ``/live/status``.
STATUS_SCHEMA: dict[str, Any] = {
    "title": "starlog.LiveStatus",
    "description": "How far the processing of starlog live is behind its source, once a second.",
    "type": "object",
    "properties": {
        "frames_seen": {"type": "integer", "description": "Frames of the source seen so far."},
        "frames_done": {"type": "integer", "description": "Frames processed (published and written)."},
        "frames_waiting": {"type": "integer", "description": "Frames seen and not yet processed."},
        "frames_skipped": {"type": "integer", "description": "Frames left out, each recorded with why."},
        "latency_ms_median": {"type": "number", "description": "From a frame's arrival to its last message, "
                                                               "median over the last second (ms)."},
        "latency_ms_max": {"type": "number", "description": "The same, largest (ms)."},
        "behind": {"type": "boolean", "description": "Whether frames are waiting longer than a second."},
        "state": {"type": "string", "description": "learning (the first frames), live, finishing."},
    },
}


class LiveServer:
    """A Foxglove WebSocket server on ``host:port`` (``port`` 0: a free one, see :attr:`port`), with a context of
    its own (nothing else a program logs reaches it)."""

    def __init__(self, *, host: str = "127.0.0.1", port: int = 8765, name: str = "starlog live") -> None:
        import foxglove

        self._foxglove = foxglove
        self.context = foxglove.Context()
        self.server = foxglove.start_server(name=name, host=host, port=port, context=self.context)
        self.host = host
        self.port = int(self.server.port)
        self._channels: dict[str, Any] = {}
        self._status = self.outlet(STATUS_TOPIC, MessageType("starlog.LiveStatus", "jsonschema",
                                                             json.dumps(STATUS_SCHEMA).encode(), "json"))

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def outlet(self, topic: str, message_type: MessageType) -> Callable[[bytes, int], None]:
        """A callable publishing ``(data, log_time)`` on ``topic`` (advertised with ``message_type``'s schema)."""
        channel = self._channels.get(topic)
        if channel is None:
            fox = self._foxglove
            schema = (fox.Schema(name=message_type.schema_name, encoding=message_type.schema_encoding,
                                 data=bytes(message_type.schema_data)) if message_type.schema_encoding else None)
            channel = self._channels[topic] = fox.Channel(topic, schema=schema,
                                                          message_encoding=message_type.message_encoding,
                                                          context=self.context)

        def publish(data: bytes, log_time: int) -> None:
            channel.log(data, log_time=log_time)

        return publish

    def status(self, record: dict[str, Any], log_time: int, warning: str | None) -> None:
        """Publish ``record`` on ``/live/status``; ``warning``, when given, as the app's status message too."""
        self._status(json.dumps(record).encode(), log_time)
        fox = self._foxglove
        if warning:
            self.server.publish_status(warning, fox.StatusLevel.Warning, id="starlog-behind")
        else:
            self.server.remove_status(["starlog-behind"])

    def stop(self) -> None:
        for channel in self._channels.values():
            channel.close()
        self.server.stop()
