"""The simulator's configuration from ``starlog simulate``'s options (:func:`starlog.simulate`'s keywords)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from starlog.errors import InvalidParameterError
from starlog.sim.camera import CameraModel
from starlog.sim.profiles import AIRY_ZERO_PER_LAMBDA_D
from starlog.sim.simulator import PRESETS, Jitter, SimulationConfig

__all__ = ["simulation_config"]


def simulation_config(*, preset: str | None = None, size: tuple[int, int] = (256, 256), stars: int = 12,
                      flux: tuple[float, float] = (5000.0, 50000.0), fps: float | None = None,
                      frames: int | None = None, duration: float | None = None, psf_sigma: float = 1.2,
                      psf: str = "gaussian", psf_fwhm: float = 0.0, moffat_beta: float = 2.5,
                      airy_lambda_d: float = 0.0, airy_zero: float = 0.0, sky: float = 20.0, read_noise: float = 3.0,
                      gain: float = 1.0, bias: float = 100.0, adc_bits: int = 16, hot_pixels: int = 0,
                      cosmic_rays: float = 0.0, jitter: Sequence[tuple[float, float]] = (),
                      drift: tuple[float, float] = (0.0, 0.0), random_walk: float = 0.0,
                      roll: tuple[float, float] | None = None, sky_attitude: tuple[float, float, float] | None = None,
                      fov: float = 12.0, mag_limit: float = 6.5, flux_mag6: float = 20000.0, seed: int = 0,
                      start_ns: int = 0) -> SimulationConfig:
    """A :class:`SimulationConfig` from the command's options: ``size`` (width, height) px, ``flux`` (min, max) e-,
    ``jitter`` [(frequency Hz, amplitude px)], ``drift`` (vx, vy) px/s, ``roll`` (frequency Hz, amplitude rad),
    ``sky_attitude`` (RA, Dec, roll) degrees; ``preset`` sets the frame rate and count, which ``fps``, ``frames``
    or ``duration`` override."""
    params: dict[str, Any] = {}
    if sky_attitude is not None:
        params.update(sky_attitude=_floats(sky_attitude), fov_deg=float(fov), magnitude_limit=float(mag_limit),
                      flux_mag6=float(flux_mag6))
    params.update(_timing(preset, None if fps is None else float(fps), frames, duration))
    params.update(_psf_shape(psf, float(psf_fwhm), float(moffat_beta), float(airy_lambda_d), float(airy_zero)))
    roll_hz, roll_rad = _floats(roll) if roll is not None else (1.0, 0.0)
    width, height = (int(v) for v in size)
    flux_min, flux_max = _floats(flux)
    return SimulationConfig(
        width=width, height=height, n_stars=int(stars), flux_min=flux_min, flux_max=flux_max,
        psf_sigma=float(psf_sigma), sky=float(sky),
        camera=CameraModel(read_noise=float(read_noise), gain=float(gain), bias=float(bias), adc_bits=int(adc_bits)),
        hot_pixels=int(hot_pixels), cosmic_rays_per_frame=float(cosmic_rays),
        jitter=tuple(Jitter(frequency_hz=f, amplitude_px=a) for f, a in map(_floats, jitter)),
        drift_px_per_s=_floats(drift), random_walk_px_per_sqrt_s=float(random_walk), roll_amplitude_rad=roll_rad,
        roll_frequency_hz=roll_hz, seed=int(seed), start_time_ns=int(start_ns), **params)


def _floats(values: Sequence[float]) -> tuple[float, ...]:
    """Numbers as floats: the configuration (and the provenance that records it) is the same whether a caller
    wrote 10 or 10.0."""
    return tuple(float(v) for v in values)


def _timing(preset: str | None, fps: float | None, frames: int | None, duration: float | None) -> dict[str, Any]:
    """Frame rate and count: 300 Hz and 300 frames, or the preset's, overridden by the options given."""
    if preset is not None and preset not in PRESETS:
        raise InvalidParameterError(f"unknown preset {preset!r}; presets: {', '.join(PRESETS)}.")
    params: dict[str, Any] = {"fps": 300.0, "n_frames": 300}
    if preset:
        params.update(PRESETS[preset])
    if fps is not None:
        params["fps"] = fps
    if duration is not None and frames is not None:
        raise InvalidParameterError("give the number of frames or the duration, not both.")
    if duration is not None:
        params["n_frames"] = max(1, int(round(duration * params["fps"])))
    elif frames is not None:
        params["n_frames"] = frames
    return params


def _psf_shape(psf: str, psf_fwhm: float, moffat_beta: float, airy_lambda_d: float, airy_zero: float
               ) -> dict[str, Any]:
    """The Moffat or Airy options of the simulation (none for the Gaussian PSF)."""
    if psf == "gaussian":
        return {}
    if airy_zero and airy_lambda_d:
        raise InvalidParameterError("give the Airy lambda/D or its first zero, not both.")
    return {"psf_model": psf, "psf_fwhm": psf_fwhm, "moffat_beta": moffat_beta,
            "airy_lambda_d": airy_lambda_d or airy_zero / AIRY_ZERO_PER_LAMBDA_D}
