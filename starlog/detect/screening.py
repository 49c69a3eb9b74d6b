"""Screening of detection candidates: hot pixels, cosmic rays, saturation, elongation.

Each test works on small stacks of windows centred on the candidates' peak pixels (one row
per candidate), so the whole frame is screened in a few array operations:

- :func:`is_spike`: a hot pixel or a cosmic-ray hit is sharper than any PSF — the mean of the
  two horizontal, or of the two vertical, neighbours of the peak pixel is below
  ``sharpness_ratio`` of it and more than 8 noise sigma below it (a Gaussian PSF of sigma
  >= ~0.55 px passes at ratio 0.2; noise spikes on faint stars fail the significance part);
- :func:`elongation`: the axis ratio from the second moments of the filtered image's
  positive part around the peak (cosmic-ray tracks are long, stars round);
- :func:`screen`: both tests, the saturation flag and the keep decision.

Coordinates: x = column, y = row, 0-based, (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.detect.flags import StarFlag

__all__ = ["elongation", "gather", "is_spike", "screen"]

F64 = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]


def gather(img: npt.NDArray[Any], yc: npt.NDArray[np.intp], xc: npt.NDArray[np.intp], r: int) -> npt.NDArray[Any]:
    """(n, 2r+1, 2r+1) windows of ``img`` centred on (yc, xc), edge pixels replicated."""
    d = np.arange(-r, r + 1)
    rr = np.clip(yc[:, None] + d, 0, img.shape[0] - 1)
    cc = np.clip(xc[:, None] + d, 0, img.shape[1] - 1)
    return img[rr[:, :, None], cc[:, None, :]]


def is_spike(box: F64, noise: F64, sharpness_ratio: float) -> Mask:
    """Hot pixel / cosmic-ray test on (n, 5, 5) background-subtracted windows centred on the peak."""
    centre = box[:, 2, 2]
    horizontal = 0.5 * (box[:, 2, 1] + box[:, 2, 3])
    vertical = 0.5 * (box[:, 1, 2] + box[:, 3, 2])
    lowest = np.minimum(horizontal, vertical)
    # a spike far above what noise can do (any detectable hot pixel is > 10 sigma) and narrower
    # than any PSF; noise spikes on faint stars are left alone by the significance condition
    return (centre - lowest > 8.0 * noise) & (lowest < sharpness_ratio * centre)


def elongation(filtered: F64) -> F64:
    """Axis ratio (>= 1) from the second moments of (n, 7, 7) background-subtracted filtered windows.

    Only the positive part counts; an empty window gives 1.
    """
    fb = np.clip(filtered, 0, None)
    d = np.arange(-3, 4, dtype=np.float64)
    s0 = fb.sum(axis=(1, 2))
    s0 = np.where(s0 > 0, s0, 1.0)
    mx = (fb * d[None, None, :]).sum(axis=(1, 2)) / s0
    my = (fb * d[None, :, None]).sum(axis=(1, 2)) / s0
    dx = d[None, None, :] - mx[:, None, None]
    dy = d[None, :, None] - my[:, None, None]
    sxx = (fb * dx * dx).sum(axis=(1, 2)) / s0
    syy = (fb * dy * dy).sum(axis=(1, 2)) / s0
    sxy = (fb * dx * dy).sum(axis=(1, 2)) / s0
    tr, det = sxx + syy, sxx * syy - sxy**2
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0))
    l1, l2 = tr / 2 + disc, np.maximum(tr / 2 - disc, 1e-12)
    return np.maximum(np.sqrt(l1 / l2), 1.0)


def screen(
    raw: F64,
    filtered: F64,
    level: F64,
    noise: F64,
    blended: Mask,
    *,
    saturation: float,
    sharpness_ratio: float,
    max_elongation: float,
    elongation_flag: float,
) -> tuple[Mask, npt.NDArray[np.uint16], F64]:
    """Screen candidates from their (n, 5, 5) raw and (n, 7, 7) filtered windows around the peak.

    Saturated candidates are kept (flag ``SATURATED``) and exempt from the spike test; blends
    and saturated stars are exempt from the elongation limit. Returns the keep mask, the flags
    (SATURATED, ELONGATED) and the elongation.
    """
    flags = np.zeros(raw.shape[0], np.uint16)
    box = raw - level[:, None, None]
    sat = (raw[:, 1:4, 1:4] >= saturation).reshape(raw.shape[0], 9).any(axis=1)
    flags[sat] |= np.uint16(StarFlag.SATURATED)
    sharp = is_spike(box, noise, sharpness_ratio) & ~sat
    elong = elongation(filtered - level[:, None, None])
    too_long = (elong > max_elongation) & ~blended & ~sat
    flags[elong > elongation_flag] |= np.uint16(StarFlag.ELONGATED)
    return ~sharp & ~too_long, flags, elong
