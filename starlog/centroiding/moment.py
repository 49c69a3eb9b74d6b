"""MOMENT: background-subtracted centre of gravity in a window (and its squared-grey variant).

``MOMENT`` (default ``weighting="optimal"``) is the iteratively re-weighted centre of gravity

    x = sum_i w_i D_i x_i / sum_i w_i D_i,     w_i = P_i(x) / (noise^2 + F P_i(x) / gain),

with ``D`` the background-subtracted pixels, ``P`` the unit pixel-integrated PSF centred on the
current estimate and ``F`` the star's flux: the noise-optimal weight. It is the Gaussian-windowed
centroid of ``sep.winpos`` for faint (background-limited) stars and the plain, unweighted centre
of gravity for bright (photon-limited) ones. ``weighting="gaussian"`` uses ``w = P`` (winpos),
``weighting="none"`` the plain centre of gravity of the whole window.

``MOMENT_SQUARED`` is the squared-grey centroid ``x = sum S_i^2 x_i / sum S_i^2`` over the
pixels of the denoised window ``S`` above twice its noise: the window is first smoothed with a
Gaussian of half the noise-optimal width (the pipeline's denoising step; without it the
squared noise of faint stars makes the classic form 1.4-2x worse than the bound).

Estimator functions work on window offsets (px from the window's centre pixel) and return
``(dx, dy, ok)``.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from starlog.centroiding.stamps import Stamps, model, per_star, pixel_edges, smooth
from starlog.errors import InvalidInputError

__all__ = ["squared_centroid", "weighted_centroid", "weighted_centroid_vectorised"]

F64 = npt.NDArray[np.float64]


def _centre_of_weights(w: F64, u: F64) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Centre ``(x, y)`` of stamps of non-negative weights ``w`` (n, k, k) on offsets ``u`` (k,); ok = any weight."""
    columns, rows = w.sum(axis=1), w.sum(axis=2)  # (n, k) marginals: one pass each over the stamps
    s0 = columns.sum(axis=1)
    ok = s0 > 0
    s0 = np.where(ok, s0, 1.0)
    cx = (columns * u[None, :]).sum(axis=1) / s0
    cy = (rows * u[None, :]).sum(axis=1) / s0
    return cx, cy, ok


def weighted_centroid(
    data: F64,
    st: Stamps,
    *,
    dx0: F64,
    dy0: F64,
    flux: F64,
    psf_sigma: F64,
    weighting: str = "optimal",
    iterations: int = 10,
    tol: float = 1e-5,
) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Iteratively re-weighted centre of gravity of each window (see module docstring), star by star in
    compiled code (:func:`starlog.centroiding.star_kernels.weighted_centres`)."""
    from starlog.centroiding.star_kernels import GAUSSIAN, NONE, OPTIMAL, weighted_centres  # numba: on first use

    n = st.data.shape[0]
    if data.shape != st.data.shape:
        raise InvalidInputError(f"data must have the stamps' shape {st.data.shape}; got {data.shape}.")
    code = {"none": NONE, "gaussian": GAUSSIAN, "optimal": OPTIMAL}[weighting]
    cx, cy, ok = np.empty(n), np.empty(n), np.empty(n, bool)
    weighted_centres(np.ascontiguousarray(data, np.float64), np.ascontiguousarray(st.valid, np.float64), st.u,
                     pixel_edges(st.u), per_star(st.noise, n, "noise"), float(st.gain), per_star(dx0, n, "dx0"),
                     per_star(dy0, n, "dy0"), per_star(flux, n, "flux"), per_star(psf_sigma, n, "psf_sigma"), code,
                     int(iterations), float(tol), float(st.h), cx, cy, ok)
    return cx, cy, ok


def weighted_centroid_vectorised(
    data: F64,
    st: Stamps,
    *,
    dx0: F64,
    dy0: F64,
    flux: F64,
    psf_sigma: F64,
    weighting: str = "optimal",
    iterations: int = 10,
    tol: float = 1e-5,
) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """:func:`weighted_centroid` vectorised over the stars in numpy: the reference the compiled one is tested
    against (every star iterates until all have converged)."""
    u = st.u
    valid = st.valid.astype(np.float64)
    noise2 = st.noise[:, None, None] ** 2
    star_flux = np.maximum(flux, 0)[:, None, None]

    def step(cx: F64, cy: F64) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
        """One centre-of-gravity evaluation with the weights centred on (cx, cy)."""
        if weighting == "none":
            w = valid
        else:
            m = model(st, cx, cy, psf_sigma)
            w = valid * m
            if weighting == "optimal":  # the pixel variance of :func:`starlog.centroiding.stamps.variance`
                w = w / (noise2 + np.maximum(star_flux * m, 0.0) / st.gain)
        return _centre_of_weights(w * data, u)

    tx, ty, ok = step(dx0, dy0)
    if weighting == "none":
        return tx, ty, ok & (np.abs(tx) < st.h) & (np.abs(ty) < st.h)
    # the fixed point x = T(x) is found with the secant method on g(x) = T(x) - x, started
    # with winpos' doubled step (a Gaussian weight as wide as the PSF converges at rate 1/2)
    x_prev, y_prev = dx0.copy(), dy0.copy()
    gx_prev, gy_prev = tx - dx0, ty - dy0
    cx = np.minimum(np.maximum(dx0 + 2.0 * gx_prev, -st.h), st.h)
    cy = np.minimum(np.maximum(dy0 + 2.0 * gy_prev, -st.h), st.h)
    for _ in range(iterations):
        tx, ty, good = step(cx, cy)
        ok &= good
        gx, gy = tx - cx, ty - cy
        if np.all((np.abs(gx) < tol) & (np.abs(gy) < tol) | ~ok):
            cx, cy = tx, ty
            break
        dgx, dgy = gx - gx_prev, gy - gy_prev
        with np.errstate(all="ignore"):
            fx = np.where(np.abs(dgx) > 1e-12, -(cx - x_prev) / dgx, 2.0)
            fy = np.where(np.abs(dgy) > 1e-12, -(cy - y_prev) / dgy, 2.0)
        fx = np.where(np.isfinite(fx) & (fx > 0.5) & (fx < 4.0), fx, 2.0)
        fy = np.where(np.isfinite(fy) & (fy > 0.5) & (fy < 4.0), fy, 2.0)
        x_prev, y_prev, gx_prev, gy_prev = cx, cy, gx, gy
        cx = np.minimum(np.maximum(cx + fx * gx, -st.h), st.h)
        cy = np.minimum(np.maximum(cy + fy * gy, -st.h), st.h)
    ok &= np.isfinite(cx) & np.isfinite(cy) & (np.abs(cx) < st.h) & (np.abs(cy) < st.h)
    return cx, cy, ok


def squared_centroid(
    data: F64, st: Stamps, *, smooth_sigma: F64 | None = None, threshold_sigma: float = 2.0
) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Squared-grey centre of gravity of the (denoised) pixels above ``threshold_sigma`` sigma.

    With ``smooth_sigma`` the window is first denoised with that Gaussian (the pipeline's
    denoising step) and the threshold applies to the smoothed noise.
    """
    u = st.u
    if smooth_sigma is not None:
        d = smooth(np.where(st.valid, data, 0.0), smooth_sigma)
        # noise of the smoothed window: white noise through a unit-area Gaussian of sigma s
        nz = st.noise / (2.0 * np.sqrt(np.pi) * np.maximum(smooth_sigma, 0.5))
    else:
        d = np.where(st.valid, data, 0.0)
        nz = st.noise
    d = np.where(d > threshold_sigma * nz[:, None, None], d, 0.0)
    return _centre_of_weights(d * d, u)
