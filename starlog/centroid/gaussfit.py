"""GAUSSFIT: weighted least-squares fit of a pixel-integrated 2-D Gaussian plus background.

Model of pixel (i, j) of a star window, DN above the local background estimate::

    mu_ij = B + F * E(j - cx; s) * E(i - cy; s),
    E(u; c, s) = Phi((u - c + 1/2) / s) - Phi((u - c - 1/2) / s)

(the PSF integrated over the pixel's area, Phi the normal CDF). Gauss-Newton with
Levenberg damping, vectorised over all stars, iteratively re-weighted with the model variance
``noise^2 + mu_star / gain`` (Poisson + read noise + sky), i.e. a Gaussian approximation of the
Poisson likelihood, which reaches the Cramer-Rao bound. The uncertainty ``sigma`` is taken from
the inverse of the normal matrix (the Fisher information) at the solution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from starlog.centroid._stamps import Stamps, profile_1d, variance

__all__ = ["GaussFitResult", "fit_gaussians"]

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class GaussFitResult:
    """Per-star fit results (arrays of N)."""

    dx: F64  # centre offset from the window centre, px
    dy: F64
    flux: F64  # DN
    flux_err: F64  # DN
    background: F64  # DN, relative to the stamp's background estimate
    psf_sigma: F64  # px
    sigma: F64  # per-axis centroid 1-sigma, px
    ok: npt.NDArray[np.bool_]


def _jacobian(st: Stamps, cx: F64, cy: F64, f: F64, s: F64, fit_background: bool,
              fit_sigma: bool) -> tuple[F64, F64]:
    """Unit model (N, W, W) and the model's derivatives (N, P, W, W) in cx, cy, F[, B][, s]."""
    ex, dex, dsx = profile_1d(st.u, cx, s, deriv=True)
    ey, dey, dsy = profile_1d(st.u, cy, s, deriv=True)
    m = ey[:, :, None] * ex[:, None, :]
    cols = [
        f[:, None, None] * ey[:, :, None] * dex[:, None, :],
        f[:, None, None] * dey[:, :, None] * ex[:, None, :],
        m,
    ]
    if fit_background:
        cols.append(np.ones_like(m))
    if fit_sigma:
        cols.append(f[:, None, None] * (dsy[:, :, None] * ex[:, None, :] + ey[:, :, None] * dsx[:, None, :]))
    return m, np.stack(cols, axis=1)


def _chi2(st: Stamps, cx: F64, cy: F64, f: F64, b: F64, s: F64, w: F64) -> F64:
    ex, _, _ = profile_1d(st.u, cx, s)
    ey, _, _ = profile_1d(st.u, cy, s)
    r = st.data - b[:, None, None] - f[:, None, None] * ey[:, :, None] * ex[:, None, :]
    return (w * r * r).sum(axis=(1, 2))


def _solve(damp: F64, g: F64, active: npt.NDArray[np.bool_]) -> F64:
    """Steps of the damped normal equations; a singular system leaves its star inactive (in place)."""
    try:
        step = np.linalg.solve(damp, g[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        step = np.zeros_like(g)
        for k in range(g.shape[0]):
            try:
                step[k] = np.linalg.solve(damp[k], g[k])
            except np.linalg.LinAlgError:
                active[k] = False
    return np.where(np.isfinite(step), step, 0.0)


def _uncertainties(st: Stamps, cx: F64, cy: F64, f: F64, s: F64, fit_background: bool,
                   fit_sigma: bool) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Per-axis centroid sigma and flux error from the undamped normal matrix (Fisher
    information) at the solution, and where it could be inverted."""
    n = cx.size
    m, j = _jacobian(st, cx, cy, f, s, fit_background, fit_sigma)
    w = st.valid / variance(st, f[:, None, None] * m)
    jw = j * w[:, None]
    a_mat = np.einsum("npij,nqij->npq", jw, j)
    npar = a_mat.shape[1]
    cov = np.full((n, npar, npar), np.nan)
    det = np.linalg.det(a_mat)
    inv_ok = np.isfinite(det) & (np.abs(det) > 0)
    if inv_ok.any():
        cov[inv_ok] = np.linalg.inv(a_mat[inv_ok])
    var = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
    good_var = np.isfinite(var) & (var > 0)
    sig = np.sqrt(np.where(good_var, var, np.inf))
    ferr = np.sqrt(np.where(np.isfinite(cov[:, 2, 2]) & (cov[:, 2, 2] > 0), cov[:, 2, 2], np.inf))
    return sig, ferr, good_var


def fit_gaussians(
    st: Stamps,
    dx0: F64,
    dy0: F64,
    flux0: F64,
    psf_sigma: F64 | float,
    *,
    fit_sigma: bool = False,
    fit_background: bool = True,
    iterations: int = 12,
    tol: float = 1e-4,
) -> GaussFitResult:
    """Fit all stamps at once (see module docstring); ``psf_sigma`` is the start/fixed value."""
    n = st.data.shape[0]
    cx, cy = dx0.astype(np.float64).copy(), dy0.astype(np.float64).copy()
    f = np.maximum(flux0.astype(np.float64), 1.0 * st.noise)
    b = np.zeros(n)
    s = np.broadcast_to(np.asarray(psf_sigma, np.float64), (n,)).copy()
    npar = 3 + int(fit_background) + int(fit_sigma)
    lam = np.full(n, 1e-3)
    active = np.ones(n, bool)
    eye = np.eye(npar)[None]
    for _ in range(iterations):
        m, j = _jacobian(st, cx, cy, f, s, fit_background, fit_sigma)
        mu_star = f[:, None, None] * m
        w = st.valid / variance(st, mu_star)
        r = st.data - b[:, None, None] - mu_star
        jw = j * w[:, None]
        a_mat = np.einsum("npij,nqij->npq", jw, j)
        g = np.einsum("npij,nij->np", jw, r)
        c0 = (w * r * r).sum(axis=(1, 2))
        step = _solve(a_mat + lam[:, None, None] * (a_mat * eye), g, active)
        step[:, :2] = np.clip(step[:, :2], -0.5, 0.5)
        if fit_sigma:
            step[:, -1] = np.clip(step[:, -1], -0.3 * s, 0.3 * s)
        ncx, ncy, nf = cx + step[:, 0], cy + step[:, 1], np.maximum(f + step[:, 2], 1e-6 * st.noise + 1e-12)
        nb = b + step[:, 3] if fit_background else b
        ns = np.clip(s + step[:, -1], 0.2, 20.0) if fit_sigma else s
        better = (_chi2(st, ncx, ncy, nf, nb, ns, w) <= c0 * (1 + 1e-9)) & active
        cx = np.where(better, ncx, cx)
        cy = np.where(better, ncy, cy)
        f = np.where(better, nf, f)
        b = np.where(better, nb, b)
        s = np.where(better, ns, s)
        lam = np.where(better, np.maximum(lam * 0.3, 1e-7), lam * 10.0)
        if np.all((np.abs(step[:, 0]) < tol) & (np.abs(step[:, 1]) < tol) | ~active):
            break
    h = st.h
    sig, ferr, good_var = _uncertainties(st, cx, cy, f, s, fit_background, fit_sigma)
    ok = active & np.isfinite(cx) & np.isfinite(cy) & (np.abs(cx) < h - 0.5) & (np.abs(cy) < h - 0.5) & (f > 0)
    return GaussFitResult(cx, cy, f, ferr, b, s, sig, ok & good_var)
