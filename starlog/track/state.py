"""Per-track arrays of :class:`~starlog.track.StarTracker`, held together so they stay in step.

Each structure is a dataclass of numpy arrays whose first axis is the track (one entry per live
track, sorted by id). :meth:`_Columns.take` selects tracks and :meth:`_Columns.concat` appends
new ones, for every array at once: no array can be forgotten when tracks are dropped or born.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

__all__ = ["TrackState", "FrameRows"]

Array = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]
_C = TypeVar("_C", bound="_Columns")


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
class TrackState(_Columns):
    """Filter state, life-cycle counters and running sums of the live tracks."""

    ids: IntArray
    x: Array  # (n, d) state means
    P: Array  # (n, d, d) state covariances
    hits: IntArray  # applied measurements, birth included
    missed: IntArray  # consecutive frames without an applied measurement
    coast: IntArray  # consecutive frames without an associated centroid
    gated_streak: IntArray  # consecutive gated frames
    age: IntArray  # frames since birth
    gated: IntArray  # gated measurements in all
    first_time: IntArray  # log_time of birth, ns
    last_time: IntArray  # log_time of the last applied measurement, ns
    sums: Array  # (n, 3): flux, x, y summed over applied measurements
    anchor: Array  # (n, 2): x, y of the filtered position at the last applied measurement

    def __len__(self) -> int:
        return int(self.ids.size)

    @classmethod
    def empty(cls, d: int) -> TrackState:
        """No track, states of dimension ``d``."""
        def ints() -> IntArray:
            return np.zeros(0, dtype=np.int64)

        return cls(ids=ints(), x=np.zeros((0, d)), P=np.zeros((0, d, d)), hits=ints(), missed=ints(),
                   coast=ints(), gated_streak=ints(), age=ints(), gated=ints(), first_time=ints(),
                   last_time=ints(), sums=np.zeros((0, 3)), anchor=np.zeros((0, 2)))

    @classmethod
    def born(cls, ids: IntArray, x: Array, P: Array, log_time: int, sums: Array) -> TrackState:
        """New tracks started by one applied measurement each at ``log_time``."""
        k = ids.size

        def zeros() -> IntArray:
            return np.zeros(k, dtype=np.int64)

        return cls(ids=ids, x=x, P=P, hits=np.ones(k, dtype=np.int64), missed=zeros(), coast=zeros(),
                   gated_streak=zeros(), age=zeros(), gated=zeros(),
                   first_time=np.full(k, log_time, dtype=np.int64),
                   last_time=np.full(k, log_time, dtype=np.int64), sums=sums, anchor=x[:, :2].copy())


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
