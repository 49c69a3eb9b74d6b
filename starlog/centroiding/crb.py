"""Cramer-Rao lower bound on the centroid of a pixel-integrated Gaussian star.

Pixel model (electrons): ``mu_ij = sky + F * E(j - x; s) * E(i - y; s)`` with ``E`` the
Gaussian integrated over the pixel; noise: Poisson (star + sky) plus Gaussian read noise,
variance ``mu_ij + read_noise^2`` (+ ``gain^2/12`` ADC quantisation if asked). The Fisher
information is summed numerically over the pixels::

    I_ab = sum_ij (d mu_ij / d a) (d mu_ij / d b) / var_ij,

and the bound on x is ``sqrt([I^-1]_xx)``. In the photon-limited limit (no sky, no read noise,
well sampled PSF) it tends to ``psf_sigma / sqrt(F)``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt
from scipy.special import erf

from starlog.errors import InvalidParameterError

__all__ = ["centroid_crb", "centroid_crb_psf"]

_SQ2 = np.sqrt(2.0)


def _prof(u: npt.NDArray[np.float64], c: float, s: float) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    a, b = (u - c + 0.5) / s, (u - c - 0.5) / s
    e = 0.5 * (erf(a / _SQ2) - erf(b / _SQ2))
    pa, pb = np.exp(-0.5 * a * a), np.exp(-0.5 * b * b)
    k = 1.0 / np.sqrt(2 * np.pi)
    return e, -k * (pa - pb) / s, -k * (a * pa - b * pb) / s


def _one(flux: float, s: float, sky: float, rn: float, qvar: float, px: float, py: float, nuisance: tuple[str, ...], half: int | None) -> float:
    h = int(np.ceil(8.0 * s)) + 3 if half is None else int(half)
    u = np.arange(-h, h + 1, dtype=np.float64)
    ex, dex, dsx = _prof(u, px, s)
    ey, dey, dsy = _prof(u, py, s)
    m = ey[:, None] * ex[None, :]
    var = sky + flux * m + rn * rn + qvar
    cols = [flux * ey[:, None] * dex[None, :], flux * dey[:, None] * ex[None, :]]
    if "flux" in nuisance:
        cols.append(m)
    if "sky" in nuisance:
        cols.append(np.ones_like(m))
    if "psf_sigma" in nuisance:
        cols.append(flux * (dsy[:, None] * ex[None, :] + ey[:, None] * dsx[None, :]))
    j = np.stack([c.ravel() for c in cols])
    v = var.ravel()
    # pixels with no expected signal and no noise carry no information (their derivative is 0 too)
    inv = np.divide(1.0, v, out=np.zeros_like(v), where=v > 0)
    info = (j * inv) @ j.T
    cov = np.linalg.inv(info)
    return float(np.sqrt(cov[0, 0]))


def centroid_crb(
    *,
    flux: float | npt.ArrayLike,
    psf_sigma: float | npt.ArrayLike,
    sky: float | npt.ArrayLike,
    read_noise: float,
    gain: float = 1.0,
    x_phase: float | npt.ArrayLike = 0.0,
    y_phase: float | npt.ArrayLike = 0.0,
    nuisance: tuple[str, ...] = (),
    quantization: bool = False,
    half_width: int | None = None,
) -> float | npt.NDArray[np.float64]:
    """Cramer-Rao lower bound on the x centroid (px) of a pixel-integrated Gaussian star.

    Parameters
    ----------
    flux : float or array_like
        Total star signal, electrons (> 0).
    psf_sigma : float or array_like
        Gaussian PSF sigma, px (> 0).
    sky : float or array_like
        Sky background, electrons per pixel (>= 0).
    read_noise : float
        Read noise, electrons RMS (>= 0).
    gain : float
        e-/DN; only used for the ADC quantisation variance ``gain^2 / 12`` when
        ``quantization`` is True.
    x_phase, y_phase : float or array_like
        Sub-pixel position of the star relative to a pixel centre, px (the bound depends on
        it for undersampled PSFs). For the y bound swap the phases.
    nuisance : tuple of str
        Parameters estimated jointly (their uncertainty inflates the bound): any of
        ``"flux"``, ``"sky"``, ``"psf_sigma"``. Default: none (known flux, sky and PSF).
    quantization : bool
        Add the ADC quantisation variance.
    half_width : int, optional
        Half-size of the pixel window summed over; default ``ceil(8 sigma) + 3``.

    Returns
    -------
    float or ndarray
        The per-axis bound, px; an array when any input is an array (broadcast).
    """
    allowed = {"flux", "sky", "psf_sigma"}
    if not set(nuisance) <= allowed:
        raise InvalidParameterError(f"nuisance must be drawn from {sorted(allowed)}, got {nuisance!r}.")
    arrs = np.broadcast_arrays(*(np.asarray(v, np.float64) for v in (flux, psf_sigma, sky, x_phase, y_phase)))
    f, s, k, px, py = arrs
    if np.any(~(f > 0)) or np.any(~(s > 0)) or np.any(~(k >= 0)) or not (read_noise >= 0) or not (gain > 0):
        raise InvalidParameterError(
            "flux and psf_sigma must be > 0, sky and read_noise >= 0, gain > 0; got "
            f"flux={flux!r}, psf_sigma={psf_sigma!r}, sky={sky!r}, read_noise={read_noise!r}, gain={gain!r}."
        )
    q = gain * gain / 12.0 if quantization else 0.0
    out = np.array(
        [
            _one(float(a), float(b), float(c), float(read_noise), q, float(d), float(e), tuple(nuisance), half_width)
            for a, b, c, d, e in zip(f.ravel(), s.ravel(), k.ravel(), px.ravel(), py.ravel())
        ]
    ).reshape(f.shape)
    return float(out) if out.ndim == 0 else out


def centroid_crb_psf(
    *,
    flux: float,
    pixel_psf: Callable[[npt.NDArray[np.float64], npt.NDArray[np.float64]], npt.NDArray[np.float64]],
    sky: float,
    read_noise: float,
    x_phase: float = 0.0,
    y_phase: float = 0.0,
    half_width: int = 12,
    step: float = 1e-3,
) -> float:
    """Cramer-Rao bound on the x centroid (px) of a star with any pixel-integrated PSF (known flux, sky, PSF).

    The same Fisher information as :func:`centroid_crb` (Poisson + read-noise variance
    ``sky + mu + read_noise^2``), with the model's position derivatives taken numerically
    (central differences of ``step`` px) from ``pixel_psf(dx, dy)``: the fraction of the flux
    in a pixel centred at offset ``(dx, dy)`` from the star (e.g.
    :meth:`starlog.sim.profiles.MoffatPSF.pixel_values`). Sums over a ``2 half_width + 1``
    square window; the bound on y is the same with the phases swapped for a circular PSF.
    """
    if not (flux > 0 and sky >= 0 and read_noise >= 0 and half_width >= 1 and step > 0):
        raise InvalidParameterError(
            f"need flux > 0, sky and read_noise >= 0, half_width >= 1, step > 0; got flux={flux!r}, sky={sky!r}, "
            f"read_noise={read_noise!r}, half_width={half_width!r}, step={step!r}.")
    u = np.arange(-half_width, half_width + 1, dtype=np.float64)
    dx, dy = u[None, :] - x_phase, u[:, None] - y_phase
    m = pixel_psf(dx, dy)
    jx = -flux * (pixel_psf(dx + step, dy) - pixel_psf(dx - step, dy)) / (2 * step)
    jy = -flux * (pixel_psf(dx, dy + step) - pixel_psf(dx, dy - step)) / (2 * step)
    var = sky + flux * m + read_noise * read_noise
    inv = np.divide(1.0, var, out=np.zeros_like(var), where=var > 0)
    info = np.array([[np.sum(jx * jx * inv), np.sum(jx * jy * inv)], [np.sum(jx * jy * inv), np.sum(jy * jy * inv)]])
    return float(np.sqrt(np.linalg.inv(info)[0, 0]))
