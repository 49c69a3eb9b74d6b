"""The ``paper`` regime: dataset conditions derived from the paper's own numbers (docs/PAPER_REGIME.md).

The paper's uncompensated RMSEs (Table 2: 0.32–0.45 px, "the discrete nature of the star
points during imaging"; its "minor perturbations" of the platform) are those of a faint,
under-sampled star whose single-frame centroid scatter the filter passes on.  Each constant
below comes from one of the paper's numbers or from a rule stated beside it; the derivation,
and the alternatives measured and dropped, are in docs/PAPER_REGIME.md.  Frame counts, rates
and platform perturbation are the ``modern`` regime's.
"""

from __future__ import annotations

import math
from typing import Any

__all__ = [
    "CENTROID",
    "COAST_S",
    "CONFIRM_HITS",
    "GATE_SIGMA_PX",
    "MAX_DISTANCE_PX",
    "PSF_SIGMA_PX",
    "READ_NOISE_E",
    "SIMULATION",
    "SNR_200HZ",
    "STEP_DIFFUSION_PX",
    "motion_for",
    "simulation_for",
    "snr_for",
    "tracker_for",
]

#: Gaussian PSF sigma, px: under-sampled (≈ 62 % of a centred star's flux in one pixel).
PSF_SIGMA_PX = 0.4
#: Read noise, e⁻ RMS, of a dark laboratory (no sky): the background noise of a frame does not
#: grow with its exposure, so a star's per-frame SNR scales with the exposure, 1 / frame rate.
READ_NOISE_E = 10.0
#: The star's flux over the background noise per pixel, F / sigma_bg, at 200 Hz: where the
#: pipeline's own Table 2 figure (STATIC, NONE, 5/10 Hz) of the 200 Hz dataset equals the
#: paper's (0.317–0.323 px); the 300 Hz dataset's SNR then follows from the exposure
#: (:func:`snr_for`), and its Table 2 figure is a prediction, not a fit.
SNR_200HZ = 7.0
#: The tracker's per-frame position diffusion of every model, px (q_floor · dt = this²): large
#: against the centroid scatter at this SNR (≈ 0.2–0.3 px per axis), so the filter's gain is
#: ≈ 0.9–0.95 and its output keeps the single-frame scatter, as the paper's 0.3–0.45 px
#: (> 10× what a running mean of 60–300 samples would leave) shows its filter did.
STEP_DIFFUSION_PX = 1.0
#: The per-axis centroid scatter the paper's Table 2 implies (0.45 px radial / √2 ≈ 0.32 px,
#: rounded up), px: the scale of the association limit below.
GATE_SIGMA_PX = 0.35
#: Largest distance between a track's prediction and an associated centroid, px: the
#: 99.99 % chi-square(2) innovation gate (√18.42 = 4.29) of a star known to ``GATE_SIGMA_PX``.
#: A coasting track's own gate grows every missed frame; without this limit it reaches
#: noise peaks pixels away and follows them.
MAX_DISTANCE_PX = math.sqrt(18.42) * GATE_SIGMA_PX
#: Applied measurements that confirm a track: at 300 Hz the star is detected in ≈ 20 % of the
#: frames, so three in a row (the tracker's default) come once every 1/0.2³ = 125 frames and a
#: short dataset may never confirm it; two come once every 25 frames, while two false
#: detections (≈ 0.07 per frame) within ``MAX_DISTANCE_PX`` of each other come about once in
#: 10⁵ frames.
CONFIRM_HITS = 2
#: How long a confirmed track coasts without a centroid before it is dropped, s: at 300 Hz the
#: star is detected in ≈ 20 % of the frames, and a gap of 0.19 s (57 frames) then occurs with
#: a probability below 1 % over the whole dataset (0.8⁵⁷ × 3248 < 0.01).
COAST_S = 0.25

#: Simulator settings that differ from the ``modern`` regime (the flux is per dataset:
#: :func:`simulation_for`).  One star: only the brightest is scored, and fainter ones at this
#: SNR would not be detected at all.
SIMULATION: dict[str, Any] = {
    "width": 64,
    "height": 64,
    "n_stars": 1,
    "psf_sigma": PSF_SIGMA_PX,
    "sky": 0.0,
}

#: Centroid-stage options: the PSF width is the optics' (not estimated from faint frames); the
#: detector is a matched filter of the pixel-integrated PSF's width (sqrt(sigma² + 1/12) =
#: 0.49 px) at 4 sigma without the 3×3 opening (a faint under-sampled star has a footprint of
#: one or two pixels), and its hot-pixel (sharpness) test is off — such a star is as sharp as a
#: hot pixel, and the simulated camera has none.
CENTROID: dict[str, Any] = {
    "psf_sigma": PSF_SIGMA_PX,
    "detect_options": {"sharpness_ratio": 0.0, "filter_sigma": round(math.sqrt(PSF_SIGMA_PX**2 + 1 / 12), 2),
                       "threshold": 4.0, "opening": False, "min_area": 1},
}


def snr_for(fps: float) -> float:
    """F / sigma_bg of a frame at ``fps``: ``SNR_200HZ · 200 / fps`` (exposure = frame period)."""
    return SNR_200HZ * 200.0 / float(fps)


def simulation_for(fps: float) -> dict[str, Any]:
    """:data:`SIMULATION` with the star's flux at ``fps`` and the dark laboratory's camera."""
    flux = snr_for(fps) * READ_NOISE_E
    return {**SIMULATION, "flux_min": flux, "flux_max": flux, "camera": {"read_noise": READ_NOISE_E}}


def motion_for(fps: float) -> dict[str, Any]:
    """Motion-model options: ``q_floor = STEP_DIFFUSION_PX² · fps`` px²/s (one step = one frame)."""
    return {"q_floor": STEP_DIFFUSION_PX**2 * float(fps)}


def tracker_for(fps: float) -> dict[str, Any]:
    """Tracker options: the association limit, ``CONFIRM_HITS`` and ``COAST_S`` of coasting (frames at ``fps``)."""
    return {"max_distance": round(MAX_DISTANCE_PX, 3), "max_missed": int(math.ceil(COAST_S * float(fps))),
            "confirm_hits": CONFIRM_HITS}
