"""The sky as the judge of centroid methods: each method's catalogue residual on the same identified stars.

When a log's frames plate-solve, every method's centroids of the identified stars can be compared with
where the catalogue puts those stars. The comparison is fair only on the same stars and the same camera
model, so:

1. **Common stars**: the (frame, catalogue star) pairs that every method identified, less the catalogue
   stars with another within ``isolation`` px (:data:`ISOLATION_PX`): where two catalogue stars blend, the
   catalogue does not say where their light's centre is; then the brighter half of them by catalogue
   magnitude (:data:`BRIGHTER`), which no method and no camera setting changes. The fainter stars of a
   field are the many; noise-limited for every method alike, their residuals would hide the differences the
   methods make.
2. **One camera per log and method**: an attitude per frame and one focal length and radial distortion
   for the whole log (:func:`starlog.attitude.camera.fit_cameras_shared`), fitted to the method's own
   positions of the common stars, from the cameras its frames were solved with. A per-frame camera would
   absorb part of the centroid errors into each frame's focal length and distortion.
3. **The figure**: the per-axis RMS of the residuals, ``sqrt(mean(dx^2 + dy^2) / 2)`` px. The catalogue's
   own errors and what the camera model cannot describe add the same amount to every method.
4. **Its confidence**: a bootstrap over the catalogue stars (:func:`starlog.centroiding.evidence.bootstrap_rms`,
   fixed seed: the same evidence gives the same figures), each star with all its frames, so that a static
   field's star, whose error at one pixel phase repeats frame after frame, counts once: the 95 % interval of
   each method's figure, the fraction of draws in which it is the least (``p_best``), and the interval of
   its ratio to the least one's (:func:`starlog.centroiding.evidence.add_confidence`).

:func:`sky_evidence` computes it; :data:`MIN_SKY_STARS` distinct common stars are needed for the evidence to
name a method (:func:`starlog.centroiding.evidence.trust`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.attitude.camera import Camera, fit_cameras_shared
from starlog.centroiding.evidence import DRAWS, MIN_SKY_STARS, add_confidence, bootstrap_rms

__all__ = ["BRIGHTER", "ISOLATION_PX", "MAX_SKY_FRAMES", "MIN_SKY_STARS", "IdentifiedFrame", "sky_evidence"]

ISOLATION_PX = 6.0
"""A catalogue star with another this close (px, at the fitted focal length) is left out: twice the solve
stage's match radius."""
BRIGHTER = 0.5
"""The share of the common stars the sky judges on: the brightest by catalogue magnitude."""
MAX_SKY_FRAMES = 500
"""Solved frames a log's evidence uses at most (evenly spaced through a longer log)."""


@dataclass(frozen=True)
class IdentifiedFrame:
    """One method's identified stars in one solved frame: ``frame`` (its number), the camera it was solved
    with, the stars' catalogue rows and their measured positions (px)."""

    frame: int
    camera: Camera
    catalogue: npt.NDArray[np.int64]
    x: npt.NDArray[np.float64]
    y: npt.NDArray[np.float64]


def _common(frames: Mapping[str, Sequence[IdentifiedFrame]], usable: npt.NDArray[np.bool_]
            ) -> list[tuple[int, npt.NDArray[np.int64], dict[str, tuple[IdentifiedFrame, npt.NDArray[np.intp]]]]]:
    """Per frame solved by every method: the ``usable`` catalogue rows every method identified (sorted) and,
    per method, its frame and the rows of its stars in that order."""
    by_frame = [{f.frame: f for f in fs} for fs in frames.values()]
    names = list(frames)
    out = []
    for number in sorted(set.intersection(*(set(b) for b in by_frame))) if by_frame else []:
        rows = [b[number].catalogue for b in by_frame]
        shared = rows[0][usable[rows[0]]]
        for r in rows[1:]:
            shared = np.intersect1d(shared, r)
        if shared.size == 0:
            continue
        picks = {}
        for name, b in zip(names, by_frame):
            f = b[number]
            order = np.argsort(f.catalogue, kind="stable")
            picks[name] = (f, order[np.searchsorted(f.catalogue[order], shared)])
        out.append((number, shared, picks))
    return out


def _brighter(common: list[tuple[int, npt.NDArray[np.int64], dict[str, tuple[IdentifiedFrame, npt.NDArray[np.intp]]]]],
              magnitudes: npt.NDArray[np.float64], share: float
              ) -> list[tuple[int, npt.NDArray[np.int64], dict[str, tuple[IdentifiedFrame, npt.NDArray[np.intp]]]]]:
    """The ``share`` of the common (frame, star) pairs of the brightest catalogue magnitude (ties kept)."""
    if not common or share >= 1.0:
        return common
    limit = float(np.quantile(np.concatenate([magnitudes[shared] for _, shared, _ in common]), share))
    out = []
    for number, shared, picks in common:
        keep = magnitudes[shared] <= limit
        if keep.any():
            out.append((number, shared[keep], {n: (f, rows[keep]) for n, (f, rows) in picks.items()}))
    return out


def _isolated(frames: Mapping[str, Sequence[IdentifiedFrame]], vectors: npt.NDArray[np.float64],
              isolation_px: float) -> npt.NDArray[np.bool_]:
    """Catalogue rows with no other catalogue star within ``isolation_px`` (an angle at the frames' median focal
    length)."""
    from scipy.spatial import cKDTree

    focal = float(np.median([f.camera.focal for fs in frames.values() for f in fs]))
    rows = np.unique(np.concatenate([f.catalogue for fs in frames.values() for f in fs]))
    keep = np.zeros(vectors.shape[0], np.bool_)
    if rows.size:
        dist, _ = cKDTree(vectors).query(vectors[rows], k=2)
        keep[rows] = dist[:, 1] > isolation_px / focal
    return keep


def sky_evidence(frames: Mapping[str, Sequence[IdentifiedFrame]], vectors: npt.NDArray[np.float64],
                 magnitudes: npt.NDArray[np.float64], *, fit_distortion: bool = True,
                 isolation_px: float = ISOLATION_PX, brighter: float = BRIGHTER, draws: int = DRAWS,
                 seed: int = 1) -> dict[str, dict[str, Any]]:
    """Per method (module docstring): ``residual_px`` (per axis), ``interval_px`` (95 %), ``p_best``,
    ``ratio_to_best`` with ``ratio_interval``, ``stars`` (distinct common catalogue stars), ``matches``
    (common frame-star pairs), ``frames``, and the camera fitted (``focal_px``, ``distortion``). ``frames``:
    each method's solved frames; ``vectors``, ``magnitudes``: the catalogue's unit vectors and magnitudes,
    indexed by the frames' rows. With no common star every figure is None."""
    names = list(frames)
    common = _common(frames, _isolated(frames, vectors, isolation_px)) if all(frames.values()) else []
    common = _brighter(common, magnitudes, brighter)
    if not common:
        return {m: {"stars": 0, "matches": 0, "frames": 0, "residual_px": None, "interval_px": None,
                    "p_best": None, "ratio_to_best": None, "ratio_interval": None} for m in names}
    stars = np.concatenate([shared for _, shared, _ in common])
    star_ids, cluster = np.unique(stars, return_inverse=True)
    sums = np.zeros((len(names), star_ids.size))
    out: dict[str, dict[str, Any]] = {}
    for k, name in enumerate(names):
        cams = [picks[name][0].camera for _, _, picks in common]
        xs = [picks[name][0].x[picks[name][1]] for _, _, picks in common]
        ys = [picks[name][0].y[picks[name][1]] for _, _, picks in common]
        vs = [vectors[shared] for _, shared, _ in common]
        start = [replace(cams[0], focal=float(np.median([c.focal for c in cams])),
                         k=float(np.median([c.k for c in cams])))] + cams[1:]
        fitted = fit_cameras_shared(start, vs, xs, ys, fit_distortion=fit_distortion)
        res = np.concatenate([np.column_stack([x - px, y - py]) for c, v, x, y in zip(fitted, vs, xs, ys)
                              for px, py, _ in [c.project(v)]])
        sums[k] = np.bincount(cluster, weights=(res * res).sum(axis=1), minlength=star_ids.size)
        out[name] = {"stars": int(star_ids.size), "matches": int(stars.size), "frames": len(common),
                     "residual_px": float(np.sqrt(np.mean(res * res))), "focal_px": float(fitted[0].focal),
                     "distortion": float(fitted[0].k)}
    counts = np.bincount(cluster, minlength=star_ids.size).astype(np.float64)
    add_confidence(out, "residual_px", bootstrap_rms(sums, counts, draws=draws, seed=seed))
    return out
