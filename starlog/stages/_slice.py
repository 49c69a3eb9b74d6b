"""``--start`` / ``--end`` for every replay stage and ``run``: the stage runs on a slice of its input.

The slice (every channel's messages with ``start <= log_time < end``, see
:mod:`starlog.io.timerange`) is cut by :func:`starlog.io.slicing.slice_log` into a hidden file
beside the output — chunks inside the range copied byte for byte, the two boundary chunks
re-encoded — and the stage runs on it unchanged, so its output holds only the range, input
channels included. The stage's provenance records the range (as written and in ns) and the
SHA-256 of the log the slice was cut from (:func:`slice_origin`). ``frame:N`` counts the messages
of the stage's input channel (frames for ``centroid``, centroid records for ``track``, track
records for ``motion`` and ``compensate``).
"""

from __future__ import annotations

import functools
import os
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from starlog.errors import InvalidParameterError, OutputExistsError, OutputFolderError
from starlog.io.reader import LogReader
from starlog.io.slicing import frame_time_lookup, slice_log
from starlog.io.stack import StackedLog
from starlog.io.timerange import ResolvedRange, TimeRange

__all__ = ["SliceOrigin", "SlicedPath", "SlicedStack", "cut_slice", "slice_origin", "sliced_stack", "time_sliced"]

LogSource = str | os.PathLike[str] | StackedLog
FrameTopic = Callable[[LogReader, dict[str, Any]], str]
F = TypeVar("F", bound=Callable[..., Any])


@dataclass(frozen=True)
class SliceOrigin:
    """The log a slice was cut from and the range it holds: what the next stage's provenance records."""

    source: LogSource
    time_range: ResolvedRange


class SlicedPath(os.PathLike[str]):
    """The path of a slice file, carrying its :class:`SliceOrigin` to the stage that reads it."""

    def __init__(self, path: Path, origin: SliceOrigin) -> None:
        self.path = path
        self.slice_origin = origin

    def __fspath__(self) -> str:
        return str(self.path)

    def __str__(self) -> str:
        return str(self.path)


class SlicedStack(StackedLog):
    """A :class:`StackedLog` whose base is a slice (``run --start/--end``); its sidecars are plain stacks, so
    only the first stage run on it records the range."""

    slice_origin: SliceOrigin | None = None


def slice_origin(log: object) -> SliceOrigin | None:
    """The :class:`SliceOrigin` of a stage's input, None when it is not a slice."""
    origin = getattr(log, "slice_origin", None)
    return origin if isinstance(origin, SliceOrigin) else None


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


def cut_slice(source: LogSource, destination: Path, time_range: TimeRange, frame_topic: Callable[[LogReader], str],
              *, compression: str = "zstd") -> SliceOrigin:
    """Write the slice of ``source`` to ``destination``; the origin of what was written."""
    with LogReader(source) as log:
        topic = frame_topic(log)
        resolved = _resolve(log, time_range, topic)
    report = slice_log(source, destination, time_range=resolved, force=True, compression=compression)
    if not report.messages.get(topic):
        destination.unlink(missing_ok=True)
        raise InvalidParameterError(f"{source}: the time range {resolved.describe()} holds no message of {topic}.")
    return SliceOrigin(source, resolved)


@contextmanager
def _hidden_file(beside: Path, suffix: str) -> Iterator[Path]:
    OutputFolderError.check(beside)
    fd, name = tempfile.mkstemp(prefix=f".{beside.name}.", suffix=suffix, dir=beside.parent or ".")
    os.close(fd)
    try:
        yield Path(name)
    finally:
        Path(name).unlink(missing_ok=True)


def time_sliced(frame_topic: FrameTopic) -> Callable[[F], F]:
    """Give a stage function ``start`` / ``end`` keywords: with either, the stage runs on the slice.

    ``frame_topic(log, keywords)`` names the channel ``frame:N`` counts, from the stage's keywords.
    """

    def decorate(stage: F) -> F:
        @functools.wraps(stage)
        def run(input_path: LogSource, output_path: str | os.PathLike[str], *args: Any,
                start: str | int | None = None, end: str | int | None = None, **kwargs: Any) -> Any:
            time_range = TimeRange.parse(start, end)
            if time_range is None:
                return stage(input_path, output_path, *args, **kwargs)
            output = Path(output_path)
            if output.exists() and not kwargs.get("force", False):
                raise OutputExistsError(output)
            with _hidden_file(output, ".slice") as sliced:
                origin = cut_slice(input_path, sliced, time_range, lambda log: frame_topic(log, kwargs),
                                   compression=kwargs.get("compression", "zstd"))
                return stage(SlicedPath(sliced, origin), output_path, *args, **kwargs)

        run.frame_topic = frame_topic  # type: ignore[attr-defined]
        return run  # type: ignore[return-value]

    return decorate


@contextmanager
def sliced_stack(source: str | os.PathLike[str], output: Path, time_range: TimeRange | None, frame_topic: FrameTopic,
                 options: dict[str, Any], *, compression: str = "zstd") -> Iterator[StackedLog]:
    """The stack ``run`` starts from: the input, or (with a range) its slice, cut once, beside ``output``."""
    if time_range is None:
        yield StackedLog.of(source)
        return
    with _hidden_file(output, ".slice") as sliced:
        origin = cut_slice(source, sliced, time_range, lambda log: frame_topic(log, options), compression=compression)
        stack = SlicedStack.of(sliced)
        stack.slice_origin = origin
        yield stack
