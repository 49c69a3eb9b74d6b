"""Per-track arrays of :class:`~starlog.tracking.StarTracker`, held together so they stay in step.

:class:`TrackState` keeps the live tracks in two tables, one row per track (sorted by id): the
floats (state mean ``x``, covariance ``P`` flattened row by row, running sums, anchor) and the
integers (:data:`INT_FIELDS`). Every named array is a view of a column range of one table, so
:meth:`TrackState.take` (select tracks) and :meth:`TrackState.concat` (append new ones) move
every array at once: none can be forgotten when tracks are dropped or born. The tables may hold
spare rows beyond the live ones (:meth:`TrackState.reserve`), where the compiled frame step
(:mod:`starlog.tracking.frame_kernel`, which reads the same layout) writes the tracks it starts.

:class:`FrameRows` holds what happened to each live track in the current frame (a dataclass of
arrays, first axis the track).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

__all__ = ["INT_FIELDS", "TrackState", "FrameRows", "float_columns"]

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]
_C = TypeVar("_C", bound="_Columns")

INT_FIELDS = ("ids", "hits", "missed", "coast", "gated_streak", "age", "gated", "first_time", "last_time")
"""Columns of the integer table, in order: track id; applied measurements (birth included);
consecutive frames without an applied measurement; consecutive frames without an associated
centroid; consecutive gated frames; frames since birth; gated measurements in all; ``log_time``
of birth and of the last applied measurement, ns."""


def float_columns(d: int) -> int:
    """Columns of the float table for states of dimension ``d``: x (d), P (d²), sums (3), anchor (2)."""
    return d + d * d + 5


def _int_column(k: int) -> property:
    def get(self: TrackState) -> IntArray:
        return self.ints[: self.n, k]

    def set(self: TrackState, value: npt.ArrayLike) -> None:
        self.ints[: self.n, k] = value

    return property(get, set, doc=f"``{INT_FIELDS[k]}``: column {k} of the integer table, an (n,) view.")


class TrackState:
    """Filter state, life-cycle counters and running sums of the live tracks.

    Parameters
    ----------
    floats : (capacity, d + d² + 5) ndarray of float64
        Per track: ``x`` (d), ``P`` (d × d, row by row), ``sums`` (flux, x, y summed over the
        applied measurements), ``anchor`` (x, y of the filtered position at the last applied
        measurement).
    ints : (capacity, 9) ndarray of int64
        Per track, the columns :data:`INT_FIELDS`.
    n : int
        Live tracks: the first ``n`` rows of both tables.
    d : int
        State dimension.
    """

    __slots__ = ("floats", "ints", "n", "d")

    ARRAYS = (*INT_FIELDS, "x", "P", "sums", "anchor")
    """The named per-track arrays (views of the tables)."""

    ids = _int_column(0)
    hits = _int_column(1)
    missed = _int_column(2)
    coast = _int_column(3)
    gated_streak = _int_column(4)
    age = _int_column(5)
    gated = _int_column(6)
    first_time = _int_column(7)
    last_time = _int_column(8)

    def __init__(self, floats: Array, ints: IntArray, n: int, d: int) -> None:
        self.floats = floats
        self.ints = ints
        self.n = n
        self.d = d

    def __len__(self) -> int:
        return self.n

    @property
    def x(self) -> Array:
        """(n, d) state means (a view)."""
        return self.floats[: self.n, : self.d]

    @x.setter
    def x(self, value: Array) -> None:
        self.floats[: self.n, : self.d] = value

    @property
    def P(self) -> Array:
        """(n, d, d) state covariances (a view)."""
        d = self.d
        return self.floats[: self.n, d : d + d * d].reshape(self.n, d, d)

    @P.setter
    def P(self, value: Array) -> None:
        d = self.d
        self.floats[: self.n, d : d + d * d] = value.reshape(self.n, d * d)

    @property
    def sums(self) -> Array:
        """(n, 3): flux, x, y summed over applied measurements (a view)."""
        start = self.d + self.d * self.d
        return self.floats[: self.n, start : start + 3]

    @property
    def anchor(self) -> Array:
        """(n, 2): x, y of the filtered position at the last applied measurement (a view)."""
        start = self.d + self.d * self.d + 3
        return self.floats[: self.n, start : start + 2]

    def take(self, index: npt.NDArray[Any]) -> TrackState:
        """The tracks selected by ``index`` (boolean mask or integer indices), in every array."""
        floats = self.floats[: self.n][index]
        return TrackState(floats, self.ints[: self.n][index], floats.shape[0], self.d)

    def concat(self, other: TrackState) -> TrackState:
        """These tracks followed by ``other``'s, in every array."""
        floats = np.concatenate((self.floats[: self.n], other.floats[: other.n]))
        ints = np.concatenate((self.ints[: self.n], other.ints[: other.n]))
        return TrackState(floats, ints, self.n + other.n, self.d)

    def reserve(self, capacity: int) -> None:
        """Make room for at least ``capacity`` tracks (the live ones kept; grows by doubling)."""
        if self.floats.shape[0] >= capacity:
            return
        size = max(capacity, 2 * self.floats.shape[0], 16)
        floats = np.zeros((size, self.floats.shape[1]))
        ints = np.zeros((size, len(INT_FIELDS)), dtype=np.int64)
        floats[: self.n] = self.floats[: self.n]
        ints[: self.n] = self.ints[: self.n]
        self.floats, self.ints = floats, ints

    @classmethod
    def empty(cls, d: int) -> TrackState:
        """No track, states of dimension ``d``."""
        return cls(np.zeros((0, float_columns(d))), np.zeros((0, len(INT_FIELDS)), dtype=np.int64), 0, d)

    @classmethod
    def born(cls, ids: IntArray, x: Array, P: Array, log_time: int, sums: Array) -> TrackState:
        """New tracks started by one applied measurement each at ``log_time``."""
        k, d = x.shape
        out = cls(np.zeros((k, float_columns(d))), np.zeros((k, len(INT_FIELDS)), dtype=np.int64), k, d)
        out.x = x
        out.P = P
        out.sums[:] = sums
        out.anchor[:] = x[:, :2]
        out.ids[:] = ids
        out.hits[:] = 1
        out.first_time[:] = log_time
        out.last_time[:] = log_time
        return out


class _Columns:
    """Take/concat over every array field of a dataclass (first axis = track)."""

    def _arrays(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}  # type: ignore[arg-type]

    def take(self: _C, index: npt.NDArray[Any]) -> _C:
        """The tracks selected by ``index`` (boolean mask or integer indices), in every array."""
        return type(self)(**{name: value[index] for name, value in self._arrays().items()})

    def concat(self: _C, other: _C) -> _C:
        """These tracks followed by ``other``'s, in every array."""
        theirs = other._arrays()
        return type(self)(
            **{name: np.concatenate((value, theirs[name])) for name, value in self._arrays().items()}
        )


@dataclass
class FrameRows(_Columns):
    """What happened to each live track in the current frame (the per-frame output columns)."""

    innovation: Array  # (n, 2) px
    nis: Array
    measured: BoolArray  # a measurement was applied (or started the track)
    gated: BoolArray  # a measurement was associated and rejected by the gate
    meas: Array  # (n, 4): the associated centroid's x, y, sigma (floored), flux

    @classmethod
    def empty(cls, n: int) -> FrameRows:
        """``n`` tracks without an associated measurement."""
        return cls(innovation=np.zeros((n, 2)), nis=np.zeros(n), measured=np.zeros(n, dtype=bool),
                   gated=np.zeros(n, dtype=bool), meas=np.zeros((n, 4)))

    @classmethod
    def born(cls, meas: Array) -> FrameRows:
        """Rows of tracks started by the centroids ``meas`` (x, y, sigma, flux)."""
        k = meas.shape[0]
        return cls(innovation=np.zeros((k, 2)), nis=np.zeros(k), measured=np.ones(k, dtype=bool),
                   gated=np.zeros(k, dtype=bool), meas=meas)
