"""Pixel PSF models for PSFFIT: the empirical PSF (ePSF) of a log, and the analytic Gaussian.

The *effective* PSF of Anderson & King (2000, PASP 112, 1360) is the PSF already integrated
over a pixel: ``E(dx, dy)`` is the fraction of a star's flux that falls in a pixel whose centre
lies at offset ``(dx, dy)`` = (pixel centre - star centre), px. A star of flux ``F`` at
``(x, y)`` on a background ``B`` gives pixel ``(i, j)`` the value ``B + F E(j - x, i - y)``.
The ePSF is tabulated on a grid oversampled ``oversampling`` times (node ``(k, l)`` at
``dy = (k - c) / ov``, ``dx = (l - c) / ov``, ``c = half_size * ov``) and interpolated between
nodes by the interpolating bicubic B-spline; it is normalised so that its sum over any integer
sub-lattice (one star's pixels) is 1 on average.

:func:`build_epsf` learns it from star windows, in the manner of Anderson & King (2000) and
photutils ``EPSFBuilder``: starting from a pixel-integrated Gaussian ``G``, it repeats (1) fit every
star's centre and flux with the current ePSF (:func:`starlog.centroiding.psffit.fit_psf`; the
background is the detection's), keeping the stars whose centre is precise enough not to blur the
grid, (2) place each star's pixels, normalised by its flux, minus ``G``, on the oversampled grid
at their offsets from the star's centre, (3) take a sigma-clipped, noise-weighted mean per node, smooth it
lightly, shrink it where it is not above its noise (Wiener) and add it to ``G``, (4) re-centre the
result on its own centroid and re-normalise it. Residuals are taken from the fixed ``G``, not
from the previous ePSF, so the shrinkage regularises instead of slowing a convergence to the noise.

Storage in a log (``starlog centroid --psf empirical``): one MCAP metadata record named
``starlog.epsf`` (:data:`starlog.topics.EPSF_METADATA`), a string map (see :meth:`EPSF.to_metadata`).
"""

from __future__ import annotations

import base64
from collections.abc import Iterable
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.ndimage import gaussian_filter, spline_filter
from scipy.ndimage import shift as spline_shift
from scipy.special import erf

from starlog.centroiding.stamps import Stamps, gather_stamps
from starlog.centroiding.psffit import fit_psf
from starlog.detect.flags import StarFlag
from starlog.errors import InvalidInputError, InvalidParameterError

__all__ = ["EPSF", "GaussianPSF", "build_epsf", "epsf_from_frames", "gaussian_epsf", "select_epsf_stars",
           "symmetric_below"]

F64 = npt.NDArray[np.float64]
_FORMAT = "starlog.epsf/1"
_SQ2 = np.sqrt(2.0)
_ISQ2PI = 1.0 / np.sqrt(2.0 * np.pi)
_PAD = 4  # zero nodes around the grid, so the spline's 4x4 support never leaves the coefficients


@dataclass(frozen=True)
class GaussianPSF:
    """The pixel-integrated circular Gaussian of sigma ``sigma`` px, as a pixel PSF model."""

    sigma: float

    def _axis(self, d: F64, deriv: bool) -> tuple[F64, F64 | None]:
        a, b = (d + 0.5) / self.sigma, (d - 0.5) / self.sigma
        e = 0.5 * (erf(a / _SQ2) - erf(b / _SQ2))
        if not deriv:
            return e, None
        return e, _ISQ2PI * (np.exp(-0.5 * a * a) - np.exp(-0.5 * b * b)) / self.sigma

    def evaluate(self, dx: F64, dy: F64, deriv: bool = False) -> tuple[F64, F64 | None, F64 | None]:
        """``E(dx, dy)`` and, with ``deriv``, its derivatives in ``dx`` and ``dy``."""
        ex, dex = self._axis(np.asarray(dx, np.float64), deriv)
        ey, dey = self._axis(np.asarray(dy, np.float64), deriv)
        if not deriv:
            return ex * ey, None, None
        return ex * ey, dex * ey, ex * dey  # type: ignore[operator]

    def evaluate_grid(self, u: F64, cx: F64, cy: F64, deriv: bool = False) -> tuple[F64, F64 | None, F64 | None]:
        """``E`` on star windows: (N, W, W) at offsets ``u[j] - cx[n]``, ``u[i] - cy[n]`` (and derivatives)."""
        ex, dex = self._axis(u[None, :] - cx[:, None], deriv)
        ey, dey = self._axis(u[None, :] - cy[:, None], deriv)
        e = ey[:, :, None] * ex[:, None, :]
        if not deriv:
            return e, None, None
        assert dex is not None and dey is not None
        return e, ey[:, :, None] * dex[:, None, :], dey[:, :, None] * ex[:, None, :]


@dataclass(frozen=True, eq=False)
class EPSF:
    """An oversampled effective PSF (see the module docstring for the convention)."""

    data: F64
    oversampling: int
    n_stars: int = 0
    _spline: list[Any] = field(default_factory=list, repr=False, compare=False)

    def __post_init__(self) -> None:
        d = np.asarray(self.data, np.float64)
        ov = int(self.oversampling)
        if d.ndim != 2 or d.shape[0] != d.shape[1] or ov < 1 or (d.shape[0] - 1) % (2 * ov):
            raise InvalidInputError(f"an ePSF grid must be square with side 2*half*oversampling+1; got "
                                    f"{d.shape} at oversampling {ov}.")
        object.__setattr__(self, "data", d)

    @property
    def half_size(self) -> int:
        """Half-size of the tabulated region, px."""
        return (self.data.shape[0] - 1) // (2 * self.oversampling)

    @property
    def offsets(self) -> F64:
        """Node offsets along one axis, px."""
        h = self.half_size
        return np.linspace(-h, h, self.data.shape[0])

    @property
    def fwhm(self) -> float:
        """Full width at half maximum of the pixel-integrated PSF, px: the mean of the four
        half-maximum crossings along the grid's axes through its centre (linear interpolation)."""
        c = (self.data.shape[0] - 1) // 2
        half = 0.5 * float(self.data[c, c])
        radii = []
        for ray in (self.data[c, c:], self.data[c, c::-1], self.data[c:, c], self.data[c::-1, c]):
            below = np.flatnonzero(ray < half)
            if below.size == 0 or below[0] == 0:
                continue
            k = int(below[0])
            radii.append(k - 1 + (ray[k - 1] - half) / (ray[k - 1] - ray[k]))
        return float(2.0 * np.mean(radii) / self.oversampling) if radii else float("nan")

    def _coefficients(self) -> F64:
        """Cubic B-spline coefficients of the grid padded with zeros (computed once per process)."""
        if not self._spline:
            padded = np.pad(self.data, _PAD)
            self._spline.append(spline_filter(padded, order=3, mode="mirror"))
        return self._spline[0]

    def evaluate(self, dx: F64, dy: F64, deriv: bool = False) -> tuple[F64, F64 | None, F64 | None]:
        """``E(dx, dy)`` by the bicubic B-spline (0 outside the grid) and, with ``deriv``, its ``dx``, ``dy`` derivatives."""
        dx, dy = np.broadcast_arrays(np.asarray(dx, np.float64), np.asarray(dy, np.float64))
        coef, ov, h = self._coefficients(), self.oversampling, self.half_size
        inside = (np.abs(dx) <= h) & (np.abs(dy) <= h)
        sx = (np.clip(dx, -h, h) + h) * ov + _PAD  # position in padded-node units
        sy = (np.clip(dy, -h, h) + h) * ov + _PAD
        ix, iy = np.floor(sx).astype(np.intp), np.floor(sy).astype(np.intp)
        wx, dwx = _bspline_weights(sx - ix, deriv)
        wy, dwy = _bspline_weights(sy - iy, deriv)
        # the 4 x 4 coefficients around each point, by flat index into the padded grid
        side = coef.shape[1]
        k = np.arange(-1, 3)
        flat = ((iy.ravel()[:, None] + k) * side)[:, :, None] + (ix.ravel()[:, None] + k)[:, None, :]
        g = coef.ravel()[flat]  # (P, 4, 4): rows a (y), columns b (x)
        wx, wy = wx.reshape(-1, 4), wy.reshape(-1, 4)
        gx = (g * wx[:, None, :]).sum(axis=2)  # (P, 4)
        shape = dx.shape
        e = np.where(inside, (gx * wy).sum(axis=1).reshape(shape), 0.0)
        if not deriv:
            return e, None, None
        assert dwx is not None and dwy is not None
        gdx = (g * dwx.reshape(-1, 4)[:, None, :]).sum(axis=2)
        ex = np.where(inside, (gdx * wy).sum(axis=1).reshape(shape) * ov, 0.0)
        ey = np.where(inside, (gx * dwy.reshape(-1, 4)).sum(axis=1).reshape(shape) * ov, 0.0)
        return e, ex, ey

    def evaluate_grid(self, u: F64, cx: F64, cy: F64, deriv: bool = False) -> tuple[F64, F64 | None, F64 | None]:
        """``E`` on star windows: (N, W, W) at offsets ``u[j] - cx[n]``, ``u[i] - cy[n]`` (and derivatives).

        The same values as :meth:`evaluate`, faster: the offsets of a window's pixels share one
        sub-pixel phase, so its 4 x 4 spline weights are the same for every pixel, and the
        coefficients each weight multiplies form one strided sub-lattice of the grid.
        """
        h, ov, n, w = self.half_size, self.oversampling, cx.size, u.size
        reach = float(np.abs(u).max() + max(np.abs(cx).max(), np.abs(cy).max())) if n else np.inf
        if not reach <= h:  # pixels beyond the grid (E = 0 there): the general path
            return self.evaluate(u[None, None, :] - cx[:, None, None], u[None, :, None] - cy[:, None, None], deriv)
        coef = self._coefficients()
        sx = (u[0] - cx + h) * ov + _PAD  # position of pixel 0 in padded-node units
        sy = (u[0] - cy + h) * ov + _PAD
        ix, iy = np.floor(sx).astype(np.intp), np.floor(sy).astype(np.intp)
        wx, dwx = _bspline_weights(sx - ix, deriv)
        wy, dwy = _bspline_weights(sy - iy, deriv)
        step = int(round((u[1] - u[0]) * ov)) if w > 1 else ov
        side = coef.shape[0]
        span = (w - 1) * step
        lattice = np.lib.stride_tricks.as_strided(
            coef, shape=(side - span, side - span, w, w),
            strides=(coef.strides[0], coef.strides[1], coef.strides[0] * step, coef.strides[1] * step))
        k = np.arange(-1, 3)
        g = lattice[(iy[:, None] + k)[:, :, None], (ix[:, None] + k)[:, None, :]]  # (N, 4, 4, W, W)
        gx = np.einsum("nabij,nb->naij", g, wx)
        e = np.einsum("naij,na->nij", gx, wy)
        if not deriv:
            return e, None, None
        ex = np.einsum("nabij,nb,na->nij", g, dwx, wy) * ov
        ey = np.einsum("naij,na->nij", gx, dwy) * ov
        return e, ex, ey

    def __getstate__(self) -> dict[str, Any]:
        return {"data": self.data, "oversampling": self.oversampling, "n_stars": self.n_stars}

    def __setstate__(self, state: dict[str, Any]) -> None:
        for key, value in state.items():
            object.__setattr__(self, key, value)
        object.__setattr__(self, "_spline", [])

    def summary(self) -> dict[str, Any]:
        """Size, oversampling, number of stars and FWHM (what ``starlog info`` shows)."""
        return {"size_px": 2 * self.half_size + 1, "grid": list(self.data.shape), "oversampling": self.oversampling,
                "n_stars": self.n_stars, "fwhm_px": round(self.fwhm, 4)}

    def to_metadata(self) -> dict[str, str]:
        """MCAP metadata map: ``format``, ``oversampling``, ``half_size``, ``n_stars``, ``fwhm_px`` and
        ``data``: the grid as little-endian float64, row-major (rows = dy), base64."""
        raw = np.ascontiguousarray(self.data, dtype="<f8").tobytes()
        return {"format": _FORMAT, "oversampling": str(self.oversampling), "half_size": str(self.half_size),
                "n_stars": str(self.n_stars), "fwhm_px": f"{self.fwhm:.6g}",
                "data": base64.b64encode(raw).decode("ascii")}

    @classmethod
    def from_metadata(cls, meta: dict[str, str]) -> EPSF:
        """Inverse of :meth:`to_metadata`."""
        if meta.get("format") != _FORMAT:
            raise InvalidInputError(f"not a {_FORMAT} record: format {meta.get('format')!r}.")
        ov, half = int(meta["oversampling"]), int(meta["half_size"])
        side = 2 * half * ov + 1
        data = np.frombuffer(base64.b64decode(meta["data"]), dtype="<f8").reshape(side, side)
        return cls(data.astype(np.float64), ov, int(meta.get("n_stars", 0)))


def _bspline_weights(t: F64, deriv: bool) -> tuple[F64, F64 | None]:
    """Cubic B-spline weights of nodes -1, 0, 1, 2 at fraction ``t`` in [0, 1) (..., 4), and their t-derivatives."""
    t2, t3 = t * t, t * t * t
    w = np.stack([(1 - t) ** 3, 3 * t3 - 6 * t2 + 4, -3 * t3 + 3 * t2 + 3 * t + 1, t3], axis=-1) / 6.0
    if not deriv:
        return w, None
    dw = np.stack([-(1 - t) ** 2, 3 * t2 - 4 * t, -3 * t2 + 2 * t + 1, t2], axis=-1) / 2.0
    return w, dw


def gaussian_epsf(sigma: float, half_size: int, oversampling: int = 4) -> EPSF:
    """The pixel-integrated Gaussian tabulated as an ePSF (the builder's starting point)."""
    o = np.linspace(-half_size, half_size, 2 * half_size * oversampling + 1)
    e, _, _ = GaussianPSF(float(sigma)).evaluate(o[None, :], o[:, None])
    return EPSF(e, oversampling)


def _node_means(k: npt.NDArray[np.intp], r: F64, w: F64, n_nodes: int, clip: float,
                passes: int = 3) -> tuple[F64, F64]:
    """Noise-weighted mean of the residuals ``r`` falling on each node ``k``, clipping at ``clip`` sigma.

    A sample is clipped when it is more than ``clip`` of its own noise (``1/sqrt(w)``) away
    from its node's mean; returns the means and the summed weights per node (0 where empty).
    """
    keep = np.ones(r.size, bool)
    mean = np.zeros(n_nodes)
    wsum = np.zeros(n_nodes)
    for _ in range(passes):
        wk = np.where(keep, w, 0.0)
        wsum = np.bincount(k, wk, n_nodes)
        mean = np.bincount(k, wk * r, n_nodes) / np.where(wsum > 0, wsum, 1.0)
        dev = (r - mean[k]) * np.sqrt(w)
        new = np.abs(dev) <= clip
        if np.array_equal(new, keep):
            break
        keep = new
    return mean, wsum


def _recentred(data: F64, ov: int, fwhm: float, passes: int = 6) -> F64:
    """Shift the grid so that its Gaussian-weighted centroid (weight width ~ the FWHM) is at offset 0."""
    o = np.arange(data.shape[0], dtype=np.float64)
    o = (o - o.mean()) / ov
    wsig = max(fwhm, 1.0)
    window = np.exp(-0.5 * (o[None, :] ** 2 + o[:, None] ** 2) / wsig**2)
    out = data
    for _ in range(passes):
        w = window * np.clip(out, 0, None)
        s = w.sum()
        if not s > 0:
            return data
        mx, my = float((w * o[None, :]).sum() / s), float((w * o[:, None]).sum() / s)
        if abs(mx) < 1e-6 and abs(my) < 1e-6:
            break
        out = spline_shift(out, (-my * ov, -mx * ov), order=3, mode="constant", cval=0.0)
    return out


def _normalised(data: F64, ov: int) -> F64:
    return data * (ov * ov / data.sum())


def build_epsf(st: Stamps, dx0: F64, dy0: F64, flux0: F64, *, psf_sigma: float, oversampling: int = 4,
               iterations: int = 10, clip: float = 3.0, smoothing: float = 0.25, tol: float = 1e-5,
               max_centre_error: float = 0.05) -> EPSF:
    """Learn the ePSF of star windows ``st`` (half-size = the ePSF's), see the module docstring.

    Parameters
    ----------
    st : Stamps
        Background-subtracted windows of bright, isolated, unsaturated stars; the ePSF's
        half-size is one pixel more than theirs.
    dx0, dy0, flux0 : (N,) arrays
        Starting centres (offsets from the window centres, px) and fluxes (DN).
    psf_sigma : float
        Sigma (px) of the starting pixel-integrated Gaussian.
    oversampling : int
        Nodes per pixel along each axis.
    iterations : int
        Maximum number of build iterations; stops earlier when the correction is below ``tol``.
    clip : float
        Sigma-clipping threshold of the per-node means (in each sample's own noise).
    smoothing : float
        Sigma (px) of the Gaussian smoothing of each correction (normalised convolution, so
        empty nodes take their neighbours' correction).
    max_centre_error : float
        Only stars whose fitted centre is this precise (1-sigma, px) shape the ePSF: a less
        precise centre places the star's pixels at wrong offsets and blurs the ePSF. With fewer
        such stars than ``oversampling^2`` the ePSF stays the starting Gaussian (``n_stars`` = 0);
        with fewer than :func:`symmetric_below` it is made point-symmetric.
    """
    n = st.data.shape[0]
    if n == 0:
        raise InvalidInputError("building an ePSF needs at least one star window.")
    if oversampling < 1 or iterations < 1:
        raise InvalidParameterError(f"oversampling and iterations must be >= 1, got {oversampling}, {iterations}.")
    ov = int(oversampling)
    cx, cy, f = dx0.astype(np.float64), dy0.astype(np.float64), np.asarray(flux0, np.float64)
    epsf, used, cx, cy, f = _build_round(st, float(psf_sigma), cx, cy, f, ov, iterations, clip, smoothing, tol,
                                         max_centre_error)
    data, n_used = epsf.data, int(used.sum())
    if n_used < ov * ov:
        return EPSF(gaussian_epsf(float(psf_sigma), st.h + 1, ov).data, ov, 0)
    if n_used < symmetric_below(ov):
        data = _normalised(0.5 * (data + data[::-1, ::-1]), ov)
    return EPSF(data, ov, n_used)


def symmetric_below(oversampling: int) -> int:
    """Stars below which an ePSF oversampled ``oversampling`` times is made point-symmetric: two per sub-pixel
    phase cell it resolves (``2 oversampling^2``); below one per cell (``oversampling^2``) it stays the starting
    Gaussian. Fewer stars leave phases learnt from one star or none, where what those stars carry besides the
    PSF (a JPEG's blocks, a demosaicing pattern, noise) is learnt as an asymmetry of the PSF, which moves every
    centre fitted with it by an amount that depends on the star's pixel phase. A point-symmetric ePSF keeps the
    radial shape they do show (a Moffat's wings, an Airy ring) and cannot move a symmetric star's centre."""
    return 2 * int(oversampling) ** 2


def _build_round(st: Stamps, sigma: float, cx: F64, cy: F64, f: F64, ov: int, iterations: int,
                 clip: float, smoothing: float, tol: float, max_centre_error: float
                 ) -> tuple[EPSF, npt.NDArray[np.bool_], F64, F64, F64]:
    """Steps (1)-(4) from the Gaussian of ``sigma`` until the ePSF changes by less than ``tol``."""
    prior = gaussian_epsf(sigma, st.h + 1, ov)  # one pixel wider than the windows: room for the centres' shifts
    epsf, used = prior, np.zeros(cx.size, bool)
    for _ in range(iterations):
        fit = fit_psf(st, cx, cy, f, epsf, fit_background=False)
        used = fit.ok & (fit.sigma <= max_centre_error)
        if not used.any():
            return prior, used, cx, cy, f
        cx, cy, f = np.where(fit.ok, fit.dx, cx), np.where(fit.ok, fit.dy, cy), np.where(fit.ok, fit.flux, f)
        correction = _correction(st, prior, cx[used], cy[used], f[used], fit.background[used], used, clip, smoothing)
        data = _normalised(_recentred(prior.data + correction, ov, prior.fwhm), ov)
        change = float(np.abs(data - epsf.data).max())
        epsf = EPSF(data, ov)
        if change < tol * data.max():
            break
    return epsf, used, cx, cy, f


def _correction(st: Stamps, epsf: EPSF, cx: F64, cy: F64, f: F64, b: F64, used: npt.NDArray[np.bool_],
                clip: float, smoothing: float) -> F64:
    """Smoothed, noise-shrunk per-node mean of the stars' normalised residuals from ``epsf`` (steps 2-3)."""
    ov, side, u = epsf.oversampling, epsf.data.shape[0], st.u
    dxg, dyg = np.broadcast_arrays(u[None, None, :] - cx[:, None, None], u[None, :, None] - cy[:, None, None])
    e, _, _ = epsf.evaluate_grid(u, cx, cy)
    data, valid = st.data[used], st.valid[used]
    var = st.noise[used, None, None] ** 2 + np.clip(f[:, None, None] * e, 0, None) / st.gain
    r = (data - b[:, None, None]) / f[:, None, None] - e
    w = f[:, None, None] ** 2 / var
    c = (side - 1) // 2
    kx, ky = np.rint(dxg * ov).astype(np.intp) + c, np.rint(dyg * ov).astype(np.intp) + c
    keep = valid & (kx >= 0) & (kx < side) & (ky >= 0) & (ky < side) & np.isfinite(r)
    node = (ky * side + kx)[keep]
    mean, wsum = _node_means(node, r[keep], w[keep], side * side, clip)
    mean, wsum = mean.reshape(side, side), wsum.reshape(side, side)
    smoothed, var, _ = _normalised_convolution(mean, wsum, smoothing * ov)
    # Wiener shrinkage towards the starting Gaussian: a correction buried in its own noise is not
    # applied (faint stars give a smooth ePSF rather than their noise)
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(var), smoothed * smoothed**2 / (smoothed**2 + var), 0.0)


def _normalised_convolution(mean: F64, wsum: F64, s: float) -> tuple[F64, F64, F64]:
    """Weighted Gaussian smoothing of node means (sigma ``s`` nodes): value, its variance, summed weight.

    The variance of the normalised convolution uses the squared kernel (a Gaussian of ``s / sqrt 2``).
    """
    num = gaussian_filter(mean * wsum, s, mode="constant")
    den = gaussian_filter(wsum, s, mode="constant")
    has = den > 1e-12 * max(float(den.max()), 1e-300)
    safe = np.where(has, den, 1.0)
    value = np.where(has, num / safe, 0.0)
    var = gaussian_filter(wsum, s / np.sqrt(2.0), mode="constant") / (4.0 * np.pi * s * s)
    return value, np.where(has, var / safe**2, np.inf), np.where(has, den, 0.0)


def select_epsf_stars(detections: npt.NDArray[Any], half_size: int, min_snr: float = 20.0) -> npt.NDArray[np.intp]:
    """Indices of the bright (matched-filter SNR >= ``min_snr``, or >= 7 when fewer than 5 reach it),
    isolated (no other detection within ``2 half_size + 1`` px) and clean (not saturated, blended,
    masked or at the border) detections."""
    det = np.asarray(detections)
    if det.size == 0:
        return np.zeros(0, np.intp)
    bad = int(StarFlag.SATURATED | StarFlag.BLENDED | StarFlag.MASKED | StarFlag.BORDER)
    snr = det["snr"] if "snr" in (det.dtype.names or ()) else np.full(det.size, np.inf)
    d2 = (det["x"][:, None] - det["x"][None, :]) ** 2 + (det["y"][:, None] - det["y"][None, :]) ** 2
    np.fill_diagonal(d2, np.inf)
    isolated = d2.min(axis=1) > (2 * half_size + 1) ** 2 if det.size > 1 else np.ones(1, bool)
    clean = ((det["flags"] & bad) == 0) & isolated
    chosen = np.flatnonzero(clean & (snr >= min_snr))
    if chosen.size < 5:  # a faint field: the best stars there are, down to SNR 7
        chosen = np.flatnonzero(clean & (snr >= min(7.0, min_snr)))
    return chosen


def _concatenate(parts: list[Stamps]) -> Stamps:
    """One :class:`Stamps` holding the windows of ``parts`` (same half-size and gain)."""
    first = parts[0]
    values = {}
    for f in fields(Stamps):
        v = getattr(first, f.name)
        values[f.name] = np.concatenate([getattr(p, f.name) for p in parts]) if isinstance(v, np.ndarray) else v
    return Stamps(**values)


def epsf_from_frames(frames: Iterable[tuple[npt.NDArray[Any], npt.NDArray[Any]]], *, psf_sigma: float,
                     half_size: int, gain: float = 1.0, read_noise: float | None = None,
                     saturation: float | None = None, oversampling: int = 4, max_stars: int = 2000,
                     min_snr: float = 20.0) -> EPSF:
    """Build the ePSF of frames ``(image, detections)`` from their bright, isolated, unsaturated stars.

    Windows of half-size ``half_size`` (the ePSF's) around the stars chosen by
    :func:`select_epsf_stars`, at most ``max_stars`` in all; starting centres and fluxes are the
    detections', the starting PSF the Gaussian of ``psf_sigma``. Raises ``InvalidInputError``
    when no star qualifies.
    """
    parts, x0, y0, f0, count = [], [], [], [], 0
    for image, det in frames:
        arr = np.asarray(image)
        sel = select_epsf_stars(det, half_size, min_snr)[: max_stars - count]
        if sel.size == 0:
            continue
        d = det[sel]
        sat = saturation if saturation is not None else (
            float(np.iinfo(arr.dtype).max) if np.issubdtype(arr.dtype, np.integer) else np.inf)
        noise = np.asarray(d["noise"], np.float64)
        if read_noise is not None:
            noise = np.maximum(noise, read_noise / gain)
        st = gather_stamps(arr, np.asarray(d["x"], np.float64), np.asarray(d["y"], np.float64), half_size,
                           np.asarray(d["background"], np.float64), np.where(noise > 0, noise, 1.0), gain, sat)
        parts.append(st)
        x0.append(d["x"] - st.xc)
        y0.append(d["y"] - st.yc)
        f0.append(np.asarray(d["flux"], np.float64))
        count += sel.size
        if count >= max_stars:
            break
    if not parts:
        raise InvalidInputError(f"no star bright (SNR >= {min_snr:g}), isolated and unsaturated enough to "
                                "build an empirical PSF.")
    return build_epsf(_concatenate(parts), np.concatenate(x0), np.concatenate(y0), np.concatenate(f0),
                      psf_sigma=psf_sigma, oversampling=oversampling)
