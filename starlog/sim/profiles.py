"""Non-Gaussian point-spread functions of the simulator: Moffat and Airy, integrated over pixels.

Both are circular and normalised to unit flux over the plane. A pixel's share of a star's flux
is the PSF integrated over the pixel's square, by Gauss-Legendre quadrature on ``nodes x nodes``
points per pixel within ``core`` px of the star and at the pixel centre beyond (the wings are
smooth there: Moffat), or everywhere (Airy: its rings are about a pixel apart). Stars are
rendered within ``extent`` px, which keeps all but a small fraction of the flux (Moffat: 1e-5 of
it, Airy: about 1 %, as a real aperture loses its far rings off the window).

Coordinates follow the starlog convention: ``x`` = column, ``y`` = row, (0, 0) at the centre
of the top-left pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.special import j1

from starlog.errors import InvalidInputError, InvalidParameterError

__all__ = ["AIRY_FWHM_PER_LAMBDA_D", "AIRY_ZERO_PER_LAMBDA_D", "AiryPSF", "MoffatPSF", "render_profile_stars"]

F64 = npt.NDArray[np.float64]
AIRY_ZERO_PER_LAMBDA_D = 1.2196698912665045
"""First dark ring radius of the Airy pattern, in units of lambda/D (in px on the focal plane)."""
AIRY_FWHM_PER_LAMBDA_D = 1.0289939
"""FWHM of the Airy core, in units of lambda/D."""


@dataclass(frozen=True)
class MoffatPSF:
    """``I(r) = (beta - 1) / (pi alpha^2) (1 + r^2 / alpha^2)^-beta``, ``alpha = FWHM / (2 sqrt(2^(1/beta) - 1))``."""

    fwhm: float
    beta: float = 2.5
    nodes: int = 4

    def __post_init__(self) -> None:
        if not (self.fwhm > 0 and np.isfinite(self.fwhm)) or not (self.beta > 1 and np.isfinite(self.beta)):
            raise InvalidParameterError(f"Moffat PSF needs FWHM > 0 and beta > 1, got {self.fwhm!r}, {self.beta!r}.")

    @property
    def alpha(self) -> float:
        return self.fwhm / (2.0 * np.sqrt(2.0 ** (1.0 / self.beta) - 1.0))

    def intensity(self, r2: F64) -> F64:
        """PSF per unit area at squared radius ``r2`` px^2."""
        a2 = self.alpha**2
        return (self.beta - 1.0) / (np.pi * a2) * (1.0 + r2 / a2) ** (-self.beta)

    @property
    def extent(self) -> float:
        """Radius (px) outside which the flux is below 1e-5 (capped at 200 px)."""
        return float(min(200.0, self.alpha * np.sqrt(1e-5 ** (1.0 / (1.0 - self.beta)) - 1.0)))

    @property
    def core(self) -> float:
        return 6.0 * self.fwhm

    def pixel_values(self, dx: F64, dy: F64) -> F64:
        """Fraction of the flux in pixels centred at offsets ``(dx, dy)`` from the star, px."""
        return _integrate(self, np.asarray(dx, np.float64), np.asarray(dy, np.float64))


@dataclass(frozen=True)
class AiryPSF:
    """``I(r) = pi / (4 L^2) [2 J1(x) / x]^2``, ``x = pi r / L``, ``L`` = lambda/D in px (first zero at 1.22 L)."""

    lambda_d: float
    nodes: int = 6

    def __post_init__(self) -> None:
        if not (self.lambda_d > 0 and np.isfinite(self.lambda_d)):
            raise InvalidParameterError(f"Airy PSF needs lambda/D > 0 px, got {self.lambda_d!r}.")

    @property
    def fwhm(self) -> float:
        return AIRY_FWHM_PER_LAMBDA_D * self.lambda_d

    def intensity(self, r2: F64) -> F64:
        x = np.pi * np.sqrt(r2) / self.lambda_d
        safe = np.where(x > 1e-8, x, 1.0)
        amp = np.where(x > 1e-8, 2.0 * j1(safe) / safe, 1.0)
        return np.pi / (4.0 * self.lambda_d**2) * amp * amp

    @property
    def extent(self) -> float:
        """20 lambda/D (about 1 % of the flux lies beyond), at least 8 px, capped at 200 px."""
        return float(np.clip(20.0 * self.lambda_d, 8.0, 200.0))

    @property
    def core(self) -> float:
        return self.extent

    def pixel_values(self, dx: F64, dy: F64) -> F64:
        """Fraction of the flux in pixels centred at offsets ``(dx, dy)`` from the star, px."""
        return _integrate(self, np.asarray(dx, np.float64), np.asarray(dy, np.float64))


def _integrate(psf: MoffatPSF | AiryPSF, dx: F64, dy: F64) -> F64:
    """Pixel integrals: Gauss-Legendre ``nodes x nodes`` within ``psf.core`` px, the centre value beyond."""
    dx, dy = np.broadcast_arrays(dx, dy)
    out = psf.intensity(dx * dx + dy * dy)
    near = np.hypot(dx, dy) <= psf.core + 1.0
    if near.any():
        t, w = np.polynomial.legendre.leggauss(psf.nodes)
        t, w = 0.5 * t, 0.5 * w  # nodes on [-1/2, 1/2], weights summing to 1
        qx = dx[near][:, None, None] + t[None, None, :]
        qy = dy[near][:, None, None] + t[None, :, None]
        out = out.copy()
        out[near] = (psf.intensity(qx * qx + qy * qy) * w[None, None, :] * w[None, :, None]).sum(axis=(1, 2))
    return out


def render_profile_stars(shape: tuple[int, int], x: npt.ArrayLike, y: npt.ArrayLike, flux: npt.ArrayLike,
                         psf: MoffatPSF | AiryPSF, *, out: F64 | None = None) -> F64:
    """Render stars with a Moffat or Airy PSF integrated over pixels (expected signal per pixel).

    Parameters as :func:`starlog.sim.psf.render_stars`, with the PSF object instead of sigma.
    """
    rows, cols = int(shape[0]), int(shape[1])
    xs = np.atleast_1d(np.asarray(x, np.float64))
    ys = np.atleast_1d(np.asarray(y, np.float64))
    fs = np.atleast_1d(np.asarray(flux, np.float64))
    if not (xs.shape == ys.shape == fs.shape):
        raise InvalidInputError(f"x, y and flux must have one value per star; got shapes {xs.shape}, {ys.shape}, "
                                f"{fs.shape}.")
    if out is None:
        out = np.zeros((rows, cols), np.float64)
    elif out.shape != (rows, cols):
        raise InvalidInputError(f"out has shape {out.shape}, expected {(rows, cols)}.")
    half = int(np.ceil(psf.extent))
    for xc, yc, f in zip(xs, ys, fs):
        c0, c1 = max(0, int(np.floor(xc)) - half), min(cols, int(np.floor(xc)) + half + 2)
        r0, r1 = max(0, int(np.floor(yc)) - half), min(rows, int(np.floor(yc)) + half + 2)
        if c0 >= c1 or r0 >= r1:
            continue
        dx = np.arange(c0, c1, dtype=np.float64)[None, :] - xc
        dy = np.arange(r0, r1, dtype=np.float64)[:, None] - yc
        out[r0:r1, c0:c1] += f * psf.pixel_values(dx, dy)
    return out
