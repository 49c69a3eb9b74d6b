"""GAUSSFIT: weighted least-squares fit of a pixel-integrated 2-D Gaussian plus background.

Model of pixel (i, j) of a star window, DN above the local background estimate::

    mu_ij = B + F * E(j - cx; s) * E(i - cy; s),
    E(u; c, s) = Phi((u - c + 1/2) / s) - Phi((u - c - 1/2) / s)

(the PSF integrated over the pixel's area, Phi the normal CDF). Gauss-Newton with
Levenberg damping, iteratively re-weighted with the model variance ``noise^2 + mu_star / gain``
(Poisson + read noise + sky), i.e. a Gaussian approximation of the Poisson likelihood, which
reaches the Cramer-Rao bound. The uncertainty ``sigma`` is taken from the inverse of the normal
matrix (the Fisher information) at the solution.

:func:`fit_gaussians` runs the fit star by star in compiled code
(:mod:`starlog.centroiding.star_kernels`); :func:`fit_gaussians_vectorised` is the same fit in
numpy, vectorised over the stars, kept as the reference the compiled one is tested against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from starlog.centroiding.stamps import INV_SQRT_2PI, Stamps, per_star, pixel_edges, pixel_profiles

__all__ = ["GaussFitResult", "fit_gaussians", "fit_gaussians_vectorised", "solve_damped"]

F64 = npt.NDArray[np.float64]
_PAIRS = {npar: np.triu_indices(npar) for npar in (3, 4, 5)}
"""(row, column) of the upper triangle of the normal matrix, per number of parameters."""


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


@dataclass
class _Profiles:
    """The 1-D pixel-integrated profiles of every star along x (rows 0..N-1) and y (rows N..2N-1).

    ``t`` are the pixel edges in sigma units, ``e`` the profile (N2, W): kept from a trial
    evaluation so that an accepted step does not evaluate the error function again.
    """

    t: F64
    e: F64

    @classmethod
    def at(cls, edges: F64, cx: F64, cy: F64, s: F64) -> "_Profiles":
        """Profiles at centres (cx, cy) and width s (the same values as :func:`profile_1d`)."""
        t = (edges[None, :] - np.concatenate([cx, cy])[:, None]) / np.concatenate([s, s])[:, None]
        return cls(t, pixel_profiles(t))

    def where(self, better: npt.NDArray[np.bool_], other: "_Profiles") -> "_Profiles":
        """Per star, these profiles where ``better``, else ``other``'s."""
        pick = np.concatenate([better, better])[:, None]
        return _Profiles(np.where(pick, self.t, other.t), np.where(pick, self.e, other.e))

    def derivatives(self, s: F64, fit_sigma: bool) -> tuple[F64, F64 | None]:
        """d e / d centre and (``fit_sigma``) d e / d s, (N2, W)."""
        sc = np.concatenate([s, s])[:, None]
        pdf = INV_SQRT_2PI * np.exp(-0.5 * self.t * self.t)
        de_dc = -(pdf[:, 1:] - pdf[:, :-1]) / sc
        if not fit_sigma:
            return de_dc, None
        tp = self.t * pdf
        return de_dc, -(tp[:, 1:] - tp[:, :-1]) / sc


class _Problem:
    """The fixed parts of one fit: stamps, noise, the parameters' pairs and (only when the PSF
    width is fitted) the Jacobian's buffer (N, P, W, W)."""

    def __init__(self, st: Stamps, fit_background: bool, fit_sigma: bool) -> None:
        n, w, _ = st.data.shape
        self.st, self.n = st, n
        self.edges = pixel_edges(st.u)
        self.noise2 = st.noise[:, None, None] ** 2
        self.valid = st.valid.astype(np.float64)
        self.fit_background, self.fit_sigma = fit_background, fit_sigma
        self.npar = 3 + int(fit_background) + int(fit_sigma)
        self.pairs = _PAIRS[self.npar]
        self.jac = np.empty((n, self.npar, w, w)) if fit_sigma else None
        if fit_sigma and fit_background:
            self.jac[:, 3] = 1.0

    def weights(self, mu_star: F64) -> F64:
        """Inverse model variance on valid pixels (noise^2 + star shot noise, as :func:`variance`)."""
        return self.valid / (self.noise2 + np.maximum(mu_star, 0.0) / self.st.gain)

    def model(self, p: _Profiles) -> F64:
        """Unit model (N, W, W)."""
        return p.e[self.n :, :, None] * p.e[: self.n, None, :]

    def normal(self, p: _Profiles, f: F64, s: F64, w: F64, wr: F64 | None = None) -> tuple[F64, F64 | None]:
        """Normal matrix J^T W J (N, P, P) and, with the weighted residuals ``wr = w r``, the gradient J^T W r (N, P)."""
        if self.fit_sigma:
            return self._normal_planes(self._jacobian(p, f, s), w, wr)
        return self._normal_separable(p, f, s, w, wr)

    def _normal_separable(self, p: _Profiles, f: F64, s: F64, w: F64, wr: F64 | None) -> tuple[F64, F64 | None]:
        """:meth:`normal` when every derivative is a row profile times a column profile.

        d mu / d cx = F ey (x) dex, d mu / d cy = F dey (x) ex, d mu / d F = ey (x) ex, d mu / d B = 1,
        so ``sum_ij w_ij a_i b_j a'_i b'_j = sum_i a_i a'_i (w @ (b b'))_i``: one (W, W) x (W, K)
        product per star instead of P (W, W) planes.
        """
        n, npar = self.n, self.npar
        dc, _ = p.derivatives(s, False)
        rows = np.empty((n, npar, p.e.shape[1]))  # per parameter: its row profile ...
        cols = np.empty((n, p.e.shape[1], npar))  # ... and its column profile
        np.multiply(f[:, None], p.e[n:], out=rows[:, 0])
        np.multiply(f[:, None], dc[n:], out=rows[:, 1])
        rows[:, 2] = p.e[n:]
        cols[:, :, 0] = dc[:n]
        cols[:, :, 1] = cols[:, :, 2] = p.e[:n]
        if self.fit_background:
            rows[:, 3] = cols[:, :, 3] = 1.0
        i, k = self.pairs
        wb = w @ (cols[:, :, i] * cols[:, :, k])  # (N, W, K)
        upper = np.einsum("nkw,nwk->nk", rows[:, i] * rows[:, k], wb)
        a_mat = np.empty((n, npar, npar))
        a_mat[:, i, k] = upper
        a_mat[:, k, i] = upper
        if wr is None:
            return a_mat, None
        return a_mat, np.einsum("npw,nwp->np", rows, wr @ cols)  # wr @ cols: (N, W, P)

    def _jacobian(self, p: _Profiles, f: F64, s: F64) -> F64:
        """The model's derivatives (N, P, W, W) in cx, cy, F[, B], s."""
        n, j = self.n, self.jac
        ex, ey = p.e[:n], p.e[n:]
        dc, ds = p.derivatives(s, True)
        dex, dey, dsx, dsy = dc[:n], dc[n:], ds[:n], ds[n:]
        np.multiply((f[:, None] * ey)[:, :, None], dex[:, None, :], out=j[:, 0])
        np.multiply((f[:, None] * dey)[:, :, None], ex[:, None, :], out=j[:, 1])
        np.multiply(ey[:, :, None], ex[:, None, :], out=j[:, 2])
        j[:, -1] = f[:, None, None] * (dsy[:, :, None] * ex[:, None, :] + ey[:, :, None] * dsx[:, None, :])
        return j

    def _normal_planes(self, j: F64, w: F64, wr: F64 | None) -> tuple[F64, F64 | None]:
        n, npar = self.n, self.npar
        j2 = j.reshape(n, npar, -1)
        jw = j2 * w.reshape(n, 1, -1)
        a_mat = jw @ j2.transpose(0, 2, 1)
        if wr is None:
            return a_mat, None
        return a_mat, (j2 @ wr.reshape(n, -1, 1))[:, :, 0]

    def chi2(self, p: _Profiles, f: F64, b: F64, w: F64) -> F64:
        ex, ey = p.e[: self.n], p.e[self.n :]
        r = self.st.data - b[:, None, None] - f[:, None, None] * ey[:, :, None] * ex[:, None, :]
        return (w * r * r).sum(axis=(1, 2))


def solve_damped(damp: F64, g: F64, active: npt.NDArray[np.bool_]) -> F64:
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


def _uncertainties(prob: _Problem, p: _Profiles, f: F64, s: F64) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Per-axis centroid sigma and flux error from the undamped normal matrix (Fisher
    information) at the solution, and where it could be inverted."""
    n = f.size
    a_mat, _ = prob.normal(p, f, s, prob.weights(f[:, None, None] * prob.model(p)))
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
    """Fit every stamp (see module docstring), star by star in compiled code
    (:func:`starlog.centroiding.star_kernels.fit_stars`); ``psf_sigma`` is the start/fixed value."""
    from starlog.centroiding.star_kernels import fit_stars  # numba: imported, and compiled, on first use

    n = st.data.shape[0]
    cx, cy, flux0 = (per_star(v, n, name) for v, name in ((dx0, "dx0"), (dy0, "dy0"), (flux0, "flux0")))
    f = np.maximum(flux0, 1.0 * st.noise)
    b = np.zeros(n)
    s = per_star(psf_sigma, n, "psf_sigma")
    sig, ferr = np.empty(n), np.empty(n)
    good_var, active = np.empty(n, bool), np.empty(n, bool)
    fit_stars(np.ascontiguousarray(st.data, np.float64), np.ascontiguousarray(st.valid, np.float64),
              per_star(st.noise, n, "noise"), float(st.gain), pixel_edges(st.u), cx, cy, f, b, s, fit_background,
              fit_sigma, int(iterations), float(tol), sig, ferr, good_var, active)
    h = st.h
    ok = active & np.isfinite(cx) & np.isfinite(cy) & (np.abs(cx) < h - 0.5) & (np.abs(cy) < h - 0.5) & (f > 0)
    return GaussFitResult(cx, cy, f, ferr, b, s, sig, ok & good_var)


def fit_gaussians_vectorised(
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
    """The same fit vectorised over stars in numpy (the reference the compiled fit is tested against).

    Every star iterates until all have converged, so its result can move by a fraction of ``tol``
    with the other stars of its frame.
    """
    n = st.data.shape[0]
    prob = _Problem(st, fit_background, fit_sigma)
    cx, cy = dx0.astype(np.float64).copy(), dy0.astype(np.float64).copy()
    f = np.maximum(flux0.astype(np.float64), 1.0 * st.noise)
    b = np.zeros(n)
    s = np.broadcast_to(np.asarray(psf_sigma, np.float64), (n,)).copy()
    lam = np.full(n, 1e-3)
    active = np.ones(n, bool)
    eye = np.eye(prob.npar)[None]
    prof = _Profiles.at(prob.edges, cx, cy, s)
    for _ in range(iterations):
        mu_star = f[:, None, None] * prob.model(prof)
        w = prob.weights(mu_star)
        r = st.data - b[:, None, None] - mu_star
        wr = w * r
        a_mat, g = prob.normal(prof, f, s, w, wr)
        c0 = (wr * r).sum(axis=(1, 2))
        step = solve_damped(a_mat + lam[:, None, None] * (a_mat * eye), g, active)
        step[:, :2] = np.minimum(np.maximum(step[:, :2], -0.5), 0.5)
        if fit_sigma:
            step[:, -1] = np.clip(step[:, -1], -0.3 * s, 0.3 * s)
        ncx, ncy, nf = cx + step[:, 0], cy + step[:, 1], np.maximum(f + step[:, 2], 1e-6 * st.noise + 1e-12)
        nb = b + step[:, 3] if fit_background else b
        ns = np.clip(s + step[:, -1], 0.2, 20.0) if fit_sigma else s
        trial = _Profiles.at(prob.edges, ncx, ncy, ns)
        better = (prob.chi2(trial, nf, nb, w) <= c0 * (1 + 1e-9)) & active
        cx = np.where(better, ncx, cx)
        cy = np.where(better, ncy, cy)
        f = np.where(better, nf, f)
        b = np.where(better, nb, b)
        s = np.where(better, ns, s)
        prof = trial.where(better, prof)
        lam = np.where(better, np.maximum(lam * 0.3, 1e-7), lam * 10.0)
        if np.all((np.abs(step[:, 0]) < tol) & (np.abs(step[:, 1]) < tol) | ~active):
            break
    h = st.h
    sig, ferr, good_var = _uncertainties(prob, prof, f, s)
    ok = active & np.isfinite(cx) & np.isfinite(cy) & (np.abs(cx) < h - 0.5) & (np.abs(cy) < h - 0.5) & (f > 0)
    return GaussFitResult(cx, cy, f, ferr, b, s, sig, ok & good_var)
