"""Pixel-integrated Gaussian point-spread function.

Coordinates follow the starlog convention: ``x`` = column, ``y`` = row, (0, 0) at the centre
of the top-left pixel, so pixel ``i`` covers ``[i - 0.5, i + 0.5)``.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.special import erf

from starlog.errors import InvalidInputError

__all__ = ["integrated_gaussian_1d", "render_stars"]

_SQRT2 = np.sqrt(2.0)


def integrated_gaussian_1d(
    pixel_index: npt.ArrayLike, centre: float, sigma: float
) -> npt.NDArray[np.float64]:
    """Fraction of a unit 1-D Gaussian falling in each pixel.

    Parameters
    ----------
    pixel_index : (n,) array_like
        Pixel indices (pixel ``i`` spans ``[i - 0.5, i + 0.5)``).
    centre : float
        Gaussian centre in pixels (pixel-centre origin).
    sigma : float
        Gaussian standard deviation in pixels, > 0.

    Returns
    -------
    (n,) ndarray of float64
        ``Phi((i + 0.5 - c) / sigma) - Phi((i - 0.5 - c) / sigma)``.
    """
    i = np.asarray(pixel_index, dtype=np.float64)
    upper = erf((i + 0.5 - centre) / (_SQRT2 * sigma))
    lower = erf((i - 0.5 - centre) / (_SQRT2 * sigma))
    return 0.5 * (upper - lower)


def render_stars(
    shape: tuple[int, int],
    x: npt.ArrayLike,
    y: npt.ArrayLike,
    flux: npt.ArrayLike,
    sigma: float | npt.ArrayLike,
    *,
    out: npt.NDArray[np.float64] | None = None,
    extent_sigmas: float = 7.0,
) -> npt.NDArray[np.float64]:
    """Render stars as pixel-integrated circular Gaussians (expected signal per pixel).

    Parameters
    ----------
    shape : (rows, cols)
        Image shape.
    x, y : (n,) array_like
        Star centres in pixels (x = column, y = row, pixel-centre origin).
    flux : (n,) array_like
        Total signal of each star (e.g. photo-electrons) over the infinite plane.
    sigma : float or (n,) array_like
        PSF standard deviation in pixels.
    out : (rows, cols) ndarray of float64, optional
        Image to add into (modified in place and returned). A new zero image otherwise.
    extent_sigmas : float
        Half-width of the rendered box in PSF sigmas; the flux outside it is below 1e-10
        of the star's at the default.

    Returns
    -------
    (rows, cols) ndarray of float64
        The expected signal per pixel (no noise, no background).
    """
    rows, cols = int(shape[0]), int(shape[1])
    xs = np.atleast_1d(np.asarray(x, dtype=np.float64))
    ys = np.atleast_1d(np.asarray(y, dtype=np.float64))
    fs = np.atleast_1d(np.asarray(flux, dtype=np.float64))
    ss = np.broadcast_to(np.asarray(sigma, dtype=np.float64), xs.shape)
    if not (xs.shape == ys.shape == fs.shape):
        raise InvalidInputError(
            f"x, y and flux must have one value per star; got shapes {xs.shape}, {ys.shape}, {fs.shape}."
        )
    if np.any(ss <= 0) or not np.all(np.isfinite(ss)):
        raise InvalidInputError(f"PSF sigma must be finite and > 0; got {np.unique(ss)!r}.")
    if out is None:
        out = np.zeros((rows, cols), dtype=np.float64)
    elif out.shape != (rows, cols):
        raise InvalidInputError(f"out has shape {out.shape}, expected {(rows, cols)}.")
    for xc, yc, f, s in zip(xs, ys, fs, ss):
        half = int(np.ceil(extent_sigmas * s)) + 1
        c0, c1 = max(0, int(np.floor(xc)) - half), min(cols, int(np.floor(xc)) + half + 2)
        r0, r1 = max(0, int(np.floor(yc)) - half), min(rows, int(np.floor(yc)) + half + 2)
        if c0 >= c1 or r0 >= r1:
            continue
        px = integrated_gaussian_1d(np.arange(c0, c1), xc, s)
        py = integrated_gaussian_1d(np.arange(r0, r1), yc, s)
        out[r0:r1, c0:c1] += f * np.outer(py, px)
    return out
