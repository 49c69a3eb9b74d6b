"""Shared fixtures: tiny simulated logs built with starlog's own writer."""

from __future__ import annotations

from pathlib import Path

import pytest

from starlog.sim import CameraModel, Jitter, SimulationConfig
from starlog.stages import simulate_log


def small_config(**overrides: object) -> SimulationConfig:
    """A small, fast simulated dataset (64x48 px, 20 frames, 3 stars)."""
    params: dict[str, object] = dict(width=64, height=48, n_stars=3, n_frames=20, fps=100.0, margin=8.0,
                                     jitter=(Jitter(frequency_hz=7.0, amplitude_px=0.1),), seed=3,
                                     camera=CameraModel(read_noise=3.0, bias=100.0))
    params.update(overrides)
    return SimulationConfig(**params)  # type: ignore[arg-type]


@pytest.fixture(scope="session")
def sim_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small simulated log, shared read-only by tests (never modify it)."""
    path = tmp_path_factory.mktemp("sim") / "small.mcap"
    simulate_log(small_config(), path)
    return path
