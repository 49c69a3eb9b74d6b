"""The tracker's options, :class:`TrackerConfig`, checked when made."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from starlog.errors import InvalidParameterError
from starlog.tracking.models import MotionModel, MotionModelConfig
from starlog.tracking.ukf import DEFAULT_GATE_PROBABILITY, SigmaPoints, gate_threshold

__all__ = ["TrackerConfig"]


@dataclass(frozen=True)
class TrackerConfig:
    """Options of :class:`StarTracker` (validated on construction).

    Parameters
    ----------
    model : MotionModel or str
        Motion model of every track (default STATIC, the paper's best model for a static
        star field, Table 2).
    motion : MotionModelConfig
        Process-noise intensities and initial velocity/acceleration uncertainty.
    points : SigmaPoints
        Merwe sigma-point scaling.
    gate_probability : float
        Innovation gate: probability that a correct measurement passes, chi-square(2 dof);
        default 0.9999 (NIS threshold 18.42). 1.0 disables the gate.
    association_radius : float
        Association window around each predicted position, px (default 3.0): star images
        are many pixels apart, while jitter and transient outliers stay within a few px.
    confirm_hits : int
        Applied measurements (birth included) that confirm a track, >= 1 (default 3).
    max_missed : int
        Consecutive frames without an associated centroid that a confirmed track survives,
        >= 0 (default 10: 33–50 ms at 200–300 Hz).
    max_gated : int
        Consecutive gated frames after which the next associated measurement is applied
        regardless of the gate, >= 1 (default 5: outliers are transient).
    sigma_floor : float
        Smallest measurement uncertainty used, px, > 0 (default 1e-3): centroids reporting
        ``sigma`` below it (e.g. 0 for a method without an uncertainty) use the floor.
    max_distance : float, optional
        When set, a centroid may be associated to a track only within this distance, px, of
        the track's filtered position at its last applied measurement, replacing the window
        and the gate (default None). A coasting track's position variance grows every frame,
        and with it the innovation gate, while a moving model's prediction drifts on its
        velocity; with a faint star of a static field detected in only some frames, either
        would let the track jump to a noise peak pixels away and follow it, or lose its star.
        The limit keeps such a track where its star was.
    """

    model: MotionModel | str = MotionModel.STATIC
    motion: MotionModelConfig = field(default_factory=MotionModelConfig)
    points: SigmaPoints = field(default_factory=SigmaPoints)
    gate_probability: float = DEFAULT_GATE_PROBABILITY
    association_radius: float = 3.0
    confirm_hits: int = 3
    max_missed: int = 10
    max_gated: int = 5
    sigma_floor: float = 1e-3
    max_distance: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "model", MotionModel.parse(self.model))
        if not isinstance(self.motion, MotionModelConfig):
            raise InvalidParameterError(
                f"TrackerConfig.motion must be a MotionModelConfig, got {self.motion!r}."
            )
        if not isinstance(self.points, SigmaPoints):
            raise InvalidParameterError(
                f"TrackerConfig.points must be a SigmaPoints, got {self.points!r}."
            )
        gate_threshold(self.gate_probability)  # validates
        for name in ("association_radius", "sigma_floor"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)):
                raise InvalidParameterError(
                    f"TrackerConfig.{name} must be a number, got {value!r}."
                )
            if not (math.isfinite(value) and value > 0):
                raise InvalidParameterError(
                    f"TrackerConfig.{name} must be finite and > 0, got {value!r}."
                )
        for name, low in (("confirm_hits", 1), ("max_missed", 0), ("max_gated", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise InvalidParameterError(
                    f"TrackerConfig.{name} must be an integer >= {low}, got {value!r}."
                )
            object.__setattr__(self, name, int(value))
        if self.max_distance is not None:
            value = self.max_distance
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) or not (
                    math.isfinite(value) and value > 0):
                raise InvalidParameterError(
                    f"TrackerConfig.max_distance must be None or a finite number > 0, got {value!r}."
                )
