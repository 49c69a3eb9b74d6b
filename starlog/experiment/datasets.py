"""The two simulated "laboratory" datasets of the paper's §3.1, in two regimes (docs/PAPER.md, "Experiments").

Regime ``paper`` (:mod:`~starlog.experiment.paper_regime`, derived from the paper's own numbers
in docs/PAPER_REGIME.md): one faint star, through the same optics, in a laboratory whose read
noise and background fix how the star's SNR falls with the exposure (= frame period, so the
300 Hz star is fainter), whose uncompensated RMSE is of the paper's size, and a tracker that
keeps the single-frame scatter and does not follow noise peaks.  Regime ``modern``, described
below: six bright stars.

Regime ``modern``: a static star field seen at 300 Hz (3248 frames) and 200 Hz (3027 frames) by a camera on a
platform with small perturbations: two sinusoidal vibrations (3.7 Hz, 0.08 px and 17 Hz,
0.04 px peak per axis) and a slow random walk (0.01 px/√s).  The jitter's RMS is 0.063 px per
axis; the experiment sets the trackers' ``sigma_floor`` to :data:`SIGMA_FLOOR_PX` = 0.06 px
(≈ that RMS) so the near-zero-process-noise STATIC model does not gate the real platform
motion away.

Frames are 128×128 px with 6 stars (5,000–50,000 e⁻, PSF σ = 1.2 px, sky 20 e⁻/px): small
enough for the whole experiment to run in a few minutes on 2 cores.  The star field's seed is
the first seed (from the dataset's base seed upwards) whose stars are at least
:data:`MIN_SEPARATION_PX` apart, so no two star images blend (a blended pair biases every
centroid by ~1 px and would make the truth protocols meaningless).  Everything is
deterministic.

``quick`` datasets (CI): 48×48 px, 2 stars (``paper``: its one star), 3.7 s of data (1110 / 740 frames): after the
filter's start-up (at most :data:`~starlog.compensation.MAX_BURN_IN_S` = 0.5 s) enough for 32
samples at 10 Hz, i.e. 16 calibration + 16 scored samples under the ``leakfree`` protocol
(the compensation needs at least 16).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from starlog.compensation import MAX_BURN_IN_S
from starlog.experiment import paper_regime
from starlog.sim import PRESETS, CameraModel, Jitter, SimulationConfig, Simulator

__all__ = [
    "JITTER",
    "REGIMES",
    "MIN_SEPARATION_PX",
    "RANDOM_WALK_PX_PER_SQRT_S",
    "SIGMA_FLOOR_PX",
    "Dataset",
    "jitter_rms_px",
    "min_separation",
    "paper_datasets",
    "regime_datasets",
]

#: The dataset regimes, in report order: the paper's (derived from its numbers) and today's.
REGIMES: tuple[str, ...] = ("paper", "modern")

#: Platform vibration of both datasets.
JITTER: tuple[Jitter, ...] = (Jitter(frequency_hz=3.7, amplitude_px=0.08), Jitter(frequency_hz=17.0, amplitude_px=0.04))
#: Platform random walk, px/√s.
RANDOM_WALK_PX_PER_SQRT_S = 0.01
#: The trackers' measurement-sigma floor used by the experiment, px (≈ per-axis jitter RMS).
SIGMA_FLOOR_PX = 0.06
#: Smallest distance between two stars of a dataset, px.
MIN_SEPARATION_PX = 12.0

_BASE_SEEDS = {"300Hz": 300, "200Hz": 200}
_QUICK_SECONDS = 3.2 + MAX_BURN_IN_S


@dataclass(frozen=True)
class Dataset:
    """One simulated dataset: its name (``"300Hz"`` / ``"200Hz"``), simulator configuration, regime,
    and the stages' settings for it (``tracker``: StarTracker options, ``motion``: motion-model
    options, ``centroid``: centroid-stage options)."""

    name: str
    config: SimulationConfig
    regime: str = "modern"
    tracker: dict[str, Any] = field(default_factory=dict)
    motion: dict[str, Any] = field(default_factory=dict)
    centroid: dict[str, Any] = field(default_factory=dict)

    @property
    def stem(self) -> str:
        """File-name stem of the dataset's logs, ``<regime>_<name>``."""
        return f"{self.regime}_{self.name}"

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (name, regime, configuration, duration, tracker settings)."""
        return {"name": self.name, "regime": self.regime, "duration_s": self.config.duration_s,
                "config": self.config.to_dict(), "tracker": dict(self.tracker), "motion": dict(self.motion),
                "centroid": dict(self.centroid)}


def jitter_rms_px(jitter: tuple[Jitter, ...]) -> float:
    """Per-axis RMS of a sum of sinusoids, px: ``sqrt(Σ a² / 2)``."""
    return math.sqrt(sum(j.amplitude_px**2 for j in jitter) / 2.0)


def min_separation(config: SimulationConfig) -> float:
    """Smallest distance between two stars of ``config``'s field, px (inf for one star)."""
    field = Simulator(config).field
    if field.x.size < 2:
        return math.inf
    d = np.hypot(field.x[:, None] - field.x[None, :], field.y[:, None] - field.y[None, :])
    return float(d[np.triu_indices(field.x.size, 1)].min())


def _separated(params: dict[str, Any], base_seed: int) -> SimulationConfig:
    """The configuration with the first seed >= ``base_seed`` whose stars are well separated."""
    for seed in itertools.count(base_seed):
        config = SimulationConfig(**params, seed=seed)
        if min_separation(config) >= MIN_SEPARATION_PX:
            return config
    raise AssertionError("unreachable")  # pragma: no cover


def paper_datasets(*, quick: bool = False, regime: str = "modern",
                   sigma_floor: float = SIGMA_FLOOR_PX) -> tuple[Dataset, ...]:
    """The 300 Hz and 200 Hz datasets of one regime (in that order), full size or ``quick``."""
    if regime not in REGIMES:
        raise ValueError(f"unknown regime {regime!r}; choose from {REGIMES}.")
    out = []
    for name, preset in (("300Hz", PRESETS["paper300"]), ("200Hz", PRESETS["paper200"])):
        fps = float(preset["fps"])
        params: dict[str, Any] = {
            "fps": fps,
            "n_frames": int(round(_QUICK_SECONDS * fps)) if quick else int(preset["n_frames"]),
            "width": 48 if quick else 128,
            "height": 48 if quick else 128,
            "n_stars": 2 if quick else 6,
            "flux_min": 5_000.0,
            "flux_max": 50_000.0,
            "psf_sigma": 1.2,
            "sky": 20.0,
            "jitter": JITTER,
            "random_walk_px_per_sqrt_s": RANDOM_WALK_PX_PER_SQRT_S,
            "margin": 10.0,
        }
        motion: dict[str, Any] = {}
        centroid: dict[str, Any] = {}
        tracker: dict[str, Any] = {"sigma_floor": float(sigma_floor)}
        if regime == "paper":
            paper = paper_regime.simulation_for(fps)
            params.update({k: v for k, v in paper.items() if not (quick and k in ("width", "height"))})
            params["camera"] = CameraModel(**paper["camera"])
            motion = paper_regime.motion_for(fps)
            centroid = dict(paper_regime.CENTROID)
            tracker.update(paper_regime.tracker_for(fps))
        out.append(Dataset(name=name, config=_separated(params, _BASE_SEEDS[name]), regime=regime,
                           tracker=tracker, motion=motion, centroid=centroid))
    return tuple(out)


def regime_datasets(regimes: tuple[str, ...] = REGIMES, *, quick: bool = False,
                    sigma_floor: float = SIGMA_FLOOR_PX) -> tuple[Dataset, ...]:
    """The dataset pair of every regime in ``regimes`` (regime order, then 300 Hz before 200 Hz)."""
    return tuple(ds for regime in regimes
                 for ds in paper_datasets(quick=quick, regime=regime, sigma_floor=sigma_floor))
