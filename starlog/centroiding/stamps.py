"""Star windows (stamps), the pixel-integrated Gaussian model, smoothing.

A stamp is the (2h+1) x (2h+1) window centred on the integer pixel nearest the coarse
position; offsets ``u = -h..h`` are relative to that centre pixel. Pixels outside the frame,
non-finite or saturated are invalid (``valid`` False, ``data`` 0) and left out everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.special import erf

from starlog.errors import InvalidInputError

__all__ = [
    "DETECTION_FIELDS",
    "INV_SQRT_2PI",
    "Stamps",
    "check_detections",
    "check_image",
    "default_saturation",
    "gather_stamps",
    "with_saturated",
    "grown_saturation",
    "profile_1d",
    "model",
    "linear_flux",
    "fisher_sigma",
    "smooth",
    "optimal_smoothing",
    "per_star",
    "pixel_edges",
    "pixel_profiles",
    "variance",
]

_SQ2 = np.sqrt(2.0)
INV_SQRT_2PI = 1.0 / np.sqrt(2.0 * np.pi)
F64 = npt.NDArray[np.float64]


DETECTION_FIELDS = ("star", "x", "y", "background", "noise", "flux", "flags")


def check_image(image: npt.ArrayLike) -> npt.NDArray[Any]:
    """``image`` as an array, :class:`InvalidInputError` unless a non-empty 2-D array of integers or floats."""
    arr = np.asarray(image)
    if arr.ndim != 2 or arr.size == 0:
        raise InvalidInputError(f"image must be a non-empty 2-D array; got shape {arr.shape}.")
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise InvalidInputError(f"image must hold integers or floats; got dtype {arr.dtype}.")
    return arr


def check_detections(detections: npt.NDArray[Any]) -> npt.NDArray[Any]:
    """``detections`` as an array, :class:`InvalidInputError` unless 1-D with the fields the windows are cut from."""
    det = np.asarray(detections)
    names = det.dtype.names or ()
    missing = [f for f in DETECTION_FIELDS if f not in names]
    if missing or det.ndim != 1:
        raise InvalidInputError(
            f"detections must be a 1-D structured array with fields {DETECTION_FIELDS} (DETECTION_DTYPE); "
            f"missing {missing}, shape {det.shape}."
        )
    return det


def default_saturation(arr: npt.NDArray[Any], saturation: float | None) -> float:
    """``saturation``, or without one the frame's: its type's maximum for integers, none (inf) for floats."""
    if saturation is not None:
        return float(saturation)
    return float(np.iinfo(arr.dtype).max) if np.issubdtype(arr.dtype, np.integer) else np.inf



def per_star(value: npt.ArrayLike, n: int, name: str) -> F64:
    """``value`` as a new contiguous float64 array of one value per star (a scalar is repeated), as the
    compiled loops take it; :class:`InvalidInputError` when it holds another number of values."""
    arr = np.asarray(value, np.float64)
    if arr.ndim == 0:
        return np.full(n, float(arr))
    if arr.shape != (n,):
        raise InvalidInputError(f"{name} must hold one value per star ({n}); got shape {arr.shape}.")
    return np.array(arr, np.float64, order="C")


@dataclass
class Stamps:
    """Windows of N stars (all arrays have N rows)."""

    data: F64  # (N, W, W) background-subtracted DN, 0 where invalid
    valid: npt.NDArray[np.bool_]  # (N, W, W)
    xc: npt.NDArray[np.intp]  # window centre column
    yc: npt.NDArray[np.intp]  # window centre row
    h: int
    background: F64  # (N,) DN
    noise: F64  # (N,) DN, background 1-sigma per pixel
    gain: float
    saturated: npt.NDArray[np.bool_]
    cut: npt.NDArray[np.bool_]  # window cut by the frame edge
    masked: npt.NDArray[np.bool_]  # non-finite pixels in the window
    satpix: npt.NDArray[np.bool_]  # (N, W, W) saturated pixels inside the frame
    clip: F64  # (N,) saturation level above the background, DN (inf: none)

    @property
    def u(self) -> F64:
        return np.arange(-self.h, self.h + 1, dtype=np.float64)


def gather_stamps(
    image: npt.NDArray[np.generic],
    x: F64,
    y: F64,
    h: int,
    background: F64,
    noise: F64,
    gain: float,
    saturation: float,
) -> Stamps:
    """Cut the windows around (x, y) out of ``image`` (never modified); compiled
    (:func:`starlog.centroiding.star_kernels.gather_windows`), the same arrays as :func:`gather_stamps_vectorised`."""
    from starlog.centroiding.star_kernels import gather_windows  # numba: imported, and compiled, on first use

    xc = np.rint(x).astype(np.intp)
    yc = np.rint(y).astype(np.intp)
    n, w = xc.size, 2 * h + 1
    if yc.shape != (n,) or h < 0:
        raise InvalidInputError(f"x and y must hold one value per star and h >= 0; got {yc.shape}, {h}.")
    if image.ndim != 2 or 0 in image.shape:
        raise InvalidInputError(f"star windows are cut from a non-empty 2-D image; got shape {image.shape}.")
    if image.dtype.kind == "f" and image.dtype.itemsize not in (4, 8):  # float16, longdouble: not compiled
        image = image.astype(np.float64)  # exact for float16; longdouble rounds as astype(float64) did
    bg = per_star(background, n, "background")
    data, valid, satpix = np.empty((n, w, w)), np.empty((n, w, w), np.bool_), np.empty((n, w, w), np.bool_)
    flags = np.empty((n, 3), np.bool_)
    if not image.dtype.isnative:  # compiled code reads native byte order only
        image = image.astype(image.dtype.newbyteorder("="))
    gather_windows(image, xc, yc, h, bg, float(saturation), data, valid, satpix, flags)
    return grown_saturation(Stamps(data=data, valid=valid, xc=xc, yc=yc, h=h,
                                   background=np.asarray(background, np.float64), noise=np.asarray(noise, np.float64),
                                   gain=float(gain), saturated=flags[:, 0], cut=flags[:, 1], masked=flags[:, 2],
                                   satpix=satpix, clip=float(saturation) - np.asarray(background, np.float64)))


def gather_stamps_vectorised(
    image: npt.NDArray[np.generic],
    x: F64,
    y: F64,
    h: int,
    background: F64,
    noise: F64,
    gain: float,
    saturation: float,
) -> Stamps:
    """:func:`gather_stamps` in numpy: the reference the tests compare the compiled loop with."""
    rows, cols = image.shape
    xc = np.rint(x).astype(np.intp)
    yc = np.rint(y).astype(np.intp)
    d = np.arange(-h, h + 1)
    rr = yc[:, None] + d
    cc = xc[:, None] + d
    inr = (rr >= 0) & (rr < rows)
    inc = (cc >= 0) & (cc < cols)
    raw = image[np.minimum(np.maximum(rr, 0), rows - 1)[:, :, None],
                np.minimum(np.maximum(cc, 0), cols - 1)[:, None, :]].astype(np.float64)
    inside = inr[:, :, None] & inc[:, None, :]
    fin = np.isfinite(raw)
    sat = raw >= saturation
    valid = inside & fin & ~sat
    data = np.where(valid, raw - background[:, None, None], 0.0)
    return grown_saturation(Stamps(
        data=data,
        valid=valid,
        xc=xc,
        yc=yc,
        h=h,
        background=np.asarray(background, np.float64),
        noise=np.asarray(noise, np.float64),
        gain=float(gain),
        saturated=(sat & inside).any(axis=(1, 2)),
        cut=~inside.all(axis=(1, 2)),
        masked=(~fin & inside).any(axis=(1, 2)),
        satpix=sat & inside,
        clip=float(saturation) - np.asarray(background, np.float64),
    ))


SHOULDER = 0.9
"""A pixel touching a saturated one (8-neighbours, repeatedly) and at least this fraction of the saturation level
above the background is saturated too (:func:`grown_saturation`)."""


def grown_saturation(st: Stamps) -> Stamps:
    """The stamps with the shoulders of each saturated core counted as saturated: the valid pixels within
    :data:`SHOULDER` of the saturation level, connected to a saturated pixel. Such a pixel is clipped too:
    a lossy codec's ringing spreads a clipped plateau's level over its neighbours (values just under the top),
    and a sensor's response bends before its full well; kept as data, they give a fit a flat top."""
    if not st.saturated.any():
        return st
    rows = np.flatnonzero(st.saturated)
    sat, valid = st.satpix[rows].copy(), st.valid[rows]
    high = valid & (st.data[rows] >= SHOULDER * st.clip[rows][:, None, None])
    for _ in range(2 * st.h + 1):
        grown = sat.copy()
        grown[:, 1:, :] |= sat[:, :-1, :]
        grown[:, :-1, :] |= sat[:, 1:, :]
        grown[:, :, 1:] |= grown[:, :, :-1].copy()
        grown[:, :, :-1] |= grown[:, :, 1:].copy()
        grown = sat | (grown & high)
        if np.array_equal(grown, sat):
            break
        sat = grown
    added = sat & ~st.satpix[rows]
    if not added.any():
        return st
    satpix, valid_all, data = st.satpix.copy(), st.valid.copy(), st.data.copy()
    satpix[rows] = sat
    valid_all[rows] &= ~added
    data[rows] = np.where(added, 0.0, data[rows])
    return replace(st, satpix=satpix, valid=valid_all, data=data)


def with_saturated(st: Stamps) -> Stamps:
    """The stamps with saturated pixels kept at their (clipped) value, for non-fit methods."""
    if not st.saturated.any():
        return st
    data = np.where(st.satpix, st.clip[:, None, None], st.data)
    return replace(st, data=data, valid=st.valid | st.satpix)


def pixel_edges(u: F64) -> F64:
    """The W + 1 pixel edges of consecutive integer offsets ``u``."""
    return (u[0] - 0.5) + np.arange(u.size + 1, dtype=np.float64)


def _sigma_column(s: F64 | float, n: int) -> F64 | float:
    """``s`` as a per-row column (n, 1), or the scalar itself (the same quotients either way)."""
    arr = np.asarray(s, np.float64)
    return float(arr) if arr.ndim == 0 else np.broadcast_to(arr, (n,))[:, None]


def pixel_profiles(t: F64) -> F64:
    """Pixel-integrated unit Gaussian of the pixel edges ``t`` in sigma units (rows, W + 1) -> (rows, W)."""
    cdf = erf(t * (1.0 / _SQ2))
    return 0.5 * (cdf[:, 1:] - cdf[:, :-1])


def profile_1d(u: F64, c: F64, s: F64 | float, deriv: bool = False) -> tuple[F64, F64 | None, F64 | None]:
    """Pixel-integrated unit Gaussian along one axis, (N, W), and its c and s derivatives.

    ``u`` must be consecutive integers (pixel offsets); the W + 1 pixel edges are evaluated once.
    """
    sc = _sigma_column(s, c.shape[0])
    t = (pixel_edges(u)[None, :] - c[:, None]) / sc  # (N, W + 1)
    e = pixel_profiles(t)
    if not deriv:
        return e, None, None
    pdf = INV_SQRT_2PI * np.exp(-0.5 * t * t)
    de_dc = -(pdf[:, 1:] - pdf[:, :-1]) / sc
    tp = t * pdf
    de_ds = -(tp[:, 1:] - tp[:, :-1]) / sc
    return e, de_dc, de_ds


def model(st: Stamps, cx: F64, cy: F64, s: F64 | float) -> F64:
    """Unit-flux pixel-integrated Gaussian at window offsets (cx, cy), (N, W, W).

    Both axes in one evaluation (the same values as :func:`profile_1d` along each).
    """
    n = cx.shape[0]
    sc = _sigma_column(s, n)
    if not isinstance(sc, float):
        sc = np.concatenate([sc, sc])
    t = (pixel_edges(st.u)[None, :] - np.concatenate([cx, cy])[:, None]) / sc
    e = pixel_profiles(t)
    return e[n:, :, None] * e[:n, None, :]


def variance(st: Stamps, signal: F64) -> F64:
    """Per-pixel variance, DN^2: background noise^2 + star shot noise (signal in DN / gain)."""
    return st.noise[:, None, None] ** 2 + np.maximum(signal, 0.0) / st.gain


def linear_flux(st: Stamps, m: F64, flux0: F64 | None = None, iterations: int = 2) -> tuple[F64, F64]:
    """Weighted least-squares amplitude of the unit model ``m`` (no background term).

    Returns the flux (DN) and its 1-sigma error (DN).
    """
    f = np.maximum(np.asarray(flux0, np.float64), 0.0) if flux0 is not None else np.zeros(m.shape[0])
    if flux0 is None:
        iterations += 1
    den = np.ones(m.shape[0])
    for _ in range(iterations):
        w = st.valid / variance(st, f[:, None, None] * m)
        num = (w * m * st.data).sum(axis=(1, 2))
        den = (w * m * m).sum(axis=(1, 2))
        f = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    err = 1.0 / np.sqrt(np.where(den > 0, den, np.inf))
    return f, np.where(np.isfinite(err), err, np.inf)


def fisher_sigma(st: Stamps, cx: F64, cy: F64, flux: F64, s: F64 | float) -> F64:
    """Per-axis Cramer-Rao sigma (px) of a star with known flux, PSF and background.

    ``sqrt((I_xx + I_yy) / 2 / det I)`` of the Fisher information of the centre,
    ``I_ab = sum_ij w_ij (d mu / d a)(d mu / d b)`` with ``w`` the inverse pixel variance
    (:func:`variance`) of the model ``mu = F ey (x) ex``; compiled
    (:func:`starlog.centroiding.star_kernels.fisher_sigmas`). inf where it cannot be inverted.
    """
    from starlog.centroiding.star_kernels import fisher_sigmas  # numba: imported, and compiled, on first use

    n = st.data.shape[0]
    out = np.empty(n)
    fisher_sigmas(np.ascontiguousarray(st.valid, np.float64), per_star(st.noise, n, "noise"), float(st.gain),
                  pixel_edges(st.u), per_star(cx, n, "cx"), per_star(cy, n, "cy"), per_star(flux, n, "flux"),
                  per_star(s, n, "s"), out)
    return out


def smooth(data: F64, s: F64) -> F64:
    """Smooth each (W, W) window with its own Gaussian of sigma ``s`` px (0 = none).

    The kernel is normalised over its full extent (zero padding beyond the window), so the
    operation is linear and the same on data and model.
    """
    n, w, _ = data.shape
    u = np.arange(w, dtype=np.float64)
    diff = u[:, None] - u[None, :]
    ss = np.maximum(s, 1e-3)[:, None, None]
    k = np.exp(-0.5 * diff[None] ** 2 / ss**2)
    k /= np.sqrt(2 * np.pi) * ss  # unit area (approximately, for ss >~ 0.5)
    k = np.where((s > 0.05)[:, None, None], k, np.eye(w)[None])
    return np.matmul(np.matmul(k, data), k.transpose(0, 2, 1))  # k @ data @ kᵀ per window


def optimal_smoothing(flux: F64, noise: F64, gain: float, psf_sigma: F64 | float, t_max: float = 2.5) -> F64:
    """Gaussian weight sigma (px) minimising the variance of a Gaussian-weighted centroid.

    Continuous-Gaussian approximation: with PSF sigma s (pixel-integrated: s^2 + 1/12),
    weight sigma w, flux F (DN), background variance v0 (DN^2) and gain g,
    ``Var = [(F/g) sd^4/s^2 + v0 pi w^4/2] / [F (sc^2/s^2) w^2/(s^2+w^2)]^2`` with
    ``sc^2 = s^2 w^2/(s^2+w^2)`` and ``sd^2 = s^2 (w^2/2)/(s^2+w^2/2)``. It gives ``w = s``
    for background-limited stars and a wide (flat) weight for photon-limited ones.
    """
    s2 = (np.broadcast_to(np.asarray(psf_sigma, np.float64), flux.shape) ** 2 + 1.0 / 12.0)[:, None]
    t = np.linspace(0.8, t_max, 35)[None, :]
    w2 = t * t * s2
    sc2 = s2 * w2 / (s2 + w2)
    sd2 = s2 * (w2 / 2) / (s2 + w2 / 2)
    f = np.maximum(flux, 1e-9)[:, None]
    num = (f / gain) * sd2 * sd2 / s2 + (noise**2)[:, None] * np.pi * w2 * w2 / 2
    den = (f * (sc2 / s2) * w2 / (s2 + w2)) ** 2
    best = np.argmin(num / den, axis=1)
    return np.sqrt(w2[np.arange(flux.size), best])
