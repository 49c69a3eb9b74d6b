"""BICUBIC: peak of the bicubic (Keys, a = -0.5) interpolation of the star's window.

The window is first smoothed with the noise-optimal Gaussian (see
:func:`starlog.centroid._stamps.optimal_smoothing`), then the continuous bicubic surface through
its pixels is maximised by Newton iterations with the analytic gradient and Hessian of the
Keys kernel (a gradient step when the Hessian is not negative definite), so the result is not
limited by any interpolation grid step.
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


def bicubic_peak(data: F64, st: Stamps, *, smooth_sigma: F64, iterations: int = 10, reach: int = 2) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
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
    for _ in range(iterations):
        x0 = np.clip(np.floor(x).astype(np.intp), 1, w - 3)
        y0 = np.clip(np.floor(y).astype(np.intp), 1, w - 3)
        cols = x0[:, None] + off[None, :]
        rows = y0[:, None] + off[None, :]
        p = sm[ar[:, None, None], rows[:, :, None], cols[:, None, :]]  # (n, 4, 4)
        kx, dkx, ddkx = keys_kernel(x[:, None] - cols)
        ky, dky, ddky = keys_kernel(y[:, None] - rows)
        gx = np.einsum("ni,nij,nj->n", ky, p, dkx)
        gy = np.einsum("ni,nij,nj->n", dky, p, kx)
        hxx = np.einsum("ni,nij,nj->n", ky, p, ddkx)
        hyy = np.einsum("ni,nij,nj->n", ddky, p, kx)
        hxy = np.einsum("ni,nij,nj->n", dky, p, dkx)
        det = hxx * hyy - hxy * hxy
        negdef = (hxx < 0) & (det > 0)
        with np.errstate(all="ignore"):
            sx = np.where(negdef, -(hyy * gx - hxy * gy) / det, 0.0)
            sy = np.where(negdef, -(hxx * gy - hxy * gx) / det, 0.0)
        scale = np.maximum(np.abs(hxx) + np.abs(hyy), 1e-300)
        sx = np.where(negdef, sx, gx / scale)
        sy = np.where(negdef, sy, gy / scale)
        sx = np.clip(np.nan_to_num(sx), -0.5, 0.5)
        sy = np.clip(np.nan_to_num(sy), -0.5, 0.5)
        x = np.clip(x + sx, 1.0, w - 2.0)
        y = np.clip(y + sy, 1.0, w - 2.0)
        if np.all((np.abs(sx) < 1e-7) & (np.abs(sy) < 1e-7)):
            break
    ok &= (x > 1.0) & (x < w - 2.0) & (y > 1.0) & (y < w - 2.0)
    return x - h, y - h, ok
