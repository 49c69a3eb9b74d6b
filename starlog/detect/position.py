"""Coarse star position: peak-window moments refined by a three-point log-parabola fit.

The intensity moments of the 5x5 background-subtracted window around the peak pixel give a
first offset; a parabola through the logarithms of the filtered image at the peak pixel and
its two neighbours, in x and in y separately (a second-order Gaussian fit, exact for a
Gaussian profile), replaces it wherever the three values are positive and the vertex lies
within one pixel::

    dx = (ln f(-1) - ln f(+1)) / (2 (ln f(-1) - 2 ln f(0) + ln f(+1)))

Offsets are in px from the peak pixel (x = column, y = row).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["coarse_offsets", "log_parabola"]

F64 = npt.NDArray[np.float64]


def log_parabola(fm: F64, f0: F64, fp: F64) -> tuple[F64, npt.NDArray[np.bool_]]:
    """Vertex offset of the parabola through (-1, ln fm), (0, ln f0), (1, ln fp), and where it is valid."""
    ok = (fm > 0) & (f0 > 0) & (fp > 0)
    with np.errstate(all="ignore"):
        lm, l0, lp = np.log(np.where(ok, fm, 1)), np.log(np.where(ok, f0, 1)), np.log(np.where(ok, fp, 1))
        den = lm - 2.0 * l0 + lp
        off = 0.5 * (lm - lp) / den
    ok &= (den < 0) & (np.abs(off) <= 1.0)
    return np.where(ok, off, 0.0), ok


def coarse_offsets(box: F64, filtered: F64) -> tuple[F64, F64]:
    """(dx, dy) of each star from its peak pixel.

    ``box``: (n, 5, 5) background-subtracted raw windows centred on the peak pixel;
    ``filtered``: (n, 3, 3) background-subtracted filtered windows, same centre.
    """
    d5 = np.arange(-2, 3, dtype=np.float64)
    pb = np.maximum(box, 0)
    w0 = pb.sum(axis=(1, 2))
    w0s = np.where(w0 > 0, w0, 1.0)
    mx = np.where(w0 > 0, (pb * d5[None, None, :]).sum(axis=(1, 2)) / w0s, 0.0)
    my = np.where(w0 > 0, (pb * d5[None, :, None]).sum(axis=(1, 2)) / w0s, 0.0)
    ox, okx = log_parabola(filtered[:, 1, 0], filtered[:, 1, 1], filtered[:, 1, 2])
    oy, oky = log_parabola(filtered[:, 0, 1], filtered[:, 1, 1], filtered[:, 2, 1])
    return np.where(okx, ox, mx), np.where(oky, oy, my)
