"""How long a log must be for each rate and protocol of a compensation, known before it runs.

:func:`~starlog.compensation.evaluate` needs :data:`~starlog.compensation.decomposition.MIN_SAMPLES`
decimated samples, and under ``leakfree`` a calibration segment of as many with a scored sample
after it (:func:`~starlog.compensation.references.calibration_fits`). The ``compensate`` stage
decimates a track of ``n`` frames after the filter's start-up (:mod:`~starlog.compensation.burnin`),
whose length is known only once the track exists; :func:`fewest_samples` counts the samples left
after the longest start-up the burn-in setting allows, so a rate and protocol that pass
:func:`shortfalls` cannot fail for want of samples.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from starlog.compensation.burnin import BurnInSetting, longest_burn_in
from starlog.compensation.decimate import RATE_TOLERANCE, decimation_indices
from starlog.compensation.decomposition import MIN_SAMPLES
from starlog.compensation.references import (
    CALIBRATION_FRACTION,
    ReferenceMode,
    ScoringProtocol,
    calibration_fits,
    reference_mode_for,
)

__all__ = ["Shortfall", "enough_samples", "fewest_samples", "frames_needed", "samples_needed", "shortfalls"]


def enough_samples(protocol: ScoringProtocol, n: int, *, calibration_fraction: float = CALIBRATION_FRACTION) -> bool:
    """Whether :func:`~starlog.compensation.evaluate` accepts ``n`` samples under ``protocol``."""
    if n < MIN_SAMPLES:
        return False
    if reference_mode_for(protocol, ReferenceMode.CALIBRATION) is ReferenceMode.GLOBAL_MEAN:
        return True
    return calibration_fits(n, fraction=calibration_fraction, minimum=MIN_SAMPLES)


def samples_needed(protocol: ScoringProtocol, *, calibration_fraction: float = CALIBRATION_FRACTION) -> int:
    """The fewest samples :func:`enough_samples` accepts under ``protocol``."""
    return _smallest(lambda n: enough_samples(protocol, n, calibration_fraction=calibration_fraction), MIN_SAMPLES)


def fewest_samples(n_frames: int, *, native_rate: float, rate_hz: float, burn_in: BurnInSetting = "auto") -> int:
    """The samples the ``compensate`` stage keeps at ``rate_hz`` from a track of ``n_frames`` at ``native_rate``
    Hz when the filter's start-up is the longest ``burn_in`` allows (:func:`~starlog.compensation.longest_burn_in`)."""
    start = longest_burn_in(n_frames, native_rate=native_rate, setting=burn_in)
    return int(decimation_indices(n_frames, native_rate=native_rate, target_rate=rate_hz, start=start).size)


def frames_needed(samples: int, *, native_rate: float, rate_hz: float, burn_in: BurnInSetting = "auto") -> int:
    """The fewest frames for which :func:`fewest_samples` gives at least ``samples``."""
    return _smallest(lambda n: fewest_samples(n, native_rate=native_rate, rate_hz=rate_hz, burn_in=burn_in) >= samples,
                     1)


def _smallest(accepts: Callable[[int], bool], low: int) -> int:
    """The smallest ``n >= low`` that ``accepts`` (which, once true, stays true as ``n`` grows)."""
    high = max(low, 1)
    while not accepts(high):
        low, high = high + 1, 2 * high
    while low < high:
        middle = (low + high) // 2
        if accepts(middle):
            high = middle
        else:
            low = middle + 1
    return high


@dataclass(frozen=True)
class Shortfall:
    """A rate and protocol a log is too short for: the samples it gives, the samples needed, and the
    frames (at ``native_rate`` Hz) a log needs for them."""

    rate_hz: float
    protocol: ScoringProtocol
    samples: int
    needed: int
    frames_needed: int
    native_rate: float

    @property
    def seconds_needed(self) -> float:
        """The shortest log that gives the samples needed, s."""
        return self.frames_needed / self.native_rate

    def describe(self) -> str:
        """One line: ``10 Hz leakfree: 18 samples, needs 31 (a log of at least 3.34 s: 1001 frames at 300 Hz)``."""
        return (f"{self.rate_hz:g} Hz {self.protocol.value}: {self.samples} samples, needs {self.needed} "
                f"(a log of at least {self.seconds_needed:.2f} s: {self.frames_needed} frames at "
                f"{self.native_rate:g} Hz)")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready fields."""
        return {"rate_hz": self.rate_hz, "protocol": self.protocol.value, "samples": self.samples,
                "needed": self.needed, "frames_needed": self.frames_needed,
                "seconds_needed": round(self.seconds_needed, 3)}


def shortfalls(n_frames: int, *, native_rate: float, rates: Sequence[float], protocols: Iterable[ScoringProtocol],
               calibration_fraction: float = CALIBRATION_FRACTION, burn_in: BurnInSetting = "auto") -> list[Shortfall]:
    """Each rate and protocol that a track of ``n_frames`` at ``native_rate`` Hz gives too few samples for
    (:func:`fewest_samples`, :func:`enough_samples`), in the order of ``rates`` then ``protocols``. Rates the
    stage refuses for themselves (not in ``(0, native_rate]``) are left to it."""
    chosen = list(protocols)
    out = []
    for rate in rates:
        rate = float(rate)
        if not 0 < rate <= native_rate * (1 + RATE_TOLERANCE):
            continue
        samples = fewest_samples(n_frames, native_rate=native_rate, rate_hz=rate, burn_in=burn_in)
        for protocol in chosen:
            if enough_samples(protocol, samples, calibration_fraction=calibration_fraction):
                continue
            needed = samples_needed(protocol, calibration_fraction=calibration_fraction)
            frames = frames_needed(needed, native_rate=native_rate, rate_hz=rate, burn_in=burn_in)
            out.append(Shortfall(rate, protocol, samples, needed, frames, native_rate))
    return out
