"""Centroid result table (structured dtype), method names and quality flags.

Coordinates: x = column, y = row, 0-based, (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

import enum

import numpy as np
import numpy.typing as npt

from starlog.detect.flags import StarFlag

__all__ = ["CENTROID_DTYPE", "CentroidFlag", "CentroidMethod", "empty_centroids"]

CentroidFlag = StarFlag
"""Quality bit flags of a centroid (the same class as :class:`starlog.detect.DetectionFlag`):
SATURATED, BORDER, FIT_FAILED, BLENDED, ELONGATED, LOW_SNR, MASKED, ARTEFACT, TRACKED."""


class CentroidMethod(enum.StrEnum):
    """Sub-pixel centroid methods, selectable by name (the paper's tables use these names).

    Attributes
    ----------
    NONE
        The coarse position: a three-point log-parabola (Gaussian) fit through the peak of
        the star's window smoothed with a Gaussian whose width adapts to the star's regime.
    MOMENT
        Background-subtracted centre of gravity in a window, iteratively re-weighted with the
        noise-optimal weight ``psf / variance`` (a generalised ``sep.winpos``); it becomes the
        plain centre of gravity for bright (photon-limited) stars.
    MOMENT_SQUARED
        The squared-grey centre of gravity (weights = squared intensity above 2 sigma) of the
        window after Gaussian denoising (see :mod:`starlog.centroiding.moment`).
    BICUBIC
        Peak of the Keys bicubic interpolation of the (adaptively smoothed) window, found by
        Newton iterations on the continuous surface (not limited by any grid step).
    GAUSSFIT
        Weighted least-squares (Poisson + read-noise variances) fit of a pixel-integrated
        circular Gaussian plus a constant background; sigma from the fit covariance.
    GRADIENT
        Radial-symmetry centre (Parthasarathy 2012) of the (adaptively smoothed) window.
    WINPOS
        The windowed position of SExtractor (``XWIN_IMAGE``) and ``sep.winpos``: the centre of
        gravity under a circular Gaussian window (sigma from the star's half-light radius)
        centred on the estimate itself, iterated to its fixed point (:mod:`starlog.centroiding.winpos`);
        sigma from its own error propagation.
    PSFFIT
        Weighted least-squares fit of a pixel PSF model (position, flux, background; sigma
        from the fit covariance): the log's empirical PSF (:mod:`starlog.centroiding.epsf`, built
        by ``starlog centroid``) when given, else the pixel-integrated Gaussian of the PSF sigma.

    Notes
    -----
    Every method except GAUSSFIT and PSFFIT has its pixel-phase bias (S-curve) and window-truncation
    bias removed by default (``debias=True`` in :func:`starlog.centroiding.measure_centroids`):
    the same estimator is run on the pixel-integrated Gaussian model of the star and the
    difference is subtracted (two fixed-point iterations).
    """

    NONE = "NONE"
    MOMENT = "MOMENT"
    MOMENT_SQUARED = "MOMENT_SQUARED"
    BICUBIC = "BICUBIC"
    GAUSSFIT = "GAUSSFIT"
    GRADIENT = "GRADIENT"
    PSFFIT = "PSFFIT"
    WINPOS = "WINPOS"


CENTROID_DTYPE = np.dtype(
    [
        ("star", np.int32),
        ("x", np.float64),
        ("y", np.float64),
        ("flux", np.float64),
        ("snr", np.float64),
        ("sigma", np.float64),
        ("peak", np.float64),
        ("background", np.float64),
        ("psf_sigma", np.float64),
        ("flags", np.uint16),
        ("n_masked", np.int32),
    ]
)
"""Structured dtype of :func:`starlog.centroiding.measure_centroids` results, one row per star.

Fields
------
star : int32
    Index of the detection within the frame (the ``star`` field of the detection).
x, y : float64
    Sub-pixel centroid, px (x = column, y = row, 0-based, pixel-centre origin). When the
    method fails, the coarse (detection) position and the flag ``FIT_FAILED``.
flux : float64
    Background-subtracted integrated signal, DN: the amplitude of the pixel-integrated
    Gaussian PSF fitted (weighted least squares) at ``(x, y)`` (GAUSSFIT: its own fit).
    Multiply by the gain for electrons.
snr : float64
    ``flux`` divided by its 1-sigma uncertainty (shot noise of the star and background noise).
sigma : float64
    The centroid's own 1-sigma uncertainty per axis, px (the mean of the x and y variances,
    square-rooted). GAUSSFIT, PSFFIT: from the fit covariance. Other methods: the Cramer-Rao bound of
    the star (from its measured flux, background noise, gain and PSF width) times the
    method's measured efficiency factor (see ``EFFICIENCY``); never NaN, always > 0.
peak : float64
    Highest background-subtracted pixel value within one pixel of the centroid, DN.
background : float64
    Local background level under the star, DN (pedestal + sky; GAUSSFIT, PSFFIT: fitted).
psf_sigma : float64
    Gaussian PSF sigma used for the star, px (given or estimated from the frame).
flags : uint16
    :class:`CentroidFlag` bits. ``MASKED``: pixels of the window were left out (``n_masked``).
n_masked : int32
    Pixels of the star's window left out of its measurement: non-finite or hot pixels, and
    pixels its fitted profile plus noise cannot explain (cosmic ray, hot pixel, a neighbour's
    wing; see :mod:`starlog.centroiding.robust`). Saturated pixels are not counted.
"""


def empty_centroids() -> npt.NDArray[np.void]:
    """Return a (0,) array of :data:`CENTROID_DTYPE`."""
    return np.zeros(0, dtype=CENTROID_DTYPE)
