"""Error decomposition and adaptive multi-strategy compensation of centroid series.

The paper's contribution (§2.2–2.5) as plain numpy/scipy algorithms on (N, 2) position series
in pixels (x = column, y = row, (0, 0) at the centre of the top-left pixel).  Modules, each
importing only those above it:

* :mod:`~starlog.compensation.series` — input validation, eq. 15 of a residual, eq. 13;
* :mod:`~starlog.compensation.burnin` — where the tracking filter's start-up ends;
* :mod:`~starlog.compensation.decimate` — equidistant (nearest-frame) decimation to 10–100 Hz;
* :mod:`~starlog.compensation.references` — the ``paper`` / ``truth`` / ``leakfree`` / ``relative``
  scoring protocols, the reference ``M`` each gives the strategies, and the motion modes
  (``keep`` / ``separate``);
* :mod:`~starlog.compensation.decomposition` — the five error categories and ``f_d``;
* :mod:`~starlog.compensation.strategies` — the five compensation strategies (eq. 1–11);
* :mod:`~starlog.compensation.selection` — scores (eq. 12), the positive-score strategies (at most three) run with rollback (eq. 13);
* :mod:`~starlog.compensation.protocols` — RMSE (eq. 15), the figures of each protocol and
  :func:`evaluate`;
* :mod:`~starlog.compensation.lengths` — the samples each protocol needs, and which rates and
  protocols a log of ``n`` frames is too short for (:func:`shortfalls`), known before tracking.
"""

from __future__ import annotations

from starlog.compensation.burnin import (
    BURN_IN_RATIO,
    MAX_BURN_IN_FRACTION,
    MAX_BURN_IN_S,
    BurnIn,
    BurnInSetting,
    burn_in,
    burn_in_cap,
    burn_in_label,
    fixed_burn_in,
    longest_burn_in,
    parse_burn_in,
)
from starlog.compensation.decimate import (
    RATE_TOLERANCE,
    decimate,
    decimation_indices,
    effective_rate,
    sampled_rate,
)
from starlog.compensation.decomposition import (
    MIN_SAMPLES,
    ErrorCategory,
    ErrorDecomposition,
    SpectralPeak,
    decompose,
)
from starlog.compensation.lengths import (
    Shortfall,
    enough_samples,
    fewest_samples,
    frames_needed,
    samples_needed,
    shortfalls,
)
from starlog.compensation.protocols import (
    FIGURE_DTYPE,
    Evaluation,
    RmseFigure,
    evaluate,
    protocol_figures,
    rmse,
)
from starlog.compensation.references import (
    CALIBRATION_FRACTION,
    MotionMode,
    ReferenceMode,
    ScoringProtocol,
    global_mean_reference,
    protocols_for,
    running_mean_reference,
    scored_start,
)
from starlog.compensation.selection import (
    PASS_DTYPE,
    TABLE_1,
    CompensationPass,
    CompensationResult,
    StrategyProfile,
    compensate,
    rank_strategies,
    strategy_scores,
)
from starlog.compensation.strategies import (
    AR_THETA,
    AccuracySource,
    Strategy,
    adaptive_median,
    adaptive_window_trend,
    apply_strategy,
    ar_prediction,
    confidence,
    confidence_weighted,
    local_smoothing,
    trend_window,
)

__all__ = [
    "AR_THETA",
    "BURN_IN_RATIO",
    "CALIBRATION_FRACTION",
    "FIGURE_DTYPE",
    "MAX_BURN_IN_FRACTION",
    "MAX_BURN_IN_S",
    "MIN_SAMPLES",
    "PASS_DTYPE",
    "RATE_TOLERANCE",
    "TABLE_1",
    "AccuracySource",
    "BurnIn",
    "BurnInSetting",
    "CompensationPass",
    "CompensationResult",
    "ErrorCategory",
    "ErrorDecomposition",
    "Evaluation",
    "MotionMode",
    "ReferenceMode",
    "RmseFigure",
    "ScoringProtocol",
    "Shortfall",
    "SpectralPeak",
    "Strategy",
    "StrategyProfile",
    "adaptive_median",
    "adaptive_window_trend",
    "apply_strategy",
    "burn_in",
    "burn_in_cap",
    "burn_in_label",
    "fixed_burn_in",
    "frames_needed",
    "longest_burn_in",
    "parse_burn_in",
    "ar_prediction",
    "compensate",
    "confidence",
    "confidence_weighted",
    "decimate",
    "decimation_indices",
    "decompose",
    "effective_rate",
    "enough_samples",
    "evaluate",
    "fewest_samples",
    "global_mean_reference",
    "local_smoothing",
    "protocol_figures",
    "protocols_for",
    "rank_strategies",
    "rmse",
    "running_mean_reference",
    "sampled_rate",
    "samples_needed",
    "scored_start",
    "shortfalls",
    "strategy_scores",
    "trend_window",
]
