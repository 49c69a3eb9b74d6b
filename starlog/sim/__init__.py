"""Star-image simulator: pixel-integrated Gaussian stars, a camera noise model and platform motion."""

from __future__ import annotations

from starlog.sim.camera import CameraModel
from starlog.sim.psf import integrated_gaussian_1d, render_stars
from starlog.sim.simulator import PRESETS, Jitter, SimulatedFrame, SimulationConfig, Simulator, StarField

__all__ = [
    "PRESETS",
    "CameraModel",
    "Jitter",
    "SimulatedFrame",
    "SimulationConfig",
    "Simulator",
    "StarField",
    "integrated_gaussian_1d",
    "render_stars",
]
