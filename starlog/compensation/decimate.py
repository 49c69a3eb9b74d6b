"""Equidistant decimation of a native-rate sequence (paper §3.1; docs/PAPER.md, "Down-sampling").

The paper down-samples its 200 / 300 Hz centroid sequences to 10–100 Hz "with equidistant
sampling intervals".  starlog keeps, for each ideal sample time of the target rate, the
native frame nearest to it (fractional-step selection):

* ideal sample times ``t_m = m / f_target`` (``m = 0, 1, 2, ...``) from the first kept frame;
* kept index ``i_m = start + floor(m * f_native / f_target + 0.5)`` (nearest frame, a tie goes
  to the later frame), while ``i_m < n``;
* when ``f_native`` is a multiple of ``f_target`` this is every ``k``-th sample
  (``k = f_native / f_target``); otherwise the steps alternate between ``floor`` and ``ceil``
  of the ratio (300 Hz -> 70 Hz: steps of 4 and 5 frames, 30 frames per 7 samples), so the
  rate over the sequence is the target rate and no two targets give the same samples;
* each kept frame is at most half a native frame period from its ideal time (1.7 ms at
  300 Hz, 2.5 ms at 200 Hz): a small sampling-time jitter, not a rate error;
* the effective rate (:func:`sampled_rate`) is ``f_native * (M - 1) / (i_last - i_0)`` for
  ``M >= 2`` kept samples — the mean rate actually obtained, within 1 % of the target for any
  sequence of a few seconds.  Use it as ``rate_hz`` downstream.

No anti-alias filter is applied (the paper's "equidistant sampling" keeps raw samples).
A target rate above the native rate is rejected (one within :data:`RATE_TOLERANCE` of it, a
native rate measured from frame times, is the native rate); the 10–100 Hz range of the paper
is not enforced (its Table 2 also uses 5 Hz).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.compensation.series import check_rate
from starlog.errors import InvalidInputError, InvalidParameterError

__all__ = ["RATE_TOLERANCE", "decimate", "decimation_indices", "effective_rate", "sampled_rate"]

#: Relative excess over the native rate that a target rate may have and still be the native rate (a native
#: rate measured from frame times, ``(n - 1) / span``, rounds a little below the nominal one).
RATE_TOLERANCE = 1e-9


def _checked_rates(native_rate: float, target_rate: float) -> tuple[float, float]:
    fn = check_rate(native_rate, name="native_rate")
    ft = check_rate(target_rate, name="target_rate")
    if ft > fn * (1 + RATE_TOLERANCE):
        raise InvalidParameterError(
            f"target_rate {ft} Hz is above the native rate {fn} Hz; decimation can only lower "
            "the rate."
        )
    return fn, min(ft, fn)


def _check_count(value: object, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise InvalidParameterError(f"{name} must be an integer >= 0; got {value!r}.")
    return int(value)


def decimation_indices(
    n: int, *, native_rate: float, target_rate: float, start: int = 0
) -> npt.NDArray[np.int64]:
    """Indices kept from a sequence of ``n`` native-rate samples (nearest frame to each ideal time).

    Parameters
    ----------
    n : int
        Length of the native sequence (>= 0).
    native_rate, target_rate : float
        Hz, ``0 < target_rate <= native_rate``.
    start : int
        First kept index (>= 0), default 0.

    Returns
    -------
    (M,) ndarray of int64
        ``start + floor(m * native_rate / target_rate + 0.5)`` for ``m = 0, 1, ...`` while below
        ``n``; strictly increasing; empty when ``start >= n``.  Apply the same indices to
        ``log_time``, positions, flux and truth so they stay aligned.

    Examples
    --------
    >>> decimation_indices(16, native_rate=300, target_rate=70).tolist()
    [0, 4, 9, 13]
    """
    n = _check_count(n, "n")
    start = _check_count(start, "start")
    fn, ft = _checked_rates(native_rate, target_rate)
    if start >= n:
        return np.zeros(0, dtype=np.int64)
    m = np.arange(int(np.ceil((n - start) * ft / fn)) + 1, dtype=np.float64)
    idx = start + np.floor(m * fn / ft + 0.5).astype(np.int64)
    return idx[idx < n]


def sampled_rate(indices: npt.ArrayLike, *, native_rate: float) -> float:
    """Mean rate of the kept samples ``indices`` of a ``native_rate`` sequence, Hz.

    ``native_rate * (M - 1) / (indices[-1] - indices[0])`` for ``M >= 2`` samples; the native
    rate for fewer (a single sample has no rate of its own).
    """
    fn = check_rate(native_rate, name="native_rate")
    idx = np.asarray(indices, dtype=np.int64)
    if idx.size < 2 or idx[-1] <= idx[0]:
        return fn
    return fn * (idx.size - 1) / float(idx[-1] - idx[0])


def effective_rate(*, native_rate: float, target_rate: float, n: int) -> float:
    """Rate obtained by decimating ``n`` samples: :func:`sampled_rate` of :func:`decimation_indices`."""
    idx = decimation_indices(n, native_rate=native_rate, target_rate=target_rate)
    return sampled_rate(idx, native_rate=native_rate)


def decimate(
    values: npt.ArrayLike, *, native_rate: float, target_rate: float, start: int = 0
) -> npt.NDArray[Any]:
    """Decimation along the first axis (:func:`decimation_indices`).

    Parameters
    ----------
    values : (N, ...) array_like
        Native-rate samples (an (N, 2) position series in px, int64 ``log_time``, ...).
    native_rate, target_rate : float
        Hz; see :func:`effective_rate` for the rate of the result.
    start : int
        First kept index.

    Returns
    -------
    (M, ...) ndarray
        A new array ``values[decimation_indices(...)]`` of the input's dtype (the input is not
        modified).

    Examples
    --------
    >>> decimate(np.arange(10.0), native_rate=300, target_rate=100)
    array([0., 3., 6., 9.])
    """
    a = np.asarray(values)
    if a.dtype.kind not in "biuf":
        raise InvalidInputError(f"values must be a numeric array; got dtype {a.dtype}.")
    if a.ndim == 0:
        raise InvalidInputError("values must have at least one dimension (samples first).")
    idx = decimation_indices(
        a.shape[0], native_rate=native_rate, target_rate=target_rate, start=start
    )
    return a[idx].copy()
