"""What a log says of each of its channels (:class:`ChannelSummary`), from each channel's extents.

A channel's *extents* are ``[count, first log_time, last log_time]`` of its messages; :func:`add_extent`
merges more messages into them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from mcap.summary import Summary

__all__ = ["ChannelSummary", "add_extent", "channel_summaries"]


@dataclass(frozen=True)
class ChannelSummary:
    """One topic of a log, as :meth:`~starlog.io.reader.LogReader.channels` lists it: its channel, or the union of
    its channels (:meth:`union`).

    ``rate_hz`` is ``(count - 1) / (last - first)`` in Hz (0 for fewer than two messages).
    ``channel_ids`` are the ids of the topic's channels; ``per_channel`` holds each one's own summary
    when there are several (empty otherwise).
    """

    topic: str
    schema_name: str
    schema_encoding: str
    message_encoding: str
    message_count: int
    first_log_time: int
    last_log_time: int
    channel_ids: tuple[int, ...] = ()
    per_channel: tuple[ChannelSummary, ...] = ()

    @classmethod
    def union(cls, parts: list[ChannelSummary]) -> ChannelSummary:
        """The summary of a topic whose channels ``parts`` summarise (ascending ids): every message counted,
        the schema and encodings of the first channel holding messages (else the first: Foxglove lists such a
        topic under its first channel's schema)."""
        if len(parts) == 1:
            return parts[0]
        held = [p for p in parts if p.message_count]
        return replace(held[0] if held else parts[0], message_count=sum(p.message_count for p in parts),
                       first_log_time=min((p.first_log_time for p in held), default=0),
                       last_log_time=max((p.last_log_time for p in held), default=0),
                       channel_ids=tuple(i for p in parts for i in p.channel_ids), per_channel=tuple(parts))

    @property
    def rate_hz(self) -> float:
        span = self.last_log_time - self.first_log_time
        return (self.message_count - 1) / (span * 1e-9) if self.message_count > 1 and span > 0 else 0.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "topic": self.topic,
            "schema": self.schema_name,
            "schema_encoding": self.schema_encoding,
            "message_encoding": self.message_encoding,
            "message_count": self.message_count,
            "first_log_time": self.first_log_time,
            "last_log_time": self.last_log_time,
            "rate_hz": self.rate_hz,
            "channel_ids": list(self.channel_ids),
        } | ({"per_channel": [p.to_dict() for p in self.per_channel]} if self.per_channel else {})


def add_extent(extents: dict[int, list[int]], cid: int, count: int, first: int, last: int) -> None:
    """Add ``count`` messages of channel ``cid`` spanning ``first..last`` to ``extents``."""
    e = extents.get(cid)
    if e is None:
        extents[cid] = [count, first, last]
    else:
        e[0] += count
        e[1], e[2] = min(e[1], first), max(e[2], last)


def channel_summaries(summary: Summary, extents: dict[int, list[int]]) -> dict[int, ChannelSummary]:
    """The :class:`ChannelSummary` of each channel of a file's ``summary`` from its ``[count, first, last]``
    extents."""
    out = {}
    for cid in sorted(summary.channels):
        ch = summary.channels[cid]
        schema = summary.schemas.get(ch.schema_id)
        count, first, last = extents.get(cid, (0, 0, 0))
        out[cid] = ChannelSummary(topic=ch.topic, schema_name=schema.name if schema else "",
                                  schema_encoding=schema.encoding if schema else "",
                                  message_encoding=ch.message_encoding, message_count=int(count),
                                  first_log_time=int(first), last_log_time=int(last), channel_ids=(cid,))
    return out
