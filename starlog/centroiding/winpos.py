"""WINPOS: the windowed position of SExtractor (``XWIN_IMAGE``, ``YWIN_IMAGE``) and ``sep.winpos``.

Reference: E. Bertin, *SExtractor documentation*, section "Windowed positional parameters"
(derivation and uncertainty: ``docs/WINPOS.md``). The centre is the fixed point of a centre of
gravity weighted by a circular Gaussian window centred on the estimate itself:

    x <- x + 2 sum_i w_i I_i (x_i - x) / sum_i w_i I_i,     w_i = exp(-r_i^2 / (2 s^2)),

over the pixels within ``r_i < 4 s`` of ``x`` (``I``: background-subtracted pixels; the factor 2
makes one step land on the centre of a Gaussian star as wide as the window), iterated until
the step is under :data:`TOLERANCE` px, at most :data:`MAX_ITERATIONS` times. The window width
``s`` is ``FWHM / 2.3548`` with ``FWHM = 2 r_half``, twice the star's half-light radius:
:func:`window_sigma`.

Functions work on windows of N stars, ``(N, W, W)`` arrays with pixel offsets ``u`` from each
window's centre pixel (:func:`windowed_centroid`, :func:`windowed_centroid_sigma`), or on a whole
image (:func:`winpos`, the same call as ``sep.winpos``).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["MAX_ITERATIONS", "TOLERANCE", "WINDOW_RADIUS", "window_sigma", "windowed_centroid",
           "windowed_centroid_sigma", "winpos"]

F64 = npt.NDArray[np.float64]

WINDOW_RADIUS = 4.0
"""Pixels farther than this many window sigmas from the estimate are left out."""
STEP_FACTOR = 2.0
"""The step's factor: the centre of gravity of a Gaussian star of sigma ``s`` under a Gaussian window of
the same ``s`` moves half-way to the star's centre."""
TOLERANCE = 2e-4
"""The iteration stops once a step moves the position by less than this, px."""
MAX_ITERATIONS = 16
MIN_WINDOW_SIGMA = 0.5 * 2.0 / 2.3548
"""The window sigma of a half-light radius of 0.5 px, SExtractor's lower bound."""
_FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


def window_sigma(psf_sigma: npt.ArrayLike) -> F64:
    """The window sigma of stars whose PSF is the pixel-integrated Gaussian of ``psf_sigma`` px:
    ``2 r_half / 2.3548``, ``r_half = sqrt(2 ln 2 (psf_sigma^2 + 1/12))`` its half-light radius, which is
    ``sqrt(psf_sigma^2 + 1/12)`` (at least :data:`MIN_WINDOW_SIGMA`)."""
    s = np.asarray(psf_sigma, np.float64)
    half_light = np.sqrt(2.0 * np.log(2.0) * (s * s + 1.0 / 12.0))
    return np.maximum(2.0 * half_light / _FWHM_PER_SIGMA, MIN_WINDOW_SIGMA)


def _weights(valid: F64, u: F64, cx: F64, cy: F64, s: F64) -> tuple[F64, F64, F64]:
    """Window weights ``(N, W, W)`` about (cx, cy) and the pixel offsets from it along x and y, ``(N, W)``.

    A pixel crossed by the window's edge counts by the part of it inside (a linear ramp over the
    pixel's width along the radius)."""
    rx = u[None, :] - cx[:, None]
    ry = u[None, :] - cy[:, None]
    r2 = ry[:, :, None] ** 2 + rx[:, None, :] ** 2
    inside = np.clip(WINDOW_RADIUS * s[:, None, None] - np.sqrt(r2) + 0.5, 0.0, 1.0)
    return valid * inside * np.exp(-r2 / (2.0 * s[:, None, None] ** 2)), rx, ry


def windowed_centroid(data: F64, valid: npt.NDArray[np.bool_], u: F64, dx0: F64, dy0: F64, sigma_window: F64, *,
                      max_iterations: int = MAX_ITERATIONS, tol: float = TOLERANCE
                      ) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Windowed position of each window (module docstring), as offsets from the window centres.

    ``data``: ``(N, W, W)`` background-subtracted pixels; ``valid``: pixels to use; ``u``: the
    offsets ``-h..h``; ``dx0, dy0``: start offsets; ``sigma_window``: ``s`` per star. Returns
    ``(dx, dy, ok)``: ok where the weighted sum stayed positive and the position inside the window.
    """
    n = data.shape[0]
    cx, cy = np.array(dx0, np.float64), np.array(dy0, np.float64)
    s = np.broadcast_to(np.asarray(sigma_window, np.float64), (n,))
    w_valid = np.asarray(valid, np.float64)
    ok = np.ones(n, bool)
    active = np.arange(n)
    h = float(u[-1])
    for _ in range(max_iterations):
        w, rx, ry = _weights(w_valid[active], u, cx[active], cy[active], s[active])
        wi = w * data[active]
        total = wi.sum(axis=(1, 2))
        positive = total > 0
        safe = np.where(positive, total, 1.0)
        step_x = STEP_FACTOR * (wi.sum(axis=1) * rx).sum(axis=1) / safe
        step_y = STEP_FACTOR * (wi.sum(axis=2) * ry).sum(axis=1) / safe
        ok[active[~positive]] = False
        step_x, step_y = np.where(positive, step_x, 0.0), np.where(positive, step_y, 0.0)
        cx[active] += step_x
        cy[active] += step_y
        moving = positive & (step_x * step_x + step_y * step_y >= tol * tol) & (np.abs(cx[active]) < h) \
            & (np.abs(cy[active]) < h)
        active = active[moving]
        if active.size == 0:
            break
    ok &= np.isfinite(cx) & np.isfinite(cy) & (np.abs(cx) < h) & (np.abs(cy) < h)
    return cx, cy, ok


def windowed_centroid_sigma(model: F64, valid: npt.NDArray[np.bool_], u: F64, cx: F64, cy: F64, sigma_window: F64,
                            noise: F64, gain: float) -> F64:
    """1-sigma uncertainty per axis of :func:`windowed_centroid` at (cx, cy), px (the mean of the two axes'
    variances, square-rooted), from the noise-free star ``model`` ``(N, W, W)`` (DN): the position is the root
    of ``g(x) = sum_i w_i(x) I_i (x_i - x)``, so a small change ``dI`` moves it by ``-dg / g'(x)``:

        var x = sum_i w_i^2 (x_i - x)^2 V_i / (sum_i w_i m_i (1 - (x_i - x)^2 / s^2))^2,

    ``V_i = noise^2 + m_i / gain`` the pixel variance (docs/WINPOS.md). Never NaN: where the denominator
    vanishes, the window sigma itself.
    """
    s = np.broadcast_to(np.asarray(sigma_window, np.float64), cx.shape)
    w, rx, ry = _weights(np.asarray(valid, np.float64), u, cx, cy, s)
    m = np.maximum(model, 0.0)
    variance = np.asarray(noise, np.float64)[:, None, None] ** 2 + m / gain
    rx2, ry2 = (rx * rx)[:, None, :], (ry * ry)[:, :, None]
    inv_s2 = 1.0 / (s * s)[:, None, None]
    out = []
    for r2 in (rx2, ry2):
        num = (w * w * r2 * variance).sum(axis=(1, 2))
        den = (w * m * (1.0 - r2 * inv_s2)).sum(axis=(1, 2))
        out.append(np.where(den > 0, num / np.where(den > 0, den, 1.0) ** 2, np.inf))
    sig = np.sqrt(0.5 * (out[0] + out[1]))
    return np.where(np.isfinite(sig) & (sig > 0), sig, s)


def winpos(image: npt.ArrayLike, x: npt.ArrayLike, y: npt.ArrayLike, sigma_window: npt.ArrayLike, *,
           max_iterations: int = MAX_ITERATIONS, tol: float = TOLERANCE) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Windowed positions in a background-subtracted ``image`` from starts (x, y), px (pixel-centre origin):
    the call of ``sep.winpos(image, x, y, sigma_window)``. Non-finite pixels and those outside the image are
    left out. Returns ``(x, y, ok)``."""
    img = np.asarray(image, np.float64)
    xa, ya = np.atleast_1d(np.asarray(x, np.float64)), np.atleast_1d(np.asarray(y, np.float64))
    s = np.maximum(np.broadcast_to(np.asarray(sigma_window, np.float64), xa.shape), MIN_WINDOW_SIGMA)
    h = int(np.ceil(WINDOW_RADIUS * float(s.max(initial=0.0)) + 2.0))
    xc, yc = np.rint(xa).astype(np.intp), np.rint(ya).astype(np.intp)
    d = np.arange(-h, h + 1)
    rows, cols = yc[:, None] + d, xc[:, None] + d
    inside = ((rows >= 0) & (rows < img.shape[0]))[:, :, None] & ((cols >= 0) & (cols < img.shape[1]))[:, None, :]
    pixels = img[np.clip(rows, 0, img.shape[0] - 1)[:, :, None], np.clip(cols, 0, img.shape[1] - 1)[:, None, :]]
    valid = inside & np.isfinite(pixels)
    dx, dy, ok = windowed_centroid(np.where(valid, pixels, 0.0), valid, d.astype(np.float64), xa - xc, ya - yc, s,
                                   max_iterations=max_iterations, tol=tol)
    return xc + dx, yc + dy, ok
