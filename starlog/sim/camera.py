"""Detector model: shot noise, read noise, gain, bias, quantisation and saturation."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidParameterError

__all__ = ["CameraModel"]


@dataclass(frozen=True, kw_only=True)
class CameraModel:
    """A linear CCD/CMOS camera.

    Attributes
    ----------
    read_noise : float
        Gaussian read noise, electrons RMS.
    gain : float
        Electrons per digital number (e⁻/DN).
    bias : float
        Offset added to every pixel, DN.
    adc_bits : int
        ADC depth; output is clipped to ``[0, 2**adc_bits - 1]`` (saturation).
    full_well : float or None
        Electrons at which a pixel saturates before the ADC (None: no full-well limit).
    """

    read_noise: float = 3.0
    gain: float = 1.0
    bias: float = 100.0
    adc_bits: int = 16
    full_well: float | None = None

    def __post_init__(self) -> None:
        if not (self.read_noise >= 0 and np.isfinite(self.read_noise)):
            raise InvalidParameterError(f"read_noise must be finite and >= 0, got {self.read_noise!r}.")
        if not (self.gain > 0 and np.isfinite(self.gain)):
            raise InvalidParameterError(f"gain must be finite and > 0 (e-/DN), got {self.gain!r}.")
        if not (1 <= self.adc_bits <= 16):
            raise InvalidParameterError(f"adc_bits must be within 1..16, got {self.adc_bits!r}.")
        if not (self.bias >= 0 and self.bias < self.saturation_dn):
            raise InvalidParameterError(
                f"bias must be within [0, {self.saturation_dn}) DN, got {self.bias!r}."
            )
        if self.full_well is not None and not self.full_well > 0:
            raise InvalidParameterError(f"full_well must be > 0, got {self.full_well!r}.")

    @property
    def saturation_dn(self) -> int:
        """Largest digital number the ADC can output."""
        return (1 << self.adc_bits) - 1

    def expose(
        self, expected_electrons: npt.NDArray[np.float64], rng: np.random.Generator
    ) -> npt.NDArray[np.uint16]:
        """Turn an expected-signal image (e⁻, sky included) into a digitised frame.

        Poisson shot noise, then the full well, then Gaussian read noise, then
        ``DN = round(e / gain + bias)`` clipped to the ADC range.
        """
        electrons = rng.poisson(np.clip(expected_electrons, 0.0, None)).astype(np.float64)
        if self.full_well is not None:
            np.minimum(electrons, self.full_well, out=electrons)
        if self.read_noise > 0:
            electrons += rng.normal(0.0, self.read_noise, size=electrons.shape)
        dn = np.rint(electrons / self.gain + self.bias)
        np.clip(dn, 0, self.saturation_dn, out=dn)
        return dn.astype(np.uint16)
