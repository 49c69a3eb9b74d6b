"""Evaluation protocols, references and the RMSE of eq. 15 (paper §2.1, §2.5; docs/PAPER.md, "Evaluation protocols").

The paper's "truth" is the global mean of the centroid sequence, and its RMSE (eq. 15) is the
radial scatter about that mean.  Strategies 1, 4 and 5 pull the measurements towards that same
mean, so the paper's figure is partly circular.  Three protocols are offered, and every
:class:`Evaluation` (and every :class:`~starlog.compensate.selection.CompensationResult`) says
which one it used:

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

All positions are pixels, ``x`` = column, ``y`` = row, (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidInputError, InvalidParameterError

if TYPE_CHECKING:  # pragma: no cover
    from starlog.compensate.selection import CompensationResult

__all__ = [
    "FIGURE_DTYPE",
    "AccuracySource",
    "Evaluation",
    "Protocol",
    "ReferenceMode",
    "RmseFigure",
    "calibration_length",
    "evaluate",
    "global_mean_reference",
    "rmse",
    "running_mean_reference",
]


class Protocol(enum.StrEnum):
    """How a compensation run is scored (docs/PAPER.md, "Evaluation protocols"); see the module docstring."""

    PAPER = "paper"
    TRUTH = "truth"
    LEAKFREE = "leakfree"


class ReferenceMode(enum.StrEnum):
    """Which reference ``M`` the strategies (and the selection) use.

    ``GLOBAL_MEAN``: mean of the whole sequence (paper, truth protocols).
    ``CALIBRATION``: mean of the first ``calibration_fraction`` of the sequence (leak-free).
    ``RUNNING_MEAN``: ``M[n]`` = mean of the samples before ``n`` (leak-free; ``M[0] = x[0]``).
    """

    GLOBAL_MEAN = "global_mean"
    CALIBRATION = "calibration"
    RUNNING_MEAN = "running_mean"


class AccuracySource(enum.StrEnum):
    """Where the sub-pixel accuracy ``A`` of eq. 10 comes from.

    ``ZERO``: ``A = 0`` (the paper: no sub-pixel interpolation).  ``SIGMA``: ``A`` = the
    centroid's own uncertainty ``sigma`` in pixels (for sub-pixel centroid methods).
    """

    ZERO = "zero"
    SIGMA = "sigma"


# ----------------------------------------------------------------------------------------------
# validation helpers shared by the compensate subpackage (private)


def _as_series(xy: npt.ArrayLike, *, name: str = "xy") -> npt.NDArray[np.float64]:
    """Validated float64 copy of an (N, 2) position series."""
    try:
        a = np.asarray(xy, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise InvalidInputError(
            f"{name} must be a numeric array of shape (N, 2) (x = column, y = row, px): {err}"
        ) from err
    if a.ndim == 1 and a.size == 0:
        a = a.reshape(0, 2)
    if a.ndim != 2 or a.shape[1] != 2:
        raise InvalidInputError(
            f"{name} must have shape (N, 2) (x = column, y = row, px); got shape {a.shape}."
        )
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        rows = np.flatnonzero(bad)[:5].tolist()
        raise InvalidInputError(
            f"{name} contains NaN or infinite values (first rows {rows}); "
            "drop or interpolate those samples before compensation."
        )
    return np.array(a, dtype=np.float64, copy=True)


def _as_samples(
    values: npt.ArrayLike, n: int, *, name: str, nonnegative: bool = False
) -> npt.NDArray[np.float64]:
    """Validated float64 copy of a per-sample (N,) array."""
    try:
        a = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise InvalidInputError(f"{name} must be a numeric array of shape ({n},): {err}") from err
    if a.shape != (n,):
        raise InvalidInputError(f"{name} must have shape ({n},) to match xy; got {a.shape}.")
    if not np.isfinite(a).all():
        raise InvalidInputError(f"{name} contains NaN or infinite values.")
    if nonnegative and (a < 0).any():
        raise InvalidInputError(f"{name} must be >= 0; got a minimum of {a.min()!r}.")
    return np.array(a, dtype=np.float64, copy=True)


def _as_reference(
    reference: npt.ArrayLike, n: int, *, name: str = "reference"
) -> npt.NDArray[np.float64]:
    """A point (2,) or per-sample (N, 2) reference, returned as a float64 (N, 2) array."""
    try:
        r = np.asarray(reference, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise InvalidInputError(f"{name} must be numeric, shape (2,) or ({n}, 2): {err}") from err
    if r.shape == (2,):
        out = np.broadcast_to(r, (n, 2)).copy()
    elif r.shape == (n, 2):
        out = r.copy()
    else:
        raise InvalidInputError(
            f"{name} must be a point of shape (2,) or a per-sample array of shape ({n}, 2); "
            f"got shape {r.shape}."
        )
    if not np.isfinite(out).all():
        raise InvalidInputError(f"{name} contains NaN or infinite values.")
    return out


def _check_rate(fs: float, *, name: str = "fs") -> float:
    try:
        value = float(fs)
    except (TypeError, ValueError) as err:
        raise InvalidParameterError(f"{name} must be a number in Hz; got {fs!r}.") from err
    if not math.isfinite(value) or value <= 0:
        raise InvalidParameterError(f"{name} must be a finite rate > 0 Hz; got {fs!r}.")
    return value


def _radial_rms(residual: npt.NDArray[np.float64]) -> float:
    """``sqrt(mean(dx**2 + dy**2))`` of an (N, 2) residual (0.0 for N = 0)."""
    if residual.shape[0] == 0:
        return 0.0
    return float(np.sqrt(np.mean(np.sum(residual * residual, axis=1))))


# ----------------------------------------------------------------------------------------------
# RMSE and references


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
    p = _as_series(xy)
    if p.shape[0] == 0:
        raise InvalidInputError("the RMSE of an empty series is undefined; pass at least 1 sample.")
    r = _as_reference(reference, p.shape[0])
    return _radial_rms(p - r)


def global_mean_reference(xy: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """The paper's truth: the global mean (2,) of the sequence (§2.1), px."""
    p = _as_series(xy)
    if p.shape[0] == 0:
        raise InvalidInputError("the mean of an empty series is undefined; pass at least 1 sample.")
    return p.mean(axis=0)


def running_mean_reference(xy: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Leak-free per-sample reference: ``M[n]`` = mean of ``xy[0:n]`` (samples before ``n``).

    ``M[0]`` has no past; it is set to ``xy[0]`` (document: the only sample whose reference
    uses itself; it lies in the unscored calibration segment under the ``leakfree`` protocol).

    Returns
    -------
    (N, 2) ndarray of float64
    """
    p = _as_series(xy)
    n = p.shape[0]
    out = np.empty_like(p)
    if n == 0:
        return out
    csum = np.cumsum(p, axis=0)
    out[0] = p[0]
    out[1:] = csum[:-1] / np.arange(1, n, dtype=np.float64)[:, None]
    return out


def calibration_length(n: int, *, fraction: float, minimum: int) -> int:
    """Number of calibration samples: ``floor(fraction * n + 0.5)``.

    Raises :class:`InvalidParameterError` unless ``0 < fraction < 1``, and
    :class:`InvalidInputError` unless the calibration segment has at least ``minimum`` samples
    and at least one sample is left to score.
    """
    f = float(fraction)
    if not math.isfinite(f) or not 0.0 < f < 1.0:
        raise InvalidParameterError(f"calibration_fraction must be in (0, 1); got {fraction!r}.")
    n_cal = int(math.floor(f * n + 0.5))
    if n_cal < minimum or n_cal >= n:
        raise InvalidInputError(
            f"a series of {n} samples with calibration_fraction={f} gives a calibration segment "
            f"of {n_cal} samples; it needs >= {minimum} samples and at least 1 scored sample "
            "after it. Use a longer series or another fraction."
        )
    return n_cal


# ----------------------------------------------------------------------------------------------
# evaluation

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
    ``heldout_mean`` (leak-free: mean of the raw held-out samples).
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


@dataclass(frozen=True)
class Evaluation:
    """Before/after RMSE of one compensation run under one protocol.

    Attributes
    ----------
    protocol : Protocol
        The protocol used.
    figures : tuple of RmseFigure
        Every figure scored under the protocol; the first is the primary one
        (paper: ``global_mean``; truth: ``truth_fixed`` if given else ``truth_series``;
        leakfree: ``heldout_mean``).
    scored_start : int
        Index of the first scored sample (0, or the calibration length under ``leakfree``).
    n_scored : int
        Number of scored samples.
    result : CompensationResult
        The compensation run (scores, decisions, compensated series).
    """

    protocol: Protocol
    figures: tuple[RmseFigure, ...]
    scored_start: int
    n_scored: int
    result: CompensationResult

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
        """JSON-ready dict: ``protocol``, ``scored_start``, ``n_scored``, ``figures`` (list of
        :data:`FIGURE_DTYPE` dicts) and ``compensation`` (:meth:`CompensationResult.to_dict`)."""
        return {
            "protocol": str(self.protocol),
            "scored_start": self.scored_start,
            "n_scored": self.n_scored,
            "figures": [f.to_dict() for f in self.figures],
            "compensation": self.result.to_dict(),
        }


def _figure(name: str, before: npt.NDArray[np.float64], after: npt.NDArray[np.float64],
            ref: npt.NDArray[np.float64]) -> RmseFigure:
    b = _radial_rms(before - ref)
    a = _radial_rms(after - ref)
    eff = (b - a) / b if b > 0 else 0.0
    return RmseFigure(reference=name, rmse_before=b, rmse_after=a, effective=float(eff),
                      n_scored=int(before.shape[0]))


def evaluate(
    xy: npt.ArrayLike,
    *,
    fs: float,
    protocol: Protocol | str,
    truth_fixed: npt.ArrayLike | None = None,
    truth_series: npt.ArrayLike | None = None,
    flux: npt.ArrayLike | None = None,
    sigma: npt.ArrayLike | None = None,
    accuracy_source: AccuracySource | str = AccuracySource.ZERO,
    leakfree_reference: ReferenceMode | str = ReferenceMode.CALIBRATION,
    calibration_fraction: float = 0.5,
    top_k: int = 3,
    rollback_threshold: float = 0.01,
) -> Evaluation:
    """Compensate a decimated centroid series and score it under one protocol.

    Parameters
    ----------
    xy : (N, 2) array_like
        Decimated centroid positions, px (x = column, y = row).
    fs : float
        Sampling rate of ``xy`` after decimation, Hz.
    protocol : Protocol or str
        ``paper``, ``truth`` or ``leakfree`` (see the module docstring).
    truth_fixed : (2,) array_like, optional
        The star's fixed true position, px.  Needed (or ``truth_series``) for ``truth``;
        scored on the held-out part under ``leakfree`` when given; ignored under ``paper``.
    truth_series : (N, 2) array_like, optional
        The jittered instantaneous true positions at the same samples, px.
    flux, sigma : (N,) array_like, optional
        Per-sample intensity and centroid uncertainty (px), passed to
        :func:`~starlog.compensate.selection.compensate`.
    accuracy_source : AccuracySource or str
        ``A`` of eq. 10: ``zero`` (paper) or ``sigma``.
    leakfree_reference : ReferenceMode or str
        ``calibration`` (default) or ``running_mean``; only for ``leakfree``.
    calibration_fraction : float
        Fraction of the samples in the unscored calibration segment (``leakfree`` only).
    top_k, rollback_threshold
        Passed to :func:`~starlog.compensate.selection.compensate`.

    Returns
    -------
    Evaluation
    """
    from starlog.compensate.selection import compensate  # local: selection imports this module

    try:
        proto = Protocol(protocol)
    except ValueError as err:
        raise InvalidParameterError(
            f"protocol must be one of {[p.value for p in Protocol]}; got {protocol!r}."
        ) from err
    p = _as_series(xy)
    n = p.shape[0]
    tf = None
    if truth_fixed is not None:
        if np.shape(truth_fixed) != (2,):
            raise InvalidInputError(
                f"truth_fixed must have shape (2,); got {np.shape(truth_fixed)}."
            )
        tf = _as_reference(truth_fixed, 1, name="truth_fixed")[0]
    ts = None
    if truth_series is not None:
        ts_arr = np.asarray(truth_series, dtype=np.float64)
        if ts_arr.shape != (n, 2):
            raise InvalidInputError(
                f"truth_series must have shape ({n}, 2) to match xy; got {ts_arr.shape}."
            )
        ts = _as_reference(ts_arr, n, name="truth_series")

    if proto is Protocol.LEAKFREE:
        try:
            mode = ReferenceMode(leakfree_reference)
        except ValueError as err:
            raise InvalidParameterError(
                f"leakfree_reference must be 'calibration' or 'running_mean'; "
                f"got {leakfree_reference!r}."
            ) from err
        if mode is ReferenceMode.GLOBAL_MEAN:
            raise InvalidParameterError(
                "leakfree_reference cannot be 'global_mean' (it would see the scored samples)."
            )
    else:
        mode = ReferenceMode.GLOBAL_MEAN
        if proto is Protocol.TRUTH and tf is None and ts is None:
            raise InvalidParameterError(
                "the 'truth' protocol needs truth_fixed and/or truth_series (simulated logs)."
            )

    result = compensate(
        p,
        fs=fs,
        flux=flux,
        sigma=sigma,
        reference_mode=mode,
        calibration_fraction=calibration_fraction,
        accuracy_source=accuracy_source,
        top_k=top_k,
        rollback_threshold=rollback_threshold,
        protocol=proto,
    )
    after = result.compensated
    figures: list[RmseFigure] = []
    if proto is Protocol.PAPER:
        start = 0
        m = np.broadcast_to(p.mean(axis=0), p.shape)
        figures.append(_figure("global_mean", p, after, m))
    else:
        start = 0 if proto is Protocol.TRUTH else result.n_selection
        b, a = p[start:], after[start:]
        if proto is Protocol.LEAKFREE:
            figures.append(_figure("heldout_mean", b, a, np.broadcast_to(b.mean(axis=0), b.shape)))
        if tf is not None:
            figures.append(_figure("truth_fixed", b, a, np.broadcast_to(tf, b.shape)))
        if ts is not None:
            figures.append(_figure("truth_series", b, a, ts[start:]))
    return Evaluation(
        protocol=proto,
        figures=tuple(figures),
        scored_start=start,
        n_scored=n - start,
        result=result,
    )
