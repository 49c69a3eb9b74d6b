"""NONE: the coarse position, a three-point log-parabola (second-order Gaussian) fit.

The window is smoothed with a Gaussian of the noise-optimal width (``optimal_smoothing``:
the PSF sigma for faint stars, wider for bright ones), its highest pixel near the centre is
found and a parabola is fitted to the logarithms of that pixel and its two neighbours, in x
and in y separately (exact for a Gaussian profile)::

    dx = (ln f(-1) - ln f(+1)) / (2 (ln f(-1) - 2 ln f(0) + ln f(+1)))
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from starlog.centroiding.stamps import Stamps, smooth

__all__ = ["log_parabola_peak", "peak_pixel"]

F64 = npt.NDArray[np.float64]


def peak_pixel(sm: F64, reach: int) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """Row/column (window indices) of each window's maximum within ``reach`` of the centre."""
    n, w, _ = sm.shape
    h = w // 2
    r = min(reach, h - 1)
    core = sm[:, h - r : h + r + 1, h - r : h + r + 1].reshape(n, -1)
    j = np.argmax(core, axis=1)
    return h - r + j // (2 * r + 1), h - r + j % (2 * r + 1)


def log_parabola_peak(data: F64, st: Stamps, *, smooth_sigma: F64, reach: int = 2) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Log-parabola peak of the smoothed windows, offsets from the window centre (px)."""
    sm = smooth(np.where(st.valid, data, 0.0), smooth_sigma)
    n = sm.shape[0]
    h = st.h
    iy, ix = peak_pixel(sm, reach)
    ar = np.arange(n)
    f0 = sm[ar, iy, ix]
    out = []
    oks = []
    for fm, fp in ((sm[ar, iy, ix - 1], sm[ar, iy, ix + 1]), (sm[ar, iy - 1, ix], sm[ar, iy + 1, ix])):
        good = (fm > 0) & (f0 > 0) & (fp > 0)
        with np.errstate(all="ignore"):
            lm, l0, lp = (np.log(np.where(good, v, 1.0)) for v in (fm, f0, fp))
            den = lm - 2 * l0 + lp
            off = 0.5 * (lm - lp) / den
        good &= (den < 0) & (np.abs(off) <= 1)
        out.append(np.where(good, off, 0.0))
        oks.append(good)
    return ix - h + out[0], iy - h + out[1], oks[0] & oks[1]
