"""Pixel-phase (S-curve) calibration learnt from a log's own stars, without a catalogue.

A centroider whose model of the star is not the real PSF (an under-sampled PSF with wings, a
pixel response that is not a box) pulls positions towards, or pushes them away from, pixel
centres by an amount that depends on the star's sub-pixel phase ``p = x - round(x)``: the
S-curve ``q = p + b(p)``, the systematic error the paper attributes to the discretisation and
sampling of the star's intensity distribution (its Section 1; Wei et al. 2019).

The true phases of many distinct stars are uniform on [-1/2, 1/2). So the distribution of the
*measured* phases ``q`` alone shows the S-curve, and its cumulative distribution ``F`` undoes
it: ``p = F(q) - 1/2`` (histogram equalisation). For an odd S-curve (a symmetric PSF) the
density of ``q`` is ``1 + 2 sum_k c_k cos(2 pi k q)`` with ``c_k = <cos 2 pi k q>``, hence

    p = q + sum_k c_k / (pi k) sin(2 pi k q).

:func:`estimate_phase_calibration` keeps the first ``harmonics`` terms (one number, the S-curve
amplitude ``-c_1 / pi``, by default: the full empirical mapping needs many hundreds of distinct
stars to beat its own sampling noise, the standard error of ``c_k`` being ``1 / sqrt(2 n)``),
corrects the coefficients for the blur of the measurement noise
(``<cos 2 pi k (q + e)> = c_k exp(-2 pi^2 k^2 sigma^2)``), pools the two axes unless they differ
significantly, and applies an amplitude only when it exceeds three standard errors (then shrunk
by ``1 - se^2 / a^2``, the non-negative garrote's factor; James-Stein's needs three or more
parameters): a centroider without S-curve, whose estimate is ~0, stays unchanged.

Each distinct star counts once: a static field shows the same phases in every frame
(:func:`distinct_samples`). :meth:`PhaseCalibration.apply` corrects positions.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.centroiding.table import CentroidFlag
from starlog.errors import InvalidInputError

__all__ = [
    "PhaseCalibration",
    "distinct_samples",
    "estimate_phase_calibration",
    "load_phase_calibrations",
    "phase_sample_mask",
    "phase_samples",
]

F64 = npt.NDArray[np.float64]

MIN_STARS = 20
"""Fewest distinct stars a calibration is estimated from (below, the amplitude's standard error,
about ``1 / (pi sqrt(2 n))`` px, exceeds 0.05 px: larger than the S-curves worth removing)."""
MIN_SNR = 20.0
"""Stars of lower flux SNR are not used: their noise blurs the phases (a centroid error of about
``psf_sigma / 10`` px and more)."""
SIGNIFICANCE = 3.0
"""An amplitude is applied only above this many standard errors (a centroider without S-curve stays
unchanged in all but ~0.3 % of logs); the two axes get separate amplitudes only when they differ by
as much."""
DISTINCT_CELL = 0.5
"""Positions (px) closer than about this, in any frames, are one star at one phase."""
DUPLICATE_SIGMAS = 5.0
DUPLICATE_MIN_PX = 0.1
"""Positions closer than ``DUPLICATE_SIGMAS`` standard errors (at least ``DUPLICATE_MIN_PX``) are one star
seen again, at one phase, however its noise scattered it (:func:`distinct_samples`)."""
_EXCLUDED = int(CentroidFlag.SATURATED | CentroidFlag.BORDER | CentroidFlag.FIT_FAILED)


def _phase(v: F64) -> F64:
    """Sub-pixel phase in [-1/2, 1/2] of pixel-centre-origin coordinates."""
    return v - np.rint(v)


@dataclass(frozen=True)
class PhaseCalibration:
    """A centroider's S-curve per axis: ``bias(q) = sum_k amplitude[k-1] sin(2 pi k q)`` px.

    ``amplitude_x/y``: the amplitudes applied per harmonic (negative: positions pulled towards
    pixel centres); ``estimate_x/y`` and ``error_x/y``: each axis's own estimate and its standard
    error; ``n_stars``: distinct stars used; ``separate_axes``: per harmonic, whether the axes
    differ (else one amplitude, from both axes' phases, is applied to both).
    """

    method: str
    amplitude_x: tuple[float, ...]
    amplitude_y: tuple[float, ...]
    estimate_x: tuple[float, ...]
    estimate_y: tuple[float, ...]
    error_x: tuple[float, ...]
    error_y: tuple[float, ...]
    n_stars: int
    separate_axes: tuple[bool, ...] = ()

    @property
    def active(self) -> bool:
        """Whether any amplitude is applied (a calibration shrunk to zero changes nothing)."""
        return any(a != 0.0 for a in self.amplitude_x + self.amplitude_y)

    def bias(self, q: F64, axis: str) -> F64:
        """The S-curve at measured phases ``q`` of axis ``"x"`` or ``"y"``, px."""
        if axis not in ("x", "y"):
            raise ValueError(f"axis must be 'x' or 'y', got {axis!r}")
        amps = self.amplitude_x if axis == "x" else self.amplitude_y
        out = np.zeros_like(q, dtype=np.float64)
        for k, a in enumerate(amps, 1):
            out += a * np.sin(2.0 * np.pi * k * q)
        return out

    def apply(self, x: npt.ArrayLike, y: npt.ArrayLike) -> tuple[F64, F64]:
        """Positions with the S-curve removed (NaN stays NaN)."""
        xa, ya = np.asarray(x, np.float64), np.asarray(y, np.float64)
        return xa - self.bias(_phase(xa), "x"), ya - self.bias(_phase(ya), "y")

    def to_dict(self) -> dict[str, Any]:
        return {"method": self.method, "n_stars": self.n_stars, "separate_axes": list(self.separate_axes),
                "amplitude_px": {"x": list(self.amplitude_x), "y": list(self.amplitude_y)},
                "estimate_px": {"x": list(self.estimate_x), "y": list(self.estimate_y)},
                "error_px": {"x": list(self.error_x), "y": list(self.error_y)}}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> PhaseCalibration:
        """The calibration of a :meth:`to_dict` record; :class:`InvalidInputError` names what is wrong."""
        if not isinstance(d, Mapping):
            raise InvalidInputError(f"not a phase calibration record (an object with 'method' and 'amplitude_px'): "
                                    f"{d!r:.200}")
        try:
            amp = d["amplitude_px"]
            est, err = d.get("estimate_px", amp), d.get("error_px", {"x": [0.0] * len(amp["x"]),
                                                                       "y": [0.0] * len(amp["y"])})

            def floats(v: Iterable[Any]) -> tuple[float, ...]:
                return tuple(float(a) for a in v)

            cal = cls(str(d["method"]), floats(amp["x"]), floats(amp["y"]), floats(est["x"]), floats(est["y"]),
                      floats(err["x"]), floats(err["y"]), int(d.get("n_stars", 0)),
                      tuple(bool(v) for v in d.get("separate_axes", ())))
        except (KeyError, TypeError, ValueError) as e:
            raise InvalidInputError(f"not a phase calibration record ({e!r}): {dict(d)!r:.200}") from None
        values = cal.amplitude_x + cal.amplitude_y + cal.estimate_x + cal.estimate_y + cal.error_x + cal.error_y
        if len({len(v) for v in (cal.amplitude_x, cal.amplitude_y, cal.estimate_x, cal.estimate_y, cal.error_x,
                                 cal.error_y)}) != 1 or not cal.amplitude_x or not np.all(np.isfinite(values)):
            raise InvalidInputError(f"phase calibration record of {cal.method}: amplitude_px, estimate_px and "
                                    f"error_px need one finite number per harmonic for each of x and y: "
                                    f"{dict(d)!r:.200}")
        for axis, amps in (("x", cal.amplitude_x), ("y", cal.amplitude_y)):
            _check_order_kept(amps, f"the phase calibration of {cal.method}, axis {axis}")
        return cal


def _check_order_kept(amplitudes: tuple[float, ...], what: str) -> None:
    """Refuse an S-curve whose correction ``p = q - bias(q)`` would not keep positions in order.

    ``q - sum_k a_k sin(2 pi k q)`` is increasing when ``sum_k 2 pi k |a_k| < 1`` (one harmonic:
    ``|a| < 1 / (2 pi)`` ≈ 0.159 px); beyond, the correction folds positions around pixel centres.
    """
    slope = sum(2.0 * np.pi * k * abs(a) for k, a in enumerate(amplitudes, 1))
    if slope >= 1.0:
        raise InvalidInputError(
            f"{what}: S-curve amplitudes {[round(a, 4) for a in amplitudes]} px would fold positions around pixel "
            f"centres (the correction keeps positions in order only while sum 2 pi k |a_k| < 1, i.e. |a| < 0.159 px "
            f"for one harmonic); positions quantised to the pixel look like this.")


def phase_sample_mask(centroids: npt.NDArray[np.void], *, min_snr: float = MIN_SNR) -> npt.NDArray[np.bool_]:
    """The rows of one frame's centroid table a calibration may learn from.

    The choice must not depend on the phase (else the phases kept are not uniform): stars with
    ``snr >= min_snr`` (the flux's SNR varies little with phase, unlike ``sigma``), finite, not
    cut by the border nor failed, and fainter than the frame's faintest saturated star (whether a
    star near the saturation level saturates depends on its phase). Blended or masked stars stay.
    """
    c = centroids
    keep = ((c["flags"] & _EXCLUDED) == 0) & np.isfinite(c["x"]) & np.isfinite(c["y"]) & (c["snr"] >= min_snr)
    saturated = (c["flags"] & int(CentroidFlag.SATURATED)) != 0
    if saturated.any():
        keep &= c["flux"] < np.min(c["flux"][saturated])
    return keep


def phase_samples(centroids: npt.NDArray[np.void], *, min_snr: float = MIN_SNR) -> tuple[F64, F64, F64]:
    """(x, y, sigma) of the rows :func:`phase_sample_mask` keeps."""
    c = centroids
    keep = phase_sample_mask(c, min_snr=min_snr)
    return (np.asarray(c["x"][keep], np.float64), np.asarray(c["y"][keep], np.float64),
            np.asarray(c["sigma"][keep], np.float64))


def distinct_samples(x: F64, y: F64, sigma: F64, *, cell: float = DISTINCT_CELL) -> tuple[F64, F64, F64]:
    """One sample per star position, in frame order (samples pooled over frames): the first in each
    ``cell`` x ``cell`` px square, less those within the noise of an earlier kept one (closer than
    :data:`DUPLICATE_SIGMAS` times their ``sigma``, at least :data:`DUPLICATE_MIN_PX`, at most ``cell``).

    A static star seen in every frame counts once, even when its noise scatters it over a square's
    edge (counted per square, such stars, at phases 0 and 1/2, would count two to four times:
    the amplitude overestimated and its standard error underestimated). A star drifting over the
    sensor counts once per square it crosses (distinct phases). The first, not the most precise: a
    centroid's precision depends on its phase.
    """
    if x.size == 0:
        return x, y, sigma
    keys = np.column_stack([np.floor(x / cell), np.floor(y / cell)]).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    first = np.sort(first)
    radius = np.clip(DUPLICATE_SIGMAS * sigma[first], DUPLICATE_MIN_PX, cell)
    pick = first[_not_near_earlier(x[first], y[first], radius, cell)]
    return x[pick], y[pick], sigma[pick]


def _not_near_earlier(x: F64, y: F64, radius: F64, cell: float) -> npt.NDArray[np.intp]:
    """Indices, in order, of the samples not within their ``radius`` (<= ``cell``) of an earlier kept one."""
    kept: dict[tuple[int, int], list[tuple[float, float]]] = {}
    out = []
    for i, (xi, yi, ri) in enumerate(zip(x.tolist(), y.tolist(), radius.tolist())):
        gx, gy = int(np.floor(xi / cell)), int(np.floor(yi / cell))
        near = (kept.get((gx + dx, gy + dy), []) for dx in (-1, 0, 1) for dy in (-1, 0, 1))
        if any((kx - xi) ** 2 + (ky - yi) ** 2 < ri * ri for square in near for kx, ky in square):
            continue
        kept.setdefault((gx, gy), []).append((xi, yi))
        out.append(i)
    return np.asarray(out, dtype=np.intp)


def _harmonic(q: F64, sigma: F64, k: int) -> tuple[float, float]:
    """Amplitude of harmonic ``k`` of the S-curve, ``-c_k / (pi k)``, and its standard error, from measured
    phases ``q`` of uncertainty ``sigma`` (``c_k`` corrected for the noise's blur)."""
    cos_k = np.cos(2.0 * np.pi * k * q)
    blur = float(np.mean(np.exp(-2.0 * np.pi**2 * k**2 * sigma**2)))
    c = float(np.mean(cos_k)) / blur
    se = float(np.std(cos_k, ddof=1)) / np.sqrt(q.size) / blur
    return float(-c / (np.pi * k)), float(se / (np.pi * k))


def _applied(amplitude: float, error: float) -> float:
    """The amplitude applied: none unless it exceeds :data:`SIGNIFICANCE` standard errors, then shrunk by
    ``1 - se^2 / a^2`` (the non-negative garrote; 0 +- 0 is none, not a division by zero)."""
    if not abs(amplitude) > SIGNIFICANCE * error:
        return 0.0
    return float(amplitude * (1.0 - (error / amplitude) ** 2))


def _axes_terms(qx: F64, qy: F64, sigma: F64, harmonics: int) -> dict[str, list[Any]]:
    """Per harmonic: each axis's estimate and error, and the amplitudes applied — one for both axes
    (their pooled phases) unless the two axes differ by more than :data:`SIGNIFICANCE` standard errors."""
    out: dict[str, list[Any]] = {key: [] for key in ("ax", "ay", "ex", "ey", "sx", "sy", "separate")}
    both, sigma2 = np.concatenate([qx, qy]), np.concatenate([sigma, sigma])
    for k in range(1, harmonics + 1):
        (ex, sx), (ey, sy), (eb, sb) = _harmonic(qx, sigma, k), _harmonic(qy, sigma, k), _harmonic(both, sigma2, k)
        separate = bool(abs(ex - ey) > SIGNIFICANCE * float(np.hypot(sx, sy)))
        out["ax"].append(_applied(ex, sx) if separate else _applied(eb, sb))
        out["ay"].append(_applied(ey, sy) if separate else _applied(eb, sb))
        for key, value in (("ex", ex), ("ey", ey), ("sx", sx), ("sy", sy), ("separate", separate)):
            out[key].append(value)
    return out


def estimate_phase_calibration(x: npt.ArrayLike, y: npt.ArrayLike, sigma: npt.ArrayLike | None = None, *,
                               method: str = "", harmonics: int = 1, min_stars: int = MIN_STARS,
                               distinct: bool = True) -> PhaseCalibration:
    """A centroider's S-curve from its measured positions of many stars (pooled over frames).

    ``sigma``: each position's own uncertainty, px (for the noise blur; default 0). With
    ``distinct`` (default) repeated positions of one star count once (:func:`distinct_samples`).
    Raises :class:`InvalidInputError` (declines) with fewer than ``min_stars`` distinct stars.
    """
    xa, ya = np.asarray(x, np.float64).ravel(), np.asarray(y, np.float64).ravel()
    sa = np.zeros_like(xa) if sigma is None else np.asarray(sigma, np.float64).ravel()
    if not (xa.shape == ya.shape == sa.shape):
        raise InvalidInputError(f"x, y and sigma must have one shape, got {xa.shape}, {ya.shape}, {sa.shape}.")
    if harmonics < 1:
        raise InvalidInputError(f"harmonics must be >= 1, got {harmonics}.")
    ok = np.isfinite(xa) & np.isfinite(ya) & np.isfinite(sa)
    xa, ya, sa = xa[ok], ya[ok], sa[ok]
    if distinct:
        xa, ya, sa = distinct_samples(xa, ya, sa)
    if xa.size < min_stars:
        raise InvalidInputError(
            f"too few distinct star positions to calibrate the pixel phase{f' of {method}' if method else ''}: "
            f"{xa.size}; it needs {min_stars} (a star seen again at the same position, within its noise, counts "
            f"once; the centroid stage uses only unsaturated stars of SNR >= {MIN_SNR:g}).")
    t = {key: tuple(v) for key, v in _axes_terms(_phase(xa), _phase(ya), sa, harmonics).items()}
    for axis in ("x", "y"):
        _check_order_kept(t["a" + axis], f"the pixel-phase estimate{f' of {method}' if method else ''}, axis {axis}")
    return PhaseCalibration(method, t["ax"], t["ay"], t["ex"], t["ey"], t["sx"], t["sy"], int(xa.size),
                            t["separate"])


def load_phase_calibrations(path: str | Path) -> dict[str, PhaseCalibration]:
    """Calibrations per method from a JSON file: a list of :meth:`PhaseCalibration.to_dict` records,
    or an object holding one under ``"phase_correction"`` (``starlog centroid --json``'s output; that
    of ``starlog info --json``, the last run's)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise InvalidInputError(f"cannot read the phase calibration file {str(path)!r}: {e}") from None
    if isinstance(data, Mapping) and "phase_correction" in data:
        data = data["phase_correction"]
    if isinstance(data, list) and data and all(isinstance(r, Mapping) and "calibrations" in r for r in data):
        data = data[-1]  # ``starlog info --json``: the records of each centroid run, the last one applies
    if isinstance(data, Mapping) and "calibrations" in data:
        data = data["calibrations"]
    if isinstance(data, Mapping) and "method" in data:
        data = [data]
    if not isinstance(data, list) or not data:
        raise InvalidInputError(f"{str(path)!r} holds no phase calibration (a list of records with 'method' and "
                                "'amplitude_px').")
    out = [PhaseCalibration.from_dict(d) for d in data]
    return {c.method: c for c in out}
