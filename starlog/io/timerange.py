"""Time ranges of a log: ``--start`` / ``--end`` as users write them, and as resolved against a log.

A bound is written one of three ways:

* ``1234567`` — a ``log_time`` in integer nanoseconds;
* ``12.5s`` — a ``log_time`` in seconds (the same clock as ``log_time``, not seconds from the
  log's start), at most nine decimals;
* ``frame:N`` — the ``log_time`` of the N-th (0-based, in ``log_time`` order) message of a
  channel: a stage's input frame or record channel.

A range is **half-open**: it holds the messages with ``start <= log_time < end``. So
``--start frame:10 --end frame:20`` keeps frames 10 to 19 (ten frames), and two ranges that meet
(``--end 5s`` then ``--start 5s``) never share a message. A missing start is the log's first
message, a missing end is after its last. An empty or reversed range, or one that holds no
message of the channel it is meant for, is an :class:`~starlog.errors.InvalidParameterError`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from typing import Any, Protocol

from starlog.errors import InvalidParameterError

__all__ = ["END_OF_TIME", "ResolvedRange", "TimeBound", "TimeRange", "parse_time_bound"]

#: One past the largest ``log_time`` MCAP can hold: an open end.
END_OF_TIME = 2**64

_FORMS = "log time in ns (1234567), seconds with an 's' suffix (12.5s) or frame:N (0-based)"
_NANOSECONDS = re.compile(r"\d+")
_SECONDS = re.compile(r"(\d+(?:\.\d*)?|\.\d+)s")
_FRAME = re.compile(r"frame:(\d+)")


@dataclass(frozen=True)
class TimeBound:
    """One bound as written: ``kind`` is ``"ns"`` (``value`` in ns) or ``"frame"`` (``value`` a message index)."""

    text: str
    kind: str
    value: int


def parse_time_bound(text: str | int, *, option: str = "--start") -> TimeBound:
    """``"1234567"``, ``"12.5s"`` or ``"frame:N"`` (or an int of ns) → :class:`TimeBound`.

    Raises :class:`InvalidParameterError` naming ``option`` for anything else (negative values,
    fractions of a nanosecond, times past 2**64 - 1 ns).
    """
    if isinstance(text, bool) or not isinstance(text, (str, int)):
        raise InvalidParameterError(f"{option} {text!r}: expected {_FORMS}.")
    written = str(text).strip()
    if _NANOSECONDS.fullmatch(written):
        return _checked(TimeBound(written, "ns", int(written)), option)
    seconds = _SECONDS.fullmatch(written)
    if seconds:
        try:
            ns = Decimal(seconds.group(1)) * 10**9
        except InvalidOperation:  # pragma: no cover - the pattern admits only decimal numbers
            raise InvalidParameterError(f"{option} {written!r}: expected {_FORMS}.") from None
        if ns != ns.to_integral_value():
            raise InvalidParameterError(f"{option} {written!r}: finer than a nanosecond (at most 9 decimals).")
        return _checked(TimeBound(written, "ns", int(ns)), option)
    frame = _FRAME.fullmatch(written)
    if frame:
        return TimeBound(written, "frame", int(frame.group(1)))
    raise InvalidParameterError(f"{option} {written!r}: expected {_FORMS}.")


def _checked(bound: TimeBound, option: str) -> TimeBound:
    if bound.value >= END_OF_TIME:
        raise InvalidParameterError(f"{option} {bound.text!r}: past the largest log_time (2**64 - 1 ns).")
    return bound


class FrameTimes(Protocol):
    """What resolving ``frame:N`` needs: the ``log_time`` of a channel's N-th message, and its count."""

    def __call__(self, index: int) -> int | None: ...


@dataclass(frozen=True)
class ResolvedRange:
    """``start_ns <= log_time < end_ns``, with the bounds as the user wrote them (None: open)."""

    start_ns: int
    end_ns: int
    start: str | None = None
    end: str | None = None
    frame_topic: str | None = None

    def contains(self, log_time: int) -> bool:
        """Whether a message at ``log_time`` is in the range."""
        return self.start_ns <= log_time < self.end_ns

    def covers(self, first: int, last: int) -> bool:
        """Whether every time of ``first..last`` (inclusive) is in the range."""
        return self.start_ns <= first and last < self.end_ns

    def overlaps(self, first: int, last: int) -> bool:
        """Whether some time of ``first..last`` (inclusive) is in the range."""
        return first < self.end_ns and last >= self.start_ns

    def describe(self) -> str:
        """``[start, end)`` as written, for messages."""
        return f"[{self.start or 'the start'}, {self.end or 'the end'})"

    def describe_ns(self) -> str:
        """The resolved bounds, for messages: ``log_time A..B ns, end exclusive`` (or ``A ns on``)."""
        if self.end_ns >= END_OF_TIME:
            return f"log_time {self.start_ns} ns on"
        return f"log_time {self.start_ns}..{self.end_ns} ns, end exclusive"

    def to_dict(self) -> dict[str, Any]:
        """The provenance form: bounds as written and resolved (``end_ns`` None when open)."""
        out: dict[str, Any] = {"start": self.start, "end": self.end, "start_ns": self.start_ns,
                               "end_ns": None if self.end_ns >= END_OF_TIME else self.end_ns}
        if self.frame_topic is not None:
            out["frame_topic"] = self.frame_topic
        return out


@dataclass(frozen=True)
class TimeRange:
    """``--start`` / ``--end`` as written (either may be None); :meth:`resolve` turns them into ns."""

    start: TimeBound | None = None
    end: TimeBound | None = None

    @classmethod
    def parse(cls, start: str | int | None, end: str | int | None) -> TimeRange | None:
        """Both options → a range, or None when neither is given."""
        if start is None and end is None:
            return None
        return cls(None if start is None else parse_time_bound(start, option="--start"),
                   None if end is None else parse_time_bound(end, option="--end"))

    @property
    def counts_frames(self) -> bool:
        """Whether a bound is ``frame:N`` (resolving needs a channel's message times)."""
        return any(b is not None and b.kind == "frame" for b in (self.start, self.end))

    def resolve(self, frame_time: FrameTimes | None = None, *, frame_topic: str | None = None) -> ResolvedRange:
        """The range in ns. ``frame_time(n)`` gives the ``log_time`` of the frame channel's n-th message
        (None past its last); ``frame:N`` as an end may name one past the last frame (up to its end).

        Raises :class:`InvalidParameterError` for a frame past the channel and for an empty or
        reversed range.
        """
        start_ns = 0 if self.start is None else self._bound_ns(self.start, frame_time, frame_topic, is_end=False)
        end_ns = END_OF_TIME if self.end is None else self._bound_ns(self.end, frame_time, frame_topic, is_end=True)
        resolved = ResolvedRange(start_ns, end_ns, None if self.start is None else self.start.text,
                                 None if self.end is None else self.end.text,
                                 frame_topic if self.counts_frames else None)
        if end_ns <= start_ns:
            raise InvalidParameterError(
                f"the time range {resolved.describe()} is {'empty' if end_ns == start_ns else 'reversed'} "
                f"(log_time {start_ns} to {end_ns} ns); --end must come after --start (the end is exclusive).")
        return resolved

    @staticmethod
    def _bound_ns(bound: TimeBound, frame_time: FrameTimes | None, topic: str | None, *, is_end: bool) -> int:
        if bound.kind == "ns":
            return bound.value
        if frame_time is None:
            raise InvalidParameterError(f"{bound.text!r}: frame:N needs a frame channel, and there is none here; "
                                        "give the time in ns or seconds.")
        found = frame_time(bound.value)
        if found is not None:
            return found
        last = frame_time(bound.value - 1) if is_end and bound.value > 0 else None
        if last is not None:  # frame:COUNT as the end: up to and including the last frame
            return last + 1
        raise InvalidParameterError(f"{'--end' if is_end else '--start'} {bound.text!r} is outside the log: "
                                    f"{topic or 'the frame channel'} has fewer frames.")
