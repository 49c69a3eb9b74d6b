"""Error decomposition of a centroid series into the paper's five categories (§2.2; docs/PAPER.md, "Error decomposition").

With ``e[n] = xy[n] - reference[n]`` (px), the decomposition is sequential, each stage fitted
on what the previous ones left:

1. **SYSTEMATIC_LOW_FREQ** — a Legendre polynomial in time of degree ``trend_degree``
   (default 3, constant included, so a bias against a truth reference counts as systematic)
   fitted by least squares to each axis.
2. **SYSTEMATIC_HIGH_FREQ** — spectral peaks standing clearly above the broadband floor.  The
   periodogram ``P(f) = |X_x(f)|^2 + |X_y(f)|^2`` of the detrended residual is searched for
   ``f >= min_peak_frequency`` (default 4 frequency bins, ``4 rate_hz / N``: anything slower is
   trend) and below Nyquist.  The broadband floor at each bin is a running median of ``P`` over
   ``+-max(8, n_bins // 16)`` bins divided by 1.678 (the median of a Gamma(2, 1) variable, the
   law of ``P`` for white noise); a local floor keeps a red, drifting spectrum (e.g. AR noise)
   from passing for peaks.  A bin is a peak when ``P`` exceeds its floor times the Gamma(2)
   quantile with false-alarm probability ``false_alarm / n_bins`` (a Bonferroni bound over the
   searched bins); the bin with the largest excess is taken first.  That peak is refined off
   the bin grid (bounded search within one bin for the maximum of ``P(f)``), a sine/cosine
   pair at that frequency is added to the least-squares design (jointly with the polynomial),
   and the search repeats on the new residual, up to ``max_peaks`` peaks.
3. **RANDOM_QUANTIZATION** — the centroid S-curve: the residual is regressed, per axis, on
   ``sin(2 pi k phi)``, ``cos(2 pi k phi)``, ``k = 1..scurve_harmonics`` (default 2), where
   ``phi = p - round(p)`` is the sub-pixel phase of the *smooth* position
   ``p = reference + trend + periodic`` (drift and vibration move the image on the pixel grid;
   measurement noise does not).  The regressors are first made orthogonal to the trend and
   periodic design, so what those explain is never counted twice.  An axis whose phases do not
   spread over the pixel (mean resultant ``|mean(exp(2 pi i phi))| > 0.9``, i.e. less than
   about 0.25 px of sub-pixel motion) gets no S-curve: there it cannot be told from a bias.
4. **MODEL_MISMATCH** — the structure the motion model leaves: a per-axis AR(``ar_order``)
   least-squares fit (default 2, as the paper's AR(2) predictor) to the remaining residual; the
   magnitude is the RMS of its one-step prediction (the AR-predictable part).
5. **MEASUREMENT_NOISE** — the white remainder.

Stages 1, 3 and 4 are kept only when an F-test against the white remainder says they are
significant at ``false_alarm`` (numerator: the component's explained sum of squares over its
number of coefficients on both axes; denominator: the remainder's mean square); a rejected
component's series is folded back into MEASUREMENT_NOISE and its magnitude reported as 0.0.

Every magnitude is a *radial* RMS like eq. 15: ``sqrt(mean(cx**2 + cy**2))`` of the component's
(N, 2) series about zero, in px.  The dominant error frequency ``f_d`` is the frequency of the
periodic peak with the largest magnitude, in Hz; **when no peak stands out it is 0.0** (and
eq. 1 then gives the largest trend window, 11).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from numpy.lib.stride_tricks import sliding_window_view
from scipy import optimize, special  # optimize up front: a lazy import made peak memory depend on whether a series has a periodic term

from starlog.compensation.series import as_reference, as_series, check_int, check_rate, radial_rms
from starlog.errors import InvalidInputError, InvalidParameterError

__all__ = [
    "MIN_SAMPLES",
    "ErrorCategory",
    "ErrorDecomposition",
    "SpectralPeak",
    "decompose",
]

MIN_SAMPLES = 16
"""Shortest series (samples) :func:`decompose` and the selection accept."""

_GAMMA2_MEDIAN = float(special.gammaincinv(2.0, 0.5))  # median of Gamma(2, 1)

_MAX_PHASE_RESULTANT = 0.9
"""S-curve fitted on an axis only when ``|mean(exp(2 pi i phi))| <= 0.9`` (phases spread over
>= ~0.25 px when uniform); below that spread an S-curve cannot be told from a bias and a
linear response."""


class ErrorCategory(enum.StrEnum):
    """The five error categories of §2.2 / Table 1."""

    SYSTEMATIC_LOW_FREQ = "SYSTEMATIC_LOW_FREQ"
    SYSTEMATIC_HIGH_FREQ = "SYSTEMATIC_HIGH_FREQ"
    MEASUREMENT_NOISE = "MEASUREMENT_NOISE"
    RANDOM_QUANTIZATION = "RANDOM_QUANTIZATION"
    MODEL_MISMATCH = "MODEL_MISMATCH"


@dataclass(frozen=True)
class SpectralPeak:
    """A periodic error component: ``frequency`` (Hz) and ``magnitude`` (radial RMS, px)."""

    frequency: float
    magnitude: float


@dataclass(frozen=True)
class ErrorDecomposition:
    """Magnitudes of the five error categories of a series.

    Attributes
    ----------
    magnitudes : dict[ErrorCategory, float]
        Radial RMS (px) of each category's component (0.0 when not significant).
    dominant_frequency : float
        ``f_d`` in Hz: frequency of the largest periodic peak; 0.0 when no peak stands out.
    peaks : tuple of SpectralPeak
        Every periodic peak found, in order of detection.
    significant : dict[ErrorCategory, bool]
        Whether each component passed its significance test (MEASUREMENT_NOISE: always True;
        SYSTEMATIC_HIGH_FREQ: True when at least one peak was found).
    total_rms : float
        Radial RMS of ``e`` itself, px.
    rate_hz : float
        Sampling rate, Hz.
    n_samples : int
        Length of the series.
    trend_degree, ar_order : int
        Model orders used.
    ar_coefficients : tuple of two tuples of float
        AR coefficients ``(a_1, ..., a_p)`` fitted to the x and y residuals.
    """

    magnitudes: dict[ErrorCategory, float]
    dominant_frequency: float
    peaks: tuple[SpectralPeak, ...] = ()
    significant: dict[ErrorCategory, bool] = field(default_factory=dict)
    total_rms: float = 0.0
    rate_hz: float = 0.0
    n_samples: int = 0
    trend_degree: int = 3
    ar_order: int = 2
    ar_coefficients: tuple[tuple[float, ...], tuple[float, ...]] = ((), ())

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict.

        Layout: ``{"magnitudes": {CATEGORY: px}, "significant": {CATEGORY: bool},
        "dominant_frequency": Hz, "peaks": [{"frequency": Hz, "magnitude": px}],
        "total_rms": px, "fs": Hz (the sampling rate), "n_samples": int, "trend_degree": int, "ar_order": int,
        "ar_coefficients": {"x": [...], "y": [...]}}``.
        """
        return {
            "magnitudes": {str(k): float(self.magnitudes.get(k, 0.0)) for k in ErrorCategory},
            "significant": {str(k): bool(self.significant.get(k, False)) for k in ErrorCategory},
            "dominant_frequency": float(self.dominant_frequency),
            "peaks": [
                {"frequency": float(p.frequency), "magnitude": float(p.magnitude)}
                for p in self.peaks
            ],
            "total_rms": float(self.total_rms),
            "fs": float(self.rate_hz),
            "n_samples": int(self.n_samples),
            "trend_degree": int(self.trend_degree),
            "ar_order": int(self.ar_order),
            "ar_coefficients": {
                "x": [float(v) for v in self.ar_coefficients[0]],
                "y": [float(v) for v in self.ar_coefficients[1]],
            },
        }


def _lstsq(design: npt.NDArray[np.float64], target: npt.NDArray[np.float64]) -> Any:
    return np.linalg.lstsq(design, target, rcond=None)[0]


def _periodogram_power(
    r: npt.NDArray[np.float64], t: npt.NDArray[np.float64], f: float
) -> float:
    w = np.exp(-2j * np.pi * f * t)
    proj = w @ r  # (2,)
    return float(np.sum(np.abs(proj) ** 2))


def _strongest_peak(
    r: npt.NDArray[np.float64], rate_hz: float, fmin: float, false_alarm: float
) -> float | None:
    n = r.shape[0]
    spec = np.fft.rfft(r, axis=0)
    power = np.sum(np.abs(spec) ** 2, axis=1)
    freqs = np.fft.rfftfreq(n, d=1.0 / rate_hz)
    sel = (freqs >= fmin) & (freqs > 0) & (freqs < 0.5 * rate_hz * (1 - 1e-12))
    if np.count_nonzero(sel) < 3:
        return None
    p_sel = power[sel]
    if p_sel.max() <= 0:
        return None
    # Local floor: running median over +-half bins (robust to a red, drifting spectrum).
    half = max(8, p_sel.size // 16)
    padded = np.pad(p_sel, half, mode="reflect") if p_sel.size > half else np.pad(
        p_sel, half, mode="edge"
    )
    floor = np.median(sliding_window_view(padded, 2 * half + 1), axis=1) / _GAMMA2_MEDIAN
    threshold = floor * float(special.gammainccinv(2.0, false_alarm / p_sel.size))  # Gamma(2) upper quantile
    excess = p_sel / np.maximum(threshold, np.finfo(float).tiny)
    top = int(np.argmax(excess))
    if excess[top] <= 1.0:
        return None
    return float(freqs[sel][top])


def _refine(
    r: npt.NDArray[np.float64], t: npt.NDArray[np.float64], f0: float, df: float,
    fmin: float, rate_hz: float,
) -> float:
    lo = max(f0 - df, fmin, 1e-12)
    hi = min(f0 + df, 0.5 * rate_hz * (1 - 1e-9))
    if hi <= lo:
        return f0
    res = optimize.minimize_scalar(
        lambda f: -_periodogram_power(r, t, f),
        bounds=(lo, hi),
        method="bounded",
        options={"xatol": df * 1e-4},
    )
    f = float(res.x)
    return f if _periodogram_power(r, t, f) >= _periodogram_power(r, t, f0) else f0


def _f_significant(ss: float, q: int, ss_w: float, dof_w: int, false_alarm: float) -> bool:
    if q <= 0 or ss <= 0:
        return False
    if ss_w <= 0:
        return True
    stat = (ss / q) / (ss_w / dof_w)
    return bool(stat > special.fdtri(q, dof_w, 1.0 - false_alarm))  # F(q, dof_w) upper quantile


@dataclass(frozen=True)
class _Settings:
    """Validated model orders and thresholds of :func:`decompose`."""

    trend_degree: int
    max_peaks: int
    scurve_harmonics: int
    ar_order: int
    false_alarm: float
    min_peak_frequency: float


def _check_settings(n: int, rate_hz: float, *, trend_degree: int, max_peaks: int,
                    min_peak_frequency: float | None, scurve_harmonics: int, ar_order: int,
                    false_alarm: float) -> _Settings:
    degree = check_int(trend_degree, name="trend_degree", lo=0, hi=8)
    peaks = check_int(max_peaks, name="max_peaks", lo=0, hi=50)
    harmonics = check_int(scurve_harmonics, name="scurve_harmonics", lo=1, hi=8)
    order = check_int(ar_order, name="ar_order", lo=1, hi=8)
    fa = float(false_alarm)
    if not 0.0 < fa < 0.5:
        raise InvalidParameterError(f"false_alarm must be in (0, 0.5); got {false_alarm!r}.")
    fmin = 4.0 * (rate_hz / n) if min_peak_frequency is None else float(min_peak_frequency)
    if not math.isfinite(fmin) or fmin < 0:
        raise InvalidParameterError(
            f"min_peak_frequency must be >= 0 Hz; got {min_peak_frequency!r}."
        )
    return _Settings(trend_degree=degree, max_peaks=peaks, scurve_harmonics=harmonics,
                     ar_order=order, false_alarm=fa, min_peak_frequency=fmin)


@dataclass(frozen=True)
class _TrendAndPeaks:
    """Stages 1 and 2: the joint least-squares design, its residual, and each component."""

    design: npt.NDArray[np.float64]
    resid: npt.NDArray[np.float64]
    trend: npt.NDArray[np.float64]
    frequencies: list[float]
    peak_series: list[npt.NDArray[np.float64]]
    periodic: npt.NDArray[np.float64]


def _fit_trend_and_peaks(e: npt.NDArray[np.float64], rate_hz: float, cfg: _Settings) -> _TrendAndPeaks:
    """Legendre trend plus up to ``max_peaks`` sinusoids, refitted jointly after each peak."""
    n = e.shape[0]
    df = rate_hz / n
    t = np.arange(n, dtype=np.float64) / rate_hz
    poly = np.polynomial.legendre.legvander(np.linspace(-1.0, 1.0, n), cfg.trend_degree)
    n_poly = poly.shape[1]
    # Leave room for the S-curve and AR regressors and for the noise estimate.
    max_cols = max(n_poly, n // 2 - 2 * cfg.scurve_harmonics - cfg.ar_order)
    design = poly
    coef = _lstsq(design, e)
    resid = e - design @ coef
    freqs: list[float] = []
    while len(freqs) < cfg.max_peaks and design.shape[1] + 2 <= max_cols:
        f0 = _strongest_peak(resid, rate_hz, cfg.min_peak_frequency, cfg.false_alarm)
        if f0 is None:
            break
        f = _refine(resid, t, f0, df, cfg.min_peak_frequency, rate_hz)
        if any(abs(f - g) < df for g in freqs):
            break
        freqs.append(f)
        cols = np.column_stack([np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t)])
        design = np.hstack([design, cols])
        coef = _lstsq(design, e)
        resid = e - design @ coef
    peak_series = [
        design[:, n_poly + 2 * i : n_poly + 2 * i + 2] @ coef[n_poly + 2 * i : n_poly + 2 * i + 2]
        for i in range(len(freqs))
    ]
    periodic = np.sum(peak_series, axis=0) if peak_series else np.zeros_like(e)
    return _TrendAndPeaks(design=design, resid=resid, trend=poly @ coef[:n_poly], frequencies=freqs,
                          peak_series=peak_series, periodic=periodic)


def _fit_scurve(resid: npt.NDArray[np.float64], design: npt.NDArray[np.float64],
                phase: npt.NDArray[np.float64], harmonics: int) -> tuple[npt.NDArray[np.float64], int]:
    """Stage 3: the S-curve series (N, 2) and its number of coefficients (both axes)."""
    scurve = np.zeros_like(resid)
    q_scurve = 0
    pinv_design = np.linalg.pinv(design)
    # The S-curve is identifiable only where the phase visits enough of the pixel.
    resultant = np.abs(np.mean(np.exp(2j * np.pi * phase), axis=0))
    for axis in range(2):
        if resultant[axis] > _MAX_PHASE_RESULTANT:
            continue
        cols_list = []
        for k in range(1, harmonics + 1):
            cols_list.append(np.sin(2 * np.pi * k * phase[:, axis]))
            cols_list.append(np.cos(2 * np.pi * k * phase[:, axis]))
        s_cols = np.column_stack(cols_list)
        s_perp = s_cols - design @ (pinv_design @ s_cols)
        # A regressor the trend/periodic design already explains (phase barely moving) is
        # unidentifiable: keep only columns with a real part left.
        keep = np.linalg.norm(s_perp, axis=0) > 1e-3 * np.linalg.norm(s_cols, axis=0)
        if not keep.any():
            continue
        s_use = s_perp[:, keep]
        rank = int(np.linalg.matrix_rank(s_use))
        if rank == 0:
            continue
        beta = _lstsq(s_use, resid[:, axis])
        scurve[:, axis] = s_use @ beta
        q_scurve += rank
    return scurve, q_scurve


def _fit_ar(resid: npt.NDArray[np.float64], order: int
            ) -> tuple[npt.NDArray[np.float64], tuple[tuple[float, ...], tuple[float, ...]]]:
    """Stage 4: the one-step AR(``order``) prediction (N, 2) of each axis, and the coefficients."""
    n = resid.shape[0]
    predicted = np.zeros_like(resid)
    coefs: list[tuple[float, ...]] = []
    for axis in range(2):
        r = resid[:, axis]
        lagged = np.column_stack([r[order - i - 1 : n - i - 1] for i in range(order)])
        a = _lstsq(lagged, r[order:])
        predicted[order:, axis] = lagged @ a
        coefs.append(tuple(float(v) for v in a))
    return predicted, (coefs[0], coefs[1])


def decompose(
    xy: npt.ArrayLike,
    *,
    rate_hz: float,
    reference: npt.ArrayLike | None = None,
    trend_degree: int = 3,
    max_peaks: int = 5,
    min_peak_frequency: float | None = None,
    scurve_harmonics: int = 2,
    ar_order: int = 2,
    false_alarm: float = 0.01,
) -> ErrorDecomposition:
    """Decompose ``e = xy - reference`` into the five error categories (§2.2).

    Parameters
    ----------
    xy : (N, 2) array_like
        Positions, px (x = column, y = row).  ``N >= MIN_SAMPLES`` (16).
    rate_hz : float
        Sampling rate, Hz.
    reference : (2,) or (N, 2) array_like, optional
        Reference positions; default the global mean of ``xy`` (the paper's truth).
    trend_degree : int
        Degree of the Legendre trend polynomial (0..8), default 3.
    max_peaks : int
        Most periodic peaks fitted (0..50), default 5.
    min_peak_frequency : float, optional
        Lowest frequency searched for peaks, Hz; default ``4 rate_hz / N``.
    scurve_harmonics : int
        Harmonics of the sub-pixel phase in the S-curve regression (1..8), default 2.
    ar_order : int
        Order of the AR model of the final residual (1..8), default 2.
    false_alarm : float
        Probability of a false detection for the peak search and the F-tests, in (0, 0.5).

    Returns
    -------
    ErrorDecomposition
        See the module docstring for the method.
    """
    p = as_series(xy)
    n = p.shape[0]
    if n < MIN_SAMPLES:
        raise InvalidInputError(
            f"the error decomposition needs at least {MIN_SAMPLES} samples; got {n}."
        )
    rate_hz = check_rate(rate_hz)
    cfg = _check_settings(n, rate_hz, trend_degree=trend_degree, max_peaks=max_peaks,
                          min_peak_frequency=min_peak_frequency, scurve_harmonics=scurve_harmonics,
                          ar_order=ar_order, false_alarm=false_alarm)
    ref = (
        np.broadcast_to(p.mean(axis=0), (n, 2)).copy()
        if reference is None
        else as_reference(reference, n)
    )
    e = p - ref
    fit = _fit_trend_and_peaks(e, rate_hz, cfg)
    smooth = ref + fit.trend + fit.periodic  # where the image is, without measurement noise
    scurve, q_scurve = _fit_scurve(fit.resid, fit.design, smooth - np.round(smooth),
                                   cfg.scurve_harmonics)
    predicted, ar_coefs = _fit_ar(fit.resid - scurve, cfg.ar_order)
    white = fit.resid - scurve - predicted
    return _categorise(e, fit, scurve, q_scurve, predicted, white, rate_hz=rate_hz, cfg=cfg,
                       ar_coefs=ar_coefs)


def _categorise(e: npt.NDArray[np.float64], fit: _TrendAndPeaks, scurve: npt.NDArray[np.float64],
                q_scurve: int, predicted: npt.NDArray[np.float64], white: npt.NDArray[np.float64], *,
                rate_hz: float, cfg: _Settings,
                ar_coefs: tuple[tuple[float, ...], tuple[float, ...]]) -> ErrorDecomposition:
    """F-test each component against the white remainder and measure the five categories."""
    n = e.shape[0]
    order = cfg.ar_order
    n_poly = cfg.trend_degree + 1
    fa = cfg.false_alarm
    ss_w = float(np.sum(white**2))
    n_params = 2 * fit.design.shape[1] + q_scurve + 2 * order
    dof_w = max(1, 2 * n - n_params)
    sig_trend = _f_significant(float(np.sum(fit.trend**2)), 2 * n_poly, ss_w, dof_w, fa)
    sig_scurve = _f_significant(float(np.sum(scurve**2)), q_scurve, ss_w, dof_w, fa)
    sig_ar = _f_significant(float(np.sum(predicted**2)), 2 * order, ss_w, dof_w, fa)
    noise = white.copy()
    if not sig_trend:
        noise += fit.trend
    if not sig_scurve:
        noise += scurve
    if not sig_ar:
        noise += predicted

    peaks = tuple(SpectralPeak(frequency=f, magnitude=radial_rms(s))
                  for f, s in zip(fit.frequencies, fit.peak_series))
    f_d = max(peaks, key=lambda pk: pk.magnitude).frequency if peaks else 0.0
    magnitudes = {
        ErrorCategory.SYSTEMATIC_LOW_FREQ: radial_rms(fit.trend) if sig_trend else 0.0,
        ErrorCategory.SYSTEMATIC_HIGH_FREQ: radial_rms(fit.periodic),
        ErrorCategory.MEASUREMENT_NOISE: radial_rms(noise),
        ErrorCategory.RANDOM_QUANTIZATION: radial_rms(scurve) if sig_scurve else 0.0,
        ErrorCategory.MODEL_MISMATCH: radial_rms(predicted) if sig_ar else 0.0,
    }
    significant = {
        ErrorCategory.SYSTEMATIC_LOW_FREQ: sig_trend,
        ErrorCategory.SYSTEMATIC_HIGH_FREQ: bool(peaks),
        ErrorCategory.MEASUREMENT_NOISE: True,
        ErrorCategory.RANDOM_QUANTIZATION: sig_scurve,
        ErrorCategory.MODEL_MISMATCH: sig_ar,
    }
    return ErrorDecomposition(
        magnitudes=magnitudes,
        dominant_frequency=float(f_d),
        peaks=peaks,
        significant=significant,
        total_rms=radial_rms(e),
        rate_hz=rate_hz,
        n_samples=n,
        trend_degree=cfg.trend_degree,
        ar_order=order,
        ar_coefficients=ar_coefs,
    )
