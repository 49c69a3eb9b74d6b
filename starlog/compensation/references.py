"""Scoring protocols and the reference ``M`` the strategies are given (paper §2.1, §2.5; docs/PAPER.md).

The paper's "truth" is the global mean of the centroid sequence, and its RMSE (eq. 15) is the
radial scatter about that mean.  Strategies 1, 4 and 5 pull the measurements towards that same
mean, so the paper's figure is partly circular.  Three protocols are offered, and every
evaluation (and every compensation result) says which one it used:

``paper``
    The reference ``M`` is the global mean of the (decimated) input sequence.  It is given to the
    strategies, to the selection / rollback of eq. 13, and the RMSE is scored about it
    (figure ``global_mean``).  This reproduces the paper's tables.
``truth``
    The strategies, the selection and the rollback still use the global mean ``M`` (what an
    operational system has), but the RMSE is scored against the simulator's truth: the fixed
    true position (figure ``truth_fixed``) and/or the jittered instantaneous true positions
    (figure ``truth_series``), whichever are given (both when both are given).
``leakfree``
    The sequence is split: the first ``calibration_fraction`` of the samples is a calibration
    segment that is never scored; the rest is the held-out, scored part.  The reference the
    strategies use is estimated only from the past: by default (``ReferenceMode.CALIBRATION``)
    the mean of the raw calibration samples; optionally (``ReferenceMode.RUNNING_MEAN``) the
    running mean of the samples strictly before ``n``.  The error decomposition, the scores and
    the rollback decisions are computed on the calibration segment only; the kept strategies are
    then applied to the whole sequence and scored on the held-out part against the mean of the
    *raw held-out samples* (figure ``heldout_mean``: a reference no strategy and no selection step
    ever saw) and against the truth on the held-out part when given.
``relative``
    Truth-free: the strategies and the selection use the global mean ``M`` (as under ``truth``),
    and the RMSE is scored against the star's static position moved by the platform motion fitted
    from the *other* stars of each frame (figure ``relative``, :mod:`starlog.platform_motion`).  The other
    stars' centroid errors are independent of this star's, so the figure is this star's error
    plus the reference's own; the reference's variance, predicted by its fit, is removed in
    quadrature.  The truth figures follow when a truth is given.

All positions are pixels, ``x`` = column, ``y`` = row, (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from starlog.compensation.series import as_series, parse_choice
from starlog.errors import InvalidInputError, InvalidParameterError

__all__ = [
    "CALIBRATION_FRACTION",
    "MotionMode",
    "ReferenceMode",
    "ScoringProtocol",
    "SelectionReference",
    "calibration_fits",
    "calibration_length",
    "global_mean_reference",
    "protocols_for",
    "reference_mode_for",
    "running_mean_reference",
    "scored_start",
    "selection_reference",
    "split_index",
]


#: Default share of a leak-free series in its unscored calibration segment.
CALIBRATION_FRACTION = 0.5


class ScoringProtocol(enum.StrEnum):
    """How a compensation run is scored; see the module docstring."""

    PAPER = "paper"
    TRUTH = "truth"
    LEAKFREE = "leakfree"
    RELATIVE = "relative"


class MotionMode(enum.StrEnum):
    """What the strategies compensate.

    ``KEEP`` (the paper's method): the star's positions, platform motion included.
    ``SEPARATE``: the star's residual series (positions minus its static position moved by the
    platform motion fitted from the other stars: centroid error alone); the positions are then
    rebuilt as static + fitted motion + compensated residual.
    """

    KEEP = "keep"
    SEPARATE = "separate"


class ReferenceMode(enum.StrEnum):
    """Which reference ``M`` the strategies (and the selection) use.

    ``GLOBAL_MEAN``: mean of the whole sequence (paper, truth protocols).
    ``CALIBRATION``: mean of the first ``calibration_fraction`` of the sequence (leak-free).
    ``RUNNING_MEAN``: ``M[n]`` = mean of the samples before ``n`` (leak-free; ``M[0] = x[0]``).
    """

    GLOBAL_MEAN = "global_mean"
    CALIBRATION = "calibration"
    RUNNING_MEAN = "running_mean"


_LEAKFREE_MODES = (ReferenceMode.CALIBRATION, ReferenceMode.RUNNING_MEAN)


def protocols_for(*, has_truth: bool) -> tuple[ScoringProtocol, ...]:
    """The protocols ``all`` stands for: ``truth`` only when the truth is known (``relative`` is asked for
    by name: it needs the other stars' tracks)."""
    if has_truth:
        return (ScoringProtocol.PAPER, ScoringProtocol.TRUTH, ScoringProtocol.LEAKFREE)
    return (ScoringProtocol.PAPER, ScoringProtocol.LEAKFREE)


def reference_mode_for(
    protocol: ScoringProtocol, leakfree_reference: ReferenceMode | str
) -> ReferenceMode:
    """The reference mode a protocol runs the strategies with.

    ``paper``, ``truth`` and ``relative`` use the global mean; ``leakfree`` uses ``leakfree_reference``
    (``calibration`` or ``running_mean``: the global mean would see the scored samples).
    """
    if protocol is not ScoringProtocol.LEAKFREE:
        return ReferenceMode.GLOBAL_MEAN
    if str(leakfree_reference) == ReferenceMode.GLOBAL_MEAN.value:
        raise InvalidParameterError(
            "leakfree_reference cannot be 'global_mean' (it would see the scored samples)."
        )
    return parse_choice(ReferenceMode, leakfree_reference, name="leakfree_reference",
                        choices=_LEAKFREE_MODES)


def global_mean_reference(xy: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """The paper's truth: the global mean (2,) of the sequence (§2.1), px."""
    p = as_series(xy)
    if p.shape[0] == 0:
        raise InvalidInputError("the mean of an empty series is undefined; pass at least 1 sample.")
    return p.mean(axis=0)


def running_mean_reference(xy: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Leak-free per-sample reference: ``M[n]`` = mean of ``xy[0:n]`` (samples before ``n``).

    ``M[0]`` has no past; it is set to ``xy[0]`` (the only sample whose reference uses itself;
    it lies in the unscored calibration segment under the ``leakfree`` protocol).

    Returns
    -------
    (N, 2) ndarray of float64
    """
    p = as_series(xy)
    n = p.shape[0]
    out = np.empty_like(p)
    if n == 0:
        return out
    csum = np.cumsum(p, axis=0)
    out[0] = p[0]
    out[1:] = csum[:-1] / np.arange(1, n, dtype=np.float64)[:, None]
    return out


def split_index(n: int, *, fraction: float) -> int:
    """Where the leak-free split falls in ``n`` samples: ``floor(fraction * n + 0.5)``.

    Raises :class:`InvalidParameterError` unless ``0 < fraction < 1``.
    """
    f = float(fraction)
    if not math.isfinite(f) or not 0.0 < f < 1.0:
        raise InvalidParameterError(f"calibration_fraction must be in (0, 1); got {fraction!r}.")
    return int(math.floor(f * n + 0.5))


def calibration_fits(n: int, *, fraction: float, minimum: int) -> bool:
    """Whether ``n`` samples split at ``fraction`` (:func:`split_index`) give a calibration segment of at
    least ``minimum`` samples with at least one sample left to score."""
    return minimum <= split_index(n, fraction=fraction) < n


def calibration_length(n: int, *, fraction: float, minimum: int) -> int:
    """Number of calibration samples, :func:`split_index`, checked to be usable.

    Raises :class:`InvalidInputError` unless the calibration segment has at least ``minimum``
    samples and at least one sample is left to score (:func:`calibration_fits`).
    """
    n_cal = split_index(n, fraction=fraction)
    if not calibration_fits(n, fraction=fraction, minimum=minimum):
        raise InvalidInputError(
            f"a series of {n} samples with calibration_fraction={float(fraction)} gives a "
            f"calibration segment of {n_cal} samples; it needs >= {minimum} samples and at least "
            "1 scored sample after it. Use a longer series or another fraction."
        )
    return n_cal


def scored_start(protocol: ScoringProtocol, n: int, *, calibration_fraction: float) -> int:
    """Index of the first scored sample: 0, or the leak-free split (:func:`split_index`)."""
    if protocol is ScoringProtocol.LEAKFREE:
        return split_index(n, fraction=calibration_fraction)
    return 0


@dataclass(frozen=True)
class SelectionReference:
    """The reference ``M`` of a run and the samples the selection may look at.

    ``values`` (N, 2) px; ``point`` (x, y) px when ``M`` is a point, None for the running mean;
    ``n_selection`` the samples the decomposition, scores and rollback see (all, or the
    calibration segment).
    """

    values: npt.NDArray[np.float64]
    point: tuple[float, float] | None
    n_selection: int


def selection_reference(
    p: npt.NDArray[np.float64], mode: ReferenceMode, *, calibration_fraction: float, minimum: int
) -> SelectionReference:
    """``M`` for a validated (N, 2) series ``p`` under ``mode`` (see :class:`ReferenceMode`)."""
    n = p.shape[0]
    if mode is ReferenceMode.GLOBAL_MEAN:
        m = p.mean(axis=0)
        return SelectionReference(np.broadcast_to(m, (n, 2)).copy(), (float(m[0]), float(m[1])), n)
    n_sel = calibration_length(n, fraction=calibration_fraction, minimum=minimum)
    if mode is ReferenceMode.CALIBRATION:
        m = p[:n_sel].mean(axis=0)
        return SelectionReference(np.broadcast_to(m, (n, 2)).copy(), (float(m[0]), float(m[1])), n_sel)
    return SelectionReference(running_mean_reference(p), None, n_sel)
