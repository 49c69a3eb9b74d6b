"""Choosing the track channels a stage reads (``--track``)."""

from __future__ import annotations

from collections.abc import Sequence

from starlog.errors import ChannelNotFoundError, InvalidInputError, InvalidParameterError
from starlog.io.reader import ChannelSummary, LogReader

__all__ = ["select_track_channels"]


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
