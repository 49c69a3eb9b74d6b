"""Compiled (numba): the centroid stage's evidence of one frame, :func:`evidence_sums`.

:func:`starlog.centroiding.evidence.evidence_sums` calls it; ``evidence_sums_vectorised`` there is its reference
(the same numbers: sums in numpy's pairwise order, :mod:`starlog.compiled_numpy`).

numba's cache is refreshed when a function's own file changes, not when a function it calls in another
file does: after editing a kernel that others call, delete the cached code (``find starlog -name '*.nb[ic]'
-delete``, docs/DEVELOPMENT.md). Divisions follow numpy (``error_model="numpy"``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from starlog.compiled_numpy import pairwise_sum

__all__ = ["evidence_sums"]


@njit(cache=True, nogil=True, error_model="numpy")
def _nearest_within(ax, ay, bx, by, order, radius, nearest):  # type: ignore[no-untyped-def]
    """For each point a, the index of its nearest point b when one lies within ``radius`` (else -1); ``order``:
    the points b sorted by x. Of equal distances the first in that order."""
    sorted_x = bx[order]
    for i in range(ax.size):
        nearest[i] = -1
        best = np.inf
        p = np.searchsorted(sorted_x, ax[i] - radius)
        while p < order.size and sorted_x[p] <= ax[i] + radius:
            j = order[p]
            d2 = (ax[i] - bx[j]) ** 2 + (ay[i] - by[j]) ** 2
            if d2 < best:
                nearest[i], best = j, d2
            p += 1
        if nearest[i] >= 0 and not math.sqrt(best) <= radius:
            nearest[i] = -1


@njit(cache=True, nogil=True, error_model="numpy")
def _matched(px, py, x, y, radius):  # type: ignore[no-untyped-def]
    """``evidence._matched_pairs``: stars of two frames each other's nearest within ``radius`` (first rows)."""
    ab, ba = np.empty(px.shape[1], np.int64), np.empty(x.shape[1], np.int64)
    _nearest_within(px[0], py[0], x[0], y[0], np.argsort(x[0], kind="mergesort"), radius, ab)
    _nearest_within(x[0], y[0], px[0], py[0], np.argsort(px[0], kind="mergesort"), radius, ba)
    count = 0
    for i in range(ab.size):
        count += ab[i] >= 0 and ba[ab[i]] == i
    before, after = np.empty(count, np.int64), np.empty(count, np.int64)
    count = 0
    for i in range(ab.size):
        if ab[i] >= 0 and ba[ab[i]] == i:
            before[count], after[count] = i, ab[i]
            count += 1
    return before, after


@njit(cache=True, nogil=True, error_model="numpy")
def _squares_about(values, centre, terms):  # type: ignore[no-untyped-def]
    """numpy's ``np.sum((values - centre) ** 2)`` (the pairwise order)."""
    for s in range(values.size):
        terms[s] = (values[s] - centre[s]) * (values[s] - centre[s])
    return 0.0 + pairwise_sum(terms, 0, values.size)


@njit(cache=True, nogil=True, error_model="numpy")
def evidence_sums(px, py, x, y, radius, apart, steps):  # type: ignore[no-untyped-def]
    """One frame's sums for :class:`~starlog.centroiding.evidence.EvidenceAccumulator`: into ``apart`` each method's
    squared differences to the others' median, into ``steps`` its squared platform-free displacements from the
    frame before (``px``, ``py``; no columns: none); returns the star pairs matched (the stars' columns before and
    after; none when under three) and each pair's squared displacement, both axes, per method."""
    methods, n = x.shape
    terms, centre, others = np.empty(max(n, px.shape[1])), np.empty(max(n, px.shape[1])), np.empty(methods)
    if methods >= 2 and n:
        for k in range(methods):
            for axis in range(2):
                values = x if axis == 0 else y
                for s in range(n):
                    m = 0
                    for j in range(methods):
                        if j != k:
                            others[m] = values[j, s]
                            m += 1
                    centre[s] = np.median(others[:m])
                apart[k] = apart[k] + _squares_about(values[k], centre[:n], terms)
    none = np.empty(0, np.int64)
    if px.shape[1] == 0 or n == 0:
        return none, none, np.empty((methods, 0))
    before, after = _matched(px, py, x, y, radius)
    if before.size < 3:
        return none, none, np.empty((methods, 0))
    moves, squares = np.empty(before.size), np.zeros((methods, before.size))
    for k in range(methods):
        for axis in range(2):
            then, now = (px, x) if axis == 0 else (py, y)
            for p in range(before.size):
                moves[p] = now[k, after[p]] - then[k, before[p]]
            centre[: before.size] = np.median(moves)
            steps[k] = steps[k] + _squares_about(moves, centre[: before.size], terms)
            for p in range(before.size):
                squares[k, p] = terms[p] if axis == 0 else squares[k, p] + terms[p]
    return before, after, squares

