"""Choosing the channels a stage reads (``--track``), and checking it read every message of them."""

from __future__ import annotations

from collections.abc import Sequence

from starlog.errors import ChannelNotFoundError, CorruptLogError, InvalidInputError, InvalidParameterError
from starlog.io.reader import ChannelSummary, LogReader

__all__ = ["check_messages_read", "select_track_channels"]


def select_track_channels(log: LogReader, track: str | Sequence[str] | None) -> list[ChannelSummary]:
    """Track channels named by ``track``: a topic (``/track/M/MODEL`` or ``M/MODEL``), a list, ``"all"``,
    or None for the only one."""
    channels = [c for c in log.channels() if c.schema_name == "starlog.Tracks"]
    if not channels:
        raise InvalidInputError(f"{log.path} has no track channel; run `starlog track` on it first.")
    if track is None:
        if len(channels) == 1:
            return channels
        raise InvalidParameterError(
            "the log has several track channels; choose with --track (or 'all'): "
            + ", ".join(c.topic for c in channels))
    names = [track] if isinstance(track, str) else list(track)
    if [n.lower() for n in names] == ["all"]:
        return channels
    by_topic = {c.topic: c for c in channels}
    chosen = []
    for name in names:
        topic = name if name.startswith("/") else f"/track/{name}"
        if topic not in by_topic:
            raise ChannelNotFoundError(log.path, topic, list(by_topic))
        chosen.append(by_topic[topic])
    return chosen


def check_messages_read(log: LogReader, topic: str, read: int, *, what: str = "messages") -> int:
    """The channel's message count (from the log's statistics), when ``read`` accounts for all of them.

    A stage never processes fewer messages than the channel holds without saying so: a mismatch
    means the log's indexes disagree with its contents, and is an error.
    """
    held = log.channel(topic).message_count
    if read != held:
        raise CorruptLogError(
            log.path, f"{read} {what} of {topic!r} were read but the channel holds {held} messages (by its "
            f"statistics): the log's indexes disagree with its contents. Check it with: starlog verify {log.path}")
    return held
