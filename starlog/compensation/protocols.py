"""Scoring a series under a protocol: the RMSE figures of eq. 15 and eq. 13, and :func:`evaluate`.

:func:`protocol_figures` is the one definition of what each protocol reports (the protocols
themselves are described in :mod:`starlog.compensation.references`): the ``compensate`` stage
reaches it through :func:`evaluate`, and the experiment also calls it directly for series too
short to compensate.

All positions are pixels, ``x`` = column, ``y`` = row, (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.compensation.series import as_reference, as_series, improvement, parse_choice, radial_rms
from starlog.compensation.references import (
    CALIBRATION_FRACTION,
    MotionMode,
    ReferenceMode,
    ScoringProtocol,
    reference_mode_for,
    scored_start,
)
from starlog.compensation.selection import CompensationResult, compensate
from starlog.compensation.strategies import AccuracySource
from starlog.errors import InvalidInputError, InvalidParameterError

__all__ = [
    "FIGURE_DTYPE",
    "Evaluation",
    "RmseFigure",
    "evaluate",
    "protocol_figures",
    "rmse",
]


def rmse(xy: npt.ArrayLike, reference: npt.ArrayLike) -> float:
    """Radial RMSE about a reference, eq. 15.

    ``sqrt(mean((x - xr)**2 + (y - yr)**2))`` in pixels.

    Parameters
    ----------
    xy : (N, 2) array_like
        Positions, px (x = column, y = row).  N >= 1.
    reference : (2,) or (N, 2) array_like
        A fixed point (eq. 15 uses the sequence mean) or per-sample reference positions.

    Returns
    -------
    float
        RMSE in pixels.
    """
    p = as_series(xy)
    if p.shape[0] == 0:
        raise InvalidInputError("the RMSE of an empty series is undefined; pass at least 1 sample.")
    r = as_reference(reference, p.shape[0])
    return radial_rms(p - r)


FIGURE_DTYPE = np.dtype(
    [
        ("reference", "U16"),
        ("rmse_before", "f8"),
        ("rmse_after", "f8"),
        ("effective", "f8"),
        ("n_scored", "i8"),
    ]
)
"""One scored RMSE figure (row of :meth:`Evaluation.figures_table`).

Fields
------
reference : str
    What the RMSE is measured about: ``global_mean`` (paper), ``truth_fixed``, ``truth_series``,
    ``heldout_mean`` (leak-free: mean of the raw held-out samples), ``relative`` (static position
    plus the motion fitted from the other stars, its own variance removed).
rmse_before : float64, px
    Eq. 15 of the uncompensated scored samples about the reference.
rmse_after : float64, px
    Eq. 15 of the compensated scored samples about the same reference.
effective : float64, 1
    Eq. 13, ``(before - after) / before``; 0.0 when ``before`` is 0.
n_scored : int64
    Number of samples scored.
"""


@dataclass(frozen=True)
class RmseFigure:
    """One RMSE figure before/after compensation; fields as in :data:`FIGURE_DTYPE`."""

    reference: str
    rmse_before: float
    rmse_after: float
    effective: float
    n_scored: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict with the fields of :data:`FIGURE_DTYPE`."""
        return {
            "reference": self.reference,
            "rmse_before": self.rmse_before,
            "rmse_after": self.rmse_after,
            "effective": self.effective,
            "n_scored": self.n_scored,
        }


def _figure(name: str, before: npt.NDArray[np.float64], after: npt.NDArray[np.float64],
            ref: npt.NDArray[np.float64]) -> RmseFigure:
    b = radial_rms(before - ref)
    a = radial_rms(after - ref)
    return RmseFigure(reference=name, rmse_before=b, rmse_after=a, effective=float(improvement(b, a)),
                      n_scored=int(before.shape[0]))


def _relative_figure(before: npt.NDArray[np.float64], after: npt.NDArray[np.float64],
                     reference: npt.NDArray[np.float64], variance: npt.NDArray[np.float64] | None, *,
                     reference_weight: float) -> RmseFigure:
    """Eq. 15 about the relative reference, over the samples that have one.

    With ``e`` the reference's error (variance ``V``, predicted by its fit) and ``x`` a series,
    ``x - truth = (x - reference) + e``.  A series independent of the other stars (the star's own
    track, or ``keep``'s output) has ``E|x - truth|² = E|x - reference|² - V``; one that carries
    ``f e`` because it was rebuilt on the reference (``separate``, ``f = reference_weight``) has
    ``E|x - truth|² ≈ E|x - reference|² + (2f - 1) V``.
    """
    ok = np.isfinite(reference).all(axis=1)
    var = float(np.mean(variance[ok])) if variance is not None and ok.any() else 0.0

    def score(xy: npt.NDArray[np.float64], extra: float) -> float:
        r = radial_rms(xy[ok] - reference[ok])
        return float(np.sqrt(max(r * r + extra, 0.0)))

    b, a = score(before, -var), score(after, (2.0 * reference_weight - 1.0) * var)
    return RmseFigure(reference="relative", rmse_before=b, rmse_after=a, effective=float(improvement(b, a)),
                      n_scored=int(ok.sum()))


def protocol_figures(
    before: npt.NDArray[np.float64],
    after: npt.NDArray[np.float64] | None = None,
    *,
    protocol: ScoringProtocol,
    start: int = 0,
    truth_fixed: npt.NDArray[np.float64] | None = None,
    truth_series: npt.NDArray[np.float64] | None = None,
    relative: npt.NDArray[np.float64] | None = None,
    relative_variance: npt.NDArray[np.float64] | None = None,
    reference_weight: float = 0.0,
) -> tuple[RmseFigure, ...]:
    """The RMSE figures (eq. 15, eq. 13) a protocol reports for one series, primary first.

    ``paper``: ``global_mean`` over every sample.  ``truth``: ``truth_fixed`` and/or
    ``truth_series`` over every sample.  ``leakfree``: ``heldout_mean`` (the mean of the raw
    samples from ``start`` on), then the truth figures, all over the samples from ``start`` on.
    ``relative``: ``relative`` about the per-sample reference ``relative`` (NaN rows: no
    reference, not scored; ``relative_variance`` its predicted radial variance, px²;
    ``reference_weight`` the share of the reference's error ``after`` carries: 0, or the motion
    factor under ``separate``),
    then the truth figures over every sample.
    ``after=None`` scores an uncompensated series (``rmse_after = rmse_before``, effective 0).
    Inputs are validated (N, 2) arrays in px; ``truth_series`` is aligned with ``before``.
    """
    if after is None:
        after = before
    if protocol is ScoringProtocol.RELATIVE:
        if relative is None:
            raise InvalidParameterError("the 'relative' protocol needs the reference from the other stars.")
        return (_relative_figure(before, after, relative, relative_variance, reference_weight=reference_weight),
                *protocol_figures(before, after, protocol=ScoringProtocol.TRUTH, truth_fixed=truth_fixed,
                                  truth_series=truth_series))
    if protocol is ScoringProtocol.PAPER:
        return (_figure("global_mean", before, after, np.broadcast_to(before.mean(axis=0), before.shape)),)
    start = start if protocol is ScoringProtocol.LEAKFREE else 0
    b, a = before[start:], after[start:]
    figures: list[RmseFigure] = []
    if protocol is ScoringProtocol.LEAKFREE:
        held_mean = b.mean(axis=0) if b.shape[0] else np.zeros(2)
        figures.append(_figure("heldout_mean", b, a, np.broadcast_to(held_mean, b.shape)))
    if truth_fixed is not None:
        figures.append(_figure("truth_fixed", b, a, np.broadcast_to(truth_fixed, b.shape)))
    if truth_series is not None:
        figures.append(_figure("truth_series", b, a, truth_series[start:]))
    return tuple(figures)


@dataclass(frozen=True)
class Evaluation:
    """Before/after RMSE of one compensation run under one protocol.

    Attributes
    ----------
    protocol : ScoringProtocol
        The protocol used.
    figures : tuple of RmseFigure
        Every figure scored under the protocol (:func:`protocol_figures`); the first is the
        primary one (paper: ``global_mean``; truth: ``truth_fixed`` if given else
        ``truth_series``; leakfree: ``heldout_mean``).
    scored_start : int
        Index of the first scored sample (0, or the calibration length under ``leakfree``).
    n_scored : int
        Number of scored samples.
    result : CompensationResult
        The compensation run (scores, decisions, compensated series; under ``separate`` the
        compensated *residual* series).
    motion : MotionMode
        ``keep`` or ``separate`` (what the strategies compensated).
    positions_after : (N, 2) ndarray or None
        Under ``separate``, the rebuilt positions (static + fitted motion + compensated residual).
    motion_factor : float
        Under ``separate``, the Wiener factor the fitted motion was added back with (0: the
        fitted motion is all noise, 1: all signal).
    """

    protocol: ScoringProtocol
    figures: tuple[RmseFigure, ...]
    scored_start: int
    n_scored: int
    result: CompensationResult
    motion: MotionMode = MotionMode.KEEP
    positions_after: npt.NDArray[np.float64] | None = None
    motion_factor: float = 0.0

    @property
    def compensated(self) -> npt.NDArray[np.float64]:
        """The positions after compensation, px (rebuilt with the platform motion under ``separate``)."""
        return self.result.compensated if self.positions_after is None else self.positions_after

    @property
    def rmse_before(self) -> float:
        """Primary figure's RMSE before compensation, px."""
        return self.figures[0].rmse_before

    @property
    def rmse_after(self) -> float:
        """Primary figure's RMSE after compensation, px."""
        return self.figures[0].rmse_after

    @property
    def effective(self) -> float:
        """Primary figure's eq. 13 improvement (fraction)."""
        return self.figures[0].effective

    def figure(self, reference: str) -> RmseFigure:
        """The figure scored about ``reference`` (KeyError when not scored)."""
        for fig in self.figures:
            if fig.reference == reference:
                return fig
        raise KeyError(reference)

    def figures_table(self) -> npt.NDArray[np.void]:
        """The figures as a structured array of :data:`FIGURE_DTYPE`."""
        rows = [
            (f.reference, f.rmse_before, f.rmse_after, f.effective, f.n_scored)
            for f in self.figures
        ]
        return np.array(rows, dtype=FIGURE_DTYPE)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict: ``protocol``, ``motion``, ``scored_start``, ``n_scored``, ``figures`` (list of
        :data:`FIGURE_DTYPE` dicts) and ``compensation`` (:meth:`CompensationResult.to_dict`)."""
        return {
            "protocol": str(self.protocol),
            "motion": str(self.motion),
            **({"motion_factor": self.motion_factor} if self.motion is MotionMode.SEPARATE else {}),
            "scored_start": self.scored_start,
            "n_scored": self.n_scored,
            "figures": [f.to_dict() for f in self.figures],
            "compensation": self.result.to_dict(),
        }


def _checked_truth(
    truth_fixed: npt.ArrayLike | None, truth_series: npt.ArrayLike | None, n: int
) -> tuple[npt.NDArray[np.float64] | None, npt.NDArray[np.float64] | None]:
    """The truth as a (2,) point and an (n, 2) series (each None when not given)."""
    tf = None
    if truth_fixed is not None:
        if np.shape(truth_fixed) != (2,):
            raise InvalidInputError(
                f"truth_fixed must have shape (2,); got {np.shape(truth_fixed)}."
            )
        tf = as_reference(truth_fixed, 1, name="truth_fixed")[0]
    ts = None
    if truth_series is not None:
        ts_arr = np.asarray(truth_series, dtype=np.float64)
        if ts_arr.shape != (n, 2):
            raise InvalidInputError(
                f"truth_series must have shape ({n}, 2) to match xy; got {ts_arr.shape}."
            )
        ts = as_reference(ts_arr, n, name="truth_series")
    return tf, ts


def evaluate(
    xy: npt.ArrayLike,
    *,
    rate_hz: float,
    protocol: ScoringProtocol | str,
    truth_fixed: npt.ArrayLike | None = None,
    truth_series: npt.ArrayLike | None = None,
    flux: npt.ArrayLike | None = None,
    sigma: npt.ArrayLike | None = None,
    accuracy_source: AccuracySource | str = AccuracySource.ZERO,
    leakfree_reference: ReferenceMode | str = ReferenceMode.CALIBRATION,
    calibration_fraction: float = CALIBRATION_FRACTION,
    top_k: int = 3,
    rollback_threshold: float = 0.01,
    motion: MotionMode | str = MotionMode.KEEP,
    static_position: npt.ArrayLike | None = None,
    platform_displacement: npt.ArrayLike | None = None,
    reference_variance: npt.ArrayLike | None = None,
    select_positive: bool = True,
) -> Evaluation:
    """Compensate a decimated centroid series and score it under one protocol.

    Parameters
    ----------
    xy : (N, 2) array_like
        Decimated centroid positions, px (x = column, y = row).
    rate_hz : float
        Sampling rate of ``xy`` after decimation, Hz.
    protocol : ScoringProtocol or str
        ``paper``, ``truth`` or ``leakfree`` (see :mod:`starlog.compensation.references`).
    truth_fixed : (2,) array_like, optional
        The star's fixed true position, px.  Needed (or ``truth_series``) for ``truth``;
        scored on the held-out part under ``leakfree`` when given; ignored under ``paper``.
    truth_series : (N, 2) array_like, optional
        The jittered instantaneous true positions at the same samples, px.
    flux, sigma : (N,) array_like, optional
        Per-sample intensity and centroid uncertainty (px), passed to
        :func:`~starlog.compensation.selection.compensate`.
    accuracy_source : AccuracySource or str
        ``A`` of eq. 10: ``zero`` (paper) or ``sigma``.
    leakfree_reference : ReferenceMode or str
        ``calibration`` (default) or ``running_mean``; only for ``leakfree``.
    calibration_fraction : float
        Fraction of the samples in the unscored calibration segment (``leakfree`` only).
    top_k, rollback_threshold, select_positive
        Passed to :func:`~starlog.compensation.selection.compensate`.
    motion : MotionMode or str
        ``keep`` (paper): compensate the positions.  ``separate``: compensate the residual
        ``xy - platform_displacement`` and add the displacement back, shrunk by its Wiener factor
        (so that the noise of a motion fitted on a still platform is not added).
    static_position : (2,) array_like, optional
        The star's static position, px (``relative`` protocol).
    platform_displacement : (N, 2) array_like, optional
        The star's displacement by the platform motion fitted from the other stars at each
        sample, px; NaN where the other stars did not give a motion (those samples are not scored
        under ``relative``, and the displacement is interpolated in time under ``separate``).
    reference_variance : (N,) array_like, optional
        Predicted radial variance of ``static_position + platform_displacement``, px².

    Returns
    -------
    Evaluation
    """
    proto = parse_choice(ScoringProtocol, protocol, name="protocol")
    mode_motion = parse_choice(MotionMode, motion, name="motion")
    p = as_series(xy)
    n = p.shape[0]
    tf, ts = _checked_truth(truth_fixed, truth_series, n)
    mode = reference_mode_for(proto, leakfree_reference)
    if proto is ScoringProtocol.TRUTH and tf is None and ts is None:
        raise InvalidParameterError(
            "the 'truth' protocol needs truth_fixed and/or truth_series (simulated logs)."
        )
    disp = _checked_displacement(platform_displacement, n)
    needs_motion = proto is ScoringProtocol.RELATIVE or mode_motion is MotionMode.SEPARATE
    if needs_motion and disp is None:
        raise InvalidParameterError(
            "the 'relative' protocol and motion 'separate' need the platform displacement fitted from "
            "the other stars (starlog.platform_motion).")
    relative = var = None
    if proto is ScoringProtocol.RELATIVE:
        assert disp is not None
        relative, var = _relative_reference(static_position, disp, reference_variance, n)
    shift, factor = None, 0.0
    if mode_motion is MotionMode.SEPARATE and disp is not None:
        shift, factor = _wiener(_filled(disp), reference_variance)
    result = compensate(p if shift is None else p - shift, rate_hz=rate_hz, flux=flux, sigma=sigma, reference_mode=mode,
                        calibration_fraction=calibration_fraction, accuracy_source=accuracy_source, top_k=top_k,
                        rollback_threshold=rollback_threshold, select_positive=select_positive, protocol=proto)
    start = scored_start(proto, n, calibration_fraction=calibration_fraction)
    after = result.compensated if shift is None else result.compensated + shift
    figures = protocol_figures(p, after, protocol=proto, start=start, truth_fixed=tf, truth_series=ts,
                               relative=relative, relative_variance=var, reference_weight=factor)
    return Evaluation(protocol=proto, figures=figures, scored_start=start,
                      n_scored=figures[0].n_scored if proto is ScoringProtocol.RELATIVE else n - start,
                      result=result, motion=mode_motion, positions_after=None if shift is None else after,
                      motion_factor=factor)


def _relative_reference(static_position: npt.ArrayLike | None, displacement: npt.NDArray[np.float64],
                        reference_variance: npt.ArrayLike | None,
                        n: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64] | None]:
    """The ``relative`` protocol's reference, the static position moved by the platform at each sample, and its
    predicted radial variance (None when not given)."""
    if static_position is None or np.shape(static_position) != (2,):
        raise InvalidParameterError("the 'relative' protocol needs the star's static position (2,).")
    var = None if reference_variance is None else np.asarray(reference_variance, dtype=np.float64).reshape(n)
    return np.asarray(static_position, dtype=np.float64) + displacement, var


def _checked_displacement(displacement: npt.ArrayLike | None, n: int) -> npt.NDArray[np.float64] | None:
    """An (n, 2) displacement, NaN rows allowed (no motion there), at least one finite row."""
    if displacement is None:
        return None
    d = np.asarray(displacement, dtype=np.float64)
    if d.shape != (n, 2):
        raise InvalidInputError(f"platform_displacement must have shape ({n}, 2) to match xy; got {d.shape}.")
    if not np.isfinite(d).all(axis=1).any():
        raise InvalidInputError("platform_displacement has no finite sample: no frame had a fitted motion.")
    return d


def _wiener(displacement: npt.NDArray[np.float64],
            variance: npt.ArrayLike | None) -> tuple[npt.NDArray[np.float64], float]:
    """The displacement shrunk towards its mean by the scalar Wiener factor ``1 - noise / spread``.

    ``variance`` is the displacement's predicted radial variance (px²) per sample: on a still
    platform the fitted motion is that noise alone and the factor is 0 (``separate`` then adds no
    noise); a motion well above it is kept whole.  Returns the displacement and the factor.
    """
    if variance is None or displacement.shape[0] < 2:
        return displacement, 1.0
    v = np.asarray(variance, dtype=np.float64)
    noise = float(np.mean(v[np.isfinite(v)])) if np.isfinite(v).any() else 0.0
    mean = displacement.mean(axis=0)
    spread = float(np.mean(np.sum((displacement - mean) ** 2, axis=1)))
    factor = float(np.clip(1.0 - noise / spread, 0.0, 1.0)) if spread > 0 else 0.0
    return mean + factor * (displacement - mean), factor


def _filled(displacement: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The displacement with its NaN rows interpolated linearly in sample index (held at the ends)."""
    ok = np.isfinite(displacement).all(axis=1)
    if ok.all():
        return displacement
    k = np.arange(displacement.shape[0])
    return np.stack([np.interp(k, k[ok], displacement[ok, axis]) for axis in (0, 1)], axis=1)
