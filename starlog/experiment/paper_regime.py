"""The ``paper`` regime: dataset conditions derived from the paper's own numbers (docs/PAPER_REGIME.md).

The paper's uncompensated RMSEs (Table 2: 0.32–0.45 px, "the discrete nature of the star
points"; Table 3: GAUSSFIT 0.10–0.36 px, MOMENT 0.90–0.93 px, BICUBIC 1.5–1.8 px, GRADIENT
2.4–3.1 px) are those of an under-sampled star at low SNR, seen through a filter that does not
average the centroids away (Table 2's STATIC figure equals Table 3's NONE "before").  Each
constant below comes from one of those numbers; the derivation is in docs/PAPER_REGIME.md.
Frame counts, rates and platform jitter are the ``modern`` regime's; the field is smaller
(64×64 px, 3 stars: only the brightest star is scored, and the run costs half as much).
"""

from __future__ import annotations

import math
from typing import Any

__all__ = ["BRIGHTEST_SNR", "CENTROID", "PSF_SIGMA_PX", "SIMULATION", "SKY_E", "STEP_DIFFUSION_PX", "motion_for"]

#: Gaussian PSF sigma, px: under-sampled (most of the flux in one pixel), so the pixel-phase
#: S-curve of the centroid methods is real.
PSF_SIGMA_PX = 0.4
#: Sky background, e⁻/px (with the camera's 3 e⁻ read noise: sigma_bg = sqrt(100 + 9) ≈ 10.4 e⁻).
SKY_E = 100.0
#: Flux of the brightest star over the background noise per pixel, F / sigma_bg: GAUSSFIT's
#: per-axis Cramér–Rao bound sqrt(8 pi) * s * sigma_bg / F (s² = PSF_SIGMA_PX² + 1/12) equal to
#: the paper's GAUSSFIT "before" (≈ 0.12 px radial, 0.085 px per axis) gives F / sigma_bg ≈ 29.
BRIGHTEST_SNR = math.sqrt(8 * math.pi) * math.sqrt(PSF_SIGMA_PX**2 + 1 / 12) / (0.12 / math.sqrt(2))
#: The tracker's per-frame position diffusion of every model, px (q_floor · dt = this²): the
#: paper's filter output keeps the single-frame scatter (its Table 2 STATIC = Table 3 NONE
#: before), so its STATIC model moves by the discretisation scale, half a pixel, per frame.
STEP_DIFFUSION_PX = 0.5

_SIGMA_BG = math.sqrt(SKY_E + 3.0**2)
_F_MAX = BRIGHTEST_SNR * _SIGMA_BG

#: Simulator settings that differ from the ``modern`` regime.
SIMULATION: dict[str, Any] = {
    "width": 64,
    "height": 64,
    "n_stars": 3,
    "psf_sigma": PSF_SIGMA_PX,
    "sky": SKY_E,
    "flux_max": _F_MAX,
    "flux_min": _F_MAX / 3.0,
}


def motion_for(fps: float) -> dict[str, Any]:
    """Motion-model options: ``q_floor = STEP_DIFFUSION_PX² · fps`` px²/s (one step = one frame)."""
    return {"q_floor": STEP_DIFFUSION_PX**2 * float(fps)}


#: Centroid-stage options: the detector's hot-pixel (sharpness) test is off — an under-sampled
#: star is as sharp as a hot pixel, and the simulated camera has none.
CENTROID: dict[str, Any] = {"detect_options": {"sharpness_ratio": 0.0}}
