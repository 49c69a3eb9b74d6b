"""How far ``starlog live`` is behind its source: frames waiting, the latency of each frame, frames skipped.

A frame's latency runs from when live saw it in the source to when its last message was written
and published. The run's latencies go into a histogram of fixed size (:class:`LatencyHistogram`:
quantiles within 1 %, memory flat however long the run), the last second's into a short window for
the once-a-second status.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["LatencyHistogram", "StatusBoard"]

#: A frame waiting longer than this means the processing is behind.
BEHIND_SECONDS = 1.0


class LatencyHistogram:
    """Latencies (ms) in logarithmic bins from 1 µs to 1000 s, 2 % wide: quantiles within 1 %."""

    _LOW, _RATIO = 1e-3, 1.02

    def __init__(self) -> None:
        self._bins = np.zeros(int(math.log(1e6 / self._LOW) / math.log(self._RATIO)) + 2, dtype=np.int64)
        self.count = 0
        self.largest = 0.0

    def add(self, ms: float) -> None:
        k = 0 if ms <= self._LOW else min(int(math.log(ms / self._LOW) / math.log(self._RATIO)) + 1,
                                          self._bins.size - 1)
        self._bins[k] += 1
        self.count += 1
        self.largest = max(self.largest, ms)

    def quantile(self, q: float) -> float:
        """The ``q``-quantile (ms, the middle of its bin; NaN when empty)."""
        if self.count == 0:
            return math.nan
        k = int(np.searchsorted(np.cumsum(self._bins), q * self.count, side="left"))
        return self._LOW * self._RATIO ** (k - 0.5) if k else self._LOW

    def to_dict(self) -> dict[str, Any]:
        return {"frames": self.count, "median_ms": self.quantile(0.5), "p99_ms": self.quantile(0.99),
                "max_ms": self.largest}


@dataclass
class StatusBoard:
    """The counts and latencies of a live run (see the module docstring)."""

    seen: int = 0
    done: int = 0
    skipped: list[dict[str, Any]] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    latency: LatencyHistogram = field(default_factory=LatencyHistogram)
    behind: bool = False
    _recent: deque[tuple[int, float]] = field(default_factory=deque)

    def frame_done(self, now_ns: int, seen_ns: int) -> None:
        ms = (now_ns - seen_ns) * 1e-6
        self.done += 1
        self.latency.add(ms)
        self._recent.append((now_ns, ms))

    def skip(self, frame: int | None, log_time: int | None, reason: str) -> None:
        """A frame left out, with why (kept for the record: a replay of the base redoes it)."""
        self.skipped.append({"frame": frame, "log_time": log_time, "reason": reason})

    def record(self, now_ns: int, waiting: int, oldest_ns: int | None, state: str) -> dict[str, Any]:
        """The status of the last second (``waiting``: frames seen, not processed; ``oldest_ns``: when the oldest
        of them was seen)."""
        while self._recent and now_ns - self._recent[0][0] > 1_000_000_000:
            self._recent.popleft()
        recent = [ms for _, ms in self._recent]
        self.behind = waiting > 0 and oldest_ns is not None and now_ns - oldest_ns > BEHIND_SECONDS * 1e9
        return {"frames_seen": self.seen, "frames_done": self.done, "frames_waiting": waiting,
                "frames_skipped": len(self.skipped),
                "latency_ms_median": float(np.median(recent)) if recent else 0.0,
                "latency_ms_max": max(recent, default=0.0), "behind": self.behind, "state": state}

    def to_dict(self) -> dict[str, Any]:
        return {"frames_seen": self.seen, "frames_done": self.done, "skipped": list(self.skipped),
                "problems": list(self.problems), "latency": self.latency.to_dict()}
