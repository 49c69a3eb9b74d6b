"""Multi-star tracking across frames: association, track life cycle, per-track statistics.

:class:`StarTracker` is fed one frame at a time (``update(log_time, x, y, sigma, flux)``,
plain numpy arrays of the frame's centroids) and returns one :data:`TRACK_DTYPE` row per
live track. Each frame:

1. **Predict** every live track to the frame's ``log_time`` with the batched UKF
   (:mod:`starlog.tracking.ukf`); ``dt`` is the ``log_time`` difference to the previous frame
   (int ns → s), so irregular frame intervals are handled exactly.
2. **Associate** centroids to tracks by an optimal assignment
   (:func:`scipy.optimize.linear_sum_assignment`) minimising the total squared Mahalanobis
   distance ``d² = νᵀ (P_pos + R)⁻¹ ν`` over admissible pairs. A pair is admissible when the
   centroid lies within ``association_radius`` px of the predicted position *or* inside the
   innovation gate (``d²`` below the chi-square(2) threshold of ``gate_probability``). With
   ``max_distance`` set, a pair is admissible instead when the centroid lies within that many
   px of the track's filtered position at its last applied measurement (where its star was
   last seen), however far the prediction has coasted since. The assignment first maximises
   the number of admissible pairs, then minimises ``d²``.
3. **Update** the associated tracks (one batched UKF update). The innovation gate then
   decides: a measurement with ``NIS > threshold`` is a transient outlier, is not applied,
   and the row is flagged ``gated`` (the track coasts on its prediction). Because the
   association window is wider than the gate (a few px against a few sigma), a one-frame
   outlier near a star is caught by the gate instead of starting a spurious track.
   Outliers are *transient*: after ``max_gated`` (default 5) consecutive gated frames the
   gate is taken to be rejecting a real change (motion the model does not expect, or a
   centroid ``sigma`` that understates the true scatter), and the next associated
   measurement is applied whatever its NIS (``measured`` true, ``nis`` above the threshold),
   so a track is never frozen for good.
4. **Start** a track for every unassociated centroid, in row-major order of position
   (ascending ``y``, then ``x``), so ids do not depend on the order of centroids in the frame:
   the same input always gives the same ids. Ids are 0, 1, 2 … and never reused. A new track's
   state is the centroid (velocity and acceleration 0) with
   :func:`~starlog.tracking.models.initial_covariance`.
5. **Life cycle.** A track is *confirmed* once it has ``confirm_hits`` applied measurements
   (default 3, birth included). A frame without an applied measurement (no centroid
   associated, or the one associated was gated) is a miss (the ``missed`` count). A
   tentative (unconfirmed) track is dropped at its first miss. A confirmed track keeps its
   id through up to ``max_missed`` (default 10) consecutive frames *without an associated
   centroid*, is re-acquired when its star comes back inside the association window, and
   is lost (dropped, id retired) at the ``max_missed + 1``-th such frame; gated frames keep
   a confirmed track alive (its star is there). Frames with no centroids at all are
   ordinary misses.

"The brightest star's track" (the paper's sequence, §2.1): :meth:`StarTracker.brightest_track`.

Each frame runs as one compiled call (:func:`starlog.tracking.frame_kernel.track_frame`) on the live
tracks' tables (:class:`~starlog.tracking.state.TrackState`); the numpy steps
(:mod:`starlog.tracking.frame_steps`, ``StarTracker(vectorised=True)``) are its reference, and take a frame
over where the call hands it back: an assignment with a choice to make (solved with scipy here) or a covariance to repair.
:meth:`StarTracker.update_block` runs the frames of a block into one row table.

Coordinates: x = column, y = row, px, (0, 0) at the centre of the top-left pixel; times are
int ns ``log_time``.

The options are :class:`~starlog.tracking.tracker_config.TrackerConfig`.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidInputError, InvalidParameterError, StarlogError
from starlog.tracking.frame_steps import (
    BAD_SIGMA,
    NON_FINITE,
    Centroids,
    apply_measurements,
    associate,
    count_frame,
    frame_arrays,
    frame_columns,
    stats_rows,
    track_rows,
)
from starlog.tracking.models import MotionModel, discretize, initial_covariance, state_dim
from starlog.tracking.state import FrameRows, TrackState
from starlog.tracking.table import TRACK_DTYPE
from starlog.tracking.tracker_config import TrackerConfig
from starlog.tracking.ukf import gate_threshold, ukf_predict

__all__ = ["TrackerConfig", "StarTracker", "NoTrackError", "track_centroids"]

Array = npt.NDArray[np.float64]


class NoTrackError(StarlogError, LookupError):
    """No track satisfies the request (e.g. no confirmed track yet for the brightest star)."""


class StarTracker:
    """Track every star of a centroid stream with a batched UKF (see module docstring).

    Parameters
    ----------
    config : TrackerConfig, optional
        All options; keyword arguments override its fields, e.g.
        ``StarTracker(model="CONSTANT_VELOCITY", max_missed=5)``.
    vectorised : bool
        Run each frame as numpy steps over all tracks (the reference of the tests) instead of
        one compiled call (:mod:`starlog.tracking.frame_kernel`, the default: the same tracks, the
        same numbers to rounding). The compiled call hands a frame to the numpy steps where
        they do what it does not: an assignment with a choice to make, a covariance to repair.
    **options
        Fields of :class:`TrackerConfig`.

    Examples
    --------
    >>> import numpy as np
    >>> tracker = StarTracker(model="STATIC")
    >>> rows = tracker.update(0, np.array([10.0]), np.array([20.0]), np.array([0.1]),
    ...                       np.array([5e4]))
    >>> rows["track"].tolist(), rows["measured"].tolist()
    ([0], [True])
    """

    def __init__(self, config: TrackerConfig | None = None, *, vectorised: bool = False,
                 **options: Any) -> None:
        base = TrackerConfig() if config is None else config
        try:
            self.config = replace(base, **options) if options else base
        except TypeError as err:
            raise InvalidParameterError(f"unknown StarTracker option: {err}.") from err
        cfg = self.config
        self.model = MotionModel.parse(cfg.model)
        self._d = state_dim(self.model)
        self._threshold = gate_threshold(cfg.gate_probability)
        self._cache: dict[int, tuple[Array, Array]] = {}
        self._last_time: int | None = None
        self._next_id = 0
        self.frames = 0
        self._tracks = TrackState.empty(self._d)  # live tracks, sorted by id
        self._lost: list[npt.NDArray[np.void]] = []
        self.vectorised = bool(vectorised)
        self._step = None if self.vectorised else _CompiledStep(self)

    # ------------------------------------------------------------------ properties
    @property
    def n_live(self) -> int:
        """Number of live tracks (tentative and confirmed)."""
        return len(self._tracks)

    @property
    def last_log_time(self) -> int | None:
        """``log_time`` of the last frame given to :meth:`update` (None before the first)."""
        return self._last_time

    # ------------------------------------------------------------------ one frame, step by step
    def _transition(self, dt_ns: int) -> tuple[Array, Array]:
        hit = self._cache.get(dt_ns)
        if hit is None:
            F, Q = discretize(self.model, dt_ns * 1e-9, config=self.config.motion)
            if len(self._cache) >= 1024:
                self._cache.clear()
            hit = self._cache[dt_ns] = (np.ascontiguousarray(F.T), Q)
        return hit

    def _frame_time(self, log_time: int) -> int:
        if isinstance(log_time, bool) or not isinstance(log_time, (int, np.integer)):
            raise InvalidInputError(f"log_time must be an integer (ns), got {log_time!r}.")
        t = int(log_time)
        if self._last_time is not None and t <= self._last_time:
            raise InvalidInputError(
                f"log_time must increase from frame to frame: got {t} after {self._last_time}."
            )
        return t

    def _predict(self, t: int) -> None:
        """Step 1: every live track's prior at ``t``."""
        tracks = self._tracks
        if len(tracks):
            assert self._last_time is not None
            Ft, Q = self._transition(t - self._last_time)
            tracks.x, tracks.P = ukf_predict(
                tracks.x, tracks.P, fx=lambda s: np.matmul(s, Ft), Q=Q, points=self.config.points
            )

    def _retire_lost(self, rows: FrameRows) -> FrameRows:
        """Step 5: drop lost tracks (before births, so that new ids follow the old ones)."""
        cfg = self.config
        tracks = self._tracks
        confirmed = tracks.hits >= cfg.confirm_hits
        lost = np.where(confirmed, tracks.coast > cfg.max_missed, tracks.missed > 0)
        if not lost.any():
            return rows
        self._lost.append(stats_rows(tracks.take(lost), self.config.confirm_hits, alive=False))
        keep = ~lost
        self._tracks = tracks.take(keep)
        return rows.take(keep)

    def _start_tracks(
        self, t: int, c: Centroids, mj: npt.NDArray[np.intp], rows: FrameRows
    ) -> FrameRows:
        """Step 4: a track per unassociated centroid, in row-major order of position."""
        free = np.ones(c.x.size, dtype=bool)
        free[mj] = False
        if not free.any():
            return rows
        new = np.flatnonzero(free)
        new = new[np.lexsort((c.x[new], c.y[new]))]
        k = new.size
        state = np.zeros((k, self._d))
        state[:, 0] = c.x[new]
        state[:, 1] = c.y[new]
        born = TrackState.born(
            ids=np.arange(self._next_id, self._next_id + k),
            x=state,
            P=initial_covariance(self.model, c.sigma[new], config=self.config.motion),
            log_time=t,
            sums=np.stack((c.flux[new], c.x[new], c.y[new]), 1),
        )
        self._next_id += k
        self._tracks = self._tracks.concat(born)
        return rows.concat(
            FrameRows.born(np.stack((c.x[new], c.y[new], c.sigma[new], c.flux[new]), 1))
        )

    # ------------------------------------------------------------------ public API
    def update(
        self,
        log_time: int,
        x: npt.ArrayLike,
        y: npt.ArrayLike,
        sigma: npt.ArrayLike,
        flux: npt.ArrayLike,
    ) -> npt.NDArray[np.void]:
        """Process one frame's centroids and return the state of every live track.

        Parameters
        ----------
        log_time : int
            Frame time, int ns; strictly increasing from call to call.
        x, y : (m,) array_like
            Centroid column and row, px (pixel-centre origin); ``m`` may be 0.
        sigma : (m,) array_like
            Each centroid's own uncertainty, px, >= 0 (``sigma_floor`` applies);
            ``R = diag(sigma², sigma²)``.
        flux : (m,) array_like
            Each centroid's flux (any unit; used for the per-track statistics).

        Returns
        -------
        (n_live,) ndarray of TRACK_DTYPE
            One row per live track (tentative ones included, see ``confirmed``), sorted by
            ``track``; rows of tracks lost in this frame are not included.

        Raises
        ------
        InvalidInputError
            On arrays of unequal length, non-finite values, negative ``sigma``, or a
            ``log_time`` that does not increase.
        """
        t = self._frame_time(log_time)
        if self._step is None:
            return self._frame_steps(t, self._centroids(*frame_arrays(x, y, sigma, flux)))
        columns = frame_columns(x, y, sigma, flux)
        cents = np.empty((columns[0].size, 4))
        for k, column in enumerate(columns):
            cents[:, k] = column
        out = np.empty(len(self._tracks) + cents.shape[0], dtype=TRACK_DTYPE)
        return out[: self._step.frame(t, cents, out)]

    def update_block(
        self, log_time: npt.ArrayLike, counts: npt.ArrayLike, table: npt.ArrayLike
    ) -> tuple[npt.NDArray[np.void], npt.NDArray[np.int64]]:
        """Process the frames of a block in turn, each as :meth:`update` does.

        Parameters
        ----------
        log_time : (f,) array_like of int
            Each frame's time, int ns; strictly increasing.
        counts : (f,) array_like of int
            Each frame's number of centroids.
        table : (k, 4) array_like
            The centroids of the frames in turn, ``k = sum(counts)``: x, y, sigma, flux (as
            :meth:`update`'s arrays).

        Returns
        -------
        rows : (r,) ndarray of TRACK_DTYPE
            The rows :meth:`update` returns for each frame, the frames in turn.
        row_counts : (f,) ndarray of int64
            Each frame's number of rows.

        Raises
        ------
        InvalidInputError
            As :meth:`update`, at the frame concerned (the frames before it are processed); on a
            table of another shape than ``(sum(counts), 4)``.
        """
        times = np.asarray(log_time, dtype=np.int64)
        sizes = np.asarray(counts, dtype=np.int64)
        cents = np.ascontiguousarray(table, dtype=np.float64)
        if (times.ndim != 1 or sizes.shape != times.shape or (sizes < 0).any()
                or cents.shape != (int(sizes.sum()), 4)):
            raise InvalidInputError(
                "log_time and counts must be 1-D arrays of one length (one entry per frame) and table "
                f"(sum(counts), 4), got shapes {times.shape}, {sizes.shape}, {cents.shape}."
            )
        ends = np.cumsum(sizes).tolist()
        frames = list(zip(times.tolist(), [0, *ends][:-1], ends, strict=True))
        if self._step is not None:
            return self._step.block(frames, cents)
        out = [self.update(t, cents[a:b, 0], cents[a:b, 1], cents[a:b, 2], cents[a:b, 3])
               for t, a, b in frames]
        rows = np.empty(sum(r.size for r in out), dtype=TRACK_DTYPE)
        if out:
            np.concatenate(out, out=rows)  # with ``out``, no promotion of the record dtypes of each pair
        return rows, np.array([r.size for r in out], dtype=np.int64)

    def _centroids(self, x: Array, y: Array, sigma: Array, flux: Array) -> Centroids:
        sigmas = np.maximum(sigma, self.config.sigma_floor)
        return Centroids(x, y, sigmas, flux, sigmas * sigmas)

    def _frame_steps(self, t: int, c: Centroids) -> npt.NDArray[np.void]:
        """One frame as numpy steps over all tracks."""
        self._predict(t)
        self._last_time = t
        self.frames += 1
        ti, mj = associate(self._tracks, c, self.config, self._threshold)
        return self._finish_steps(t, c, ti, mj)

    def _finish_steps(self, t: int, c: Centroids, ti: npt.NDArray[np.intp],
                      mj: npt.NDArray[np.intp]) -> npt.NDArray[np.void]:
        """The numpy steps of a frame after its association."""
        rows, associated = apply_measurements(self._tracks, t, c, ti, mj, self.config, self._threshold)
        count_frame(self._tracks, rows, associated)
        rows = self._retire_lost(rows)
        rows = self._start_tracks(t, c, mj, rows)
        return track_rows(self._tracks, rows, self.config.confirm_hits)

    def track_stats(self) -> npt.NDArray[np.void]:
        """Summary of every track started so far (live and lost), sorted by id.

        Returns
        -------
        ndarray of TRACK_STATS_DTYPE
        """
        live = stats_rows(self._tracks, self.config.confirm_hits, alive=True)
        out = np.concatenate([*self._lost, live]) if self._lost else live
        return out[np.argsort(out["track"], kind="stable")]

    def brightest_track(self, *, min_hits_fraction: float = 0.9) -> int:
        """Id of "the brightest star's track" (the paper's centroid sequence, §2.1).

        Rule: among *confirmed* tracks (live or lost), keep those with at least
        ``min_hits_fraction`` times the largest number of associated measurements (applied
        or gated) of any confirmed track (so a star seen in nearly every frame beats a brief
        bright transient); of those, return the one with the highest mean flux over its
        applied measurements; ties go to the smaller id. Gated measurements count as seen:
        a model that rejects many measurements of a bright star (STATIC under platform
        jitter with a small ``sigma``) must still pick the same star as the other models.

        Parameters
        ----------
        min_hits_fraction : float
            In (0, 1]; 1.0 keeps only the tracks with the most measurements.

        Returns
        -------
        int
            The track id.

        Raises
        ------
        NoTrackError
            When no track is confirmed yet.
        """
        if not (0.0 < float(min_hits_fraction) <= 1.0):
            raise InvalidParameterError(
                f"min_hits_fraction must be in (0, 1], got {min_hits_fraction!r}."
            )
        stats = self.track_stats()
        stats = stats[stats["confirmed"]]
        if stats.size == 0:
            raise NoTrackError(
                f"no confirmed track after {self.frames} frames (a track is confirmed after "
                f"{self.config.confirm_hits} applied measurements)."
            )
        seen = stats["hits"] + stats["gated"]
        need = min_hits_fraction * seen.max()
        cand = stats[seen >= need - 1e-9]
        best = np.lexsort((cand["track"], -cand["mean_flux"]))[0]
        return int(cand["track"][best])


class _CompiledStep:
    """The frames of a :class:`StarTracker` as one compiled call each (:func:`starlog.tracking.frame_kernel.track_frame`)
    on its track tables, the numpy steps taking over where the call hands back."""

    def __init__(self, tracker: StarTracker) -> None:
        # numba: imported, and compiled, on first use
        from starlog.tracking.frame_kernel import Status, finish_frame, parameters, track_frame

        cfg = tracker.config
        d = tracker._d
        _, wc = cfg.points.weights(d)
        self.tracker = tracker
        self.status, self.track_frame, self.finish_frame = Status, track_frame, finish_frame
        self.fpar, self.ipar = parameters(
            scale=cfg.points.scale(d), wc0=wc[0], wi=wc[1], gate=tracker._threshold,
            radius2=cfg.association_radius**2,
            max_distance2=-1.0 if cfg.max_distance is None else cfg.max_distance**2,
            floor=cfg.sigma_floor, velocity_var=cfg.motion.init_velocity_sigma**2,
            acceleration_var=cfg.motion.init_acceleration_sigma**2, confirm_hits=cfg.confirm_hits,
            max_missed=cfg.max_missed, max_gated=cfg.max_gated)
        self.still = (np.eye(d), np.zeros((d, d)))  # Fᵀ and Q when there is no track (not used)
        self.lost = TrackState.empty(d)  # where the call copies the tracks it drops

    def frame(self, t: int, cents: Array, out: npt.NDArray[np.void]) -> int:
        """The frame at ``t`` with the centroids ``cents`` ((m, 4) x, y, sigma, flux), its rows written to
        ``out`` (room for ``n_live + m``); returns their number."""
        tr, lost = self.tracker, self.lost
        tracks = tr._tracks
        n = tracks.n
        if tracks.floats.shape[0] < n + cents.shape[0] or lost.floats.shape[0] < n:  # room for births, losses
            tracks.reserve(n + cents.shape[0])
            lost.reserve(tracks.floats.shape[0])
        ft, q = tr._transition(t - tr._last_time) if n else self.still
        status, rows, n_lost, born = self.track_frame(tracks.floats, tracks.ints, n, cents, t, tr._next_id, ft, q,
                                                      self.fpar, self.ipar, out, lost.floats, lost.ints)
        if status:
            return self._handed_back(status, t, cents, out)
        tr._last_time = t
        tr.frames += 1
        return self._done(rows, n_lost, born)

    def _done(self, rows: int, n_lost: int, born: int) -> int:
        """The call's bookkeeping after a frame: the live tracks, the next id, the lost tracks' statistics."""
        tr = self.tracker
        tr._tracks.n = rows
        tr._next_id += born
        if n_lost:
            self.lost.n = n_lost
            tr._lost.append(stats_rows(self.lost, tr.config.confirm_hits, alive=False))
            self.lost.n = 0
        return int(rows)

    def _handed_back(self, status: int, t: int, cents: Array, out: npt.NDArray[np.void]) -> int:
        """The frame after the call handed it back (``status``): an error, or the numpy steps' turn."""
        tr, code = self.tracker, self.status
        if status == code.BAD_VALUES:
            raise InvalidInputError(NON_FINITE)
        if status == code.BAD_SIGMA:
            raise InvalidInputError(BAD_SIGMA)
        c = tr._centroids(*cents.T)
        if status == code.REPAIR_PREDICT:
            return _copied(tr._frame_steps(t, c), out)
        tr._last_time = t  # the tracks are predicted
        tr.frames += 1
        ti, mj = associate(tr._tracks, c, tr.config, tr._threshold)
        if status == code.ASSIGN:
            tracks, lost = tr._tracks, self.lost
            status, rows, n_lost, born = self.finish_frame(
                tracks.floats, tracks.ints, tracks.n, tr._d, cents, t, tr._next_id, ti, mj, self.fpar, self.ipar,
                out, lost.floats, lost.ints)
            if status == code.DONE:
                return self._done(rows, n_lost, born)
        return _copied(tr._finish_steps(t, c, ti, mj), out)  # REPAIR_UPDATE

    def block(self, frames: list[tuple[int, int, int]],
              cents: Array) -> tuple[npt.NDArray[np.void], npt.NDArray[np.int64]]:
        """:meth:`StarTracker.update_block` of the frames ``(log_time, first, end)`` of ``cents``, their rows
        written to one table (grown when births need more room)."""
        tr = self.tracker
        out = np.empty(len(frames) * len(tr._tracks) + cents.shape[0], dtype=TRACK_DTYPE)
        row_counts = []
        pos = 0
        for t, a, b in frames:
            end = pos + len(tr._tracks) + b - a
            if end > out.size:
                grown = np.empty(max(end, 2 * out.size), dtype=TRACK_DTYPE)
                grown[:pos] = out[:pos]
                out = grown
            row_counts.append(self.frame(tr._frame_time(t), cents[a:b], out[pos:end]))
            pos += row_counts[-1]
        return out[:pos], np.array(row_counts, dtype=np.int64)


def _copied(rows: npt.NDArray[np.void], out: npt.NDArray[np.void]) -> int:
    """``rows`` copied to the start of ``out``; their number."""
    out[: rows.size] = rows
    return int(rows.size)


def track_centroids(
    log_time: npt.ArrayLike,
    x: npt.ArrayLike,
    y: npt.ArrayLike,
    sigma: npt.ArrayLike,
    flux: npt.ArrayLike,
    *,
    config: TrackerConfig | None = None,
    frame_times: npt.ArrayLike | None = None,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.void], StarTracker]:
    """Track a whole centroid table (one row per centroid) frame by frame.

    Parameters
    ----------
    log_time : (k,) array_like of int
        Frame time of each centroid, ns; rows of one frame share it.
    x, y, sigma, flux : (k,) array_like
        Centroid columns (see :meth:`StarTracker.update`).
    config : TrackerConfig, optional
        Tracker options.
    frame_times : array_like of int, optional
        Every frame's ``log_time`` (ns), so that frames without centroids are processed
        too; by default the distinct values of ``log_time``.

    Returns
    -------
    row_time : (r,) ndarray of int64
        ``log_time`` of each output row.
    rows : (r,) ndarray of TRACK_DTYPE
        The concatenated per-frame outputs.
    tracker : StarTracker
        The tracker after the last frame (for :meth:`StarTracker.brightest_track`).
    """
    t = np.asarray(log_time, dtype=np.int64)
    xs, ys, sigmas, fluxes = frame_arrays(x, y, sigma, flux)
    if t.shape != xs.shape:
        raise InvalidInputError(f"log_time must have shape {xs.shape}, got {t.shape}.")
    frames = np.unique(t) if frame_times is None else np.unique(np.asarray(frame_times, np.int64))
    order = np.argsort(t, kind="stable")
    ts = t[order]
    starts = np.searchsorted(ts, frames, side="left")
    stops = np.searchsorted(ts, frames, side="right")
    tracker = StarTracker(config)
    times: list[npt.NDArray[np.int64]] = []
    outs: list[npt.NDArray[np.void]] = []
    for ft, a, b in zip(frames.tolist(), starts.tolist(), stops.tolist(), strict=True):
        idx = order[a:b]
        rows = tracker.update(ft, xs[idx], ys[idx], sigmas[idx], fluxes[idx])
        outs.append(rows)
        times.append(np.full(rows.size, ft, dtype=np.int64))
    if not outs:
        return np.zeros(0, np.int64), np.zeros(0, TRACK_DTYPE), tracker
    return np.concatenate(times), np.concatenate(outs), tracker
