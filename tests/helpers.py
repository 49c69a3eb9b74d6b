"""Plain helpers shared by the tests (fixtures live in ``conftest.py``)."""

from __future__ import annotations

from starlog.io import LogWriter
from starlog.sim import CameraModel, Jitter, SimulationConfig


def small_config(**overrides: object) -> SimulationConfig:
    """A small, fast simulated dataset (64x48 px, 20 frames, 3 stars)."""
    params: dict[str, object] = dict(width=64, height=48, n_stars=3, n_frames=20, fps=100.0, margin=8.0,
                                     jitter=(Jitter(frequency_hz=7.0, amplitude_px=0.1),), seed=3,
                                     camera=CameraModel(read_noise=3.0, bias=100.0))
    params.update(overrides)
    return SimulationConfig(**params)  # type: ignore[arg-type]


def killed_writer_bytes(writer: LogWriter) -> bytes:
    """What a writer killed now leaves: the header, every chunk and its message indexes flushed, no summary
    and no footer. The writer is then aborted (its temporary file removed)."""
    writer.flush()
    data = writer._tmp_path.read_bytes()
    writer.abort()
    return data
