"""A frame's PSF width, and what it sets: the star windows' size and the detector's spike test.

:func:`estimate_psf_sigma` fits a free-width Gaussian to the frame's best stars; :func:`window_half_size` is the
windows' half-size for a width; :func:`detect_options_for_psf` relaxes the detector's hot-pixel test for an
undersampled PSF (:data:`UNDERSAMPLED_PSF_SIGMA`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.centroiding.gaussfit import fit_gaussians
from starlog.centroiding.stamps import (
    check_detections,
    check_image,
    default_saturation,
    gather_stamps,
    linear_flux,
    model,
)
from starlog.centroiding.table import CentroidFlag
from starlog.errors import InvalidParameterError

__all__ = ["HOT_PIXEL_SHARPNESS", "UNDERSAMPLED_PSF_SIGMA", "detect_options_for_psf", "estimate_psf_sigma",
           "window_half_size"]


def window_half_size(psf_sigma: float, window: int | None = None) -> int:
    """Half-size of a star's window, px: ``window`` when given (>= 2), else ``max(3, ceil(3.5 psf_sigma) + 1)``."""
    if window is not None:
        if window < 2:
            raise InvalidParameterError(f"window (half-size) must be >= 2 px, got {window!r}.")
        return int(window)
    return max(3, int(np.ceil(3.5 * psf_sigma)) + 1)


def estimate_psf_sigma(
    image: npt.ArrayLike,
    detections: npt.NDArray[Any],
    *,
    gain: float = 1.0,
    saturation: float | None = None,
    max_stars: int = 10,
    min_snr: float = 20.0,
    default: float = 1.0,
) -> float:
    """Gaussian PSF sigma of a frame (px): median of free-sigma fits of its best stars.

    Uses up to ``max_stars`` of the brightest detections with matched-filter SNR above
    ``min_snr`` (or, when fewer than 5 reach it, above 7) that are neither saturated, blended,
    masked nor at the border. Returns ``default`` when no star qualifies.
    """
    arr = check_image(image)
    det = check_detections(detections)
    bad = int(CentroidFlag.SATURATED | CentroidFlag.BLENDED | CentroidFlag.MASKED | CentroidFlag.BORDER)
    clean = det[(det["flags"] & bad) == 0]
    snr = clean["snr"] if "snr" in (det.dtype.names or ()) else np.full(clean.size, np.inf)
    use = clean[snr >= min_snr]
    if use.size < 5:  # a faint field: the best stars there are, down to SNR 7
        use = clean[snr >= min(7.0, min_snr)]
    if use.size == 0:
        return float(default)
    use = use[np.argsort(-use["flux"])[:max_stars]]
    sat = default_saturation(arr, saturation)
    # first guess from second moments of a 11x11 window
    st = gather_stamps(arr, use["x"], use["y"], 5, use["background"], use["noise"], gain, sat)
    d = np.where(st.data > 2 * st.noise[:, None, None], st.data, 0.0)
    s0 = d.sum(axis=(1, 2))
    u = st.u
    with np.errstate(all="ignore"):
        mx = (d.sum(axis=1) * u).sum(axis=1) / s0
        my = (d.sum(axis=2) * u).sum(axis=1) / s0
        vx = (d.sum(axis=1) * u * u).sum(axis=1) / s0 - mx * mx
        vy = (d.sum(axis=2) * u * u).sum(axis=1) / s0 - my * my
    guess = np.sqrt(np.clip(0.5 * (vx + vy) - 1.0 / 12.0, 0.09, 16.0))
    g0 = float(np.nanmedian(guess)) if np.isfinite(guess).any() else default
    h = int(np.clip(np.ceil(3.0 * g0) + 1, 3, 10))  # wide enough, bounded for speed
    st = gather_stamps(arr, use["x"], use["y"], h, use["background"], use["noise"], gain, sat)
    dx0, dy0 = use["x"] - st.xc, use["y"] - st.yc
    f0, _ = linear_flux(st, model(st, dx0, dy0, g0), use["flux"])
    fit = fit_gaussians(st, dx0, dy0, f0, g0, fit_sigma=True, iterations=5, tol=1e-3)
    good = fit.ok & (fit.psf_sigma > 0.21) & (fit.psf_sigma < 19.9)
    if not good.any():
        return float(g0)
    return float(np.median(fit.psf_sigma[good]))


UNDERSAMPLED_PSF_SIGMA = 0.7
"""PSF sigma, px, below which a frame's stars are near the limit of the detector's default spike test
(a Gaussian of sigma 0.55 px centred on a pixel has neighbours at its ``sharpness_ratio`` 0.2 of the
peak): part of them, the sharpest sub-pixel phases and the noisiest, would be rejected as hot pixels."""

HOT_PIXEL_SHARPNESS = 0.02
"""The spike test's ``sharpness_ratio`` for undersampled frames: a Gaussian of sigma 0.25 px centred on a
pixel has neighbours at 0.024 of its peak, so only a candidate sharper than any focused star (a hot pixel,
a one-pixel cosmic-ray hit: neighbours at the noise) is rejected."""


def detect_options_for_psf(psf_sigma: float, detect_options: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The detector's options for a frame of PSF sigma ``psf_sigma``: for an undersampled PSF
    (:data:`UNDERSAMPLED_PSF_SIGMA`) the spike test keeps every star a focused optic gives
    (:data:`HOT_PIXEL_SHARPNESS`), unless the options set ``sharpness_ratio`` themselves."""
    options = dict(detect_options or {})
    if psf_sigma < UNDERSAMPLED_PSF_SIGMA and "sharpness_ratio" not in options:
        options["sharpness_ratio"] = HOT_PIXEL_SHARPNESS
    return options
