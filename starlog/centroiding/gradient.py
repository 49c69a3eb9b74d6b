"""GRADIENT: radial-symmetry centre (Parthasarathy 2012, Nature Methods 9, 724).

Intensity gradients are taken at the pixel corners (Roberts cross, as in the paper) of the
window, smoothed with the noise-optimal Gaussian. Each gradient defines a line through its
corner; the centre is the point closest, in the weighted least-squares sense, to all lines,
with weights ``|grad|^2 / distance-to-centre`` (the paper's weighting; the distance to the
previous estimate, starting from the gradient-weighted centroid). Lines are handled through
their normals, so vertical/horizontal gradients need no special case. Two passes.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from starlog.centroiding.stamps import Stamps, smooth

__all__ = ["radial_symmetry_centre"]

F64 = npt.NDArray[np.float64]


def radial_symmetry_centre(data: F64, st: Stamps, *, smooth_sigma: F64, passes: int = 2) -> tuple[F64, F64, npt.NDArray[np.bool_]]:
    """Radial-symmetry centre of each window, offsets from the window centre (px)."""
    sm = smooth(np.where(st.valid, data, 0.0), smooth_sigma)
    u = st.u
    cu = u[:-1] + 0.5  # corner coordinates
    gx = 0.5 * ((sm[:, :-1, 1:] - sm[:, :-1, :-1]) + (sm[:, 1:, 1:] - sm[:, 1:, :-1]))
    gy = 0.5 * ((sm[:, 1:, :-1] - sm[:, :-1, :-1]) + (sm[:, 1:, 1:] - sm[:, :-1, 1:]))
    vmask = st.valid[:, :-1, :-1] & st.valid[:, 1:, :-1] & st.valid[:, :-1, 1:] & st.valid[:, 1:, 1:]
    g2 = (gx * gx + gy * gy) * vmask
    px = cu[None, None, :]
    py = cu[None, :, None]
    s0 = g2.sum(axis=(1, 2))
    ok = s0 > 0
    s0 = np.where(ok, s0, 1.0)
    cx = (g2 * px).sum(axis=(1, 2)) / s0
    cy = (g2 * py).sum(axis=(1, 2)) / s0
    # normal of the gradient line: (-gy, gx); line: nx*(X - px) + ny*(Y - py) = 0
    nx, ny = -gy, gx
    c_p = nx * px + ny * py
    for _ in range(passes):
        d = np.sqrt((px - cx[:, None, None]) ** 2 + (py - cy[:, None, None]) ** 2)
        w = vmask / np.maximum(d, 0.25)
        a11 = (w * nx * nx).sum(axis=(1, 2))
        a12 = (w * nx * ny).sum(axis=(1, 2))
        a22 = (w * ny * ny).sum(axis=(1, 2))
        b1 = (w * nx * c_p).sum(axis=(1, 2))
        b2 = (w * ny * c_p).sum(axis=(1, 2))
        det = a11 * a22 - a12 * a12
        good = det > 0
        det = np.where(good, det, 1.0)
        ncx = (a22 * b1 - a12 * b2) / det
        ncy = (a11 * b2 - a12 * b1) / det
        ok &= good & np.isfinite(ncx) & np.isfinite(ncy)
        cx = np.where(ok, ncx, cx)
        cy = np.where(ok, ncy, cy)
    ok &= (np.abs(cx) < st.h) & (np.abs(cy) < st.h)
    return cx, cy, ok
