"""Matching projected catalogue stars to measured centroids in the image, one to one."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["match_nearest", "match_mutual", "isolated"]


def match_nearest(cat_x: npt.NDArray[np.float64], cat_y: npt.NDArray[np.float64], x: npt.NDArray[np.float64],
                  y: npt.NDArray[np.float64], radius: float) -> npt.NDArray[np.int64]:
    """Greedy one-to-one nearest matching: per catalogue star the index of its detection (-1: none within
    ``radius`` px). Catalogue stars are served in order of their distance to their nearest detection."""
    out = np.full(cat_x.size, -1, dtype=np.int64)
    if x.size == 0 or cat_x.size == 0:
        return out
    d = np.hypot(x[None, :] - cat_x[:, None], y[None, :] - cat_y[:, None])
    used = np.zeros(x.size, bool)
    for i in np.argsort(d.min(axis=1)):
        j = int(np.argmin(np.where(used, np.inf, d[i])))
        if d[i, j] <= radius:
            out[i] = j
            used[j] = True
    return out


def match_mutual(cat_x: npt.NDArray[np.float64], cat_y: npt.NDArray[np.float64], x: npt.NDArray[np.float64],
                 y: npt.NDArray[np.float64], radius: float) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Pairs (catalogue index, detection index) that are each other's nearest and closer than ``radius`` px.

    Vectorised, one to one by construction; a detection with two catalogue stars about equally near
    keeps only the nearer (the other stays unmatched rather than mismatched).
    """
    if x.size == 0 or cat_x.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    d2 = np.square(x[None, :] - cat_x[:, None]) + np.square(y[None, :] - cat_y[:, None])
    nearest_det = np.argmin(d2, axis=1)
    nearest_cat = np.argmin(d2, axis=0)
    cat = np.flatnonzero((nearest_cat[nearest_det] == np.arange(cat_x.size))
                         & (d2[np.arange(cat_x.size), nearest_det] <= radius * radius))
    return cat, nearest_det[cat]


def isolated(x: npt.NDArray[np.float64], y: npt.NDArray[np.float64], distance: float) -> npt.NDArray[np.bool_]:
    """True for points with no other point closer than ``distance``."""
    if x.size < 2:
        return np.ones(x.size, bool)
    d = np.hypot(x[None, :] - x[:, None], y[None, :] - y[:, None])
    np.fill_diagonal(d, np.inf)
    return d.min(axis=1) >= distance
