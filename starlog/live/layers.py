"""The files ``starlog live`` writes as frames arrive, and how they become the layers ``run`` writes.

* :class:`PublishingWriter` — a :class:`~starlog.io.writer.LogWriter` that also publishes every
  message it writes, the same bytes under the same schema, on the Foxglove server
  (:mod:`starlog.live.server`): what Foxglove shows live is what the layer records. Its chunks are
  closed and handed to the system at least every :data:`FLUSH_SECONDS`, so a crash loses at most
  that much (``starlog recover`` rebuilds the hidden ``.partial`` file it leaves).
* :class:`PrefixLog` — the first frames of the source (and every other message and metadata record
  with them) as a complete log: the centroid stage learns its parameters from a log's first frames
  (PSF width, phase calibration, mode), and live learns them from the same frames.
* :func:`relayer` — the messages of a file written without its base, written again as a layer on it
  (the attitude, computed per frame while the stages below it were still being written).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

from mcap.records import Channel, Schema

from starlog.io.provenance import PROVENANCE_METADATA_NAME
from starlog.io.reader import LogReader
from starlog.codecs.schemas import MessageType
from starlog.io.writer import LogWriter
from starlog.replay.layer import StageOutput, extend_log, record_provenance

__all__ = ["FLUSH_SECONDS", "PrefixLog", "PublishingWriter", "close_on_base", "relayer"]

#: The longest a message waits in memory before its chunk is written and handed to the system.
FLUSH_SECONDS = 0.5


class PublishingWriter(LogWriter):
    """A log writer that publishes each message it writes on ``publish(topic, message_type)``'s channel (a
    callable ``(data, log_time)``), and flushes at least every :data:`FLUSH_SECONDS` (:meth:`tick`)."""

    def __init__(self, path: str | os.PathLike[str], *, publish: Any, **options: Any) -> None:
        super().__init__(path, **options)
        self._publish = publish
        self._outlets: dict[int, Any] = {}
        self._flushed = time.monotonic()

    def add_channel(self, topic: str, message_type: MessageType, **options: Any) -> int:
        channel_id = super().add_channel(topic, message_type, **options)
        self._outlets[channel_id] = self._publish(topic, message_type)
        return channel_id

    def write(self, channel: int | str, *, log_time: int, data: bytes, publish_time: int | None = None) -> None:
        super().write(channel, log_time=log_time, data=data, publish_time=publish_time)
        outlet = self._outlets.get(channel if isinstance(channel, int) else self.topics[channel])
        if outlet is not None:
            outlet(bytes(data), log_time)

    def tick(self, now: float) -> None:
        """Flush when the last flush is :data:`FLUSH_SECONDS` old."""
        if now - self._flushed >= FLUSH_SECONDS:
            self.flush()
            self._flushed = now


class PrefixLog:
    """The source's first messages, up to ``frames`` frames, as a complete log at ``path`` (module docstring)."""

    def __init__(self, path: Path, frames: int) -> None:
        self.path = path
        self.frames = frames
        self.seen = 0
        self._writer = LogWriter(path, force=True, validate=False)
        self._channels: dict[str, int] = {}

    @property
    def full(self) -> bool:
        return self.seen >= self.frames

    def add(self, schema: Schema | None, channel: Channel, log_time: int, data: bytes, *, frame: bool) -> None:
        """One message of the source (``frame``: of its image channel)."""
        cid = self._channels.get(channel.topic)
        if cid is None:
            message_type = MessageType(schema.name if schema else "", schema.encoding if schema else "",
                                       bytes(schema.data) if schema else b"", channel.message_encoding)
            cid = self._channels[channel.topic] = self._writer.add_channel(channel.topic, message_type)
        self._writer.write(cid, log_time=log_time, data=data)
        self.seen += frame

    def close(self, metadata: list[tuple[str, dict[str, str]]]) -> Path:
        """The log, complete, with the source's metadata records."""
        for name, record in metadata:
            self._writer.add_metadata(name, record)
        return self._writer.close()

    def abort(self) -> None:
        self._writer.abort()


def relayer(provisional: Path, base: Path, output: Path, *, stage: str, parameters: dict[str, Any],
            metadata: list[tuple[str, dict[str, str]]], compression: str) -> None:
    """Write the messages and metadata records of ``provisional`` (a complete file without a base) into a layer on
    ``base`` at ``output``, with ``metadata`` records and the stage's provenance; ``provisional`` is removed."""
    with LogReader(provisional, chain=False) as source, \
            extend_log(base, output, stage=stage, parameters=parameters, force=True, compression=compression) as (_, out):
        _copy_messages(source, out)
        for name, record in [*source.metadata(), *metadata]:
            if name != PROVENANCE_METADATA_NAME:
                out.writer.add_metadata(name, record)
    if provisional != output:
        provisional.unlink(missing_ok=True)


def _copy_messages(source: LogReader, out: StageOutput) -> None:
    ids: dict[str, int] = {}
    summary = source.files[0].summary
    for channel in sorted(summary.channels.values(), key=lambda c: c.id):
        schema = summary.schemas.get(channel.schema_id)
        message_type = MessageType(schema.name if schema else "", schema.encoding if schema else "",
                                   bytes(schema.data) if schema else b"", channel.message_encoding)
        ids[channel.topic] = out.add_channel(channel.topic, message_type)
    for _, channel, message in source.raw_messages(list(ids)):
        out.writer.write(ids[channel.topic], log_time=message.log_time, data=message.data)


def close_on_base(writer: LogWriter, out: StageOutput, base: LogReader, *, stage: str, parameters: dict[str, Any],
                  metadata: list[tuple[str, dict[str, str]]]) -> None:
    """Close ``writer``, written without its base, as a layer on ``base`` with its provenance and ``metadata``."""
    layer = base.layer_base()
    try:
        writer.attach_base(layer)
    except BaseException:
        layer.cancel()
        raise
    for name, record in metadata:
        writer.add_metadata(name, record)
    record_provenance(out, stage, parameters, layer.digest())
    writer.close()
