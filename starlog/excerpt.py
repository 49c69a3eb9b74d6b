"""``starlog filter`` and ``starlog cat``: some channels and a time range of any log, as a log or as JSON lines.

Both select channels by :mod:`fnmatch` globs (``--topic``, ``--exclude-topic``) and messages by
``--start`` / ``--end`` (half-open, :mod:`starlog.io.timerange`). ``frame:N`` counts the messages
of ``frame_topic``: by default the only channel selected, else the log's image channel (as the
stages choose it). ``filter`` writes a new log through :func:`starlog.io.copying.copy_log`
(chunks kept whole are copied byte for byte) and records its own provenance; ``cat`` streams
each message as plain values (:mod:`starlog.codecs.plain_values`), which the command prints as JSON lines.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from typing import Any

from starlog.version import __version__
from starlog.errors import InvalidParameterError, StarlogError
from starlog.codecs.images import choose_image_topic
from starlog.codecs.plain_values import PlainValues
from starlog.io.provenance import BackgroundDigest, Provenance
from starlog.io.reader import LogReader
from starlog.io.copying import CopyReport, TopicSelection, check_topics_exist, frame_time_lookup, copy_log
from starlog.io.timerange import ResolvedRange, TimeRange

__all__ = ["cat_messages", "filter_log"]


def _selected(log: LogReader, selection: TopicSelection) -> list[str]:
    check_topics_exist(log, selection.include)
    chosen = [t for t in log.topics if selection.keeps(t)]
    if not chosen:
        raise InvalidParameterError(f"{log.path}: the topic selection keeps no channel "
                                    f"(channels: {', '.join(log.topics) or 'none'}).")
    return chosen


def _image_topic_for_frames(log: LogReader) -> str:
    """The channel ``frame:N`` counts when several are selected: the image channel, else say how to name one."""
    try:
        return choose_image_topic(log.path, log.channels(), None)[0]
    except StarlogError as err:
        raise InvalidParameterError(f"{err} frame:N counts the messages of one channel: name it with "
                                    "--frame-topic TOPIC, or select a single channel with --topic.") from None


def _resolve(log: LogReader, time_range: TimeRange | None, chosen: list[str], frame_topic: str | None
             ) -> ResolvedRange | None:
    """The range in ns; an error when it lies outside every selected channel."""
    if time_range is None:
        return None
    topic = None
    if time_range.counts_frames:
        topic = frame_topic or (chosen[0] if len(chosen) == 1 else _image_topic_for_frames(log))
    resolved = time_range.resolve(None if topic is None else frame_time_lookup(log, topic), frame_topic=topic)
    spans = [(c.first_log_time, c.last_log_time) for c in log.channels() if c.topic in chosen and c.message_count]
    if not any(resolved.overlaps(lo, hi) for lo, hi in spans):
        first, last = min((s[0] for s in spans), default=0), max((s[1] for s in spans), default=0)
        raise InvalidParameterError(
            f"{log.path}: the time range {resolved.describe()} ({resolved.describe_ns()}) is outside the selected "
            f"channels (log_time {first}..{last} ns).")
    return resolved


def filter_log(
    input_path: str | os.PathLike[str],
    output_path: str | os.PathLike[str],
    *,
    topics: Sequence[str] = (),
    exclude_topics: Sequence[str] = (),
    start: str | int | None = None,
    end: str | int | None = None,
    frame_topic: str | None = None,
    force: bool = False,
    compression: str = "zstd",
) -> CopyReport:
    """Write the channels matching ``topics`` (default: all) and not ``exclude_topics``, in ``[start, end)``.

    Keeps schemas, metadata (provenance) and attachments in the range; adds a provenance record
    (stage ``filter``). Chunks kept whole are copied byte for byte; chunks only partly kept are
    re-encoded with ``compression``. Works on any MCAP log (foreign, unindexed).
    """
    selection = TopicSelection(tuple(topics), tuple(exclude_topics))
    digest = BackgroundDigest(input_path)  # the provenance's input SHA-256, hashed while the chunks are copied
    try:
        with LogReader(input_path) as log:
            chosen = _selected(log, selection)
            resolved = _resolve(log, TimeRange.parse(start, end), chosen, frame_topic)
        parameters: dict[str, Any] = {**selection.to_dict(),
                                      "range": None if resolved is None else resolved.to_dict()}
        report = copy_log(input_path, output_path, topics=selection, time_range=resolved, force=force,
                           compression=compression,
                           provenance=lambda: Provenance(stage="filter", version=__version__, parameters=parameters,
                                                         input_digest=digest.result(), channels=[]))
    finally:
        digest.cancel()
    if not sum(report.messages.values()):
        os.unlink(output_path)
        raise InvalidParameterError(f"{input_path}: the time range {resolved.describe() if resolved else ''} holds "
                                    "no message of the selected channels; nothing written.")
    return report


def cat_messages(
    input_path: str | os.PathLike[str],
    *,
    topics: Sequence[str] = (),
    exclude_topics: Sequence[str] = (),
    start: str | int | None = None,
    end: str | int | None = None,
    frame_topic: str | None = None,
    limit: int | None = None,
    notes: list[str] | None = None,
) -> Iterator[dict[str, Any]]:
    """Each selected message, in ``log_time`` order, as ``{topic, log_time, publish_time, sequence, message}``
    (``message``: :class:`~starlog.codecs.plain_values.PlainValues`' plain values); ``notes`` gets the reader's notes on how the log was read, once every message is given."""
    if limit is not None and limit < 0:
        raise InvalidParameterError(f"--limit must be >= 0, got {limit}.")
    selection = TopicSelection(tuple(topics), tuple(exclude_topics))
    render = PlainValues()
    with LogReader(input_path) as log:
        chosen = _selected(log, selection)
        resolved = _resolve(log, TimeRange.parse(start, end), chosen, frame_topic)
        lo, hi = (None, None) if resolved is None else (resolved.start_ns, resolved.end_ns)
        messages = log.raw_messages(chosen, start=lo, end=hi, views=True, mixed=True)  # each line by its own schema
        for count, (schema, channel, message) in enumerate(messages):
            if limit is not None and count >= limit:
                break
            yield {"topic": channel.topic, "log_time": message.log_time, "publish_time": message.publish_time,
                   "sequence": message.sequence, "message": render(schema, channel, message.data)}
        if notes is not None:
            notes.extend(log.notes)
