"""Which centroid method to trust in a log, from the log alone (no catalogue, no simulator truth).

The figure of merit is each method's **frame-to-frame noise**: between consecutive frames, a
star's position changes by the platform's motion plus the two frames' centroid errors. The
platform's motion is common to every star, so the displacement of each star minus the median
displacement of all stars matched in the two frames is the difference of two centroid errors; its
RMS divided by sqrt(2) is the method's noise per frame and axis (photon noise, the method's own
noise, and an S-curve where stars move over pixel phases). **The recommended method is the one of
least frame-to-frame noise**, over at least :data:`MIN_STARS` star pairs; with fewer (a log whose
frames do not show the same stars, or one frame) none is named. Its confidence is a bootstrap over the
stars (:func:`bootstrap_rms`: a star is followed from frame to frame while it is matched, and all its
pairs are drawn together): the 95 % interval of each method's noise and the fraction of draws in which it
is the least (``p_best``).

The sky is the other judge: when the frames plate-solve, each method's residual against the catalogue
on the same identified stars (:mod:`starlog.attitude.sky_evidence`, recorded by ``starlog solve``)
measures its whole error, bias included, which frame-to-frame noise cannot see (a static star's error at
its one pixel phase repeats in every frame). :func:`trust` names the method from whichever evidence a
log has: the sky's when it has enough common stars, else the frame-to-frame noise, else none, saying why.

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

from starlog.centroiding.table import CentroidFlag

__all__ = ["DRAWS", "MIN_STARS", "EvidenceAccumulator", "FrameEvidence", "FrameSums", "add_confidence",
           "bootstrap_rms", "evidence_sums", "evidence_sums_vectorised", "frame_evidence", "recommend", "trust"]

F64 = npt.NDArray[np.float64]

MIN_STARS = 20
"""Fewest star pairs (a star in two consecutive frames) the rule needs to name a method."""
MATCH_RADIUS = 1.0
"""px: a star's positions in consecutive frames, each the other's nearest, closer than this are one star."""
MAX_SIGMAS = 100_000
"""Reported sigmas kept per method for their median (the first ones, in frame order)."""
MIN_SKY_STARS = 20
"""Fewest distinct catalogue stars common to every method for the sky to name one."""
MAX_STARS = 100_000
"""Stars followed for the bootstrap at most; later ones share their sums with earlier ones (modulo)."""
DRAWS = 2000
"""Bootstrap draws."""
_CHUNK = 250
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


@dataclass(frozen=True)
class FrameSums:
    """One frame's sums for :class:`EvidenceAccumulator`: per method, the sum of squared differences of its
    positions to the other methods' median (0 with one method) and of the squared platform-free displacements of
    the stars matched to the frame before; the matched stars' columns in that frame and in this one (none when
    under three pairs), and each pair's squared displacement over both axes, ``(methods, pairs)``."""

    apart: F64
    steps: F64
    before: npt.NDArray[np.intp]
    after: npt.NDArray[np.intp]
    squares: F64


def evidence_sums(previous: FrameEvidence | None, frame: FrameEvidence) -> FrameSums:
    """:class:`FrameSums` of a frame, compiled (:func:`starlog.centroiding.evidence_kernel.evidence_sums`; the same
    numbers as :func:`evidence_sums_vectorised`, but where two stars are at exactly the same distance)."""
    from starlog.centroiding.evidence_kernel import evidence_sums as compiled  # numba: imported, and compiled, on use

    methods = frame.x.shape[0]
    apart, steps = np.zeros(methods), np.zeros(methods)
    before = previous if previous is not None else FrameEvidence(*(np.zeros((methods, 0)),) * 3)
    i, j, squares = compiled(np.ascontiguousarray(before.x, np.float64), np.ascontiguousarray(before.y, np.float64),
                             np.ascontiguousarray(frame.x, np.float64), np.ascontiguousarray(frame.y, np.float64),
                             MATCH_RADIUS, apart, steps)
    return FrameSums(apart, steps, i.astype(np.intp, copy=False), j.astype(np.intp, copy=False), squares)


def evidence_sums_vectorised(previous: FrameEvidence | None, frame: FrameEvidence) -> FrameSums:
    """:func:`evidence_sums` in numpy: the reference the tests compare the compiled loop with."""
    methods, n = frame.x.shape
    apart, steps = np.zeros(methods), np.zeros(methods)
    if methods >= 2 and n:
        for k in range(methods):
            others = [j for j in range(methods) if j != k]
            dx = frame.x[k] - np.median(frame.x[others], axis=0)
            dy = frame.y[k] - np.median(frame.y[others], axis=0)
            apart[k] = float(np.sum(dx * dx) + np.sum(dy * dy))
    none = np.zeros(0, np.intp)
    if previous is None:
        return FrameSums(apart, steps, none, none, np.zeros((methods, 0)))
    i, j = _matched_pairs(previous, frame)
    if i.size < 3:
        return FrameSums(apart, steps, none, none, np.zeros((methods, 0)))
    squares = np.empty((methods, i.size))
    for k in range(methods):
        sx = frame.x[k, j] - previous.x[k, i]
        sy = frame.y[k, j] - previous.y[k, i]
        sx, sy = sx - np.median(sx), sy - np.median(sy)
        steps[k] = float(np.sum(sx * sx) + np.sum(sy * sy))
        squares[k] = sx * sx + sy * sy
    return FrameSums(apart, steps, i, j, squares)


@dataclass
class EvidenceAccumulator:
    """The evidence of a log's frames, pooled per method (:meth:`add` in frame order, :meth:`result`); each
    frame's sums by :func:`evidence_sums`, or its numpy form with ``vectorised``."""

    methods: list[str]
    vectorised: bool = False
    steps: list[float] = field(init=False)  # per method: sum of squared platform-free displacements, both axes
    apart: list[float] = field(init=False)  # per method: sum of squared differences to the others' median
    sigmas: list[list[npt.NDArray[np.float64]]] = field(init=False)
    pairs: int = field(default=0, init=False)
    stars: int = field(default=0, init=False)
    previous: FrameEvidence | None = field(default=None, init=False)
    followed: npt.NDArray[np.int64] = field(init=False)  # the previous frame's stars' numbers (-1: none yet)
    star_sums: npt.NDArray[np.float64] = field(init=False)  # (methods, stars followed): squared displacements
    star_pairs: npt.NDArray[np.float64] = field(init=False)  # pairs per star followed
    next_star: int = field(default=0, init=False)

    def __post_init__(self) -> None:
        self.steps, self.apart = [0.0] * len(self.methods), [0.0] * len(self.methods)
        self.sigmas = [[] for _ in self.methods]
        self.followed = np.zeros(0, np.int64)
        self.star_sums, self.star_pairs = np.zeros((len(self.methods), 0)), np.zeros(0)

    def add(self, frame: FrameEvidence) -> None:
        n = frame.x.shape[1]
        if self.stars < MAX_SIGMAS and n:
            for k in range(len(self.methods)):
                self.sigmas[k].append(frame.sigma[k, : MAX_SIGMAS - self.stars])
        self.stars += n
        sums = (evidence_sums_vectorised if self.vectorised else evidence_sums)(self.previous, frame)
        if len(self.methods) >= 2 and n:
            self.apart = [total + float(a) for total, a in zip(self.apart, sums.apart)]
        followed = np.full(n, -1, np.int64)
        if sums.before.size:
            self.pairs += int(sums.before.size)
            self.steps = [total + float(d) for total, d in zip(self.steps, sums.steps)]
            followed[sums.after] = self._star_numbers(sums.before)
            for k in range(len(self.methods)):
                np.add.at(self.star_sums[k], followed[sums.after], sums.squares[k])
            np.add.at(self.star_pairs, followed[sums.after], 1.0)
        self.previous, self.followed = frame, followed

    def _star_numbers(self, i: npt.NDArray[np.intp]) -> npt.NDArray[np.int64]:
        """The numbers of the previous frame's stars ``i``, a new one for each not followed yet (modulo
        :data:`MAX_STARS`); the per-star sums grow to hold them."""
        numbers = self.followed[i].copy()
        new = numbers < 0
        numbers[new] = (self.next_star + np.arange(int(new.sum()))) % MAX_STARS
        self.next_star += int(new.sum())
        size = min(self.next_star, MAX_STARS)
        if size > self.star_pairs.size:
            pad = min(max(size, 2 * self.star_pairs.size, 64), MAX_STARS) - self.star_pairs.size
            self.star_sums = np.pad(self.star_sums, ((0, 0), (0, pad)))
            self.star_pairs = np.pad(self.star_pairs, (0, pad))
        return numbers

    def result(self) -> dict[str, dict[str, Any]]:
        """Per method: ``pairs`` (star pairs of consecutive frames) and ``noise_px`` (frame-to-frame noise per frame
        and axis) with its ``interval_px`` (95 %) and ``p_best`` (:func:`add_confidence`; None without pairs),
        ``stars``, ``median_sigma_px`` and ``apart_px`` (RMS difference to the others' median, per axis)."""
        out = {}
        for k, m in enumerate(self.methods):
            sig = np.concatenate(self.sigmas[k]) if self.sigmas[k] else np.zeros(0)
            # a displacement holds two frames' errors: its variance per axis is twice the noise's
            noise = float(np.sqrt(self.steps[k] / (4 * self.pairs))) if self.pairs else None
            apart = float(np.sqrt(self.apart[k] / (2 * self.stars))) if self.stars and len(self.methods) > 1 else None
            out[m] = {"pairs": self.pairs, "noise_px": noise, "stars": self.stars,
                      "median_sigma_px": float(np.median(sig)) if sig.size else None, "apart_px": apart,
                      "interval_px": None, "p_best": None}
        seen = self.star_pairs > 0
        if self.pairs and seen.any():
            boot = bootstrap_rms(self.star_sums[:, seen], self.star_pairs[seen]) / np.sqrt(2.0)
            add_confidence(out, "noise_px", boot)
        return out


def bootstrap_rms(sums: npt.NDArray[np.float64], counts: npt.NDArray[np.float64], *, draws: int = DRAWS,
                  seed: int = 1) -> npt.NDArray[np.float64]:
    """Bootstrap draws of each method's RMS per axis, ``(draws, methods)``: ``sums`` ``(methods, stars)`` holds
    each star's sum of squared errors over both axes, ``counts`` its error pairs (x, y); every draw resamples
    the stars with replacement, the same ones for every method (fixed ``seed``: the same figures each time)."""
    rng = np.random.default_rng(seed)
    n = counts.size
    out = np.empty((draws, sums.shape[0]))
    for start in range(0, draws, _CHUNK):
        size = min(_CHUNK, draws - start)
        picks = rng.integers(0, n, (size, n))
        weights = np.zeros((size, n))
        np.add.at(weights, (np.repeat(np.arange(size), n), picks.ravel()), 1.0)
        out[start:start + size] = np.sqrt((weights @ sums.T) / np.maximum(2.0 * (weights @ counts), 1.0)[:, None])
    return out


def add_confidence(evidence: dict[str, dict[str, Any]], key: str, boot: npt.NDArray[np.float64]) -> None:
    """Each method's 95 % ``interval_px`` of its figure ``key``, ``p_best`` (the fraction of draws in which it
    is the least) and ``ratio_to_best`` with its ``ratio_interval`` (against the least figure, draw by draw),
    from bootstrap draws ``(draws, methods)`` in the order of ``evidence``."""
    names = list(evidence)
    best = min(range(len(names)), key=lambda k: (evidence[names[k]][key], names[k]))
    wins = np.bincount(np.argmin(boot, axis=1), minlength=len(names)) / boot.shape[0]
    for k, name in enumerate(names):
        lo, hi = np.percentile(boot[:, k], [2.5, 97.5])
        r_lo, r_hi = np.percentile(boot[:, k] / np.maximum(boot[:, best], 1e-300), [2.5, 97.5])
        evidence[name].update({"interval_px": [float(lo), float(hi)], "p_best": float(wins[k]),
                               "ratio_to_best": evidence[name][key] / max(evidence[names[best]][key], 1e-300),
                               "ratio_interval": [float(r_lo), float(r_hi)]})


def recommend(evidence: Mapping[str, Mapping[str, Any]]) -> tuple[str | None, str]:
    """The method to trust by the frame-to-frame rule (module docstring), and the one-line reason (or why none
    is named)."""
    usable = {m: e for m, e in evidence.items() if e.get("noise_px") is not None}
    pairs = max((int(e.get("pairs", 0)) for e in evidence.values()), default=0)
    if not usable or pairs < MIN_STARS:
        return None, (f"no method named: {pairs} stars were seen in consecutive frames; the rule (least "
                      f"frame-to-frame noise) needs {MIN_STARS}.")
    ranked = sorted(usable, key=lambda m: (usable[m]["noise_px"], m))
    best = ranked[0]
    sigma = usable[best].get("median_sigma_px")
    claim = f"; its own sigma {sigma:.4f} px" if sigma is not None else ""
    return best, (f"{best}: the least frame-to-frame noise, platform motion removed ("
                  f"{_figure(usable, best, 'noise_px', ranked)}; {pairs} star pairs){claim}.")


def _figure(evidence: Mapping[str, Mapping[str, Any]], best: str, key: str, ranked: list[str]) -> str:
    """``0.0583 px per axis, 95 % 0.0531-0.0640, least in 62 % of draws; next M 0.0590, x1.012 (0.99-1.03)``."""
    e = evidence[best]
    text = f"{e[key]:.4f} px per axis"
    if e.get("interval_px"):
        lo, hi = e["interval_px"]
        text += f", 95 % {lo:.4f}-{hi:.4f}, least in {100 * e['p_best']:.0f} % of bootstrap draws over stars"
    if len(ranked) > 1:
        nxt = evidence[ranked[1]]
        text += f"; next {ranked[1]} {nxt[key]:.4f}"
        if nxt.get("ratio_interval"):
            r_lo, r_hi = nxt["ratio_interval"]
            text += f", x{nxt['ratio_to_best']:.3f} (95 % {r_lo:.3f}-{r_hi:.3f})"
    return text


def trust(noise: Mapping[str, Mapping[str, Any]] | None, sky: Mapping[str, Mapping[str, Any]] | None, *,
          sky_missing: str = "the log was not plate-solved (starlog solve --centroids all)") -> dict[str, Any]:
    """Which method to trust from whichever evidence the log has (module docstring): the sky's catalogue residuals
    (``sky``: :func:`starlog.attitude.sky_evidence.sky_evidence`) on at least :data:`MIN_SKY_STARS` common
    stars, else the frame-to-frame noise (``noise``: :meth:`EvidenceAccumulator.result`), else none.

    Returns ``method`` (None: none named), ``evidence`` (``"sky"``, ``"frame-to-frame"`` or None), ``figure_px``,
    ``interval_px``, ``p_best`` and ``reason`` (one line, naming why the other evidence was not used);
    ``sky_missing`` says why there is no sky evidence when ``sky`` is None."""
    sky_why = _sky_unusable(sky, sky_missing)
    if sky_why is None:
        assert sky is not None
        ranked = sorted(sky, key=lambda m: (sky[m]["residual_px"], m))
        best, e = ranked[0], sky[ranked[0]]
        reason = (f"{best}: the least catalogue residual on the same identified stars, one camera model per log ("
                  f"{_figure(sky, best, 'residual_px', ranked)}; {e['stars']} stars in {e['frames']} frames)")
        named, _ = recommend(noise) if noise else (None, "")
        if named is not None:
            reason += f"; frame-to-frame noise names {named} ({noise[named]['noise_px']:.4f} px)"
        return {"method": best, "evidence": "sky", "figure_px": e["residual_px"], "interval_px": e["interval_px"],
                "p_best": e["p_best"], "reason": reason + "."}
    method, why = recommend(noise) if noise else (None, "no method named: the log has no centroid evidence.")
    if method is None:
        return {"method": None, "evidence": None, "figure_px": None, "interval_px": None, "p_best": None,
                "reason": f"{why.removesuffix('.')}; no catalogue evidence: {sky_why}."}
    assert noise is not None
    e = noise[method]
    return {"method": method, "evidence": "frame-to-frame", "figure_px": e["noise_px"],
            "interval_px": e.get("interval_px"), "p_best": e.get("p_best"),
            "reason": f"{why.removesuffix('.')}; no catalogue evidence: {sky_why}."}


def _sky_unusable(sky: Mapping[str, Mapping[str, Any]] | None, missing: str) -> str | None:
    """Why the sky's evidence cannot name a method (None: it can)."""
    if not sky:
        return missing
    if len(sky) < 2:
        return f"one method solved ({next(iter(sky))}): the sky compares two or more"
    stars = min(int(e.get("stars") or 0) for e in sky.values())
    if stars < MIN_SKY_STARS or any(e.get("residual_px") is None for e in sky.values()):
        return f"{stars} catalogue stars were identified by every method; the sky needs {MIN_SKY_STARS}"
    return None
