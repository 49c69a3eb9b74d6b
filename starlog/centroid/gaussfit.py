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
    u = st.u
    cx, cy = dx0.astype(np.float64).copy(), dy0.astype(np.float64).copy()
    f = np.maximum(flux0.astype(np.float64), 1.0 * st.noise)
    b = np.zeros(n)
    s = np.broadcast_to(np.asarray(psf_sigma, np.float64), (n,)).copy()
    npar = 3 + int(fit_background) + int(fit_sigma)
    lam = np.full(n, 1e-3)
    active = np.ones(n, bool)
    h = st.h
    a_mat = np.zeros((n, npar, npar))
    eye = np.eye(npar)[None]

    def jac(cx: F64, cy: F64, f: F64, s: F64):  # noqa: ANN202
        ex, dex, dsx = profile_1d(u, cx, s, deriv=True)
        ey, dey, dsy = profile_1d(u, cy, s, deriv=True)
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

    def chi2(cx: F64, cy: F64, f: F64, b: F64, s: F64, w: F64) -> F64:
        ex, _, _ = profile_1d(u, cx, s)
        ey, _, _ = profile_1d(u, cy, s)
        r = st.data - b[:, None, None] - f[:, None, None] * ey[:, :, None] * ex[:, None, :]
        return (w * r * r).sum(axis=(1, 2))

    for _ in range(iterations):
        m, j = jac(cx, cy, f, s)
        mu_star = f[:, None, None] * m
        w = st.valid / variance(st, mu_star)
        r = st.data - b[:, None, None] - mu_star
        jw = j * w[:, None]
        a_mat = np.einsum("npij,nqij->npq", jw, j)
        g = np.einsum("npij,nij->np", jw, r)
        c0 = (w * r * r).sum(axis=(1, 2))
        damp = a_mat + lam[:, None, None] * (a_mat * eye)
        try:
            step = np.linalg.solve(damp, g[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            step = np.zeros_like(g)
            for k in range(n):
                try:
                    step[k] = np.linalg.solve(damp[k], g[k])
                except np.linalg.LinAlgError:
                    active[k] = False
        step = np.where(np.isfinite(step), step, 0.0)
        step[:, :2] = np.clip(step[:, :2], -0.5, 0.5)
        if fit_sigma:
            step[:, -1] = np.clip(step[:, -1], -0.3 * s, 0.3 * s)
        ncx, ncy, nf = cx + step[:, 0], cy + step[:, 1], np.maximum(f + step[:, 2], 1e-6 * st.noise + 1e-12)
        nb = b + step[:, 3] if fit_background else b
        ns = np.clip(s + step[:, -1], 0.2, 20.0) if fit_sigma else s
        c1 = chi2(ncx, ncy, nf, nb, ns, w)
        better = (c1 <= c0 * (1 + 1e-9)) & active
        cx = np.where(better, ncx, cx)
        cy = np.where(better, ncy, cy)
        f = np.where(better, nf, f)
        b = np.where(better, nb, b)
        s = np.where(better, ns, s)
        lam = np.where(better, np.maximum(lam * 0.3, 1e-7), lam * 10.0)
        if np.all((np.abs(step[:, 0]) < tol) & (np.abs(step[:, 1]) < tol) | ~active):
            break
    # covariance at the solution (undamped)
    m, j = jac(cx, cy, f, s)
    w = st.valid / variance(st, f[:, None, None] * m)
    jw = j * w[:, None]
    a_mat = np.einsum("npij,nqij->npq", jw, j)
    ok = active & np.isfinite(cx) & np.isfinite(cy) & (np.abs(cx) < h - 0.5) & (np.abs(cy) < h - 0.5) & (f > 0)
    cov = np.full((n, npar, npar), np.nan)
    det = np.linalg.det(a_mat)
    inv_ok = np.isfinite(det) & (np.abs(det) > 0)
    if inv_ok.any():
        cov[inv_ok] = np.linalg.inv(a_mat[inv_ok])
    var = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
    good_var = np.isfinite(var) & (var > 0)
    ok &= good_var
    sig = np.sqrt(np.where(good_var, var, np.inf))
    ferr = np.sqrt(np.where(np.isfinite(cov[:, 2, 2]) & (cov[:, 2, 2] > 0), cov[:, 2, 2], np.inf))
    return GaussFitResult(cx, cy, f, ferr, b, s, sig, ok)
