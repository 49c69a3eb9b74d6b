"""Compiled (numba) frame step of :class:`~starlog.tracking.StarTracker`: every live track in one call.

The numpy steps of the tracker (``StarTracker(vectorised=True)``) spend their time in the fixed cost
of dozens of small array operations a frame, not in arithmetic: a frame holds tens of stars of 2-6
state variables. :func:`track_frame` does the whole frame in one call on the tables of
:class:`~starlog.tracking.state.TrackState` (floats: ``x``, ``P`` row by row, ``sums``, ``anchor``;
integers: the columns named below, in the order of :data:`~starlog.tracking.state.INT_FIELDS`):
validate the centroids; predict every track (Merwe sigma points from a Cholesky factor through the
motion model and the unscented transform, as :func:`~starlog.tracking.ukf.ukf_predict`, computed from
the points' offsets from their mean); associate; update the associated tracks behind the innovation
gate (as :func:`~starlog.tracking.ukf.ukf_update`); count; retire the lost tracks; start new ones; write
the :data:`~starlog.tracking.TRACK_DTYPE` rows. The numpy steps are the
reference the tests compare it with, and it hands over to them where they do what is not compiled:

* an association with a choice to make. When every admissible (track, centroid) pair is the only
  admissible pair of its track and of its centroid, every optimal assignment holds all of them (one
  left out could replace a pair at the inadmissible cost, for less), so no solver is needed.
  Otherwise the step stops after the prediction (:data:`ASSIGN`); the caller solves the assignment
  with scipy as the numpy step does and calls :func:`finish_frame`;
* a covariance that rounding made indefinite, which the numpy step repairs (an eigenvalue floor):
  the step stops before that step changes anything (:data:`REPAIR_PREDICT`,
  :data:`REPAIR_UPDATE`) and the caller takes the numpy steps.

The numbers agree with the numpy steps to rounding, not bit for bit: numpy's matrix products sum in
another order, and its prediction forms the sigma points ``x ± L[:, i]`` before subtracting their
mean, which rounds the offsets to the precision of ``x`` (a few 1e-14 px at 500 px). The association's
tests are the numpy step's very expressions. One module, as
numba's cache is refreshed when a function's own file changes, not when a function it calls in
another file does. Compiled on first use and cached beside this file (``__pycache__``), or in numba's
user cache when the package folder is read-only. Divisions follow numpy (``error_model="numpy"``).
"""

from __future__ import annotations

import enum
import math

import numpy as np
import numpy.typing as npt
from numba import njit

INT_COLUMNS = ("ids", "hits", "missed", "coast", "gated_streak", "age", "gated", "first_time", "last_time")
"""The integer table's columns as this module reads them (the tests check them against ``INT_FIELDS``)."""
_IDS, _HITS, _MISSED, _COAST, _STREAK, _AGE, _GATED, _FIRST, _LAST = range(9)

#: Statuses of :func:`track_frame` and :func:`finish_frame`: done; a non-finite x, y or flux; a sigma < 0 or
#: inf; a prior covariance needs the numpy repair (nothing changed); the association has a choice to make
#: (tracks predicted); an updated covariance needs the numpy repair (tracks predicted, nothing else changed).
DONE, BAD_VALUES, BAD_SIGMA, REPAIR_PREDICT, ASSIGN, REPAIR_UPDATE = range(6)


class Status(enum.IntEnum):
    """The statuses above, for the caller."""

    DONE = DONE
    BAD_VALUES = BAD_VALUES
    BAD_SIGMA = BAD_SIGMA
    REPAIR_PREDICT = REPAIR_PREDICT
    ASSIGN = ASSIGN
    REPAIR_UPDATE = REPAIR_UPDATE


#: Float parameters (``fpar``): sigma-point scale ``d + lambda``; covariance weights Wc0 (the centre point) and
#: Wi (the others, also their mean weight: the centre point's offset from ``x`` is 0, so its mean weight does
#: not enter); gate threshold; association radius²; max_distance² (< 0: none); sigma floor; initial velocity
#: and acceleration variances.
F_SCALE, F_WC0, F_WI, F_GATE, F_RADIUS2, F_MAXDIST2, F_FLOOR, F_VEL_VAR, F_ACC_VAR = range(9)
#: Integer parameters (``ipar``): confirm_hits, max_missed, max_gated.
I_CONFIRM, I_MAX_MISSED, I_MAX_GATED = range(3)


def parameters(*, scale: float, wc0: float, wi: float, gate: float, radius2: float,
               max_distance2: float, floor: float, velocity_var: float, acceleration_var: float,
               confirm_hits: int, max_missed: int, max_gated: int
               ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
    """``(fpar, ipar)`` of :func:`track_frame` from the tracker's options (``max_distance2 < 0``: none)."""
    fpar = np.empty(9)
    fpar[F_SCALE], fpar[F_WC0], fpar[F_WI] = scale, wc0, wi
    fpar[F_GATE], fpar[F_RADIUS2], fpar[F_MAXDIST2], fpar[F_FLOOR] = gate, radius2, max_distance2, floor
    fpar[F_VEL_VAR], fpar[F_ACC_VAR] = velocity_var, acceleration_var
    ipar = np.empty(3, dtype=np.int64)
    ipar[I_CONFIRM], ipar[I_MAX_MISSED], ipar[I_MAX_GATED] = confirm_hits, max_missed, max_gated
    return fpar, ipar

# per-track values of the frame (``fr``): innovation x, y; NIS; the associated centroid's x, y, sigma, flux
_NU_X, _NU_Y, _NIS, _MEAS_X, _MEAS_Y, _MEAS_S, _MEAS_F = range(7)
_ASSOCIATED, _MEASURED = 1, 2  # bits of ``flag``


@njit(cache=True, nogil=True, error_model="numpy")
def _cholesky(fs, k, d, scale, low):  # type: ignore[no-untyped-def]
    """Lower Cholesky factor of ``scale * P`` of track ``k`` into ``low``; False if not positive definite."""
    for r in range(d):
        for s in range(r + 1):
            acc = scale * fs[k, d + r * d + s]
            for q in range(s):
                acc -= low[r, q] * low[s, q]
            if r == s:
                if not (acc > 0.0 and acc < math.inf):
                    return False
                low[r, r] = math.sqrt(acc)
            else:
                low[r, s] = acc / low[s, s]
        for s in range(r + 1, d):
            low[r, s] = 0.0
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def _factor_all(fs, tracks, count, d, scale, lows):  # type: ignore[no-untyped-def]
    """The factors of the tracks ``tracks[:count]``; False when one is not positive definite."""
    for i in range(count):
        if not _cholesky(fs, tracks[i], d, scale, lows[i]):
            return False
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def _predict_track(fs, k, d, low, ft, q, wi, fl, fx):  # type: ignore[no-untyped-def]
    """Prior of track ``k`` in place: the unscented transform of the sigma points ``x ± L[:, i]`` through the
    linear ``F``, from their offsets ``± F L[:, i]`` from ``F x`` (their weighted mean: the weights sum to 1):
    mean ``F x``, covariance ``Σ 2 Wi (F L[:, i]) (F L[:, i])ᵀ + Q`` (exactly symmetric). ``fl``, ``fx``:
    scratch (d, d) and (d,)."""
    for r in range(d):
        acc = 0.0
        for c in range(d):
            acc += fs[k, c] * ft[c, r]
        fx[r] = acc
        for i in range(d):
            acc = 0.0
            for c in range(d):
                acc += low[c, i] * ft[c, r]
            fl[r, i] = acc
    w2 = 2.0 * wi
    for a in range(d):
        fs[k, a] = fx[a]
        for b in range(a + 1):
            acc = 0.0
            for i in range(d):
                acc += fl[a, i] * fl[b, i]
            value = w2 * acc + q[a, b]
            fs[k, d + a * d + b] = value
            fs[k, d + b * d + a] = value


@njit(cache=True, nogil=True, error_model="numpy")
def _predict(fs, n, d, ft, q, fpar):  # type: ignore[no-untyped-def]
    """Every track's prior at this frame; False (nothing changed) when a factor needs the numpy repair."""
    tracks = np.arange(n)
    lows = np.empty((n, d, d))
    if not _factor_all(fs, tracks, n, d, fpar[F_SCALE], lows):
        return False
    fl = np.empty((d, d))
    fx = np.empty(d)
    for k in range(n):
        _predict_track(fs, k, d, lows[k], ft, q, fpar[F_WI], fl, fx)
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def _check(cx, cy, cs, cf):  # type: ignore[no-untyped-def]
    """:data:`BAD_VALUES` for a non-finite x, y or flux, :data:`BAD_SIGMA` for a sigma < 0 or inf."""
    for j in range(cx.size):
        if not (math.isfinite(cx[j]) and math.isfinite(cy[j]) and math.isfinite(cf[j])):
            return BAD_VALUES
    for j in range(cx.size):
        if not (cs[j] >= 0.0 and cs[j] < math.inf):
            return BAD_SIGMA
    return DONE


@njit(cache=True, nogil=True, error_model="numpy")
def _mahalanobis2(fs, k, d, j, cx, cy, var):  # type: ignore[no-untyped-def]
    """``d² = νᵀ (P_pos + R)⁻¹ ν`` of track ``k`` and centroid ``j``, the numpy step's very expression."""
    nx = cx[j] - fs[k, 0]
    ny = cy[j] - fs[k, 1]
    a = fs[k, d] + var[j]
    b = fs[k, d + 1]
    cc = fs[k, 2 * d + 1] + var[j]
    return (cc * nx * nx - 2.0 * b * nx * ny + a * ny * ny) / (a * cc - b * b)


@njit(cache=True, nogil=True, error_model="numpy")
def _admissible(fs, k, d, cx, cy, var, fpar, per_centroid):  # type: ignore[no-untyped-def]
    """Centroids admissible for track ``k`` (counted into ``per_centroid``): how many, and the last one.

    Admissible as in the numpy step: within the association radius or inside the gate of the predicted
    position, or, with ``max_distance``, within it of the anchor. One pass without branches, which the
    compiler vectorises."""
    px, py, p00, p01, p11 = fs[k, 0], fs[k, 1], fs[k, d], fs[k, d + 1], fs[k, 2 * d + 1]
    ax, ay = fs[k, d + d * d + 3], fs[k, d + d * d + 4]
    radius2, gate, limit2 = fpar[F_RADIUS2], fpar[F_GATE], fpar[F_MAXDIST2]
    found = 0
    last = -1
    for j in range(cx.size):
        nx = cx[j] - px
        ny = cy[j] - py
        a = p00 + var[j]
        cc = p11 + var[j]
        d2 = (cc * nx * nx - 2.0 * p01 * nx * ny + a * ny * ny) / (a * cc - p01 * p01)
        ex = cx[j] - ax
        ey = cy[j] - ay
        near = ((nx * nx + ny * ny) <= radius2) | (d2 <= gate)
        ok = np.int64(((ex * ex + ey * ey) <= limit2) if limit2 >= 0.0 else near)
        per_centroid[j] += ok
        found += ok
        last = max(last, ok * (j + 1) - 1)
    return found, last


@njit(cache=True, nogil=True, error_model="numpy")
def _pairs(fs, n, d, cx, cy, var, fpar, ti, mj):  # type: ignore[no-untyped-def]
    """The admissible pairs when each is the only one of its track and of its centroid: their number, the
    tracks in ``ti`` (ascending) and centroids in ``mj``; -1 when the assignment has a choice to make."""
    per_centroid = np.zeros(cx.size, dtype=np.int64)
    count = 0
    for k in range(n):
        found, last = _admissible(fs, k, d, cx, cy, var, fpar, per_centroid)
        if found > 1:
            return -1
        if found:
            ti[count] = k
            mj[count] = last
            count += 1
    largest = -math.inf
    for p in range(count):
        if per_centroid[mj[p]] > 1:
            return -1
        d2 = _mahalanobis2(fs, ti[p], d, mj[p], cx, cy, var)
        if math.isnan(d2):
            return -1
        largest = max(largest, d2)
    if count and not largest < 1e3 * (largest + 1.0):  # the numpy step's inadmissible cost
        return -1
    return count


@njit(cache=True, nogil=True, error_model="numpy")
def _update_track(fs, k, d, low, zx, zy, var, gate, w, work, out):  # type: ignore[no-untyped-def]
    """Gated UKF update of track ``k`` with ``z = (zx, zy)``, ``R = var I`` and weights ``w`` = (Wc0, Wi):
    writes ``out`` = (innovation x, y, NIS) and returns whether the measurement was applied (where it was not,
    the prior is kept). ``work`` = (Pxz, K, new P) scratch arrays.

    The sigma points' offsets from ``x`` are ``0`` and ``± L[:, i]``; their positions' offsets from the
    predicted measurement ``ẑ`` are those minus ``ẑ − h(x)``, as in :func:`~starlog.tracking.ukf.ukf_update`."""
    pxz, gain, pnew = work
    wc0, wi = w
    mh0, mh1 = _mean_offset(low, d, wi)
    s00 = wc0 * mh0 * mh0
    s01 = wc0 * mh0 * mh1
    s11 = wc0 * mh1 * mh1
    for r in range(d):
        pxz[r, 0] = 0.0
        pxz[r, 1] = 0.0
    for i in range(d):
        u0, u1 = low[0, i] - mh0, low[1, i] - mh1  # the +L[:, i] point
        v0, v1 = -low[0, i] - mh0, -low[1, i] - mh1  # the -L[:, i] point
        s00 += wi * u0 * u0 + wi * v0 * v0
        s01 += wi * u0 * u1 + wi * v0 * v1
        s11 += wi * u1 * u1 + wi * v1 * v1
        for r in range(d):
            pxz[r, 0] += low[r, i] * (wi * u0) - low[r, i] * (wi * v0)
            pxz[r, 1] += low[r, i] * (wi * u1) - low[r, i] * (wi * v1)
    s00 += var
    s11 += var
    det = s00 * s11 - s01 * s01
    i00, i01, i11 = s11 / det, -s01 / det, s00 / det
    nu0 = (zx - fs[k, 0]) - mh0
    nu1 = (zy - fs[k, 1]) - mh1
    sn0 = i00 * nu0 + i01 * nu1
    sn1 = i01 * nu0 + i11 * nu1
    out[0], out[1], out[2] = nu0, nu1, nu0 * sn0 + nu1 * sn1
    if not out[2] <= gate:
        return False
    for r in range(d):
        gain[r, 0] = pxz[r, 0] * i00 + pxz[r, 1] * i01
        gain[r, 1] = pxz[r, 0] * i01 + pxz[r, 1] * i11
    for r in range(d):
        for c in range(d):
            pnew[r, c] = fs[k, d + r * d + c] - (pxz[r, 0] * gain[c, 0] + pxz[r, 1] * gain[c, 1])
    for r in range(d):
        fs[k, r] += pxz[r, 0] * sn0 + pxz[r, 1] * sn1
    for r in range(d):
        for c in range(d):
            fs[k, d + r * d + c] = (pnew[r, c] + pnew[c, r]) * 0.5
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def _mean_offset(low, d, wi):  # type: ignore[no-untyped-def]
    """``ẑ − h(x)``: the weighted mean of the sigma points' position offsets (0 up to rounding)."""
    mh0 = 0.0
    mh1 = 0.0
    for q in range(d):
        mh0 += wi * low[0, q]
        mh1 += wi * low[1, q]
    for q in range(d):
        mh0 += wi * -low[0, q]
        mh1 += wi * -low[1, q]
    return mh0, mh1


@njit(cache=True, nogil=True, error_model="numpy")
def _apply(fs, ints, d, cx, cy, sf, cf, var, ti, mj, count, t, fpar, ipar, fr, flag):  # type: ignore[no-untyped-def]
    """Gated update of the associated tracks ``ti[:count]`` with the centroids ``mj[:count]``; False (nothing
    changed) when a factor needs the numpy repair. A track gated ``max_gated`` frames in a row has no gate."""
    lows = np.empty((count, d, d))
    if not _factor_all(fs, ti, count, d, fpar[F_SCALE], lows):
        return False
    work = (np.empty((d, 2)), np.empty((d, 2)), np.empty((d, d)))
    w = (fpar[F_WC0], fpar[F_WI])
    sums = d + d * d
    for p in range(count):
        k, j = ti[p], mj[p]
        gate = math.inf if ints[k, _STREAK] >= ipar[I_MAX_GATED] else fpar[F_GATE]
        applied = _update_track(fs, k, d, lows[p], cx[j], cy[j], var[j], gate, w, work, fr[k])
        fr[k, _MEAS_X], fr[k, _MEAS_Y], fr[k, _MEAS_S], fr[k, _MEAS_F] = cx[j], cy[j], sf[j], cf[j]
        flag[k] = _ASSOCIATED | (_MEASURED if applied else 0)
        if applied:
            ints[k, _HITS] += 1
            ints[k, _LAST] = t
            fs[k, sums] += cf[j]
            fs[k, sums + 1] += cx[j]
            fs[k, sums + 2] += cy[j]
            fs[k, sums + 3] = fs[k, 0]
            fs[k, sums + 4] = fs[k, 1]
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def _count(ints, n, flag):  # type: ignore[no-untyped-def]
    """Life-cycle counters after this frame's measurements."""
    for k in range(n):
        associated = (flag[k] & _ASSOCIATED) != 0
        measured = (flag[k] & _MEASURED) != 0
        if associated and not measured:
            ints[k, _GATED] += 1
            ints[k, _STREAK] += 1
        else:
            ints[k, _STREAK] = 0
        ints[k, _MISSED] = 0 if measured else ints[k, _MISSED] + 1
        ints[k, _COAST] = 0 if associated else ints[k, _COAST] + 1
        ints[k, _AGE] += 1


@njit(cache=True, nogil=True, error_model="numpy")
def _retire(fs, ints, n, ipar, fr, flag, lost_f, lost_i):  # type: ignore[no-untyped-def]
    """Drop the lost tracks (copied to ``lost_f``, ``lost_i``), the others kept in order with their frame
    values; returns (kept, lost). A tentative track is lost at its first miss, a confirmed one after
    ``max_missed`` frames without an associated centroid."""
    kept = 0
    lost = 0
    for k in range(n):
        if ints[k, _HITS] >= ipar[I_CONFIRM]:
            gone = ints[k, _COAST] > ipar[I_MAX_MISSED]
        else:
            gone = ints[k, _MISSED] > 0
        if gone:
            lost_f[lost] = fs[k]
            lost_i[lost] = ints[k]
            lost += 1
            continue
        if kept != k:
            fs[kept] = fs[k]
            ints[kept] = ints[k]
            fr[kept] = fr[k]
            flag[kept] = flag[k]
        kept += 1
    return kept, lost


@njit(cache=True, nogil=True, error_model="numpy")
def _start(fs, ints, at, d, cx, cy, sf, cf, free, t, next_id, fpar, fr, flag):  # type: ignore[no-untyped-def]
    """A track per free centroid, in row-major order of position (ascending y, then x; ties in input
    order), in rows ``at``, ``at + 1``, … with ids from ``next_id``; returns how many."""
    new = np.flatnonzero(free)
    by_x = new[np.argsort(cx[new], kind="mergesort")]
    new = by_x[np.argsort(cy[by_x], kind="mergesort")]
    for b in range(new.size):
        k, j = at + b, new[b]
        fs[k] = 0.0
        fs[k, 0], fs[k, 1] = cx[j], cy[j]
        for r in range(d):
            var = sf[j] * sf[j] if r < 2 else (fpar[F_VEL_VAR] if r < 4 else fpar[F_ACC_VAR])
            fs[k, d + r * d + r] = var
        sums = d + d * d
        fs[k, sums], fs[k, sums + 1], fs[k, sums + 2] = cf[j], cx[j], cy[j]
        fs[k, sums + 3], fs[k, sums + 4] = cx[j], cy[j]
        ints[k] = 0
        ints[k, _IDS] = next_id + b
        ints[k, _HITS] = 1
        ints[k, _FIRST] = t
        ints[k, _LAST] = t
        fr[k] = 0.0
        fr[k, _MEAS_X], fr[k, _MEAS_Y], fr[k, _MEAS_S], fr[k, _MEAS_F] = cx[j], cy[j], sf[j], cf[j]
        flag[k] = _MEASURED
    return new.size


@njit(cache=True, nogil=True, error_model="numpy")
def _write_rows(out, fs, ints, total, d, fr, flag, confirm):  # type: ignore[no-untyped-def]
    """The :data:`~starlog.tracking.TRACK_DTYPE` rows of the first ``total`` tracks."""
    for k in range(total):
        row = out[k]
        row["track"] = ints[k, _IDS]
        row["x"] = fs[k, 0]
        row["y"] = fs[k, 1]
        row["vx"] = fs[k, 2] if d >= 4 else 0.0
        row["vy"] = fs[k, 3] if d >= 4 else 0.0
        row["cov_xx"] = fs[k, d]
        row["cov_xy"] = fs[k, d + 1]
        row["cov_yy"] = fs[k, 2 * d + 1]
        row["innovation_x"] = fr[k, _NU_X]
        row["innovation_y"] = fr[k, _NU_Y]
        row["nis"] = fr[k, _NIS]
        measured = (flag[k] & _MEASURED) != 0
        row["measured"] = measured
        row["gated"] = (flag[k] & _ASSOCIATED) != 0 and not measured
        row["meas_x"] = fr[k, _MEAS_X]
        row["meas_y"] = fr[k, _MEAS_Y]
        row["meas_sigma"] = fr[k, _MEAS_S]
        row["flux"] = fr[k, _MEAS_F]
        row["age"] = ints[k, _AGE]
        row["missed"] = ints[k, _MISSED]
        row["confirmed"] = ints[k, _HITS] >= confirm
        row["hits"] = ints[k, _HITS]


@njit(cache=True, nogil=True, error_model="numpy")
def _floored(cs, floor):  # type: ignore[no-untyped-def]
    """The centroids' sigma raised to the floor, and its square (``R``'s diagonal)."""
    sf = np.maximum(cs, floor)
    return sf, sf * sf


@njit(cache=True, nogil=True, error_model="numpy")
def _finish(fs, ints, n, d, cx, cy, cs, cf, t, next_id, ti, mj, count, fpar, ipar, out, lost_f,
            lost_i):  # type: ignore[no-untyped-def]
    """Update, count, retire, start, write the rows: the frame after its association."""
    m = cx.size
    sf, var = _floored(cs, fpar[F_FLOOR])
    fr = np.zeros((n + m, 7))
    flag = np.zeros(n + m, dtype=np.int64)
    if count and not _apply(fs, ints, d, cx, cy, sf, cf, var, ti, mj, count, t, fpar, ipar, fr, flag):
        return REPAIR_UPDATE, 0, 0, 0
    _count(ints, n, flag)
    kept, lost = _retire(fs, ints, n, ipar, fr, flag, lost_f, lost_i)
    free = np.ones(m, dtype=np.bool_)
    for p in range(count):
        free[mj[p]] = False
    born = _start(fs, ints, kept, d, cx, cy, sf, cf, free, t, next_id, fpar, fr, flag)
    _write_rows(out, fs, ints, kept + born, d, fr, flag, ipar[I_CONFIRM])
    return DONE, kept + born, lost, born


@njit(cache=True, nogil=True, error_model="numpy")
def track_frame(fs, ints, n, cents, t, next_id, ft, q, fpar, ipar, out, lost_f, lost_i):  # type: ignore[no-untyped-def]
    """One frame of the tracker on the ``n`` live tracks of the tables ``fs`` (floats) and ``ints``.

    ``cents``: the frame's ``m`` centroids, (m, 4) x, y, sigma, flux; ``t``: its ``log_time``, ns; ``next_id``:
    the id of the next track started; ``ft``, ``q``: ``Fᵀ`` and ``Q`` over the step from the last frame;
    ``fpar``, ``ipar``: the parameters (``F_*``, ``I_*``). The tables need room for ``n + m`` tracks, ``out``
    (TRACK_DTYPE) for ``n + m`` rows and ``lost_f``, ``lost_i`` for ``n`` tracks.

    Returns (status, rows written to ``out``, tracks lost (copied to ``lost_f``, ``lost_i``), tracks
    started). The live tracks are then the first ``rows`` of the tables.
    """
    cx, cy, cs, cf = cents[:, 0], cents[:, 1], cents[:, 2], cents[:, 3]
    status = _check(cx, cy, cs, cf)
    if status != DONE:
        return status, 0, 0, 0
    d = ft.shape[0]
    if n and not _predict(fs, n, d, ft, q, fpar):
        return REPAIR_PREDICT, 0, 0, 0
    ti = np.empty(n, dtype=np.int64)
    mj = np.empty(n, dtype=np.int64)
    count = 0
    if n and cx.size:
        _, var = _floored(cs, fpar[F_FLOOR])
        count = _pairs(fs, n, d, cx, cy, var, fpar, ti, mj)
        if count < 0:
            return ASSIGN, 0, 0, 0
    return _finish(fs, ints, n, d, cx, cy, cs, cf, t, next_id, ti, mj, count, fpar, ipar, out, lost_f, lost_i)


@njit(cache=True, nogil=True, error_model="numpy")
def finish_frame(fs, ints, n, d, cents, t, next_id, ti, mj, fpar, ipar, out, lost_f,
                 lost_i):  # type: ignore[no-untyped-def]
    """The rest of a frame that :func:`track_frame` left at :data:`ASSIGN`, with the assignment's pairs
    (tracks ``ti``, centroids ``mj``). Returns as :func:`track_frame`."""
    cx, cy, cs, cf = cents[:, 0], cents[:, 1], cents[:, 2], cents[:, 3]
    return _finish(fs, ints, n, d, cx, cy, cs, cf, t, next_id, ti, mj, ti.size, fpar, ipar, out, lost_f,
                   lost_i)
