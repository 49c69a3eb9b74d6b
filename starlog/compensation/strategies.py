"""The five compensation strategies of §2.3, read as docs/PAPER.md ("Compensation strategies") says.

Every strategy is a plain function on an (N, 2) position series ``xy`` in pixels (x = column,
y = row); it returns a new (N, 2) float64 array and never modifies its inputs.  An empty series
gives an empty (0, 2) result.  ``reference`` is the truth ``M`` of the paper: a point (2,) or a
per-sample (N, 2) array (the leak-free running mean).

1. :func:`adaptive_window_trend` — eq. 1–3.
2. :func:`adaptive_median` — eq. 4.
3. :func:`local_smoothing` — eq. 5–6.
4. :func:`ar_prediction` — eq. 7–9.
5. :func:`confidence_weighted` — eq. 10–11.

:func:`apply_strategy` dispatches on :class:`Strategy`.
"""

from __future__ import annotations

import enum
import math

import numpy as np
import numpy.typing as npt
from numpy.lib.stride_tricks import sliding_window_view

from starlog.compensation.series import as_reference, as_samples, as_series, check_rate
from starlog.errors import InvalidParameterError

__all__ = [
    "AR_THETA",
    "AccuracySource",
    "MEDIAN_WINDOW_MAX",
    "MEDIAN_WINDOW_MIN",
    "NOISE_HALF_WIDTH",
    "SMOOTHING_HALF_WIDTH",
    "TREND_WINDOW_MAX",
    "TREND_WINDOW_MIN",
    "Strategy",
    "adaptive_median",
    "adaptive_window_trend",
    "apply_strategy",
    "ar_prediction",
    "ar_weights",
    "confidence",
    "confidence_weighted",
    "local_noise_level",
    "local_smoothing",
    "local_variance",
    "median_window",
    "moving_average",
    "trend_window",
]

TREND_WINDOW_MIN = 3
TREND_WINDOW_MAX = 11
MEDIAN_WINDOW_MIN = 3
MEDIAN_WINDOW_MAX = 11
NOISE_HALF_WIDTH = 5
"""Half-width (samples) of the window the local noise level of eq. 4 is estimated over."""
SMOOTHING_HALF_WIDTH = 2
"""Half-width (samples) of the window of the local variance of eq. 5 (5 samples)."""


class Strategy(enum.StrEnum):
    """The five compensation strategies (§2.3, Table 1)."""

    ADAPTIVE_WINDOW_TREND = "ADAPTIVE_WINDOW_TREND"
    ADAPTIVE_MEDIAN = "ADAPTIVE_MEDIAN"
    LOCAL_SMOOTHING = "LOCAL_SMOOTHING"
    AR_PREDICTION = "AR_PREDICTION"
    CONFIDENCE_WEIGHTED = "CONFIDENCE_WEIGHTED"


class AccuracySource(enum.StrEnum):
    """Where the sub-pixel accuracy ``A`` of eq. 10 comes from.

    ``ZERO``: ``A = 0`` (the paper: no sub-pixel interpolation).  ``SIGMA``: ``A`` = the
    centroid's own uncertainty ``sigma`` in pixels (for sub-pixel centroid methods).
    """

    ZERO = "zero"
    SIGMA = "sigma"


# ---------------------------------------------------------------------------------------------
# 1. adaptive window trend estimation (eq. 1-3)


def trend_window(*, rate_hz: float, dominant_frequency: float) -> int:
    """Trend window of eq. 1: nearest odd integer to ``rate_hz / (2 f_d)``, clipped to [3, 11].

    With ``v = rate_hz / (2 f_d)`` the nearest odd integer is ``2 floor(v / 2) + 1``; at a tie (``v``
    an even integer, equally far from two odd numbers) this takes the larger one.
    ``f_d = 0`` (no dominant frequency, see :func:`~starlog.compensation.decomposition.decompose`)
    is the limit ``v -> inf``: 11.

    Examples
    --------
    >>> trend_window(rate_hz=100, dominant_frequency=10), trend_window(rate_hz=100, dominant_frequency=20)
    (5, 3)
    """
    rate_hz = check_rate(rate_hz)
    fd = float(dominant_frequency)
    if not math.isfinite(fd) or fd < 0:
        raise InvalidParameterError(
            f"dominant_frequency must be a finite frequency >= 0 Hz; got {dominant_frequency!r}."
        )
    if fd == 0.0:
        return TREND_WINDOW_MAX
    v = rate_hz / (2.0 * fd)
    if v >= TREND_WINDOW_MAX:
        return TREND_WINDOW_MAX
    w = 2 * int(math.floor(v / 2.0)) + 1
    return int(min(TREND_WINDOW_MAX, max(TREND_WINDOW_MIN, w)))


def moving_average(xy: npt.ArrayLike, *, window: int) -> npt.NDArray[np.float64]:
    """Centred moving average of eq. 2, ``T[n] = mean(x[n - h .. n + h])``, ``h = window // 2``.

    Edges: near the ends the window is truncated to the samples that exist, so ``T[n]`` is the
    mean of ``x[max(0, n - h) .. min(N - 1, n + h)]`` (no padding, no phase shift in the
    interior).

    Parameters
    ----------
    xy : (N, 2) array_like
        Positions, px.
    window : int
        Odd window length >= 1.
    """
    p = as_series(xy)
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or window < 1 or (
        window % 2 == 0
    ):
        raise InvalidParameterError(f"window must be an odd integer >= 1; got {window!r}.")
    n = p.shape[0]
    if n == 0:
        return p
    h = int(window) // 2
    csum = np.vstack([np.zeros((1, 2)), np.cumsum(p, axis=0)])
    idx = np.arange(n)
    lo = np.maximum(idx - h, 0)
    hi = np.minimum(idx + h, n - 1) + 1
    return (csum[hi] - csum[lo]) / (hi - lo)[:, None]


def adaptive_window_trend(
    xy: npt.ArrayLike,
    *,
    rate_hz: float,
    dominant_frequency: float,
    reference: npt.ArrayLike,
) -> npt.NDArray[np.float64]:
    """Strategy 1, adaptive window trend estimation (eq. 1–3).

    ``W`` from eq. 1 (:func:`trend_window`), the trend ``T`` from eq. 2
    (:func:`moving_average`, truncated windows at the ends), and eq. 3 read as removing the
    trend's *error* so the output stays a position: ``y[n] = x[n] - (T[n] - M[n])``.

    Parameters
    ----------
    xy : (N, 2) array_like
        Positions, px.
    rate_hz : float
        Sampling rate, Hz.
    dominant_frequency : float
        ``f_d`` in Hz (0.0: none, window 11).
    reference : (2,) or (N, 2) array_like
        ``M``, px.
    """
    p = as_series(xy)
    w = trend_window(rate_hz=rate_hz, dominant_frequency=dominant_frequency)
    m = as_reference(reference, p.shape[0])
    if p.shape[0] == 0:
        return p
    return p - (moving_average(p, window=w) - m)


# ---------------------------------------------------------------------------------------------
# 2. adaptive median filtering (eq. 4)


def _nan_windows(a: npt.NDArray[np.float64], left: int, length: int) -> npt.NDArray[np.float64]:
    """Row ``j``: ``a[j - left .. j - left + length - 1]`` of a 1-D array, NaN outside it.

    Gives ``len(a) + 1`` rows (callers keep the first ``N``).
    """
    right = length - left
    padded = np.concatenate([np.full(left, np.nan), a, np.full(right, np.nan)])
    return sliding_window_view(padded, length)


def local_noise_level(xy: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Local noise level (px) per sample and axis: the "SNR" of eq. 4 as docs/PAPER.md reads it.

    For sample ``n`` and each axis, the first differences ``d[k] = x[k + 1] - x[k]`` lying inside
    ``[n - 5, n + 5]`` (truncated at the ends; 10 differences in the interior) give
    ``1.4826 * median(|d - median(d)|) / sqrt(2)``: a robust (MAD) standard deviation of white
    noise, insensitive to a slow trend.  Series shorter than 2 samples have level 0.

    Returns
    -------
    (N, 2) ndarray of float64
    """
    p = as_series(xy)
    n = p.shape[0]
    out = np.zeros((n, 2))
    if n < 2:
        return out
    h = NOISE_HALF_WIDTH
    d = np.diff(p, axis=0)  # (n - 1, 2); d[k] lies between samples k and k + 1
    for axis in range(2):
        # differences inside [n - h, n + h] are d[n - h .. n + h - 1] (2h of them)
        win = _nan_windows(d[:, axis], h, 2 * h)[:n]
        med = np.nanmedian(win, axis=1)
        mad = np.nanmedian(np.abs(win - med[:, None]), axis=1)
        out[:, axis] = 1.4826 * mad / math.sqrt(2.0)
    return out


def median_window(noise_level: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """Median window of eq. 4: ``max(3, min(11, floor(10 s + 3)))`` with ``s`` in px.

    An even result is raised to the next odd size so the window has a centre sample
    (e.g. ``s = 0.1`` px: ``floor(4.0) = 4 -> 5``).
    """
    s = np.asarray(noise_level, dtype=np.float64)
    w = np.floor(10.0 * s + 3.0)
    w = np.clip(np.nan_to_num(w, nan=MEDIAN_WINDOW_MIN, posinf=MEDIAN_WINDOW_MAX), 3, 11)
    w = w.astype(np.int64)
    return np.where(w % 2 == 0, w + 1, w)


def adaptive_median(xy: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Strategy 2, adaptive median filtering (eq. 4).

    Each axis separately: the window ``W[n]`` comes from eq. 4 with the local noise level of
    :func:`local_noise_level` (px); ``y[n]`` is the median of ``x[n - W//2 .. n + W//2]``.  As
    the paper says, only samples whose whole window fits in the series are filtered; the others
    (the first and last ``W[n] // 2`` samples) are left unchanged.
    """
    p = as_series(xy)
    n = p.shape[0]
    out = p.copy()
    if n < MEDIAN_WINDOW_MIN:
        return out
    windows = median_window(local_noise_level(p))
    idx = np.arange(n)
    for axis in range(2):
        for w in np.unique(windows[:, axis]):
            w = int(w)
            if w > n:
                continue
            h = w // 2
            sel = (windows[:, axis] == w) & (idx >= h) & (idx <= n - 1 - h)
            if not sel.any():
                continue
            med = np.median(sliding_window_view(p[:, axis], w), axis=1)  # centred at h..n-1-h
            out[sel, axis] = med[idx[sel] - h]
    return out


# ---------------------------------------------------------------------------------------------
# 3. local trajectory smoothing (eq. 5-6)


def local_variance(xy: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """``sigma^2_local`` of eq. 5 (px^2): 2-D scatter of the positions in a 5-sample window.

    ``var(x[k]) + var(y[k])`` (population variance, ddof = 0) over
    ``k in [n - 2, n + 2]``, truncated at the ends.

    Returns
    -------
    (N,) ndarray of float64
    """
    p = as_series(xy)
    n = p.shape[0]
    if n == 0:
        return np.zeros(0)
    h = SMOOTHING_HALF_WIDTH
    total = np.zeros(n)
    for axis in range(2):
        win = _nan_windows(p[:, axis], h, 2 * h + 1)[:n]
        mean = np.nanmean(win, axis=1)
        total += np.nanmean((win - mean[:, None]) ** 2, axis=1)
    return total


def local_smoothing(xy: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Strategy 3, local trajectory smoothing (eq. 5–6, as written).

    ``alpha[n] = 1 - exp(-sigma^2_local[n])`` (eq. 5, :func:`local_variance`, px^2) and
    ``y[n] = (1 - alpha) x[n] + alpha / 2 (x[n - 1] + x[n + 1])`` (eq. 6), the same ``alpha``
    for both axes.  The first and last samples (no neighbour on one side) are unchanged.
    """
    p = as_series(xy)
    n = p.shape[0]
    out = p.copy()
    if n < 3:
        return out
    alpha = (1.0 - np.exp(-local_variance(p)))[1:-1, None]
    out[1:-1] = (1.0 - alpha) * p[1:-1] + 0.5 * alpha * (p[:-2] + p[2:])
    return out


# ---------------------------------------------------------------------------------------------
# 4. AR(2) error prediction (eq. 7-9)


def ar_weights(order: int = 2, *, decay: float = 0.5) -> npt.NDArray[np.float64]:
    """Eq. 8: ``theta_k = exp(-decay k) / sum_j exp(-decay j)``, ``k = 1..order``."""
    k = np.arange(1, int(order) + 1, dtype=np.float64)
    w = np.exp(-decay * k)
    return w / w.sum()


AR_THETA = ar_weights(2)
"""``(theta_1, theta_2)`` of eq. 8: (0.62246, 0.37754)."""


def ar_prediction(
    xy: npt.ArrayLike, *, reference: npt.ArrayLike, prediction_weight: float = 0.7
) -> npt.NDArray[np.float64]:
    """Strategy 4, AR(2) error prediction (eq. 7–9).

    ``e[n] = x[n] - M[n]`` is the error of the *input* (measured) sequence;
    ``e_hat[n] = theta_1 e[n - 1] + theta_2 e[n - 2]`` (eq. 7, :data:`AR_THETA`); eq. 9 read as
    blending the predicted position with the measurement:
    ``y[n] = 0.7 (M[n] + e_hat[n]) + 0.3 x[n]``.  The first two samples have no two past errors
    and are left unchanged.
    """
    p = as_series(xy)
    m = as_reference(reference, p.shape[0])
    wgt = float(prediction_weight)
    if not 0.0 <= wgt <= 1.0:
        raise InvalidParameterError(
            f"prediction_weight must be in [0, 1]; got {prediction_weight!r}."
        )
    out = p.copy()
    if p.shape[0] < 3:
        return out
    e = p - m
    e_hat = AR_THETA[0] * e[1:-1] + AR_THETA[1] * e[:-2]
    out[2:] = wgt * (m[2:] + e_hat) + (1.0 - wgt) * p[2:]
    return out


# ---------------------------------------------------------------------------------------------
# 5. confidence-weighted truth correction (eq. 10-11)


def confidence(
    xy: npt.ArrayLike,
    *,
    reference: npt.ArrayLike,
    flux: npt.ArrayLike | None = None,
    accuracy: npt.ArrayLike | None = None,
) -> npt.NDArray[np.float64]:
    """Confidence ``gamma`` of eq. 10 per sample.

    ``gamma = clip((I / 100 + (1 - 10 A)) * 1/2 * exp(-D), 0.1, 0.9)`` with

    * ``I`` the intensity normalised to [0, 1] by dividing by the sequence's maximum flux
      (negative flux counts as 0; no flux, or a maximum of 0, gives ``I = 1`` / ``I = 0``);
    * ``A`` the sub-pixel accuracy in px (>= 0; ``None`` means 0, the paper without sub-pixel
      interpolation);
    * ``D = |G - M|`` the distance in px from the measurement to the reference.

    As written, ``I / 100 <= 0.01`` and, with ``A >= 0``, ``gamma <= 0.505``: the upper clip at
    0.9 is never reached by valid input.

    Returns
    -------
    (N,) ndarray of float64
    """
    p = as_series(xy)
    n = p.shape[0]
    m = as_reference(reference, n)
    if flux is None:
        intensity = np.ones(n)
    else:
        f = np.maximum(as_samples(flux, n, name="flux"), 0.0)
        top = float(f.max()) if n else 0.0
        intensity = f / top if top > 0 else np.zeros(n)
    a = np.zeros(n) if accuracy is None else as_samples(accuracy, n, name="accuracy",
                                                         nonnegative=True)
    d = np.hypot(*(p - m).T) if n else np.zeros(0)
    gamma = (intensity / 100.0 + (1.0 - 10.0 * a)) * 0.5 * np.exp(-d)
    return np.clip(gamma, 0.1, 0.9)


def confidence_weighted(
    xy: npt.ArrayLike,
    *,
    reference: npt.ArrayLike,
    flux: npt.ArrayLike | None = None,
    accuracy: npt.ArrayLike | None = None,
) -> npt.NDArray[np.float64]:
    """Strategy 5, confidence-weighted truth correction (eq. 10–11, as written).

    ``output = gamma G + (1 - gamma) M`` with ``gamma`` from :func:`confidence`, ``G`` the
    measurement and ``M`` the reference (same ``gamma`` on both axes).
    """
    p = as_series(xy)
    m = as_reference(reference, p.shape[0])
    g = confidence(p, reference=m, flux=flux, accuracy=accuracy)[:, None]
    return g * p + (1.0 - g) * m


# ---------------------------------------------------------------------------------------------


def apply_strategy(
    strategy: Strategy | str,
    xy: npt.ArrayLike,
    *,
    rate_hz: float,
    reference: npt.ArrayLike,
    dominant_frequency: float = 0.0,
    flux: npt.ArrayLike | None = None,
    accuracy: npt.ArrayLike | None = None,
) -> npt.NDArray[np.float64]:
    """Run one strategy by name with the inputs every strategy may need.

    Parameters
    ----------
    strategy : Strategy or str
    xy : (N, 2) array_like
        Positions, px.
    rate_hz : float
        Sampling rate, Hz (strategy 1).
    reference : (2,) or (N, 2) array_like
        ``M``, px (strategies 1, 4, 5).
    dominant_frequency : float
        ``f_d``, Hz (strategy 1).
    flux, accuracy : (N,) array_like, optional
        ``I`` and ``A`` of eq. 10 (strategy 5).
    """
    try:
        s = Strategy(strategy)
    except ValueError as err:
        raise InvalidParameterError(
            f"unknown strategy {strategy!r}; expected one of {[v.value for v in Strategy]}."
        ) from err
    if s is Strategy.ADAPTIVE_WINDOW_TREND:
        return adaptive_window_trend(
            xy, rate_hz=rate_hz, dominant_frequency=dominant_frequency, reference=reference
        )
    if s is Strategy.ADAPTIVE_MEDIAN:
        return adaptive_median(xy)
    if s is Strategy.LOCAL_SMOOTHING:
        return local_smoothing(xy)
    if s is Strategy.AR_PREDICTION:
        return ar_prediction(xy, reference=reference)
    return confidence_weighted(xy, reference=reference, flux=flux, accuracy=accuracy)
