"""Robust star windows: pixels that the star's model plus noise cannot explain are left out.

A cosmic-ray track, a hot pixel or a neighbour's wing inside a star's window adds charge the
star's profile does not predict. Each pixel's residual over the predicted star (its fitted
profile, ``mu``) is compared with the pixel's predicted noise,

    z = (d - mu) / sqrt(noise^2 + mu / gain + (e_core * mu)^2 + (e_halo * peak)^2),

(background noise, the star's shot noise, and the model's own error for PSFs that are not
exactly the model: ``e_core`` and ``e_halo`` are measured on the frame's bright stars, cores
and wings, by :func:`model_error`, 0 when the model fits), and pixels with ``z > k`` are
masked, their 8-neighbours with ``z > GROW_SIGMA`` too (the faint edge of a track). The star
is re-fitted without them and the test repeated, five fits at most (:func:`mask_outliers`).
Only excesses are masked: every artefact named above adds charge, and a dead pixel belongs in
a bad-pixel map. Where the model misses the frame's stars (:attr:`ModelError.significant`),
an outlier must also be light that is not mirrored about the star (a star's own light is
symmetric, a trail or a halo included; an artefact is not).

``k`` is not a tuning constant: it is the level a window of ``n`` clean pixels exceeds by
chance with probability :data:`FALSE_MASK_PROBABILITY` (:func:`clip_level`), moved to the
skewed tail of shot noise (:func:`skew_corrected`), so a clean star is masked in about one
window in a thousand whatever the window size, the camera or the PSF.

The star's model is a parameter (:data:`Predictor`): the pixel-integrated Gaussian fit by
default (:func:`gaussian_predictor`); another PSF model (an empirical PSF) plugs in the same way.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.special import ndtri

from starlog.centroiding.stamps import Stamps, model, variance
from starlog.centroiding.gaussfit import fit_gaussians

__all__ = [
    "FALSE_MASK_PROBABILITY",
    "GROW_SIGMA",
    "ModelError",
    "Predictor",
    "clip_level",
    "core_flux",
    "gaussian_predictor",
    "mask_outliers",
    "mask_windows",
    "model_error",
    "outlier_pixels",
    "skew_corrected",
    "suspect_pixels",
    "symmetry_centre",
    "symmetry_shifts",
    "symmetry_shifts_vectorised",
    "take_stamps",
    "without_pixels",
]

F64 = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]

FALSE_MASK_PROBABILITY = 1e-3
"""Chance that a clean window (exact model) has at least one pixel masked."""

GROW_SIGMA = 2.0
"""Neighbours of a masked pixel are masked from this many sigma of excess (a track's faint edge)."""

_MEDIAN_CHI2_1 = 0.45494
"""Median of a chi-square variable with one degree of freedom."""

Predictor = Callable[[Stamps, F64, F64, F64], tuple[F64, F64, F64]]
"""``predict(stamps, dx, dy, flux) -> (mu, dx, dy)``: each star's fitted model (DN above the
stamp background, (N, W, W), on the stamps' valid pixels) and its fitted centre, starting from
``(dx, dy, flux)``."""


def clip_level(n_pixels: int | npt.NDArray[np.integer], probability: float = FALSE_MASK_PROBABILITY) -> F64:
    """Excess (in sigma) that ``n_pixels`` independent Gaussian pixels pass with total chance ``probability``.

    One-sided per-pixel tail ``probability / n`` (union bound): ``k = Phi^-1(1 - probability / n)``;
    3.7 sigma for an 81-pixel window, 4.0 for 289 pixels.
    """
    n = np.maximum(np.asarray(n_pixels, np.float64), 1.0)
    return np.asarray(-ndtri(probability / n), np.float64)


def _max3x3(a: F64) -> F64:
    """Each window's maximum over every pixel's 3x3 neighbourhood (inside the window)."""
    out = a.copy()
    out[:, 1:, :] = np.maximum(out[:, 1:, :], a[:, :-1, :])
    out[:, :-1, :] = np.maximum(out[:, :-1, :], a[:, 1:, :])
    rows = out.copy()
    out[:, :, 1:] = np.maximum(out[:, :, 1:], rows[:, :, :-1])
    out[:, :, :-1] = np.maximum(out[:, :, :-1], rows[:, :, 1:])
    return out


def _dilate(mask: Mask) -> Mask:
    """Each window's mask grown by one pixel into its 8-neighbours."""
    out = mask.copy()
    out[:, 1:, :] |= mask[:, :-1, :]
    out[:, :-1, :] |= mask[:, 1:, :]
    grown = out.copy()
    grown[:, :, 1:] |= out[:, :, :-1]
    grown[:, :, :-1] |= out[:, :, 1:]
    return grown


def skew_corrected(k: F64, sd: F64, gain: float) -> F64:
    """The ``k``-sigma level of Gaussian noise moved to the same tail probability of shot noise.

    Photon noise is skewed: in DN its third cumulant is its variance / gain, so the skewness is
    at most ``1 / (gain sd)`` (all of the variance Poissonian). The Cornish-Fisher expansion
    gives the level ``k + (k^2 - 1) skew / 6``; the bound keeps it conservative (read noise
    only makes the true tail lighter).
    """
    skew = np.minimum(1.0 / (gain * sd), 1.0)
    return k + (k * k - 1.0) * skew / 6.0


@dataclass(frozen=True)
class ModelError:
    """How far the frame's stars depart from their model beyond noise (:func:`model_error`).

    ``core``: relative to the local model (a core shape the model lacks); ``halo``: relative to
    the star's peak (wings the model lacks, e.g. a real PSF's halo around a Gaussian core);
    ``misfit``: how much the bright stars' residuals exceed their noise, in variance.
    """

    core: float = 0.0
    halo: float = 0.0
    misfit: float = 1.0

    @property
    def significant(self) -> bool:
        """The bright stars' residuals exceed their noise by half its variance or more (``misfit``:
        the typical star's median of ``r^2 / var`` over a chi-square's, 1 when the model fits; its
        spread over ten stars is ~0.1): then only light that is not mirrored about the star can
        be an artefact."""
        return self.misfit > 1.5

    def variance(self, mu: F64) -> F64:
        """The model error's variance at each pixel of the predicted stars ``mu``, DN^2."""
        base = mu.min(axis=(1, 2), keepdims=True)
        star = np.clip(mu - base, 0.0, None)
        peak = star.max(axis=(1, 2), keepdims=True)
        return (self.core * star) ** 2 + (self.halo * peak) ** 2


def _excess_level(r: F64, var: F64, scale: F64, use: Mask) -> float:
    """sqrt of the median of ``(r^2 / m1 - var) / scale^2`` over the ``use`` pixels: 0 for pure noise,
    else the departure per ``scale``."""
    if not use.any():
        return 0.0
    t = (r[use] ** 2 / _MEDIAN_CHI2_1 - var[use]) / scale[use] ** 2
    return float(np.sqrt(max(float(np.median(t)), 0.0)))


def model_error(st: Stamps, mu: F64, min_snr: float = 10.0) -> ModelError:
    """The model's error on the frame, measured on its stars: how far they depart from ``mu`` beyond noise.

    ``core``: over the pixels where the predicted star is ``min_snr`` times its noise (where a
    model error shows at all), the median of ``(r^2 / m1 - var) / mu^2`` (``m1``: the median of a
    chi-square with one degree of freedom, so pure noise gives 0). ``halo``: the same relative
    to the star's peak over the wing (model 1e-4 to 0.1 of the peak) of stars whose peak is
    ``min_snr`` times the noise. An artefact touches a few pixels and does not move a median;
    a PSF the model does not describe moves every core or wing pixel.
    """
    var = variance(st, mu)
    r = st.data - mu
    base = mu.min(axis=(1, 2), keepdims=True)
    star = mu - base
    core = st.valid & (star > min_snr * np.sqrt(var))
    eps = _excess_level(r, var, star, core)
    peak = star.max(axis=(1, 2), keepdims=True)
    rel = star / np.where(peak > 0, peak, 1.0)
    wing = st.valid & (rel >= 1e-4) & (rel <= 0.1) & (peak > min_snr * st.noise[:, None, None])
    halo = _excess_level(r, var + (eps * star) ** 2, np.broadcast_to(peak, star.shape), wing)
    lit = core | (wing & (star > np.sqrt(var)))  # where the star is above its noise
    bright = lit.any(axis=(1, 2))
    if not bright.any():
        return ModelError(eps, halo)
    ratio = np.where(lit, r * r / (_MEDIAN_CHI2_1 * var), np.nan)[bright]
    misfit = float(np.median(np.nanmedian(ratio.reshape(ratio.shape[0], -1), axis=1)))
    return ModelError(eps, halo, misfit)


def symmetry_shifts(st: Stamps, reach: int = 2) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """Each star's centre of symmetry, as twice its offset from the window centre (up to ``reach``
    half pixels per axis: a window may be centred on an artefact next to its star).

    The reflection that changes the window least (mean absolute difference between the pixels
    and their mirrors, over the valid pairs inside the window): a star's light decides it
    whatever its shape, and an artefact weighs on every candidate alike. Compiled
    (:func:`starlog.centroiding.star_kernels.symmetry_shifts`); :func:`symmetry_shifts_vectorised` is the same in
    numpy, bit for bit.
    """
    from starlog.centroiding.star_kernels import symmetry_shifts as compiled  # numba: imported, and compiled, on use

    n = st.data.shape[0]
    shift_x, shift_y = np.empty(n, np.intp), np.empty(n, np.intp)
    compiled(np.ascontiguousarray(st.data, np.float64), np.ascontiguousarray(st.valid, np.bool_), int(reach),
             shift_x, shift_y)
    return shift_x, shift_y


def symmetry_shifts_vectorised(st: Stamps, reach: int = 2) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """:func:`symmetry_shifts` in numpy: the reference the tests compare the compiled loop with."""
    n = st.data.shape[0]
    best = np.full(n, np.inf)
    shift_x = np.zeros(n, np.intp)
    shift_y = np.zeros(n, np.intp)
    for sy in range(-reach, reach + 1):
        for sx in range(-reach, reach + 1):
            mirror, inside = _mirrored(st.data, (np.full(n, sx), np.full(n, sy)))
            mirror_valid, _ = _mirrored(st.valid, (np.full(n, sx), np.full(n, sy)))
            pair = st.valid & mirror_valid & inside
            cost = (np.abs(st.data - mirror) * pair).sum(axis=(1, 2)) / np.maximum(pair.sum(axis=(1, 2)), 1)
            better = cost < best
            best = np.where(better, cost, best)
            shift_x = np.where(better, sx, shift_x)
            shift_y = np.where(better, sy, shift_y)
    return shift_x, shift_y


def symmetry_centre(st: Stamps) -> tuple[F64, F64]:
    """Each star's centre of symmetry (offsets from the window centre, to the half pixel): a start
    that an artefact does not pull, unlike a centroid or a fit over the whole window."""
    shift_x, shift_y = symmetry_shifts(st)
    return 0.5 * shift_x, 0.5 * shift_y


def _mirrored(a: npt.NDArray[Any], shifts: tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]
              ) -> tuple[npt.NDArray[Any], Mask]:
    """Each window point-reflected about its star's centre of symmetry (:func:`symmetry_shifts`):
    the value at the mirror pixel of every pixel, and where that mirror pixel lies inside the window."""
    n, w, _ = a.shape
    h = (w - 1) // 2
    idx = np.arange(w)
    jx = 2 * h + shifts[0][:, None] - idx[None, :]
    jy = 2 * h + shifts[1][:, None] - idx[None, :]
    inside = ((jy >= 0) & (jy < w))[:, :, None] & ((jx >= 0) & (jx < w))[:, None, :]
    rows = np.arange(n)[:, None, None]
    return a[rows, np.clip(jy, 0, w - 1)[:, :, None], np.clip(jx, 0, w - 1)[:, None, :]], inside


def outlier_pixels(st: Stamps, mu: F64, k: F64 | float | None = None, error: ModelError = ModelError(),
                   symmetric: bool | None = None) -> Mask:
    """Valid pixels whose excess over ``mu`` is above ``k`` sigma of their predicted noise (plus grown edges).

    With ``symmetric``, an outlier must also stand ``k`` sigma above the brightest pixel around
    its mirror pixel (point reflection about the star's centre of symmetry, within one pixel):
    a star's own light is symmetric even where the model is not (a trailed or elongated PSF, a
    halo), an artefact is not; a pixel whose mirror is outside the window is judged on the
    model alone. ``symmetric`` default: only when the model misses the frame's stars
    (:attr:`ModelError.significant`); where the model fits, it alone is the best judge. A star with
    saturated pixels is always judged by symmetry: its model, fitted to what is left of it (its wings),
    cannot describe the light next to its clipped core (bloom, a JPEG's ringing), which is mirrored
    about the star like the rest of it.
    ``k`` default: :func:`clip_level` of each window's number of valid pixels, moved to the
    shot-noise tail (:func:`skew_corrected`); ``error``: the model's own error
    (:func:`model_error`).
    """
    if k is None:
        k = clip_level(st.valid.sum(axis=(1, 2)))
    kk = np.broadcast_to(np.asarray(k, np.float64), (st.data.shape[0],))[:, None, None]
    sd = np.sqrt(variance(st, mu))
    excess = np.where(st.valid, st.data - mu, 0.0)
    var = sd * sd + error.variance(mu)
    z = excess / np.sqrt(var)
    level = skew_corrected(kk, sd, st.gain)
    core = z > level
    by_symmetry = (error.significant if symmetric is None else symmetric) | st.saturated
    if not core.any() or not by_symmetry.any():
        return st.valid & (core | (_dilate(core) & (z > GROW_SIGMA))) if core.any() else core
    # the star's own light is mirrored about its centre: a pixel no brighter (beyond noise) than
    # the brightest pixel around its mirror is that light, not an artefact
    mirror_max, inside = _mirrored(_max3x3(np.where(st.valid | st.satpix, _with_clipped(st), -np.inf)),
                                   symmetry_shifts(st))
    mirror_max = np.where(inside, mirror_max, -np.inf)
    core &= ~by_symmetry[:, None, None] | ((st.data - mirror_max) > level * np.sqrt(2.0 * var))
    if not core.any():
        return core
    return st.valid & (core | (_dilate(core) & (z > GROW_SIGMA)))


def _with_clipped(st: Stamps) -> F64:
    """The windows' pixels with the saturated ones at their clipped level (a saturated mirror pixel is at
    least that bright)."""
    return np.where(st.satpix, st.clip[:, None, None], st.data) if st.saturated.any() else st.data


def suspect_pixels(st: Stamps, mu: F64) -> tuple[Mask, ModelError]:
    """:func:`outlier_pixels` of the model ``mu`` with the frame's :func:`model_error` (model test
    only: ``mu`` may be centred on an artefact, its mirror pixels with it), and that error.

    A clean frame costs one comparison: no pixel above the plain ``k``-sigma level (a lower
    bound of the full test's level) means no outlier, and the rest is skipped; nor does any
    when no pixel passes the shot-noise level with the model's error left out (the model error
    only adds variance), checked on the few pixels above the plain level.
    """
    k = clip_level(st.valid.sum(axis=(1, 2)))[:, None, None]
    r = st.data - mu
    var = variance(st, mu)
    above = st.valid & (r > 0) & (r * r > k * k * var)
    if not above.any():
        return np.zeros_like(st.valid), ModelError()
    sd = np.sqrt(var[above])
    if not np.any(r[above] > skew_corrected(np.broadcast_to(k, r.shape)[above], sd, st.gain) * sd):
        return np.zeros_like(st.valid), ModelError()
    error = model_error(st, mu)
    return outlier_pixels(st, mu, error=error, symmetric=False), error


def take_stamps(st: Stamps, rows: npt.NDArray[np.intp]) -> Stamps:
    """The stamps of the stars ``rows`` only."""
    per_star = {f.name: getattr(st, f.name)[rows] for f in fields(st)
                if isinstance(getattr(st, f.name), np.ndarray) and np.ndim(getattr(st, f.name)) >= 1}
    return replace(st, **per_star)


def without_pixels(st: Stamps, mask: Mask) -> Stamps:
    """The stamps with the pixels of ``mask`` left out (invalid, data 0)."""
    valid = st.valid & ~mask
    return replace(st, valid=valid, data=np.where(valid, st.data, 0.0), satpix=st.satpix & ~mask)


def gaussian_predictor(psf_sigma: F64) -> Predictor:
    """The pixel-integrated Gaussian of width ``psf_sigma`` (per star) fitted with a constant background."""

    def predict(st: Stamps, dx: F64, dy: F64, flux: F64) -> tuple[F64, F64, F64]:
        fit = fit_gaussians(st, dx, dy, flux, psf_sigma, iterations=6, tol=1e-3)
        cx = np.where(fit.ok, fit.dx, dx)
        cy = np.where(fit.ok, fit.dy, dy)
        f = np.where(fit.ok, fit.flux, flux)
        b = np.where(fit.ok, fit.background, 0.0)
        return f[:, None, None] * model(st, cx, cy, psf_sigma) + b[:, None, None], cx, cy

    return predict


def core_flux(st: Stamps, unit: F64) -> F64:
    """Each star's flux from its core alone: the median of data / model where the unit model is at
    least half its peak (an artefact on the wing does not enter; one in the core is outvoted)."""
    core = st.valid & (unit >= 0.5 * unit.max(axis=(1, 2), keepdims=True)) & (unit > 0)
    ratio = np.where(core, st.data / np.where(core, unit, 1.0), np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a window without a valid core pixel: 0 below
        flux = np.nanmedian(ratio.reshape(ratio.shape[0], -1), axis=1)
    return np.where(np.isfinite(flux), np.maximum(flux, 0.0), 0.0)


def mask_outliers(st: Stamps, predict: Predictor, dx: F64, dy: F64, start: F64, *, error: ModelError = ModelError(),
                  iterations: int = 5) -> tuple[Stamps, Mask, F64, F64]:
    """Mask the pixels the star's fitted model cannot explain, re-fitting after each pass.

    ``start``: a first prediction of each star (N, W, W), e.g. the model at its
    :func:`symmetry_centre` scaled to :func:`core_flux`, not fitted to the window (an artefact
    can pull a fit onto itself); ``(dx, dy)``: its centre. Each pass fits ``predict`` (from ``(dx, dy)``) without the current mask
    and tests every pixel of the window against that fit again (a pixel wrongly suspected
    comes back); it stops when the mask no longer changes or after ``iterations`` fits.
    ``error``: the model's own error on the frame (:func:`model_error`).
    Returns the stamps without the masked pixels, the mask (N, W, W) and the last fitted centre.
    """
    mask = outlier_pixels(st, start, error=error, symmetric=False)  # the start is no fit: every suspect out
    cx, cy = dx, dy
    flux = np.maximum(start.sum(axis=(1, 2)), 0.0)
    for _ in range(iterations):
        mu, cx, cy = predict(without_pixels(st, mask), cx, cy, flux)
        new = outlier_pixels(st, mu, error=error)
        if np.array_equal(new, mask):
            break
        mask = new
    return without_pixels(st, mask), mask, cx, cy


def mask_windows(st: Stamps, rows: npt.NDArray[np.intp], psf: F64, error: ModelError = ModelError()
                 ) -> tuple[Stamps, Mask, F64, F64]:
    """:func:`mask_outliers` of the stars ``rows`` with the pixel-integrated Gaussian of width ``psf``
    (one value per star of ``st``), started from the model at their :func:`symmetry_centre` scaled
    to their :func:`core_flux` (neither is pulled by an artefact, unlike the coarse position).

    Returns the stamps of those stars without the masked pixels, the mask and the fitted centre.
    """
    sub = take_stamps(st, rows)
    sx, sy = symmetry_centre(sub)
    unit = model(sub, sx, sy, psf[rows])
    start = core_flux(sub, unit)[:, None, None] * unit
    return mask_outliers(sub, gaussian_predictor(psf[rows]), sx, sy, start, error=error)
