"""Equidistant decimation of a native-rate sequence (paper §3.1; docs/PAPER.md, "Down-sampling").

The paper down-samples its 200 / 300 Hz centroid sequences to 10–100 Hz "with equidistant
sampling intervals".  starlog keeps every ``k``-th sample:

* ``k = floor(f_native / f_target + 0.5)`` (round half up, never below 1);
* kept indices ``start, start + k, start + 2k, ...`` (``start`` = 0 by default);
* the effective rate is ``f_native / k`` — which differs from the target when ``f_native`` is
  not a multiple of it (300 Hz -> 40 Hz: ``k = 8``, 37.5 Hz; 200 Hz -> 30 Hz: ``k = 7``,
  28.571... Hz).  Use the effective rate as ``rate_hz`` downstream.

No anti-alias filter is applied (the paper's "equidistant sampling" keeps raw samples).
A target rate above the native rate is rejected; the 10–100 Hz range of the paper is not
enforced (its Table 2 also uses 5 Hz).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.compensate._series import check_rate
from starlog.errors import InvalidInputError, InvalidParameterError

__all__ = ["decimate", "decimation_indices", "decimation_step", "effective_rate"]


def decimation_step(*, native_rate: float, target_rate: float) -> int:
    """Decimation step ``k = max(1, floor(native_rate / target_rate + 0.5))``.

    Parameters
    ----------
    native_rate : float
        Rate of the input sequence, Hz (> 0).
    target_rate : float
        Wanted rate, Hz (> 0, <= ``native_rate``).

    Returns
    -------
    int
        Keep every ``k``-th sample.

    Raises
    ------
    InvalidParameterError
        When a rate is not a finite positive number or ``target_rate > native_rate``.
    """
    fn = check_rate(native_rate, name="native_rate")
    ft = check_rate(target_rate, name="target_rate")
    if ft > fn:
        raise InvalidParameterError(
            f"target_rate {ft} Hz is above the native rate {fn} Hz; decimation can only lower "
            "the rate."
        )
    return max(1, int(math.floor(fn / ft + 0.5)))


def effective_rate(*, native_rate: float, target_rate: float) -> float:
    """Rate actually obtained, ``native_rate / k`` Hz (see :func:`decimation_step`)."""
    k = decimation_step(native_rate=native_rate, target_rate=target_rate)
    return float(native_rate) / k


def decimation_indices(
    n: int, *, native_rate: float, target_rate: float, start: int = 0
) -> npt.NDArray[np.int64]:
    """Indices kept from a sequence of ``n`` native-rate samples.

    Parameters
    ----------
    n : int
        Length of the native sequence (>= 0).
    native_rate, target_rate : float
        As in :func:`decimation_step`.
    start : int
        First kept index (>= 0), default 0.

    Returns
    -------
    (M,) ndarray of int64
        ``arange(start, n, k)``; empty when ``start >= n``.  Apply the same indices to
        ``log_time``, positions, flux and truth so they stay aligned.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise InvalidParameterError(f"n must be an integer >= 0; got {n!r}.")
    if isinstance(start, bool) or not isinstance(start, (int, np.integer)) or start < 0:
        raise InvalidParameterError(f"start must be an integer >= 0; got {start!r}.")
    k = decimation_step(native_rate=native_rate, target_rate=target_rate)
    return np.arange(int(start), int(n), k, dtype=np.int64)


def decimate(
    values: npt.ArrayLike, *, native_rate: float, target_rate: float, start: int = 0
) -> npt.NDArray[Any]:
    """Equidistant decimation along the first axis (every ``k``-th sample).

    Parameters
    ----------
    values : (N, ...) array_like
        Native-rate samples (an (N, 2) position series in px, int64 ``log_time``, ...).
    native_rate, target_rate : float
        Hz; see :func:`decimation_step` for ``k`` and :func:`effective_rate` for the rate of
        the result.
    start : int
        First kept index.

    Returns
    -------
    (M, ...) ndarray
        A new array ``values[start::k]`` of the input's dtype (the input is not modified).

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
