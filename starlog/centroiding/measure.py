"""Sub-pixel centroids of detected stars, by method name: the dispatch of the methods.

:func:`measure_centroids` (one method) and :func:`measure_methods` (several, the windows prepared once) cut a
window around each detection, take the PSF width of the frame when it is not given
(:func:`~starlog.centroiding.psf_width.estimate_psf_sigma`), run the chosen method on all windows at once, remove
the method's pixel-phase (S-curve) and window-truncation bias with the pixel-integrated Gaussian model of the star
(``debias``), measure the flux with a weighted PSF fit and attach an uncertainty; the robust pass measures again
the windows holding pixels their star cannot explain, a failed method falls back to the coarse position. The
tracked frame finishes GAUSSFIT's rows here (:func:`gaussfit_rows`); :func:`artefact_detections` judges
detections in the same windows.

Coordinates: x = column, y = row, 0-based, (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.centroiding.artefacts import detection_threshold, find_artefacts, light_reach
from starlog.centroiding.bicubic import bicubic_peak
from starlog.centroiding.coarse import log_parabola_peak
from starlog.centroiding.epsf import EPSF, GaussianPSF
from starlog.centroiding.gaussfit import GaussFitResult, fit_gaussians
from starlog.centroiding.gradient import radial_symmetry_centre
from starlog.centroiding.moment import squared_centroid, weighted_centroid
from starlog.centroiding.psf_width import estimate_psf_sigma, window_half_size
from starlog.centroiding.psffit import fit_psf
from starlog.centroiding.robust import mask_windows, suspect_pixels, take_stamps
from starlog.centroiding.stamps import (
    Stamps,
    check_detections,
    check_image,
    default_saturation,
    fisher_sigma,
    gather_stamps,
    linear_flux,
    model,
    optimal_smoothing,
    with_saturated,
)
from starlog.centroiding.table import CENTROID_DTYPE, CentroidFlag, CentroidMethod, empty_centroids
from starlog.centroiding.winpos import window_sigma, windowed_centroid, windowed_centroid_sigma
from starlog.errors import InvalidParameterError

__all__ = ["EFFICIENCY", "artefact_detections", "gaussfit_rows", "measure_centroids", "measure_methods"]

F64 = npt.NDArray[np.float64]

EFFICIENCY: dict[CentroidMethod, float] = {
    CentroidMethod.NONE: 1.0,
    CentroidMethod.MOMENT: 1.0,
    CentroidMethod.MOMENT_SQUARED: 1.05,
    CentroidMethod.BICUBIC: 1.0,
    CentroidMethod.GAUSSFIT: 1.0,
    CentroidMethod.GRADIENT: 1.08,
    CentroidMethod.PSFFIT: 1.0,
    CentroidMethod.WINPOS: 1.0,
}
"""Ratio of each method's measured RMS error to the Cramer-Rao bound (median over the
benchmark's regimes, ``tools/bench_centroid.py``); ``sigma`` = bound x this factor.
GAUSSFIT and PSFFIT take their sigma from the fit covariance instead, WINPOS from its own error
propagation (:func:`starlog.centroiding.winpos.windowed_centroid_sigma`)."""

_SQUARED_SMOOTH = 0.5
_GRADIENT_SMOOTH = 0.75


@dataclass(frozen=True)
class _Estimator:
    """A non-fit method with what it needs besides the windows (one value per star, fixed for a frame).

    ``smooth`` is the noise-optimal smoothing width (:func:`optimal_smoothing`); the radial-
    symmetry centre and the squared centre of gravity take a narrower one (measured best
    widths, ``tools/bench_centroid.py``). ``iterations`` bounds MOMENT's re-weighting.
    """

    method: CentroidMethod
    flux: F64
    psf: F64
    smooth: F64
    weighting: str
    iterations: int = 10

    def __call__(self, data: F64, st: Stamps, x0: F64, y0: F64) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
        """Offsets (dx, dy) from the window centres and where they are valid; ``x0, y0``: start (MOMENT)."""
        method = self.method
        if method is CentroidMethod.NONE:
            return log_parabola_peak(data, st, smooth_sigma=self.smooth)
        if method is CentroidMethod.MOMENT:
            return weighted_centroid(data, st, dx0=x0, dy0=y0, flux=self.flux, psf_sigma=self.psf,
                                     weighting=self.weighting, iterations=self.iterations)
        if method is CentroidMethod.MOMENT_SQUARED:
            return squared_centroid(data, st, smooth_sigma=_SQUARED_SMOOTH * self.smooth)
        if method is CentroidMethod.BICUBIC:
            return bicubic_peak(data, st, smooth_sigma=self.smooth)
        if method is CentroidMethod.GRADIENT:
            return radial_symmetry_centre(data, st, smooth_sigma=_GRADIENT_SMOOTH * self.smooth)
        if method is CentroidMethod.WINPOS:
            return windowed_centroid(data, st.valid, st.u, x0, y0, window_sigma(self.psf))
        raise InvalidParameterError(f"no estimator for method {method!r}.")  # pragma: no cover


@dataclass(frozen=True)
class _Measured:
    """One method's result for every star: offsets from the window centres, flux, errors, fitted background."""

    dx: F64
    dy: F64
    ok: npt.NDArray[np.bool_]
    flux: F64
    flux_err: F64
    sigma: F64
    psf: F64
    background: F64
    unit: F64 | None = None  # the unit model at (dx, dy) (dx0, dy0 where not ok), when the method made it


def _fit(st: Stamps, dx0: F64, dy0: F64, f0: F64, psf: F64, fit_psf_sigma: bool) -> _Measured:
    """GAUSSFIT: every value from the weighted least-squares fit (sigma from its covariance)."""
    fit = fit_gaussians(st, dx0, dy0, f0, psf, fit_sigma=fit_psf_sigma)
    return _Measured(fit.dx, fit.dy, fit.ok, fit.flux, fit.flux_err, fit.sigma, fit.psf_sigma,
                     np.where(fit.ok, fit.background, 0.0))


def _psf_fit(st: Stamps, dx0: F64, dy0: F64, f0: F64, psf: F64, epsf: EPSF | None) -> _Measured:
    """PSFFIT: every value from the weighted least-squares fit of the ePSF (or the Gaussian of ``psf``)."""
    fit = fit_psf(st, dx0, dy0, f0, epsf if epsf is not None else GaussianPSF(float(psf[0])))
    return _Measured(fit.dx, fit.dy, fit.ok, fit.flux, fit.flux_err, fit.sigma, psf,
                     np.where(fit.ok, fit.background, 0.0))


def _estimate(meth: CentroidMethod, st: Stamps, dx0: F64, dy0: F64, f0: F64, psf: F64, *, gain: float,
              weighting: str, debias: bool, passes: int | None = None) -> _Measured:
    """A non-fit method, debiased with the star's model; flux from a PSF fit at the centroid."""
    fm = np.maximum(f0, 0)
    estimator = _Estimator(meth, fm, psf, optimal_smoothing(fm, st.noise, gain, psf), weighting)
    # saturated pixels enter the non-fit estimators at their clipped value (and the model
    # used for debiasing is clipped the same way)
    se = with_saturated(st)
    ex, ey, ok = estimator(se.data, se, dx0, dy0)
    dx, dy = ex.copy(), ey.copy()
    if debias:
        on_model = replace(estimator, iterations=4)  # the model's estimate starts next to its fixed point
        # MOMENT's raw bias is already < 3e-4 px: one pass leaves ~1e-7 px
        secant = meth is CentroidMethod.WINPOS  # its S-curve's slope is far from 1 on under-sampled stars
        previous: tuple[F64, F64, F64, F64] | None = None
        for _ in range(passes or {CentroidMethod.MOMENT: 1, CentroidMethod.WINPOS: 4}.get(meth, 2)):
            mdl = np.minimum(fm[:, None, None] * model(st, dx, dy, psf), se.clip[:, None, None]) * se.valid
            mx, my, mok = on_model(mdl, se, dx, dy)
            good = ok & mok & np.isfinite(mx) & np.isfinite(my)
            sx, sy = (_secant_slope(dx, mx, previous[0], previous[1]), _secant_slope(dy, my, previous[2], previous[3])
                      ) if secant and previous is not None else (1.0, 1.0)
            previous = (dx, mx, dy, my)
            dx = np.where(good, dx + (ex - mx) / sx, dx)
            dy = np.where(good, dy + (ey - my) / sy, dy)
    ok &= np.isfinite(dx) & np.isfinite(dy) & (np.abs(dx) < st.h) & (np.abs(dy) < st.h)
    cx, cy = np.where(ok, dx, dx0), np.where(ok, dy, dy0)
    unit = model(st, cx, cy, psf)
    flux, ferr = linear_flux(st, unit, f0, iterations=1)
    if meth is CentroidMethod.WINPOS:
        sig = windowed_centroid_sigma(np.maximum(flux, 0)[:, None, None] * unit, se.valid, st.u, cx, cy,
                                      window_sigma(psf), st.noise, gain)
    else:
        sig = fisher_sigma(st, cx, cy, np.maximum(flux, 0), psf) * EFFICIENCY[meth]
    return _Measured(dx, dy, ok, flux, ferr, sig, psf, np.zeros_like(flux), unit)


def _secant_slope(position: F64, estimate: F64, position_before: F64, estimate_before: F64) -> F64:
    """Slope of a method's estimate against the true position from two debiasing passes (1 where they are too
    close to tell, kept within [0.2, 2]): the fixed-point step divided by it is the secant method's."""
    step = position - position_before
    with np.errstate(all="ignore"):
        slope = np.where(np.abs(step) > 1e-9, (estimate - estimate_before) / step, 1.0)
    return np.where(np.isfinite(slope), np.clip(slope, 0.2, 2.0), 1.0)


def _with_fallback(m: _Measured, st: Stamps, dx0: F64, dy0: F64, f0: F64) -> _Measured:
    """Failed stars keep the coarse position, a flux fitted there and twice the bound as sigma."""
    ok = m.ok & np.isfinite(m.dx) & np.isfinite(m.dy)
    dx, dy = np.where(ok, m.dx, dx0), np.where(ok, m.dy, dy0)
    flux, ferr, sig = m.flux, m.flux_err, m.sigma
    if not ok.all():
        fl2, fe2 = linear_flux(st, model(st, dx, dy, m.psf), np.maximum(f0, 0))
        flux = np.where(ok, flux, fl2)
        ferr = np.where(ok, ferr, fe2)
        sig = np.where(ok, sig, fisher_sigma(st, dx, dy, np.maximum(flux, 0), m.psf) * 2.0)
    sig = np.where(np.isfinite(sig) & (sig > 0), sig, m.psf)
    ferr = np.where(np.isfinite(ferr) & (ferr > 0), ferr, np.inf)
    return replace(m, dx=dx, dy=dy, ok=ok, flux=flux, flux_err=ferr, sigma=sig)


def _peak_near(st: Stamps, dx: F64, dy: F64) -> F64:
    """Highest background-subtracted pixel within one pixel of the centroid (a saturated one at its clipped level)."""
    n, h = dx.size, st.h
    ix = np.minimum(np.maximum(np.rint(dx).astype(np.intp) + h, 1), 2 * h - 1)
    iy = np.minimum(np.maximum(np.rint(dy).astype(np.intp) + h, 1), 2 * h - 1)
    ar = np.arange(n)[:, None]
    d3 = np.arange(-1, 2)
    sp = with_saturated(st)
    raw = np.where(sp.valid, sp.data, -np.inf)
    p3 = raw[ar[:, :, None], (iy[:, None] + d3)[:, :, None], (ix[:, None] + d3)[:, None, :]]
    peak = p3.reshape(n, -1).max(axis=1)
    return np.where(np.isfinite(peak), peak, 0.0)


def _check_options(method: CentroidMethod | str, gain: float, read_noise: float | None, psf_sigma: float | None,
                   weighting: str) -> CentroidMethod:
    try:
        meth = CentroidMethod(method)
    except ValueError as err:
        raise InvalidParameterError(
            f"unknown centroid method {method!r}; choose one of {[m.value for m in CentroidMethod]}."
        ) from err
    if not (gain > 0 and np.isfinite(gain)):
        raise InvalidParameterError(f"gain must be finite and > 0 (e-/DN), got {gain!r}.")
    if read_noise is not None and not (read_noise >= 0):
        raise InvalidParameterError(f"read_noise must be >= 0 e-, got {read_noise!r}.")
    if psf_sigma is not None and not (psf_sigma > 0 and np.isfinite(psf_sigma)):
        raise InvalidParameterError(f"psf_sigma must be finite and > 0 px, got {psf_sigma!r}.")
    if weighting not in ("optimal", "gaussian", "none"):
        raise InvalidParameterError(f"weighting must be 'optimal', 'gaussian' or 'none', got {weighting!r}.")
    return meth


def measure_centroids(
    image: npt.ArrayLike,
    detections: npt.NDArray[Any],
    *,
    method: CentroidMethod | str = CentroidMethod.GAUSSFIT,
    gain: float = 1.0,
    read_noise: float | None = None,
    psf_sigma: float | None = None,
    window: int | None = None,
    saturation: float | None = None,
    debias: bool = True,
    weighting: str = "optimal",
    fit_psf_sigma: bool = False,
    epsf: EPSF | None = None,
    robust: bool = True,
) -> npt.NDArray[np.void]:
    """Sub-pixel centroids of detected stars.

    Parameters
    ----------
    image : (rows, cols) array_like
        The frame the detections come from, DN (uint8/uint16/float; pedestal allowed).
    detections : ndarray of DETECTION_DTYPE
        From :func:`starlog.detect.detect_stars` (fields star, x, y, background, noise, flux,
        flags are used).
    method : CentroidMethod or str
        NONE, MOMENT, MOMENT_SQUARED, BICUBIC, GAUSSFIT, GRADIENT, PSFFIT or WINPOS.
    gain : float
        Camera gain, e-/DN (for the star's shot noise in weights and ``sigma``).
    read_noise : float, optional
        Read noise, e- RMS: a floor on the background noise (``read_noise / gain`` DN). The
        measured background noise (detections' ``noise``) is used otherwise.
    psf_sigma : float, optional
        Gaussian PSF sigma, px. Estimated from the frame's bright stars when not given.
    window : int, optional
        Half-size of the square window, px. Default ``max(3, ceil(3.5 psf_sigma) + 1)``.
    saturation : float, optional
        Saturation level, DN (default: the dtype maximum for integers, none for floats).
        Saturated pixels are left out.
    debias : bool
        Remove the pixel-phase / truncation bias of non-fit methods with the star's model.
    weighting : {"optimal", "gaussian", "none"}
        MOMENT weighting (see :mod:`starlog.centroiding.moment`).
    fit_psf_sigma : bool
        GAUSSFIT: fit the PSF sigma per star too (default: fixed to ``psf_sigma``).
    epsf : EPSF, optional
        PSFFIT: the empirical PSF to fit (:func:`starlog.centroiding.epsf.build_epsf`); without
        it, PSFFIT fits the pixel-integrated Gaussian of ``psf_sigma``. Other methods ignore it.
    robust : bool
        Leave out the pixels of a star's window that its fitted profile plus noise cannot
        explain (cosmic ray, hot pixel, a neighbour's wing) and measure the star again
        (:mod:`starlog.centroiding.robust`); such stars are flagged ``MASKED``, with the count in
        ``n_masked``.

    Returns
    -------
    ndarray of CENTROID_DTYPE, shape (n,)
        One row per detection, in the detections' order; (0,) when there are none.
    """
    (rows,) = measure_methods(image, detections, [method], gain=gain, read_noise=read_noise, psf_sigma=psf_sigma,
                              window=window, saturation=saturation, debias=debias, weighting=weighting,
                              fit_psf_sigma=fit_psf_sigma, epsf=epsf, robust=robust).values()
    return rows


def measure_methods(image: npt.ArrayLike, detections: npt.NDArray[Any], methods: Iterable[CentroidMethod | str], *,
                    gain: float = 1.0, read_noise: float | None = None, psf_sigma: float | None = None,
                    window: int | None = None, saturation: float | None = None, debias: bool = True,
                    weighting: str = "optimal", fit_psf_sigma: bool = False, epsf: EPSF | None = None,
                    robust: bool = True) -> dict[CentroidMethod, npt.NDArray[np.void]]:
    """:func:`measure_centroids` by several methods, ``{method: rows}``: the stars' windows, coarse
    positions and first fluxes, which do not depend on the method, are prepared once."""
    arr = check_image(image)
    det = check_detections(detections)
    meths = [_check_options(m, gain, read_noise, psf_sigma, weighting) for m in methods]
    if det.size == 0:
        return {m: empty_centroids() for m in meths}
    psf = float(psf_sigma) if psf_sigma is not None else estimate_psf_sigma(arr, det, gain=gain, saturation=saturation)
    options = {"gain": gain, "weighting": weighting, "debias": debias, "fit_psf_sigma": fit_psf_sigma, "epsf": epsf}
    frames: dict[int, _Frame] = {}
    out: dict[CentroidMethod, npt.NDArray[np.void]] = {}
    for meth in meths:
        h = window_half_size(psf, window)
        if meth is CentroidMethod.PSFFIT and epsf is not None:
            h = max(2, min(h, epsf.half_size - 1))  # the ePSF covers every pixel of the window at any sub-pixel shift
        if h not in frames:
            frames[h] = _prepare(arr, det, h, psf, gain, read_noise, default_saturation(arr, saturation))
        out[meth] = _centroids_of(meth, frames[h], robust=robust, **options)
    return out


@dataclass(frozen=True)
class _Frame:
    """What every method starts from: the detections, their windows, the coarse offsets from the
    window centres, a first flux there, the PSF width per star and the window pixels left out."""

    det: npt.NDArray[Any]
    st: Stamps
    dx0: F64
    dy0: F64
    f0: F64
    psf: F64
    left_out: npt.NDArray[np.int32]


def _prepare(arr: npt.NDArray[Any], det: npt.NDArray[Any], h: int, psf: float, gain: float,
             read_noise: float | None, saturation: float) -> _Frame:
    st = _star_stamps(arr, det, h, gain, read_noise, saturation)
    dx0, dy0 = np.asarray(det["x"], np.float64) - st.xc, np.asarray(det["y"], np.float64) - st.yc
    psf_arr = np.full(det.size, psf)
    f0, _ = linear_flux(st, model(st, dx0, dy0, psf_arr), np.asarray(det["flux"], np.float64), iterations=1)
    return _Frame(det, st, dx0, dy0, f0, psf_arr, _left_out(st, arr.shape))


def _centroids_of(meth: CentroidMethod, frame: _Frame, *, robust: bool, measured: _Measured | None = None,
                  **options: Any) -> npt.NDArray[np.void]:
    """One method's CENTROID_DTYPE rows from a prepared frame (robust re-measurement included); ``measured``:
    the method's result on the frame's windows, when already at hand."""
    st, dx0, dy0, f0, psf = frame.st, frame.dx0, frame.dy0, frame.f0, frame.psf
    if measured is None:
        measured = _measure(meth, st, dx0, dy0, f0, psf, **options)
    n_masked = frame.left_out.copy()
    if robust:
        measured, st, n_outliers = _remeasure_robust(meth, st, measured, dx0, dy0, f0, psf, **options)
        n_masked += n_outliers
    return _centroid_table(frame.det, st, _with_fallback(measured, st, dx0, dy0, f0), n_masked)


def gaussfit_rows(detections: npt.NDArray[Any], stamps: Stamps, dx0: F64, dy0: F64, f0: F64, fit: GaussFitResult,
                  left_out: npt.NDArray[np.int32], *, psf_sigma: float, gain: float, fit_psf_sigma: bool = False,
                  robust: bool = True) -> npt.NDArray[np.void]:
    """GAUSSFIT's rows of :func:`measure_methods` from its first steps done elsewhere (the tracked frame's compiled
    loops): the detections' windows as it cuts them, the coarse offsets, the first flux, the fit from there
    (:func:`~starlog.centroiding.gaussfit.fit_gaussians` with ``psf_sigma``) and the window pixels left out. The rest,
    the robust re-measurement, a failed fit's fallback and the table, is done here: the same bytes."""
    measured = _Measured(fit.dx, fit.dy, fit.ok, fit.flux, fit.flux_err, fit.sigma, fit.psf_sigma,
                         np.where(fit.ok, fit.background, 0.0))
    frame = _Frame(detections, stamps, dx0, dy0, f0, np.full(dx0.size, float(psf_sigma)), left_out)
    return _centroids_of(CentroidMethod.GAUSSFIT, frame, robust=robust, measured=measured, gain=gain,
                         weighting="optimal", debias=True, fit_psf_sigma=fit_psf_sigma)


def _measure(meth: CentroidMethod, st: Stamps, dx0: F64, dy0: F64, f0: F64, psf: F64, *, gain: float,
             weighting: str, debias: bool, fit_psf_sigma: bool, epsf: EPSF | None = None,
             passes: int | None = None) -> _Measured:
    """One method on every window; ``epsf``: the PSF PSFFIT fits; ``passes``: debiasing passes of a
    non-fit method (default: its own)."""
    if meth is CentroidMethod.GAUSSFIT:
        return _fit(st, dx0, dy0, f0, psf, fit_psf_sigma)
    if meth is CentroidMethod.PSFFIT:
        return _psf_fit(st, dx0, dy0, f0, psf, epsf)
    return _estimate(meth, st, dx0, dy0, f0, psf, gain=gain, weighting=weighting, debias=debias, passes=passes)


def _left_out(st: Stamps, shape: tuple[int, ...]) -> npt.NDArray[np.int32]:
    """Pixels of each window inside the frame that are invalid but not saturated (non-finite, hot)."""
    d = np.arange(-st.h, st.h + 1)
    rows = ((st.yc[:, None] + d >= 0) & (st.yc[:, None] + d < shape[0])).sum(axis=1)
    cols = ((st.xc[:, None] + d >= 0) & (st.xc[:, None] + d < shape[1])).sum(axis=1)
    invalid = (~st.valid & ~st.satpix).sum(axis=(1, 2))
    return (invalid - (d.size**2 - rows * cols)).astype(np.int32)


def _remeasure_robust(meth: CentroidMethod, st: Stamps, m: _Measured, dx0: F64, dy0: F64, f0: F64, psf: F64,
                      **options: Any) -> tuple[_Measured, Stamps, npt.NDArray[np.int32]]:
    """Stars whose window holds pixels their model at the method's centroid cannot explain are
    measured again without the pixels :func:`mask_outliers` leaves out.

    Clean windows cost one model evaluation; only suspect ones are fitted and re-measured.
    Returns the results, the stamps (masked pixels invalid) and the masked pixels per star.
    """
    n_out = np.zeros(st.xc.size, np.int32)
    ok = m.ok & np.isfinite(m.dx) & np.isfinite(m.dy)
    cx, cy = np.where(ok, m.dx, dx0), np.where(ok, m.dy, dy0)
    flux = np.where(ok & np.isfinite(m.flux), m.flux, f0)
    unit = m.unit if m.unit is not None else model(st, cx, cy, m.psf)
    mu = np.maximum(flux, 0)[:, None, None] * unit + m.background[:, None, None]
    suspect, error = suspect_pixels(st, mu)
    strayed = _strayed(cx - dx0, cy - dy0, m.psf)
    rows = np.flatnonzero(suspect.any(axis=(1, 2)) | strayed)
    if rows.size == 0:
        return m, st, n_out
    clean, mask, fx, fy = mask_windows(st, rows, psf, error)
    hit = mask.any(axis=(1, 2)) | strayed[rows]
    rows, clean, fx, fy = rows[hit], take_stamps(clean, np.flatnonzero(hit)), fx[hit], fy[hit]
    if rows.size == 0:
        return m, st, n_out
    f1, _ = linear_flux(clean, model(clean, fx, fy, psf[rows]), f0[rows], iterations=1)
    # a window with holes is far from symmetric: the debiasing needs more fixed-point passes
    again = _measure(meth, clean, fx, fy, f1, psf[rows], passes=3, **options)
    n_out[rows] = mask[hit].sum(axis=(1, 2))
    out = replace(st, valid=st.valid.copy(), data=st.data.copy(), satpix=st.satpix.copy())
    out.valid[rows], out.data[rows], out.satpix[rows] = clean.valid, clean.data, clean.satpix
    merged = {name: getattr(m, name).copy() for name in ("dx", "dy", "ok", "flux", "flux_err", "sigma", "psf",
                                                         "background")}
    for name, values in merged.items():
        values[rows] = getattr(again, name)
    return _Measured(**merged), out, n_out


def _strayed(dx: F64, dy: F64, psf: F64) -> npt.NDArray[np.bool_]:
    """Centroids farther from the detection than a star's light reaches (:func:`light_reach`):
    drawn off by an artefact in the window (a cosmic ray a re-weighted centre of gravity converged on)."""
    return np.hypot(dx, dy) > light_reach(psf)


def _star_stamps(arr: npt.NDArray[Any], det: npt.NDArray[Any], h: int, gain: float, read_noise: float | None,
                 saturation: float) -> Stamps:
    """Windows of half-size ``h`` around the detections, with their background and noise (read-noise floor)."""
    noise = np.asarray(det["noise"], np.float64)
    if read_noise is not None:
        noise = np.maximum(noise, read_noise / gain)
    noise = np.where(np.isfinite(noise) & (noise > 0), noise, 1.0)
    bg = np.asarray(det["background"], np.float64)
    return gather_stamps(arr, np.asarray(det["x"], np.float64), np.asarray(det["y"], np.float64), h,
                         np.where(np.isfinite(bg), bg, 0.0), noise, gain, saturation)


def _centroid_table(det: npt.NDArray[Any], st: Stamps, m: _Measured,
                    n_masked: npt.NDArray[np.int32] | None = None) -> npt.NDArray[np.void]:
    """The CENTROID_DTYPE rows: positions, flux, SNR, sigma, peak, background, flags, masked pixels."""
    snr = np.where(np.isfinite(m.flux_err), m.flux / m.flux_err, 0.0)
    flags = np.asarray(det["flags"], np.uint16).copy()
    flags &= np.uint16(~int(CentroidFlag.FIT_FAILED | CentroidFlag.LOW_SNR) & 0xFFFF)
    flags[st.saturated] |= np.uint16(CentroidFlag.SATURATED)
    flags[st.cut] |= np.uint16(CentroidFlag.BORDER)
    flags[st.masked] |= np.uint16(CentroidFlag.MASKED)
    flags[~m.ok] |= np.uint16(CentroidFlag.FIT_FAILED)
    flags[snr < 5.0] |= np.uint16(CentroidFlag.LOW_SNR)
    out = np.zeros(det.size, dtype=CENTROID_DTYPE)
    out["star"] = det["star"]
    out["x"] = st.xc + m.dx
    out["y"] = st.yc + m.dy
    out["flux"] = m.flux
    out["snr"] = snr
    out["sigma"] = m.sigma
    out["peak"] = _peak_near(st, m.dx, m.dy)
    out["background"] = np.asarray(det["background"], np.float64) + m.background
    out["psf_sigma"] = m.psf
    if n_masked is not None:
        out["n_masked"] = n_masked
        flags[n_masked > 0] |= np.uint16(CentroidFlag.MASKED)
    out["flags"] = flags
    return out


def artefact_detections(image: npt.ArrayLike, detections: npt.NDArray[Any], *, psf_sigma: float, gain: float = 1.0,
                        read_noise: float | None = None, window: int | None = None, saturation: float | None = None,
                        detect_options: Mapping[str, Any] | None = None,
                        candidates: npt.NDArray[np.bool_] | None = None) -> npt.NDArray[np.bool_]:
    """Which detections exist only because of an artefact (:mod:`starlog.centroiding.artefacts`), judged in
    their windows (``window``, ``gain``, ``read_noise``, ``saturation`` as in :func:`measure_centroids`)
    under the threshold rule of the detector's ``detect_options`` (:func:`starlog.detect.detect_stars`).

    ``candidates``: judge only these detections (the others are not artefacts), e.g. the
    :func:`masked_rows` of their centroids: a window the robust pass left whole is one its star's
    profile explains, so a clean frame costs nothing here.
    """
    arr = check_image(image)
    det = check_detections(detections)
    if det.size == 0 or (candidates is not None and not np.any(candidates)):
        return np.zeros(det.size, np.bool_)
    psf = float(psf_sigma)
    frame = _prepare(arr, det, window_half_size(psf, window), psf, gain, read_noise, default_saturation(arr, saturation))
    noise = np.asarray(det["noise"], np.float64)
    noise = np.where(np.isfinite(noise) & (noise > 0), noise, frame.st.noise)
    threshold, filter_sigma = detection_threshold(detect_options)
    return find_artefacts(frame.st, frame.dx0, frame.dy0, frame.f0, frame.psf, noise, threshold=threshold,
                          filter_sigma=filter_sigma, candidates=candidates)
