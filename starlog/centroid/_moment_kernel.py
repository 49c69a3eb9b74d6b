"""MOMENT compiled (numba): the iteratively re-weighted centre of gravity, star by star.

The same fixed-point search as :func:`~starlog.centroid.moment.weighted_centroid_vectorised`
(the centre of gravity with weights centred on the estimate, solved by the secant method from
winpos' doubled first step), one window at a time: a star stops when its own update is below
``tol``, so its result does not depend on the other stars of its frame.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from starlog.centroid._gaussfit_kernel import _profile

NONE, GAUSSIAN, OPTIMAL = 0, 1, 2
"""Weighting codes: the plain centre of gravity, the PSF (winpos), the noise-optimal weight."""


@njit(cache=True, nogil=True)
def _centre(data, valid, u, edges, cx, cy, s, var0, flux, gain, weighting, ex, ey, col, row):  # type: ignore[no-untyped-def]
    """One centre-of-gravity evaluation with the weights centred on (cx, cy): (x, y, any weight)."""
    w_size = u.size
    if weighting != NONE:
        _profile(edges, cx, s, ex)
        _profile(edges, cy, s, ey)
    col[:] = 0.0
    row[:] = 0.0
    for i in range(w_size):
        for j in range(w_size):
            if weighting == NONE:
                w = valid[i, j]
            else:
                m = ey[i] * ex[j]
                w = valid[i, j] * m
                if weighting == OPTIMAL:
                    w = w / (var0 + max(flux * m, 0.0) / gain)
            v = w * data[i, j]
            col[j] += v
            row[i] += v
    s0 = 0.0
    for j in range(w_size):
        s0 += col[j]
    ok = s0 > 0
    if not ok:
        s0 = 1.0
    x = y = 0.0
    for j in range(w_size):
        x += col[j] * u[j]
        y += row[j] * u[j]
    return x / s0, y / s0, ok


@njit(cache=True, nogil=True)
def weighted_centres(data, valid, u, edges, noise, gain, dx0, dy0, flux, psf_sigma, weighting, iterations, tol,
                     h, cx_out, cy_out, ok_out):  # type: ignore[no-untyped-def]
    """Fill ``cx_out``, ``cy_out``, ``ok_out`` for every window (arrays as in ``Stamps``; see the module)."""
    n, w_size, _ = data.shape
    ex, ey, col, row = np.empty(w_size), np.empty(w_size), np.empty(w_size), np.empty(w_size)
    for k in range(n):
        var0, f, s = noise[k] * noise[k], max(flux[k], 0.0), psf_sigma[k]
        tx, ty, ok = _centre(data[k], valid[k], u, edges, dx0[k], dy0[k], s, var0, f, gain, weighting, ex, ey,
                             col, row)
        if weighting == NONE:
            cx_out[k], cy_out[k] = tx, ty
            ok_out[k] = ok and abs(tx) < h and abs(ty) < h
            continue
        x_prev, y_prev = dx0[k], dy0[k]
        gx_prev, gy_prev = tx - x_prev, ty - y_prev
        cx = min(max(x_prev + 2.0 * gx_prev, -h), h)
        cy = min(max(y_prev + 2.0 * gy_prev, -h), h)
        for _ in range(iterations):
            tx, ty, good = _centre(data[k], valid[k], u, edges, cx, cy, s, var0, f, gain, weighting, ex, ey, col,
                                   row)
            ok = ok and good
            gx, gy = tx - cx, ty - cy
            if (abs(gx) < tol and abs(gy) < tol) or not ok:
                cx, cy = tx, ty
                break
            fx = _secant_factor(cx - x_prev, gx - gx_prev)
            fy = _secant_factor(cy - y_prev, gy - gy_prev)
            x_prev, y_prev, gx_prev, gy_prev = cx, cy, gx, gy
            cx = min(max(cx + fx * gx, -h), h)
            cy = min(max(cy + fy * gy, -h), h)
        cx_out[k], cy_out[k] = cx, cy
        ok_out[k] = ok and math.isfinite(cx) and math.isfinite(cy) and abs(cx) < h and abs(cy) < h


@njit(cache=True, nogil=True)
def _secant_factor(dx, dg):  # type: ignore[no-untyped-def]
    """The secant step's factor on g(x) = T(x) - x, kept within (0.5, 4); 2 (winpos) when undefined."""
    if abs(dg) <= 1e-12:
        return 2.0
    factor = -dx / dg
    return factor if math.isfinite(factor) and 0.5 < factor < 4.0 else 2.0
