"""Where the tracking filter's start-up ends, so that scoring can skip it (docs/PAPER.md, "Burn-in").

The centroid sequence the paper compensates is the output of an unscented Kalman filter.  Its
first samples carry the filter's initialisation: the STATIC model is a running mean, so its
first output is one raw centroid and its error falls like ``1 / sqrt(n)``; the moving models
settle within a few frames.  Scoring from frame 0 lets those few samples dominate a short
window's squared error.  The burn-in is therefore::

    burn_in = first native sample n with  P[n] <= ratio * P_steady   (ratio = 2)

with ``P[n]`` the filter's posterior position variance (``(cov_xx + cov_yy) / 2``, px²) and
``P_steady`` its steady state, estimated as the median of ``P`` over the last ``tail`` (5 %) of
the sequence.  A model without process noise (STATIC) never reaches a steady state — its
variance keeps falling like ``1 / n`` — so the test alone would skip half the sequence; the
burn-in is capped at ``max_samples`` (the experiment and the ``compensate`` stage use
:data:`MAX_BURN_IN_S` seconds of frames, and at most :data:`MAX_BURN_IN_FRACTION` of the
sequence).  The result says whether the cap applied.

What is skipped is a :data:`BurnInSetting` (``--burn-in`` of ``compensate`` and ``experiment``):
``"auto"`` (the rule above, the default), ``"off"`` (score from the first frame), or a fixed
number of seconds (:func:`parse_burn_in`, :func:`fixed_burn_in`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.compensation.series import as_samples
from starlog.errors import InvalidParameterError

__all__ = ["BURN_IN_RATIO", "MAX_BURN_IN_FRACTION", "MAX_BURN_IN_S", "BurnIn", "BurnInSetting", "burn_in",
           "burn_in_cap", "burn_in_label", "fixed_burn_in", "longest_burn_in", "parse_burn_in"]

#: The filter has settled once its position variance is within this factor of the steady state.
BURN_IN_RATIO = 2.0
#: Longest burn-in skipped, s (a filter without process noise never settles).
MAX_BURN_IN_S = 0.5
#: Longest burn-in skipped, as a fraction of the sequence (short logs keep most of their samples).
MAX_BURN_IN_FRACTION = 0.1
_TAIL = 0.05

#: What scoring skips: ``"auto"`` (the variance rule), ``"off"`` (nothing) or a number of seconds.
BurnInSetting = str | float


@dataclass(frozen=True)
class BurnIn:
    """The start-up of one filtered sequence.

    ``samples``: native samples skipped (index of the first scored one); ``steady_variance``:
    ``P_steady``, px²; ``capped``: the variance had not come within ``ratio`` of the steady
    state by ``max_samples``.
    """

    samples: int
    steady_variance: float
    capped: bool

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict of the fields."""
        return {"samples": self.samples, "steady_variance": self.steady_variance, "capped": self.capped}


def burn_in(variance: npt.ArrayLike, *, max_samples: int, ratio: float = BURN_IN_RATIO) -> BurnIn:
    """The burn-in of a sequence of posterior position variances (px², native rate).

    Parameters
    ----------
    variance : (N,) array_like
        Posterior position variance of each native sample, px² (>= 0).
    max_samples : int
        Cap on the burn-in, samples (>= 0).
    ratio : float
        Settled once ``P[n] <= ratio * P_steady`` (> 1; default 2).

    Returns
    -------
    BurnIn
        ``samples = 0`` for an empty sequence.
    """
    v = as_samples(variance, int(np.size(variance)), name="variance", nonnegative=True)
    if isinstance(max_samples, bool) or not isinstance(max_samples, (int, np.integer)) or max_samples < 0:
        raise InvalidParameterError(f"max_samples must be an integer >= 0; got {max_samples!r}.")
    if not (math.isfinite(ratio) and ratio > 1.0):
        raise InvalidParameterError(f"ratio must be a finite number > 1; got {ratio!r}.")
    n = v.size
    if n == 0:
        return BurnIn(samples=0, steady_variance=0.0, capped=False)
    tail = v[n - max(1, int(math.ceil(_TAIL * n))):]
    steady = float(np.median(tail))
    settled = np.flatnonzero(v <= ratio * steady)
    first = int(settled[0]) if settled.size else n
    if first > max_samples:
        return BurnIn(samples=int(max_samples), steady_variance=steady, capped=True)
    return BurnIn(samples=first, steady_variance=steady, capped=False)


def burn_in_cap(n: int, *, native_rate: float) -> int:
    """The cap on the burn-in of ``n`` samples at ``native_rate`` Hz:
    ``min(floor(MAX_BURN_IN_S · rate + 0.5), floor(MAX_BURN_IN_FRACTION · n))``."""
    return max(0, min(int(math.floor(MAX_BURN_IN_S * native_rate + 0.5)), int(math.floor(MAX_BURN_IN_FRACTION * n))))


def parse_burn_in(value: BurnInSetting | None) -> BurnInSetting:
    """``"auto"``, ``"off"`` or seconds (>= 0; ``0`` is ``"off"``) from a CLI string or a value; None is ``"auto"``."""
    if value is None:
        return "auto"
    if isinstance(value, str):
        text = value.strip().lower()
        if text in ("auto", "off"):
            return text
        try:
            value = float(text.removesuffix("s"))
        except ValueError:
            raise InvalidParameterError(f"burn-in must be 'auto', 'off' or seconds >= 0; got {value!r}.") from None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value >= 0):
        raise InvalidParameterError(f"burn-in must be 'auto', 'off' or seconds >= 0; got {value!r}.")
    return "off" if value == 0 else float(value)


def burn_in_label(setting: BurnInSetting) -> str:
    """The setting as recorded: ``auto``, ``off`` or ``<seconds> s``."""
    return setting if isinstance(setting, str) else f"{setting:g} s"


def fixed_burn_in(n: int, *, native_rate: float, seconds: float) -> BurnIn:
    """A burn-in of ``seconds`` of frames (``floor(seconds · rate + 0.5)``, at most ``n - 1``); no variance test (``steady_variance`` 0)."""
    samples = max(0, min(int(math.floor(seconds * native_rate + 0.5)), n - 1))
    return BurnIn(samples=samples, steady_variance=0.0, capped=False)


def longest_burn_in(n: int, *, native_rate: float, setting: BurnInSetting) -> int:
    """The most of ``n`` samples at ``native_rate`` Hz that the burn-in under ``setting`` can skip: the cap
    (:func:`burn_in_cap`) for ``"auto"``, none for ``"off"``, :func:`fixed_burn_in` for seconds."""
    if setting == "off":
        return 0
    if isinstance(setting, str):
        return burn_in_cap(n, native_rate=native_rate)
    return fixed_burn_in(n, native_rate=native_rate, seconds=float(setting)).samples
