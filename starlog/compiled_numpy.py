"""numpy's results in compiled (numba) loops, bit for bit: its pairwise float64 sum and NaN-propagating maxima.

numpy adds up to 128 float64 values in eight partial sums combined in a tree (:func:`block_sum`) and a longer run
as the sum of its two halves, cut at a multiple of eight (:func:`pairwise_sum`); a reduction starts from 0, so
``0.0 + block_sum(...)`` is ``sum`` of the window, -0.0 included. The kernels of :mod:`starlog.detect` and
:mod:`starlog.centroiding` sum their windows with these, so they give the numpy forms' bits.

numba's cache is refreshed when a function's own file changes, not when a function it calls in another
file does: after editing a kernel that others call, delete the cached code (``find starlog -name '*.nb[ic]'
-delete``, docs/DEVELOPMENT.md). Divisions follow numpy (``error_model="numpy"``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["block_sum", "maximum", "minimum", "pairwise_sum"]


@njit(cache=True, nogil=True, error_model="numpy")
def maximum(a, b):  # type: ignore[no-untyped-def]
    """``np.maximum(a, b)``: NaN propagates, of two equal values the second (+0 for -0 and +0)."""
    return a if (a > b or a != a) else b


@njit(cache=True, nogil=True, error_model="numpy")
def minimum(a, b):  # type: ignore[no-untyped-def]
    """``np.minimum(a, b)``: NaN propagates."""
    return a if (a < b or a != a) else b


@njit(cache=True, nogil=True, error_model="numpy")
def block_sum(a, start, n):  # type: ignore[no-untyped-def]
    """numpy's pairwise sum of ``a[start:start + n]``, n <= 128: eight partial sums combined in a tree."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[start + i]
        return res
    r0, r1, r2, r3 = a[start], a[start + 1], a[start + 2], a[start + 3]
    r4, r5, r6, r7 = a[start + 4], a[start + 5], a[start + 6], a[start + 7]
    i = start + 8
    whole = start + n - n % 8
    while i < whole:
        r0 += a[i]
        r1 += a[i + 1]
        r2 += a[i + 2]
        r3 += a[i + 3]
        r4 += a[i + 4]
        r5 += a[i + 5]
        r6 += a[i + 6]
        r7 += a[i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < start + n:
        res += a[i]
        i += 1
    return res


@njit(cache=True, nogil=True, error_model="numpy")
def pairwise_sum(a, start, n):  # type: ignore[no-untyped-def]
    """numpy's float64 sum of ``a[start:start + n]`` as ``sum(axis=(1, 2))`` takes one window: above 128 values
    the sum of its two halves (cut at a multiple of eight), :func:`block_sum` below. numpy recurses; here a
    stack does (numba's cache does not load recursive functions safely)."""
    if n <= 128:
        return block_sum(a, start, n)
    starts, counts, stages = np.empty(64, np.int64), np.empty(64, np.int64), np.empty(64, np.int64)
    sums = np.empty(64)
    top, done = 0, 0
    starts[0], counts[0], stages[0] = start, n, 0
    while top >= 0:
        s, m = starts[top], counts[top]
        if m <= 128:
            sums[done] = block_sum(a, s, m)
            done += 1
            top -= 1
            continue
        half = m // 2
        half -= half % 8
        if stages[top] == 2:
            done -= 1
            sums[done - 1] = sums[done - 1] + sums[done]
            top -= 1
            continue
        stages[top] += 1
        top += 1
        starts[top], counts[top], stages[top] = (s, half, 0) if stages[top - 1] == 1 else (s + half, m - half, 0)
    return sums[0]

