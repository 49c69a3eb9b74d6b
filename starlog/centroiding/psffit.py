"""PSFFIT: weighted least-squares fit of a pixel PSF model (position, flux, background).

Model of pixel (i, j) of a star window, DN above the local background estimate::

    mu_ij = B + F * E(u_j - cx, u_i - cy)

with ``E`` a pixel-integrated PSF (:class:`starlog.centroiding.epsf.EPSF`, the empirical PSF
interpolated by a bicubic spline, or :class:`~starlog.centroiding.epsf.GaussianPSF`). As in
GAUSSFIT: Gauss-Newton with Levenberg damping, vectorised over all stars, re-weighted with the
model variance ``noise^2 + mu_star / gain`` (a Gaussian approximation of the Poisson
likelihood, which reaches the Cramer-Rao bound of that PSF); ``sigma`` (per axis) and the flux
error come from the inverse of the normal matrix (the Fisher information) at the solution.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from starlog.centroiding.gaussfit import solve_damped
from starlog.centroiding.stamps import Stamps, variance

__all__ = ["PixelPSF", "PSFFitResult", "fit_psf"]

F64 = npt.NDArray[np.float64]


class PixelPSF(Protocol):
    """A pixel-integrated PSF: ``E(dx, dy)`` at offsets pixel centre - star centre, px, with derivatives."""

    def evaluate(self, dx: F64, dy: F64, deriv: bool = False) -> tuple[F64, F64 | None, F64 | None]: ...

    def evaluate_grid(self, u: F64, cx: F64, cy: F64, deriv: bool = False) -> tuple[F64, F64 | None, F64 | None]: ...


@dataclass(frozen=True)
class PSFFitResult:
    """Per-star fit results (arrays of N)."""

    dx: F64  # centre offset from the window centre, px
    dy: F64
    flux: F64  # DN
    flux_err: F64  # DN
    background: F64  # DN, relative to the stamp's background estimate
    sigma: F64  # per-axis centroid 1-sigma, px
    ok: npt.NDArray[np.bool_]


def _jacobian(st: Stamps, psf: PixelPSF, cx: F64, cy: F64, f: F64, fit_background: bool) -> tuple[F64, F64]:
    """Unit model (N, W, W) and the model's derivatives (N, P, W, W) in cx, cy, F[, B]."""
    m, ex, ey = psf.evaluate_grid(st.u, cx, cy, deriv=True)
    assert ex is not None and ey is not None
    fn = f[:, None, None]
    cols = [-fn * ex, -fn * ey, m]
    if fit_background:
        cols.append(np.ones_like(m))
    return m, np.stack(cols, axis=1)


def _chi2(st: Stamps, psf: PixelPSF, cx: F64, cy: F64, f: F64, b: F64, w: F64) -> F64:
    m, _, _ = psf.evaluate_grid(st.u, cx, cy)
    r = st.data - b[:, None, None] - f[:, None, None] * m
    return (w * r * r).sum(axis=(1, 2))


def _uncertainties(st: Stamps, psf: PixelPSF, cx: F64, cy: F64, f: F64,
                   fit_background: bool) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Per-axis centroid sigma and flux error from the inverse normal matrix, and where it could be inverted."""
    n = cx.size
    m, j = _jacobian(st, psf, cx, cy, f, fit_background)
    w = st.valid / variance(st, f[:, None, None] * m)
    jw = j * w[:, None]
    a_mat = np.einsum("npij,nqij->npq", jw, j)
    cov = np.full_like(a_mat, np.nan)
    det = np.linalg.det(a_mat)
    inv_ok = np.isfinite(det) & (np.abs(det) > 0)
    if inv_ok.any():
        cov[inv_ok] = np.linalg.inv(a_mat[inv_ok])
    var = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1]) if n else np.zeros(0)
    good = np.isfinite(var) & (var > 0)
    sig = np.sqrt(np.where(good, var, np.inf))
    ferr = np.sqrt(np.where(np.isfinite(cov[:, 2, 2]) & (cov[:, 2, 2] > 0), cov[:, 2, 2], np.inf))
    return sig, ferr, good


def fit_psf(st: Stamps, dx0: F64, dy0: F64, flux0: F64, psf: PixelPSF, *, fit_background: bool = True,
            iterations: int = 12, tol: float = 1e-4) -> PSFFitResult:
    """Fit ``psf`` to all stamps at once (see the module docstring); ``dx0, dy0, flux0``: the start."""
    n = st.data.shape[0]
    cx, cy = np.asarray(dx0, np.float64).copy(), np.asarray(dy0, np.float64).copy()
    f = np.maximum(np.asarray(flux0, np.float64), 1.0 * st.noise)
    b = np.zeros(n)
    npar = 3 + int(fit_background)
    lam = np.full(n, 1e-3)
    active = np.ones(n, bool)
    eye = np.eye(npar)[None]
    for _ in range(iterations):
        m, j = _jacobian(st, psf, cx, cy, f, fit_background)
        mu_star = f[:, None, None] * m
        w = st.valid / variance(st, mu_star)
        r = st.data - b[:, None, None] - mu_star
        jw = j * w[:, None]
        a_mat = np.einsum("npij,nqij->npq", jw, j)
        g = np.einsum("npij,nij->np", jw, r)
        c0 = (w * r * r).sum(axis=(1, 2))
        step = solve_damped(a_mat + lam[:, None, None] * (a_mat * eye), g, active)
        step[:, :2] = np.clip(step[:, :2], -0.5, 0.5)
        ncx, ncy = cx + step[:, 0], cy + step[:, 1]
        nf = np.maximum(f + step[:, 2], 1e-6 * st.noise + 1e-12)
        nb = b + step[:, 3] if fit_background else b
        better = (_chi2(st, psf, ncx, ncy, nf, nb, w) <= c0 * (1 + 1e-9)) & active
        cx, cy = np.where(better, ncx, cx), np.where(better, ncy, cy)
        f, b = np.where(better, nf, f), np.where(better, nb, b)
        lam = np.where(better, np.maximum(lam * 0.3, 1e-7), lam * 10.0)
        if np.all((np.abs(step[:, 0]) < tol) & (np.abs(step[:, 1]) < tol) | ~active):
            break
    sig, ferr, good = _uncertainties(st, psf, cx, cy, f, fit_background)
    h = st.h
    ok = active & np.isfinite(cx) & np.isfinite(cy) & (np.abs(cx) < h - 0.5) & (np.abs(cy) < h - 0.5) & (f > 0)
    return PSFFitResult(cx, cy, f, ferr, b, sig, ok & good)
