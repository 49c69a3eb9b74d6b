"""BICUBIC: peak of the bicubic (Keys, a = -0.5) interpolation of the star's window.

The window is first smoothed with the noise-optimal Gaussian (see
:func:`starlog.centroiding.stamps.optimal_smoothing`), then the continuous bicubic surface through
its pixels is maximised one axis at a time (two rounds) inside a +-1 px bracket.  Along one axis
the surface is a cubic polynomial between two pixel centres (the Keys kernel with a = -0.5 is
Catmull-Rom), so its gradient is a quadratic whose zeros are solved in closed form, interval by
interval: the result is exact, not limited by any interpolation grid step or iteration count.
(Newton steps on the whole surface stall because its second derivative jumps at the pixel
centres.)
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from starlog.centroiding.stamps import Stamps, smooth
from starlog.centroiding.coarse import peak_pixel

__all__ = ["bicubic_peak", "keys_kernel"]

F64 = npt.NDArray[np.float64]
_A = -0.5
#: How far outside [0, 1] a zero of the slope still counts as the interval's (rounding of the quadratic).
_EDGE = 1e-9


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


def _keys_value(t: F64) -> F64:
    """The Keys kernel at ``t`` (:func:`keys_kernel`'s value only: the weights of a line through the window)."""
    a = np.abs(t)
    return np.where(a <= 1, (_A + 2) * a**3 - (_A + 3) * a**2 + 1,
                    np.where(a < 2, _A * a**3 - 5 * _A * a**2 + 8 * _A * a - 4 * _A, 0.0))


def _clamp(v: npt.NDArray[np.generic], lo: float, hi: float) -> npt.NDArray[np.generic]:
    """``np.clip`` without its per-call overhead (this runs a few times per star and axis)."""
    return np.minimum(np.maximum(v, lo), hi)


def _line_coefficients(q: F64) -> tuple[F64, F64, F64, F64]:
    """Cubic ``c0 + c1 u + c2 u² + c3 u³`` of the Catmull-Rom curve through ``q[..., 0:4]`` (samples at
    -1, 0, 1, 2) for ``u`` in [0, 1]: the Keys (a = -0.5) interpolation between samples 1 and 2."""
    q0, q1, q2, q3 = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return q1, 0.5 * (q2 - q0), q0 - 2.5 * q1 + 2.0 * q2 - 0.5 * q3, -0.5 * q0 + 1.5 * q1 - 1.5 * q2 + 0.5 * q3


def _maxima_in_unit(c1: F64, c2: F64, c3: F64) -> F64:
    """The zeros of the cubic's slope ``c1 + 2 c2 u + 3 c3 u²`` in [0, 1] that are maxima, stacked on a
    new last axis of length 2 (NaN where none): a zero is a maximum where the slope falls through it."""
    a, b, c = 3.0 * c3, 2.0 * c2, c1
    with np.errstate(all="ignore"):
        disc = b * b - 4.0 * a * c
        root = np.sqrt(np.where(disc >= 0, disc, np.nan))
        # the numerically stable pair: q = -(b + sign(b) sqrt(disc)) / 2; roots q / a and c / q
        qq = -0.5 * (b + np.where(b >= 0, root, -root))
        linear = np.abs(a) <= 1e-12 * (np.abs(b) + np.abs(c) + 1e-300)
        u = np.stack([np.where(linear, -c / b, qq / a), np.where(linear, np.nan, c / qq)], axis=-1)
    falling = (b[..., None] + 2.0 * a[..., None] * u) < 0
    # a maximum on a pixel centre may come out a rounding error outside both intervals it ends
    inside = (u >= -_EDGE) & (u <= 1.0 + _EDGE)
    return np.where(falling & inside, np.minimum(np.maximum(u, 0.0), 1.0), np.nan)


def _line_maximum(values: F64, c: F64, lo: F64, hi: F64) -> F64:
    """Coordinate of the highest maximum of the Keys interpolation of each row of ``values`` (n, w)
    within [lo, hi]; ``c`` where there is none."""
    n, w = values.shape
    # a 2 px bracket meets at most three unit intervals
    k = _clamp(np.floor(lo).astype(np.intp)[:, None] + np.arange(3)[None, :], 1, w - 3)  # (n, 3)
    q = values[np.arange(n)[:, None, None], k[:, :, None] + np.arange(-1, 3)[None, None, :]]  # (n, 3, 4)
    c0, c1, c2, c3 = (v[..., None] for v in _line_coefficients(q))
    u = _maxima_in_unit(c1[..., 0], c2[..., 0], c3[..., 0])  # (n, 3, 2)
    v = k[:, :, None] + u
    value = c0 + u * (c1 + u * (c2 + u * c3))
    inside = np.isfinite(u) & (v >= lo[:, None, None]) & (v <= hi[:, None, None])
    value = np.where(inside, value, -np.inf).reshape(n, -1)
    best = np.argmax(value, axis=1)
    found = np.isfinite(value[np.arange(n), best])
    return np.where(found, v.reshape(n, -1)[np.arange(n), best], c)


def bicubic_peak(
    data: F64, st: Stamps, *, smooth_sigma: F64, rounds: int = 2, reach: int = 2
) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Continuous maximum of the bicubic surface, offsets from the window centre (px)."""
    sm = smooth(np.where(st.valid, data, 0.0), smooth_sigma)
    n, w, _ = sm.shape
    h = st.h
    iy, ix = peak_pixel(sm, reach)
    x = ix.astype(np.float64)
    y = iy.astype(np.float64)
    ok = np.ones(n, bool)

    for _ in range(rounds):
        for axis in (0, 1):
            c = x if axis == 0 else y
            other = y if axis == 0 else x
            lo, hi = _clamp(c - 1.0, 1.0, w - 2.0), _clamp(c + 1.0, 1.0, w - 2.0)
            line = _values_along(sm, other, axis)
            slope = _line_slope(line, np.stack([lo, hi], axis=1))
            bracket = (slope[:, 0] > 0) & (slope[:, 1] < 0)
            ok &= bracket
            found = np.where(bracket, _line_maximum(line, c, lo, hi), c)
            if axis == 0:
                x = found
            else:
                y = found
    ok &= (x > 1.0) & (x < w - 2.0) & (y > 1.0) & (y < w - 2.0)
    return x - h, y - h, ok


def _values_along(sm: F64, other: F64, axis: int) -> F64:
    """(n, w) values of the Keys surface on the line through ``other`` (a row coordinate for
    ``axis`` 0, a column coordinate for ``axis`` 1), at every pixel centre along ``axis``."""
    n, w, _ = sm.shape
    o0 = _clamp(np.floor(other).astype(np.intp), 1, w - 3)
    idx = o0[:, None] + np.arange(-1, 3)[None, :]  # (n, 4)
    weights = _keys_value(other[:, None] - idx)
    ar = np.arange(n)[:, None]
    lines = sm[ar, idx, :] if axis == 0 else sm[ar, :, idx]  # (n, 4, w) either way
    return np.einsum("nk,nkw->nw", weights, lines)


def _line_slope(values: F64, v: F64) -> F64:
    """d/dv of the Keys interpolation of each row of ``values`` (n, w) at ``v`` (n, m)."""
    n, w = values.shape
    k = _clamp(np.floor(v).astype(np.intp), 1, w - 3)
    q = values[np.arange(n)[:, None, None], k[..., None] + np.arange(-1, 3)]  # (n, m, 4)
    _, c1, c2, c3 = _line_coefficients(q)
    u = v - k
    return c1 + u * (2.0 * c2 + 3.0 * c3 * u)
