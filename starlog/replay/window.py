"""``--start`` / ``--end`` for every replay stage and ``run``: the stage runs on a window of its input.

The range (see :mod:`starlog.io.timerange`) is resolved against the stage's input channel and the
stage reads its input through a :class:`~starlog.io.reader.LogView`: every channel's messages with
``start <= log_time < end``. Nothing is copied; the stage's layer holds its channels for the range
only, and its provenance records the range (as written and in ns). ``frame:N`` counts the messages
of the stage's input channel (frames for ``centroid``, centroid records for ``track``, track
records for ``motion`` and ``compensate``).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from starlog.errors import InvalidParameterError
from starlog.io.reader import LogReader, LogSource, LogView, source_path
from starlog.io.copying import frame_time_lookup
from starlog.io.timerange import ResolvedRange, TimeRange

__all__ = ["window_of", "windowed"]

FrameTopic = Callable[[LogReader, dict[str, Any]], str]
F = TypeVar("F", bound=Callable[..., Any])


def _resolve(log: LogReader, time_range: TimeRange, topic: str) -> ResolvedRange:
    """The range in ns against ``topic``; an error when it holds none of its messages."""
    resolved = time_range.resolve(frame_time_lookup(log, topic), frame_topic=topic)
    channel = log.channel(topic)
    if channel.message_count == 0 or not resolved.overlaps(channel.first_log_time, channel.last_log_time):
        span = (f"log_time {channel.first_log_time}..{channel.last_log_time} ns" if channel.message_count
                else "no message")
        raise InvalidParameterError(
            f"{log.path}: the time range {resolved.describe()} ({resolved.describe_ns()}) is outside {topic} "
            f"({span}).")
    return resolved


def window_of(source: str | os.PathLike[str], time_range: TimeRange | None, frame_topic: Callable[[LogReader], str]
              ) -> LogSource:
    """``source``, or (with a range) the :class:`LogView` of it that holds the range; an error when the range
    holds no message of the channel ``frame_topic`` names."""
    if time_range is None:
        return source
    with LogReader(source) as log:
        topic = frame_topic(log)
        resolved = _resolve(log, time_range, topic)
    view = LogView(Path(source_path(source)), resolved)
    with LogReader(view) as log:
        if not log.channel(topic).message_count:
            raise InvalidParameterError(f"{source}: the time range {resolved.describe()} holds no message of "
                                        f"{topic}.")
    return view


def windowed(frame_topic: FrameTopic) -> Callable[[F], F]:
    """Give a stage function ``start`` / ``end`` keywords: with either, the stage runs on that window.

    ``frame_topic(log, keywords)`` names the channel ``frame:N`` counts, from the stage's keywords.
    """

    def decorate(stage: F) -> F:
        @functools.wraps(stage)
        def run(input_path: LogSource, output_path: str | os.PathLike[str], *args: Any,
                start: str | int | None = None, end: str | int | None = None, **kwargs: Any) -> Any:
            time_range = TimeRange.parse(start, end)
            if time_range is not None:
                input_path = window_of(input_path, time_range, lambda log: frame_topic(log, kwargs))
            return stage(input_path, output_path, *args, **kwargs)

        run.frame_topic = frame_topic  # type: ignore[attr-defined]
        return run  # type: ignore[return-value]

    return decorate
