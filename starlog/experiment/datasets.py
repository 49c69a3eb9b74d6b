"""The two simulated "laboratory" datasets of the paper's §3.1 (docs/PAPER.md).

A static star field seen at 300 Hz (3248 frames) and 200 Hz (3027 frames) by a camera on a
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

``quick`` datasets (CI): 48×48 px, 2 stars, 3.2 s of data (960 / 640 frames): enough for 32
samples at 10 Hz, i.e. 16 calibration + 16 scored samples under the ``leakfree`` protocol
(the compensation needs at least 16).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from starlog.sim import PRESETS, Jitter, SimulationConfig, Simulator

__all__ = [
    "JITTER",
    "MIN_SEPARATION_PX",
    "RANDOM_WALK_PX_PER_SQRT_S",
    "SIGMA_FLOOR_PX",
    "Dataset",
    "jitter_rms_px",
    "paper_datasets",
]

#: Platform vibration of both datasets.
JITTER: tuple[Jitter, ...] = (Jitter(frequency_hz=3.7, amplitude_px=0.08), Jitter(frequency_hz=17.0, amplitude_px=0.04))
#: Platform random walk, px/√s.
RANDOM_WALK_PX_PER_SQRT_S = 0.01
#: The trackers' measurement-sigma floor used by the experiment, px (≈ per-axis jitter RMS).
SIGMA_FLOOR_PX = 0.06
#: Smallest distance between two stars of a dataset, px.
MIN_SEPARATION_PX = 12.0

_BASE_SEEDS = {"300Hz": 300, "200Hz": 200}
_QUICK_SECONDS = 3.2


@dataclass(frozen=True)
class Dataset:
    """One simulated dataset: its name (``"300Hz"`` / ``"200Hz"``) and simulator configuration."""

    name: str
    config: SimulationConfig

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (name, configuration, duration)."""
        return {"name": self.name, "duration_s": self.config.duration_s, "config": self.config.to_dict()}


def jitter_rms_px(jitter: tuple[Jitter, ...]) -> float:
    """Per-axis RMS of a sum of sinusoids, px: ``sqrt(Σ a² / 2)``."""
    return math.sqrt(sum(j.amplitude_px**2 for j in jitter) / 2.0)


def _min_separation(config: SimulationConfig) -> float:
    field = Simulator(config).field
    if field.x.size < 2:
        return math.inf
    d = np.hypot(field.x[:, None] - field.x[None, :], field.y[:, None] - field.y[None, :])
    return float(d[np.triu_indices(field.x.size, 1)].min())


def _separated(params: dict[str, Any], base_seed: int) -> SimulationConfig:
    """The configuration with the first seed >= ``base_seed`` whose stars are well separated."""
    for seed in itertools.count(base_seed):
        config = SimulationConfig(**params, seed=seed)
        if _min_separation(config) >= MIN_SEPARATION_PX:
            return config
    raise AssertionError("unreachable")  # pragma: no cover


def paper_datasets(*, quick: bool = False) -> tuple[Dataset, ...]:
    """The 300 Hz and 200 Hz datasets (in that order), full size or ``quick``."""
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
        out.append(Dataset(name=name, config=_separated(params, _BASE_SEEDS[name])))
    return tuple(out)
