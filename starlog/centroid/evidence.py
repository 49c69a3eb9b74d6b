"""Which centroid method to trust in a log, from the log alone (no catalogue, no simulator truth).

The figure of merit is each method's **frame-to-frame noise**: between consecutive frames, a
star's position changes by the platform's motion plus the two frames' centroid errors. The
platform's motion is common to every star, so the displacement of each star minus the median
displacement of all stars matched in the two frames is the difference of two centroid errors; its
RMS divided by sqrt(2) is the method's noise per frame and axis (photon noise, the method's own
noise, and an S-curve where stars move over pixel phases). **The recommended method is the one of
least frame-to-frame noise**, over at least :data:`MIN_STARS` star pairs; with fewer (a log whose
frames do not show the same stars, or one frame) none is named.

Shown beside it as evidence, not used by the rule: each method's median reported ``sigma`` (its
own claim, which the tracker uses; it should match the noise), the RMS difference of its positions
to the median of the other methods on the same stars (a method apart from the others), and its
pixel-phase calibration (amplitude and standard error).

:func:`frame_evidence` takes one frame's centroid tables; :class:`EvidenceAccumulator` pools the
frames in order; :func:`recommend` applies the rule.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.centroid.table import CentroidFlag

__all__ = ["MIN_STARS", "EvidenceAccumulator", "FrameEvidence", "evidence_sums", "evidence_sums_vectorised",
           "frame_evidence", "recommend"]

F64 = npt.NDArray[np.float64]

MIN_STARS = 20
"""Fewest star pairs (a star in two consecutive frames) the rule needs to name a method."""
MATCH_RADIUS = 1.0
"""px: a star's positions in consecutive frames, each the other's nearest, closer than this are one star."""
MAX_SIGMAS = 100_000
"""Reported sigmas kept per method for their median (the first ones, in frame order)."""
_EXCLUDED = int(CentroidFlag.FIT_FAILED | CentroidFlag.SATURATED | CentroidFlag.BORDER)


@dataclass(frozen=True)
class FrameEvidence:
    """One frame's stars every method measured (not failed, saturated or cut by the border): positions and
    reported sigmas, ``(methods, stars)`` each."""

    x: npt.NDArray[np.float64]
    y: npt.NDArray[np.float64]
    sigma: npt.NDArray[np.float64]


def frame_evidence(tables: Sequence[npt.NDArray[np.void]]) -> FrameEvidence:
    """:class:`FrameEvidence` of one frame's centroid tables, one per method, each one row per detection in the
    detections' order (the centroid stage's tables)."""
    if not tables or tables[0].size == 0:
        empty = np.zeros((len(tables), 0))
        return FrameEvidence(empty, empty, empty)
    x = np.stack([np.asarray(t["x"], np.float64) for t in tables])
    y = np.stack([np.asarray(t["y"], np.float64) for t in tables])
    good = np.all(np.isfinite(x) & np.isfinite(y), axis=0)
    for t in tables:
        good &= (t["flags"] & _EXCLUDED) == 0
    return FrameEvidence(x[:, good], y[:, good], np.stack([np.asarray(t["sigma"], np.float64) for t in tables])[:, good])


def _matched_pairs(before: FrameEvidence, after: FrameEvidence) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """Stars of two frames that are each other's nearest (first method's positions) within :data:`MATCH_RADIUS`."""
    from scipy.spatial import cKDTree

    if before.x.shape[1] == 0 or after.x.shape[1] == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    a = np.column_stack([before.x[0], before.y[0]])
    b = np.column_stack([after.x[0], after.y[0]])
    dist_ab, ab = cKDTree(b).query(a)
    _, ba = cKDTree(a).query(b)
    i = np.flatnonzero((dist_ab <= MATCH_RADIUS) & (ba[ab] == np.arange(a.shape[0])))
    return i, ab[i]


def evidence_sums(previous: FrameEvidence | None, frame: FrameEvidence) -> tuple[F64, F64, int]:
    """One frame's sums for :class:`EvidenceAccumulator`, compiled (:func:`starlog.centroid._kernels.evidence_sums`;
    the same numbers as :func:`evidence_sums_vectorised`, but where two stars are at exactly the same distance)."""
    from starlog.centroid._kernels import evidence_sums as compiled  # numba: imported, and compiled, on first use

    methods = frame.x.shape[0]
    apart, steps = np.zeros(methods), np.zeros(methods)
    before = previous if previous is not None else FrameEvidence(*(np.zeros((methods, 0)),) * 3)
    pairs = compiled(np.ascontiguousarray(before.x, np.float64), np.ascontiguousarray(before.y, np.float64),
                     np.ascontiguousarray(frame.x, np.float64), np.ascontiguousarray(frame.y, np.float64),
                     MATCH_RADIUS, apart, steps)
    return apart, steps, int(pairs)


def evidence_sums_vectorised(previous: FrameEvidence | None, frame: FrameEvidence) -> tuple[F64, F64, int]:
    """Per method, the sum of squared differences of its positions to the other methods' median (0 with one
    method), the sum of squared platform-free displacements of the stars matched to ``previous``, and the pairs
    matched (0, and no displacements, when under three): the numpy form of :func:`evidence_sums`."""
    methods, n = frame.x.shape
    apart, steps = np.zeros(methods), np.zeros(methods)
    if methods >= 2 and n:
        for k in range(methods):
            others = [j for j in range(methods) if j != k]
            dx = frame.x[k] - np.median(frame.x[others], axis=0)
            dy = frame.y[k] - np.median(frame.y[others], axis=0)
            apart[k] = float(np.sum(dx * dx) + np.sum(dy * dy))
    if previous is None:
        return apart, steps, 0
    i, j = _matched_pairs(previous, frame)
    if i.size < 3:
        return apart, steps, 0
    for k in range(methods):
        sx = frame.x[k, j] - previous.x[k, i]
        sy = frame.y[k, j] - previous.y[k, i]
        sx, sy = sx - np.median(sx), sy - np.median(sy)
        steps[k] = float(np.sum(sx * sx) + np.sum(sy * sy))
    return apart, steps, int(i.size)


@dataclass
class EvidenceAccumulator:
    """The evidence of a log's frames, pooled per method (:meth:`add` in frame order, :meth:`result`)."""

    methods: list[str]
    steps: list[float] = field(init=False)  # per method: sum of squared platform-free displacements, both axes
    apart: list[float] = field(init=False)  # per method: sum of squared differences to the others' median
    sigmas: list[list[npt.NDArray[np.float64]]] = field(init=False)
    pairs: int = field(default=0, init=False)
    stars: int = field(default=0, init=False)
    previous: FrameEvidence | None = field(default=None, init=False)

    def __post_init__(self) -> None:
        self.steps, self.apart = [0.0] * len(self.methods), [0.0] * len(self.methods)
        self.sigmas = [[] for _ in self.methods]

    def add(self, frame: FrameEvidence) -> None:
        n = frame.x.shape[1]
        if self.stars < MAX_SIGMAS and n:
            for k in range(len(self.methods)):
                self.sigmas[k].append(frame.sigma[k, : MAX_SIGMAS - self.stars])
        self.stars += n
        apart, steps, pairs = evidence_sums(self.previous, frame)
        if len(self.methods) >= 2 and n:
            self.apart = [total + float(a) for total, a in zip(self.apart, apart)]
        if pairs:
            self.pairs += pairs
            self.steps = [total + float(d) for total, d in zip(self.steps, steps)]
        self.previous = frame

    def result(self) -> dict[str, dict[str, Any]]:
        """Per method: ``pairs`` (star pairs of consecutive frames) and ``noise_px`` (frame-to-frame noise per frame
        and axis), ``stars``, ``median_sigma_px`` and ``apart_px`` (RMS difference to the others' median, per axis)."""
        out = {}
        for k, m in enumerate(self.methods):
            sig = np.concatenate(self.sigmas[k]) if self.sigmas[k] else np.zeros(0)
            # a displacement holds two frames' errors: its variance per axis is twice the noise's
            noise = float(np.sqrt(self.steps[k] / (4 * self.pairs))) if self.pairs else None
            apart = float(np.sqrt(self.apart[k] / (2 * self.stars))) if self.stars and len(self.methods) > 1 else None
            out[m] = {"pairs": self.pairs, "noise_px": noise, "stars": self.stars,
                      "median_sigma_px": float(np.median(sig)) if sig.size else None, "apart_px": apart}
        return out


def recommend(evidence: Mapping[str, Mapping[str, Any]]) -> tuple[str | None, str]:
    """The method to trust by the module's rule, and the one-line reason (or why none is named)."""
    usable = {m: e for m, e in evidence.items() if e.get("noise_px") is not None}
    pairs = max((int(e.get("pairs", 0)) for e in evidence.values()), default=0)
    if not usable or pairs < MIN_STARS:
        return None, (f"no method named: {pairs} stars were seen in consecutive frames; the rule (least "
                      f"frame-to-frame noise) needs {MIN_STARS}.")
    ranked = sorted(usable, key=lambda m: (usable[m]["noise_px"], m))
    best = ranked[0]
    sigma = usable[best].get("median_sigma_px")
    next_one = f", next {ranked[1]} {usable[ranked[1]]['noise_px']:.4f}" if len(ranked) > 1 else ""
    claim = f"; its own sigma {sigma:.4f} px" if sigma is not None else ""
    return best, (f"{best}: the least frame-to-frame noise, platform motion removed ({usable[best]['noise_px']:.4f} "
                  f"px per axis{next_one}; {pairs} star pairs){claim}.")
