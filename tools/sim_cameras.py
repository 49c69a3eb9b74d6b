"""Simulated cameras for ``tools/bench_realsky.py``: the real sky rendered by starlog's simulator through other
optics and sensors, written as folders of frames the benchmark reads like a real camera's.

Each camera is eight frames of the catalogue's stars (cedar-solve's Hipparcos table, the one the benchmark
solves against, down to its faintest magnitude so that no catalogue star is missing from the frame) at eight
fixed pointings (:data:`POINTINGS`), rendered by :class:`starlog.sim.Simulator` with one PSF (pixel-integrated
Gaussian, Moffat or Airy) and camera (gain, read noise, full well), then, for some, made into what a cheaper
sensor or pipeline writes (8 bits, JPEG, a demosaiced colour sensor, 2 x 2 binning: the benchmark's
:func:`write_degraded`). The catalogue is then exact and every residual is the centroid error plus what the
camera refit absorbs. The PSFs and sensors are chosen to span what the real frames do not show (wide, winged
and diffraction PSFs, saturated cores, colour), not to favour any method.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from starlog.sim import SimulationConfig, Simulator
from starlog.sim.camera import CameraModel

__all__ = ["POINTINGS", "SIM_CAMERAS", "write_camera"]

POINTINGS = ((30.0, 40.0, 10.0), (100.0, 20.0, 80.0), (150.0, -30.0, 150.0), (200.0, 60.0, 200.0),
             (250.0, -10.0, 260.0), (300.0, 35.0, 320.0), (340.0, -50.0, 30.0), (60.0, 0.0, 100.0))
"""(RA, Dec, roll) deg of the eight frames of every simulated camera."""

_BASE: dict[str, Any] = {"width": 1024, "height": 768, "fov_deg": 11.4, "magnitude_limit": 9.0, "flux_mag6": 3000.0,
                         "sky": 50.0, "margin": 4.0}
SIM_CAMERAS: dict[str, dict[str, Any]] = {
    "sim-gauss-0.55": {"psf_sigma": 0.55},
    "sim-gauss-1.5": {"psf_sigma": 1.5, "flux_mag6": 6000.0},
    "sim-moffat-4": {"psf_model": "moffat", "psf_fwhm": 4.0, "fov_deg": 20.0, "flux_mag6": 9000.0},
    "sim-airy-3": {"psf_model": "airy", "psf_fwhm": 3.0, "flux_mag6": 6000.0},
    "sim-gauss-1.2-saturated": {"psf_sigma": 1.2, "flux_mag6": 20000.0, "full_well": 30000.0},
    "sim-gauss-1.5-jpeg-85": {"psf_sigma": 1.5, "flux_mag6": 6000.0, "gain": 0.01, "sensor": "jpeg-85"},
    "sim-moffat-4-colour-jpeg": {"psf_model": "moffat", "psf_fwhm": 4.0, "fov_deg": 20.0, "flux_mag6": 9000.0,
                                 "gain": 0.01, "sensor": "colour-jpeg-90"},
    "sim-gauss-1.2-bayer": {"psf_sigma": 1.2, "flux_mag6": 6000.0, "sensor": "bayer-demosaiced"},
}
"""Each simulated camera: the simulator's PSF and field options, ``full_well`` (e-; saturated cores), ``gain``
(e-/DN, 1 unless given: the 8-bit sensors' 0.01 puts the sky at about 20 of 255 and saturates the stars brighter
than magnitude 4, as a consumer camera's exposure does) and ``sensor``, one of the benchmark's ``DEGRADED`` kinds
(None: the 16-bit frames as rendered)."""


def _render(options: dict[str, Any], folder: Path) -> None:
    """The eight 16-bit frames of one camera's optics into ``folder`` as TIFFs."""
    import tifffile

    spec = {**_BASE, **{k: v for k, v in options.items() if k not in ("sensor", "full_well", "gain")}}
    camera = CameraModel(read_noise=5.0, gain=options.get("gain", 1.0), bias=100.0, adc_bits=16,
                         full_well=options.get("full_well"))
    for k, pointing in enumerate(POINTINGS):
        config = SimulationConfig(**spec, sky_attitude=pointing, camera=camera, n_frames=1, seed=k + 1)
        frame = Simulator(config).render(0)
        tifffile.imwrite(str(folder / f"frame{k}.tiff"), np.asarray(frame.image, np.uint16))


def write_camera(name: str, folder: Path, degrade: Any) -> None:
    """Camera ``name`` (:data:`SIM_CAMERAS`) into ``folder``; ``degrade(images, kind, folder)``: the benchmark's
    :func:`write_degraded`."""
    options = SIM_CAMERAS[name]
    sensor = options.get("sensor")
    if sensor is None:
        _render(options, folder)
        return
    with tempfile.TemporaryDirectory(prefix="simcam-") as tmp:
        _render(options, Path(tmp))
        degrade(Path(tmp), sensor, folder)
