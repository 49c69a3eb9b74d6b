"""Adaptive strategy selection with rollback (§2.4, eq. 12–14; docs/PAPER.md, "Adaptive selection").

Score (eq. 12, with eq. 14 reduced to an indicator as docs/PAPER.md reads it)::

    Score_j = sum_k A_k * C_jk * E_j * (1 - D_j),   C_jk = 1 if k is a target of j else 0

with ``A_k`` the magnitude (px) of error category ``k`` from the decomposition and ``E_j``,
``D_j`` and the targets from Table 1 (:data:`TABLE_1`; its first row is the trend-estimation
strategy, the paper repeats the median filter's name by mistake).

The highest-scoring strategies whose score is > 0 — at most ``top_k`` (3), fewer when fewer
apply — run one after the other in descending score; ties keep Table 1's order (a stable sort),
so the ranking is deterministic.  A strategy scored 0 targets no error the decomposition found,
so the paper's selection does not run it; ``select_positive=False`` runs the ``top_k`` best
whatever their score (an ablation).  Each pass is
applied to the output of the previous kept pass, with the decomposition (``f_d``) of the
input; after each pass eq. 13 ``Effective = (RMSE_before - RMSE_after) / RMSE_before`` is
computed about the selection reference (eq. 15), and the pass is rolled back when
``Effective < rollback_threshold`` (1 %).  ``RMSE_before = 0`` counts as ``Effective = 0``.

Leak-free reference modes (:class:`~starlog.compensation.references.ReferenceMode`): the
decomposition, the scores and the rollback see only the calibration segment, then the kept
strategies run, in order, on the whole series.  The strategies are filters of the measurements
and may use neighbouring samples (the centred windows of strategies 1–3 reach up to 5 samples
ahead); only the reference ``M`` is restricted to the past.  During selection the flux of
eq. 10 is normalised by the calibration segment's maximum, in the final pass by the whole
sequence's (its weight, ``I / 100``, is at most 0.01).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.compensation.series import (
    as_samples,
    as_series,
    check_int,
    check_rate,
    improvement,
    parse_choice,
    radial_rms,
)
from starlog.compensation.decomposition import (
    MIN_SAMPLES,
    ErrorCategory,
    ErrorDecomposition,
    decompose,
)
from starlog.compensation.references import (
    CALIBRATION_FRACTION,
    ReferenceMode,
    ScoringProtocol,
    SelectionReference,
    selection_reference,
)
from starlog.compensation.strategies import AccuracySource, Strategy, apply_strategy
from starlog.errors import InvalidInputError, InvalidParameterError

__all__ = [
    "PASS_DTYPE",
    "TABLE_1",
    "CompensationPass",
    "CompensationResult",
    "StrategyProfile",
    "compensate",
    "rank_strategies",
    "strategy_scores",
]


@dataclass(frozen=True)
class StrategyProfile:
    """One row of Table 1: effect ``E_j``, execution cost ``D_j`` and target categories."""

    strategy: Strategy
    effect: float
    cost: float
    targets: frozenset[ErrorCategory]


TABLE_1: tuple[StrategyProfile, ...] = (
    StrategyProfile(
        Strategy.ADAPTIVE_WINDOW_TREND, 0.7, 0.3, frozenset({ErrorCategory.SYSTEMATIC_LOW_FREQ})
    ),
    StrategyProfile(
        Strategy.ADAPTIVE_MEDIAN,
        0.6,
        0.2,
        frozenset({ErrorCategory.SYSTEMATIC_HIGH_FREQ, ErrorCategory.MEASUREMENT_NOISE}),
    ),
    StrategyProfile(
        Strategy.LOCAL_SMOOTHING,
        0.5,
        0.1,
        frozenset({ErrorCategory.RANDOM_QUANTIZATION, ErrorCategory.MEASUREMENT_NOISE}),
    ),
    StrategyProfile(Strategy.AR_PREDICTION, 0.8, 0.4, frozenset({ErrorCategory.MODEL_MISMATCH})),
    StrategyProfile(
        Strategy.CONFIDENCE_WEIGHTED,
        0.9,
        0.5,
        frozenset({ErrorCategory.SYSTEMATIC_LOW_FREQ, ErrorCategory.MODEL_MISMATCH}),
    ),
)
"""Table 1 of the paper (first row read as the trend-estimation strategy)."""


def strategy_scores(
    magnitudes: Mapping[ErrorCategory | str, float],
    *,
    table: tuple[StrategyProfile, ...] = TABLE_1,
) -> dict[Strategy, float]:
    """Eq. 12 for every strategy of ``table``.

    Parameters
    ----------
    magnitudes : mapping ErrorCategory (or its name) -> float
        ``A_k`` in px; missing categories count as 0.

    Returns
    -------
    dict[Strategy, float]
        In table order.
    """
    mags: dict[ErrorCategory, float] = {}
    for key, value in magnitudes.items():
        try:
            mags[ErrorCategory(key)] = float(value)
        except ValueError as err:
            raise InvalidParameterError(f"unknown error category {key!r}.") from err
    return {
        row.strategy: sum(mags.get(k, 0.0) for k in row.targets) * row.effect * (1.0 - row.cost)
        for row in table
    }


def rank_strategies(
    scores: Mapping[Strategy, float], *, table: tuple[StrategyProfile, ...] = TABLE_1
) -> tuple[Strategy, ...]:
    """Strategies by descending score; ties keep ``table`` order (deterministic)."""
    order = [row.strategy for row in table if row.strategy in scores]
    return tuple(sorted(order, key=lambda s: -scores[s]))  # sorted() is stable


PASS_DTYPE = np.dtype(
    [
        ("rank", "i4"),
        ("strategy", "U24"),
        ("score", "f8"),
        ("rmse_before", "f8"),
        ("rmse_after", "f8"),
        ("effective", "f8"),
        ("kept", "?"),
    ]
)
"""One compensation pass (row of :meth:`CompensationResult.passes_table`).

Fields
------
rank : int32
    0-based position in the run order (0 = highest score).
strategy : str
    :class:`~starlog.compensation.strategies.Strategy` name.
score : float64, px
    Eq. 12 score.
rmse_before : float64, px
    Eq. 15 of the series entering the pass, about the selection reference, on the selection
    samples.
rmse_after : float64, px
    Same for the pass's output.
effective : float64, 1
    Eq. 13.
kept : bool
    False when the pass was rolled back (``effective < rollback_threshold``).
"""


@dataclass(frozen=True)
class CompensationPass:
    """One strategy pass; fields as in :data:`PASS_DTYPE`."""

    rank: int
    strategy: Strategy
    score: float
    rmse_before: float
    rmse_after: float
    effective: float
    kept: bool

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict with the fields of :data:`PASS_DTYPE`."""
        return {
            "rank": self.rank,
            "strategy": str(self.strategy),
            "score": self.score,
            "rmse_before": self.rmse_before,
            "rmse_after": self.rmse_after,
            "effective": self.effective,
            "kept": self.kept,
        }


@dataclass(frozen=True)
class CompensationResult:
    """Outcome of :func:`compensate`.

    Attributes
    ----------
    compensated : (N, 2) ndarray of float64
        The compensated series, px (x = column, y = row).
    decomposition : ErrorDecomposition
        Decomposition of the selection samples about the selection reference.
    scores : dict[Strategy, float]
        Eq. 12 score of every strategy, Table 1 order.
    order : tuple of Strategy
        Strategies run, in order (the best ``top_k`` with a score > 0, or the ``top_k`` best
        when ``select_positive`` is False).
    passes : tuple of CompensationPass
        One record per strategy run (scores, RMSEs, eq. 13, kept / rolled back).
    protocol : ScoringProtocol
        The scoring protocol the run belongs to.
    reference_mode : ReferenceMode
        How the reference ``M`` was built.
    reference_point : tuple of float or None
        ``M`` (x, y) px when it is a point (global mean, calibration mean); None for the
        running mean.
    n_samples : int
        Length of the series.
    n_selection : int
        Samples used for the decomposition, the scores and the rollback decisions
        (``n_samples``, or the calibration length for the leak-free reference modes).
    rmse_before, rmse_after : float
        Eq. 15 on the selection samples about the selection reference before the first pass
        and after the last kept pass, px.
    rate_hz : float
        Sampling rate, Hz.
    top_k : int
    rollback_threshold : float
    accuracy_source : AccuracySource
        ``A`` of eq. 10.
    select_positive : bool
        Only strategies with a score > 0 were run.
        ``A`` of eq. 10.
    """

    compensated: npt.NDArray[np.float64]
    decomposition: ErrorDecomposition
    scores: dict[Strategy, float]
    order: tuple[Strategy, ...]
    passes: tuple[CompensationPass, ...]
    protocol: ScoringProtocol
    reference_mode: ReferenceMode
    reference_point: tuple[float, float] | None
    n_samples: int
    n_selection: int
    rmse_before: float
    rmse_after: float
    rate_hz: float
    top_k: int
    rollback_threshold: float
    accuracy_source: AccuracySource
    select_positive: bool = True

    @property
    def kept(self) -> tuple[Strategy, ...]:
        """Strategies whose pass was kept, in run order."""
        return tuple(p.strategy for p in self.passes if p.kept)

    def passes_table(self) -> npt.NDArray[np.void]:
        """The passes as a structured array of :data:`PASS_DTYPE`."""
        rows = [
            (p.rank, str(p.strategy), p.score, p.rmse_before, p.rmse_after, p.effective, p.kept)
            for p in self.passes
        ]
        return np.array(rows, dtype=PASS_DTYPE)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready decision record (no arrays, no NaN).

        Layout: ``{"protocol", "reference_mode", "reference_point": [x, y] | null,
        "n_samples", "n_selection", "fs", "top_k", "select_positive", "rollback_threshold", "accuracy_source",
        "rmse_before", "rmse_after", "scores": {STRATEGY: score}, "order": [STRATEGY, ...],
        "kept": [STRATEGY, ...], "passes": [PASS_DTYPE dict, ...],
        "decomposition": ErrorDecomposition.to_dict()}``, with ``fs`` the sampling rate
        :attr:`rate_hz` (the log format's key).  The compensated series itself is not included
        (it is the per-sample output).
        """
        return {
            "protocol": str(self.protocol),
            "reference_mode": str(self.reference_mode),
            "reference_point": None
            if self.reference_point is None
            else [float(v) for v in self.reference_point],
            "n_samples": self.n_samples,
            "n_selection": self.n_selection,
            "fs": self.rate_hz,
            "top_k": self.top_k,
            "select_positive": self.select_positive,
            "rollback_threshold": self.rollback_threshold,
            "accuracy_source": str(self.accuracy_source),
            "rmse_before": self.rmse_before,
            "rmse_after": self.rmse_after,
            "scores": {str(k): float(v) for k, v in self.scores.items()},
            "order": [str(s) for s in self.order],
            "kept": [str(s) for s in self.kept],
            "passes": [p.to_dict() for p in self.passes],
            "decomposition": self.decomposition.to_dict(),
        }


@dataclass(frozen=True)
class _Settings:
    """The validated options of :func:`compensate`."""

    mode: ReferenceMode
    accuracy_source: AccuracySource
    protocol: ScoringProtocol
    top_k: int
    rollback_threshold: float
    select_positive: bool


def _check_settings(reference_mode: ReferenceMode | str, accuracy_source: AccuracySource | str,
                    protocol: ScoringProtocol | str | None, top_k: int, rollback_threshold: float,
                    n_strategies: int, select_positive: bool) -> _Settings:
    mode = parse_choice(ReferenceMode, reference_mode, name="reference_mode")
    acc_src = parse_choice(AccuracySource, accuracy_source, name="accuracy_source")
    if protocol is None:
        proto = ScoringProtocol.PAPER if mode is ReferenceMode.GLOBAL_MEAN else ScoringProtocol.LEAKFREE
    else:
        proto = parse_choice(ScoringProtocol, protocol, name="protocol")
    if (proto is ScoringProtocol.LEAKFREE) != (mode is not ReferenceMode.GLOBAL_MEAN):
        raise InvalidParameterError(
            f"protocol {proto.value!r} does not go with reference_mode {mode.value!r}: "
            "'paper' and 'truth' use 'global_mean'; 'leakfree' uses 'calibration' or "
            "'running_mean'."
        )
    k = check_int(top_k, name="top_k", lo=1, hi=n_strategies)
    thr = float(rollback_threshold)
    if not np.isfinite(thr):
        raise InvalidParameterError(
            f"rollback_threshold must be finite; got {rollback_threshold!r}."
        )
    if not isinstance(select_positive, (bool, np.bool_)):
        raise InvalidParameterError(f"select_positive must be True or False; got {select_positive!r}.")
    return _Settings(mode=mode, accuracy_source=acc_src, protocol=proto, top_k=k,
                     rollback_threshold=thr, select_positive=bool(select_positive))


def _per_sample_inputs(
    n: int, flux: npt.ArrayLike | None, sigma: npt.ArrayLike | None, source: AccuracySource
) -> tuple[npt.NDArray[np.float64] | None, npt.NDArray[np.float64] | None]:
    """Validated flux ``I`` and accuracy ``A`` of eq. 10 (None: not given / ``A = 0``)."""
    flux_a = None if flux is None else as_samples(flux, n, name="flux")
    if source is AccuracySource.SIGMA:
        if sigma is None:
            raise InvalidParameterError("accuracy_source='sigma' needs sigma (px per sample).")
        return flux_a, as_samples(sigma, n, name="sigma", nonnegative=True)
    if sigma is not None:
        as_samples(sigma, n, name="sigma", nonnegative=True)  # validate even when unused
    return flux_a, None


def _head(a: npt.NDArray[np.float64] | None, n: int) -> npt.NDArray[np.float64] | None:
    return None if a is None else a[:n]


def _run_passes(
    xy: npt.NDArray[np.float64], reference: npt.NDArray[np.float64], *, rate_hz: float,
    decomposition: ErrorDecomposition, order: tuple[Strategy, ...], scores: dict[Strategy, float],
    flux: npt.NDArray[np.float64] | None, accuracy: npt.NDArray[np.float64] | None,
    threshold: float,
) -> tuple[npt.NDArray[np.float64], list[CompensationPass]]:
    """Run ``order`` one after the other, rolling back each pass that improves eq. 13 by less
    than ``threshold``; returns the output of the last kept pass and one record per pass."""
    current = xy
    passes: list[CompensationPass] = []
    for rank, strategy in enumerate(order):
        candidate = apply_strategy(
            strategy, current, rate_hz=rate_hz, reference=reference,
            dominant_frequency=decomposition.dominant_frequency, flux=flux, accuracy=accuracy,
        )
        before = radial_rms(current - reference)
        after = radial_rms(candidate - reference)
        effective = improvement(before, after)
        kept = bool(effective >= threshold)
        if kept:
            current = candidate
        passes.append(CompensationPass(rank=rank, strategy=strategy, score=float(scores[strategy]),
                                       rmse_before=float(before), rmse_after=float(after),
                                       effective=float(effective), kept=kept))
    return current, passes


def _replay_kept(
    xy: npt.NDArray[np.float64], passes: list[CompensationPass], *, rate_hz: float,
    reference: npt.NDArray[np.float64], decomposition: ErrorDecomposition,
    flux: npt.NDArray[np.float64] | None, accuracy: npt.NDArray[np.float64] | None,
) -> npt.NDArray[np.float64]:
    """The kept strategies, in order, on the whole series (leak-free modes)."""
    out = xy
    for record in passes:
        if record.kept:
            out = apply_strategy(
                record.strategy, out, rate_hz=rate_hz, reference=reference,
                dominant_frequency=decomposition.dominant_frequency, flux=flux, accuracy=accuracy,
            )
    return out


def compensate(
    xy: npt.ArrayLike,
    *,
    rate_hz: float,
    flux: npt.ArrayLike | None = None,
    sigma: npt.ArrayLike | None = None,
    reference_mode: ReferenceMode | str = ReferenceMode.GLOBAL_MEAN,
    calibration_fraction: float = CALIBRATION_FRACTION,
    accuracy_source: AccuracySource | str = AccuracySource.ZERO,
    top_k: int = 3,
    rollback_threshold: float = 0.01,
    protocol: ScoringProtocol | str | None = None,
    table: tuple[StrategyProfile, ...] = TABLE_1,
    select_positive: bool = True,
) -> CompensationResult:
    """Decompose, score, and run the best strategies with rollback (§2.4, Figure 1).

    Parameters
    ----------
    xy : (N, 2) array_like
        Decimated centroid series, px (x = column, y = row), finite.  ``N >= 16``
        (:data:`~starlog.compensation.decomposition.MIN_SAMPLES`); with a leak-free reference
        mode the calibration segment must have >= 16 samples and leave >= 1 after it.
    rate_hz : float
        Sampling rate of ``xy``, Hz.
    flux : (N,) array_like, optional
        Intensity ``I`` of eq. 10 (normalised by its maximum); default all equal.
    sigma : (N,) array_like, optional
        Centroid uncertainty, px (>= 0); ``A`` of eq. 10 when ``accuracy_source='sigma'``.
    reference_mode : ReferenceMode or str
        ``global_mean`` (paper): ``M`` = mean of ``xy``, selection on all samples.
        ``calibration``: ``M`` = mean of the first ``calibration_fraction`` of ``xy``;
        ``running_mean``: ``M[n]`` = mean of ``xy[:n]`` (leak-free modes: see the module
        docstring).
    calibration_fraction : float
        In (0, 1); leak-free modes only.
    accuracy_source : AccuracySource or str
        ``zero`` (``A = 0``, paper) or ``sigma``.
    top_k : int
        Most strategies to run (1..5), default 3.
    rollback_threshold : float
        Minimum eq. 13 improvement to keep a pass, default 0.01.
    protocol : ScoringProtocol or str, optional
        Label recorded in the result; default ``paper`` for ``global_mean`` and ``leakfree``
        otherwise.  ``paper`` / ``truth`` need ``global_mean``; ``leakfree`` needs a leak-free
        mode.
    table : tuple of StrategyProfile
        Table 1 (override for experiments).
    select_positive : bool
        Run only strategies whose eq. 12 score is > 0 (default, the paper's selection); False
        runs the ``top_k`` best whatever their score.

    Returns
    -------
    CompensationResult
    """
    p = as_series(xy)
    n = p.shape[0]
    rate_hz = check_rate(rate_hz)
    cfg = _check_settings(reference_mode, accuracy_source, protocol, top_k, rollback_threshold,
                          len(table), select_positive)
    if n < MIN_SAMPLES:
        raise InvalidInputError(
            f"compensation needs at least {MIN_SAMPLES} samples; got {n}. Use a longer "
            "sequence or a higher decimated rate."
        )
    flux_a, accuracy = _per_sample_inputs(n, flux, sigma, cfg.accuracy_source)
    ref = selection_reference(p, cfg.mode, calibration_fraction=calibration_fraction,
                              minimum=MIN_SAMPLES)
    n_sel = ref.n_selection
    sel_xy, sel_ref = p[:n_sel], ref.values[:n_sel]
    decomposition = decompose(sel_xy, rate_hz=rate_hz, reference=sel_ref)
    scores = strategy_scores(decomposition.magnitudes, table=table)
    ranked = rank_strategies(scores, table=table)
    if cfg.select_positive:
        ranked = tuple(s for s in ranked if scores[s] > 0.0)
    order = ranked[: cfg.top_k]
    current, passes = _run_passes(
        sel_xy, sel_ref, rate_hz=rate_hz, decomposition=decomposition, order=order,
        scores=scores, flux=_head(flux_a, n_sel), accuracy=_head(accuracy, n_sel),
        threshold=cfg.rollback_threshold,
    )
    compensated = current if n_sel == n else _replay_kept(
        p, passes, rate_hz=rate_hz, reference=ref.values, decomposition=decomposition,
        flux=flux_a, accuracy=accuracy,
    )
    return _result(compensated, decomposition, scores, order, passes, cfg, ref, n=n,
                   rmse_first=radial_rms(sel_xy - sel_ref), rmse_last=radial_rms(current - sel_ref),
                   rate_hz=rate_hz)


def _result(compensated: npt.NDArray[np.float64], decomposition: ErrorDecomposition,
            scores: dict[Strategy, float], order: tuple[Strategy, ...],
            passes: list[CompensationPass], cfg: _Settings, ref: SelectionReference, *, n: int,
            rmse_first: float, rmse_last: float, rate_hz: float) -> CompensationResult:
    return CompensationResult(
        compensated=np.array(compensated, dtype=np.float64, copy=True),
        decomposition=decomposition,
        scores=scores,
        order=tuple(order),
        passes=tuple(passes),
        protocol=cfg.protocol,
        reference_mode=cfg.mode,
        reference_point=ref.point,
        n_samples=n,
        n_selection=ref.n_selection,
        rmse_before=float(rmse_first),
        rmse_after=float(rmse_last),
        rate_hz=rate_hz,
        top_k=cfg.top_k,
        rollback_threshold=cfg.rollback_threshold,
        accuracy_source=cfg.accuracy_source,
        select_positive=cfg.select_positive,
    )
