"""Compiled (numba): the sigma-clipped plane of every background cell.

The vectorised fit (:func:`~starlog.detect.background._fit_planes_vectorised`) passes over the
cells' samples some twenty times (residuals, masks, sums, products); here each cell is reduced
in one pass an iteration, in a loop. The estimates are the same, the sums taken in float64.
Divisions follow numpy (``error_model="numpy"``): a zero denominator gives inf or nan, not an
exception (a cell whose kept samples span one column has no x slope, and keeps its values).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model="numpy")
def fit_planes(values, level, noise, clip_sigma, iterations, slope_x, slope_y):  # type: ignore[no-untyped-def]
    """Refine every cell's ``level`` and ``noise`` in place and fill its slopes.

    ``values`` (cells, m * m) float32 holds each cell's samples row by row (NaN: none); each
    iteration keeps the samples within ``clip_sigma`` x noise of the current plane and refits
    level and slopes to them (at least 8 kept, else the cell keeps its values). Samples that all
    lie on the plane (digitised values of a noise below one step) give a noise of 0, rounding's
    negative variance too: the caller's floor applies.
    """
    m = int(round(math.sqrt(values.shape[1])))
    offset = np.empty(m, np.float32)
    for a in range(m):
        offset[a] = np.float32(a - (m - 1) / 2)
    for cell in range(values.shape[0]):
        row = values[cell]
        med, sig, bx, by = level[cell], noise[cell], 0.0, 0.0
        for _ in range(iterations):
            base, gx, gy = np.float32(med), np.float32(bx), np.float32(by)
            lim = np.float32(clip_sigma * max(sig, 1e-12))
            n = s0 = s2 = sx = sy = sxx = syy = 0.0
            for a in range(m):
                for b in range(m):
                    r = row[a * m + b] - (base + gx * offset[b] + gy * offset[a])
                    if abs(r) <= lim:  # NaN compares False
                        n += 1.0
                        s0 += r
                        s2 += float(r) * float(r)
                        sx += r * offset[b]
                        sy += r * offset[a]
                        sxx += offset[b] * offset[b]
                        syy += offset[a] * offset[a]
            if n < 8:
                continue
            d0, dbx, dby = s0 / n, sx / sxx, sy / syy
            var = max((s2 - n * d0 * d0 - dbx * dbx * sxx - dby * dby * syy) / max(n - 3.0, 1.0), 0.0)
            if math.isfinite(d0) and math.isfinite(dbx) and math.isfinite(dby) and var >= 0:
                med, bx, by, sig = med + d0, bx + dbx, by + dby, math.sqrt(var)
        level[cell], noise[cell], slope_x[cell], slope_y[cell] = med, sig, bx, by
