"""The matched-filtered frame's noise measured, for frames whose noise is not white.

The detector's threshold is ``threshold`` times the filtered noise, predicted from the per-pixel
noise as ``noise * sum(k1^2)`` (``k1`` the filter's 1-D kernel): exact when neighbouring pixels'
noise is independent, as a sensor's read and shot noise are. Processing that mixes neighbouring
pixels breaks that: JPEG's 8x8 block quantisation and ringing, demosaicing, defocus applied to
the noise, interpolation. Then the filtered noise is several times the prediction, and the
threshold passes hundreds of noise peaks a frame.

The filtered noise is measured on the frame itself, from its lower tail: stars only add light,
so the values below the background level are noise alone however dense the field. On a grid of
about 16,000 pixels (every ``stride``-th row and column, at least the filter's reach apart, so
that their filtered noise is nearly independent), ``z = (filtered - level) / (noise *
sum(k1^2))`` has, for white Gaussian noise, a 2.28 % quantile of -2; the factor is that quantile
over -2. On white noise it stays within about 0.9-1.15 (the quantile's sampling error on 16,000
pixels, and the background's clipped noise estimate); it is applied only above
:data:`WHITE_NOISE_LIMIT`, so frames of independent pixel noise are detected exactly as the white
prediction says.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from starlog.detect.background import Background

__all__ = ["WHITE_NOISE_LIMIT", "filtered_noise_factor"]

WHITE_NOISE_LIMIT = 1.3
"""Measured over predicted filtered noise above which the frame's noise is taken as correlated."""

_TAIL, _TAIL_SIGMA = 0.0228, 2.0  # the standard normal's 2.28 % quantile is -2.0
_SAMPLES = 16384


def filtered_noise_factor(filtered: npt.NDArray[np.float32], bg: Background, k1: npt.NDArray[np.float64]) -> float:
    """The filtered frame's noise over its white-noise prediction ``noise * sum(k1^2)`` (module
    docstring; ``k1`` the filter's 1-D kernel); 1.0 when it is within :data:`WHITE_NOISE_LIMIT` or
    cannot be measured. Pixels the kernel's reach from an edge are left out: the reflected filter
    counts pixels twice there, which raises the noise of white noise too."""
    knorm = float(np.sum(k1**2))
    reach = k1.size // 2
    rows, cols = filtered.shape
    stride = max(reach + 1, int(np.sqrt(max(rows - 2 * reach, 0) * max(cols - 2 * reach, 0) / _SAMPLES)))
    ys = np.arange(reach + stride // 2, rows - reach, stride)
    xs = np.arange(reach + stride // 2, cols - reach, stride)
    if ys.size * xs.size * _TAIL < 10:
        return 1.0
    level, noise = bg.level_noise_grid(ys, xs)
    scale = noise * knorm
    z = (filtered[ys[0]::stride, xs[0]::stride][: ys.size, : xs.size] - level) / np.where(scale > 0, scale, np.nan)
    z = z[np.isfinite(z)]
    k = int(_TAIL * z.size)
    if k < 10:
        return 1.0
    factor = float(-np.partition(z, k)[k] / _TAIL_SIGMA)
    return factor if factor > WHITE_NOISE_LIMIT else 1.0
