"""Plain helpers shared by the tests (fixtures live in ``conftest.py``)."""

from __future__ import annotations

from starlog.sim import CameraModel, Jitter, SimulationConfig


def small_config(**overrides: object) -> SimulationConfig:
    """A small, fast simulated dataset (64x48 px, 20 frames, 3 stars)."""
    params: dict[str, object] = dict(width=64, height=48, n_stars=3, n_frames=20, fps=100.0, margin=8.0,
                                     jitter=(Jitter(frequency_hz=7.0, amplitude_px=0.1),), seed=3,
                                     camera=CameraModel(read_noise=3.0, bias=100.0))
    params.update(overrides)
    return SimulationConfig(**params)  # type: ignore[arg-type]
