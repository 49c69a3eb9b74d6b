"""Validation of the inputs every compensate module takes, and the two numbers they all compute.

The leaf of :mod:`starlog.compensation`: it imports nothing from the package.  Position series
are (N, 2) float64 arrays in pixels (x = column, y = row, (0, 0) at the centre of the top-left
pixel); rates are in Hz.
"""

from __future__ import annotations

import enum
import math
from typing import TypeVar

import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidInputError, InvalidParameterError

__all__ = [
    "as_reference",
    "as_samples",
    "as_series",
    "check_int",
    "check_rate",
    "improvement",
    "parse_choice",
    "radial_rms",
]

E = TypeVar("E", bound=enum.Enum)


def as_series(xy: npt.ArrayLike, *, name: str = "xy") -> npt.NDArray[np.float64]:
    """Validated float64 copy of an (N, 2) position series (finite; empty input gives (0, 2))."""
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


def as_samples(
    values: npt.ArrayLike, n: int, *, name: str, nonnegative: bool = False
) -> npt.NDArray[np.float64]:
    """Validated float64 copy of a per-sample (N,) array (flux, sigma, accuracy)."""
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


def as_reference(
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


def check_rate(rate_hz: float, *, name: str = "rate_hz") -> float:
    """A sampling rate as a finite float > 0 Hz."""
    try:
        value = float(rate_hz)
    except (TypeError, ValueError) as err:
        raise InvalidParameterError(f"{name} must be a number in Hz; got {rate_hz!r}.") from err
    if not math.isfinite(value) or value <= 0:
        raise InvalidParameterError(f"{name} must be a finite rate > 0 Hz; got {rate_hz!r}.")
    return value


def check_int(value: object, *, name: str, lo: int, hi: int) -> int:
    """An integer (not a bool) in ``[lo, hi]``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
        raise InvalidParameterError(f"{name} must be an integer in [{lo}, {hi}]; got {value!r}.")
    return int(value)


def parse_choice(kind: type[E], value: object, *, name: str, choices: tuple[E, ...] | None = None) -> E:
    """``kind(value)``, restricted to ``choices`` when given (default: every member)."""
    allowed = tuple(kind) if choices is None else choices
    try:
        member = kind(value)
    except ValueError:
        member = None
    if member is None or member not in allowed:
        raise InvalidParameterError(
            f"{name} must be one of {[m.value for m in allowed]}; got {value!r}."
        )
    return member


def radial_rms(residual: npt.NDArray[np.float64]) -> float:
    """Eq. 15 of an (N, 2) residual: ``sqrt(mean(dx**2 + dy**2))`` px (0.0 for N = 0)."""
    if residual.shape[0] == 0:
        return 0.0
    return float(np.sqrt(np.mean(np.sum(residual * residual, axis=1))))


def improvement(before: float, after: float) -> float:
    """Eq. 13, ``(before - after) / before``; 0.0 when ``before`` is 0."""
    return (before - after) / before if before > 0 else 0.0
