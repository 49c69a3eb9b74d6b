"""BICUBIC: peak of the bicubic (Keys, a = -0.5) interpolation of the star's window.

The window is first smoothed with the noise-optimal Gaussian (see
:func:`starlog.centroid._stamps.optimal_smoothing`), then the continuous bicubic surface through
its pixels is maximised with the analytic gradient of the Keys kernel: each axis in turn is
solved for a zero of the gradient by the Illinois false-position method in a +-1 px bracket
(two rounds; the surface's second derivative jumps at the pixel centres, which stalls Newton
steps), so the result is not limited by any interpolation grid step.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from starlog.centroid._stamps import Stamps, smooth
from starlog.centroid.coarse import peak_pixel

__all__ = ["bicubic_peak", "keys_kernel"]

F64 = npt.NDArray[np.float64]
_A = -0.5


def keys_kernel(t: F64) -> tuple[F64, F64, F64]:
    """Keys cubic convolution kernel (a = -0.5) and its first and second derivatives."""
    a = np.abs(t)
    sg = np.sign(t)
    in1 = a <= 1
    in2 = (a > 1) & (a < 2)
    k = np.where(in1, (_A + 2) * a**3 - (_A + 3) * a**2 + 1, np.where(in2, _A * a**3 - 5 * _A * a**2 + 8 * _A * a - 4 * _A, 0.0))
    d1 = np.where(in1, 3 * (_A + 2) * a**2 - 2 * (_A + 3) * a, np.where(in2, 3 * _A * a**2 - 10 * _A * a + 8 * _A, 0.0)) * sg
    d2 = np.where(in1, 6 * (_A + 2) * a - 2 * (_A + 3), np.where(in2, 6 * _A * a - 10 * _A, 0.0))
    return k, d1, d2


def _keys_value_or_slope(t: F64, slope: bool) -> F64:
    """The Keys kernel (``slope`` False) or its first derivative at ``t``: :func:`keys_kernel`'s
    expressions, one of them only (the peak search needs one per axis and call)."""
    a = np.abs(t)
    in1 = a <= 1
    in2 = (a > 1) & (a < 2)
    if not slope:
        return np.where(in1, (_A + 2) * a**3 - (_A + 3) * a**2 + 1,
                        np.where(in2, _A * a**3 - 5 * _A * a**2 + 8 * _A * a - 4 * _A, 0.0))
    return np.where(in1, 3 * (_A + 2) * a**2 - 2 * (_A + 3) * a,
                    np.where(in2, 3 * _A * a**2 - 10 * _A * a + 8 * _A, 0.0)) * np.sign(t)


def bicubic_peak(
    data: F64, st: Stamps, *, smooth_sigma: F64, iterations: int = 20, rounds: int = 2, reach: int = 2
) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Continuous maximum of the bicubic surface, offsets from the window centre (px)."""
    sm = smooth(np.where(st.valid, data, 0.0), smooth_sigma)
    n, w, _ = sm.shape
    h = st.h
    iy, ix = peak_pixel(sm, reach)
    x = ix.astype(np.float64)
    y = iy.astype(np.float64)
    ar = np.arange(n)
    ok = np.ones(n, bool)
    off = np.arange(-1, 3)

    def grad(x: F64, y: F64, axis: int) -> F64:
        """d/dx (axis 0) or d/dy (axis 1) of the bicubic surface at (x, y)."""
        x0 = np.clip(np.floor(x).astype(np.intp), 1, w - 3)
        y0 = np.clip(np.floor(y).astype(np.intp), 1, w - 3)
        cols = x0[:, None] + off[None, :]
        rows = y0[:, None] + off[None, :]
        p = sm[ar[:, None, None], rows[:, :, None], cols[:, None, :]]  # (n, 4, 4)
        kx = _keys_value_or_slope(x[:, None] - cols, slope=axis == 0)
        ky = _keys_value_or_slope(y[:, None] - rows, slope=axis == 1)
        return np.einsum("ni,nij,nj->n", ky, p, kx)

    # the Keys surface's second derivative jumps at the pixel centres, so Newton steps with
    # the analytic Hessian stall there. Instead each axis in turn is solved for a zero of the
    # gradient by the Illinois (modified false-position) method inside a +-1 px bracket.
    for _ in range(rounds):
        for axis in (0, 1):
            c = x if axis == 0 else y
            lo, hi = np.clip(c - 1.0, 1.0, w - 2.0), np.clip(c + 1.0, 1.0, w - 2.0)

            def g_at(v: F64, axis: int = axis) -> F64:
                return grad(v, y, 0) if axis == 0 else grad(x, v, 1)

            glo, ghi = g_at(lo), g_at(hi)
            bracket = (glo > 0) & (ghi < 0)
            ok &= bracket
            side = np.zeros(n)
            for _ in range(iterations):
                with np.errstate(all="ignore"):
                    m = np.where(bracket, (lo * ghi - hi * glo) / (ghi - glo), c)
                m = np.where(np.isfinite(m), m, 0.5 * (lo + hi))
                gm = g_at(m)
                right = gm > 0  # the root is above m
                lo = np.where(right, m, lo)
                glo = np.where(right, gm, glo)
                hi = np.where(right, hi, m)
                ghi = np.where(right, ghi, gm)
                # Illinois: halve the stale end's value when the same end is kept twice
                ghi = np.where(right & (side > 0), 0.5 * ghi, ghi)
                glo = np.where(~right & (side < 0), 0.5 * glo, glo)
                side = np.where(right, 1.0, -1.0)
                c = m
                if np.all(hi - lo < 1e-9):
                    break
            if axis == 0:
                x = np.where(bracket, c, x)
            else:
                y = np.where(bracket, c, y)
    ok &= (x > 1.0) & (x < w - 2.0) & (y > 1.0) & (y < w - 2.0)
    return x - h, y - h, ok
