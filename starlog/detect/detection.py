"""Star detection: matched filter, k-sigma threshold, connected components, screening.

Steps (the paper's "denoising, background estimation, foreground extraction, connected
components, morphology, screening, moments + second-order fit"; docs/PAPER.md, "Single-frame extraction"):

1. background level and noise maps (:func:`starlog.detect.estimate_background`);
2. denoising: the background-subtracted frame is smoothed with a Gaussian of
   ``filter_sigma`` px (a matched filter for a Gaussian PSF);
3. foreground: pixels whose filtered value exceeds ``threshold`` times the filtered noise (the
   white-noise prediction, or the frame's measured filtered noise where neighbouring pixels'
   noise is correlated: JPEG, demosaicing, blur; :mod:`starlog.detect.correlated_noise`);
4. morphology: a 3x3 cross opening removes one-pixel bridges and specks;
5. connected components (8-connectivity), screened by area; each component's local maxima
   of the filtered image are peaks, and a component with several peaks separated by a
   significant saddle is split (flag ``BLENDED``) — :mod:`starlog.detect.components`;
6. screening: hot pixels and cosmic-ray hits are rejected because they are sharper than any
   PSF, and so are footprints elongated beyond ``max_elongation``; saturated stars are kept
   and flagged ``SATURATED`` (:mod:`starlog.detect.screening`); a peak that is not significant
   once the filter's larger noise near the frame edge is accounted for is dropped; stars
   within ``border`` pixels of the edge are flagged ``BORDER``;
7. coarse position: the intensity moments of the peak's 5x5 neighbourhood, refined by a
   three-point log-parabola (second-order Gaussian) fit through the filtered image's peak
   pixel and its neighbours in x and in y (:mod:`starlog.detect.position`).

Coordinates: x = column, y = row, 0-based, (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

import functools
import warnings
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from starlog.detect.flags import StarFlag
from starlog.detect.background import Background, estimate_background
from starlog.detect.components import Components, Peaks, component_peaks, find_components
from starlog.detect.correlated_noise import filtered_noise_factor
from starlog.detect.position import coarse_offsets
from starlog.detect.screening import gather, screen
from starlog.errors import InvalidInputError, InvalidParameterError

__all__ = ["DETECTION_DTYPE", "DetectionWarning", "detect_stars", "empty_detections", "matched_filter",
           "matched_filter_kernel"]

DETECTION_DTYPE = np.dtype(
    [
        ("star", np.int32),
        ("x", np.float64),
        ("y", np.float64),
        ("x_peak", np.int32),
        ("y_peak", np.int32),
        ("flux", np.float64),
        ("peak", np.float64),
        ("background", np.float64),
        ("noise", np.float64),
        ("snr", np.float64),
        ("area", np.int32),
        ("x_min", np.int32),
        ("x_max", np.int32),
        ("y_min", np.int32),
        ("y_max", np.int32),
        ("elongation", np.float64),
        ("flags", np.uint16),
    ]
)
"""Structured dtype of :func:`detect_stars` results, one row per detected star.

Fields
------
star : int32
    Index of the detection within the frame, 0..n-1, in order of decreasing ``flux``.
x, y : float64
    Coarse position, px (x = column, y = row, pixel-centre origin): moments refined by a
    three-point log-parabola fit on the filtered image (the ``NONE`` centroid).
x_peak, y_peak : int32
    Pixel of the filtered image's local maximum, px.
flux : float64
    Background-subtracted sum over the star's thresholded footprint (isophotal), DN; for a
    blended component the sum is shared in proportion to the peaks' filtered values.
peak : float64
    Highest background-subtracted pixel value within one pixel of ``(x_peak, y_peak)``, DN.
background : float64
    Local background level at the peak from the background map, DN.
noise : float64
    Local per-pixel background noise (1 sigma) from the noise map, DN.
snr : float64
    Matched-filter signal-to-noise ratio at the peak (filtered value / filtered noise).
area : int32
    Number of pixels of the thresholded footprint (whole component if blended), px.
x_min, x_max, y_min, y_max : int32
    Inclusive bounding box of the footprint, px.
elongation : float64
    Axis ratio (>= 1) from the second moments of the filtered image around the peak.
flags : uint16
    :class:`starlog.detect.DetectionFlag` bits (SATURATED, BORDER, BLENDED, ELONGATED,
    LOW_SNR, MASKED; ARTEFACT is set by :func:`starlog.centroiding.extract_stars`).
"""


_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))


class DetectionWarning(UserWarning):
    """A frame cannot hold stars (no finite pixel): the result is empty."""


def empty_detections() -> npt.NDArray[np.void]:
    """Return a (0,) array of :data:`DETECTION_DTYPE`."""
    return np.zeros(0, dtype=DETECTION_DTYPE)


def detect_stars(
    image: npt.ArrayLike,
    *,
    threshold: float = 5.0,
    filter_sigma: float = 1.5,
    min_area: int = 3,
    max_area: int = 20000,
    saturation: float | None = None,
    border: int = 3,
    mesh: int = 64,
    sharpness_ratio: float = 0.2,
    max_elongation: float = 2.5,
    elongation_flag: float = 1.6,
    deblend: bool = True,
    deblend_nsigma: float = 3.0,
    deblend_contrast: float = 0.05,
    max_stars: int | None = None,
    background: Background | None = None,
    opening: bool = True,
) -> npt.NDArray[np.void]:
    """Detect stars in one frame.

    Parameters
    ----------
    image : (rows, cols) array_like
        Frame in DN (uint8, uint16 or float; bias/background pedestal allowed).
    threshold : float
        Detection threshold in sigma of the matched-filtered noise (k-sigma).
    filter_sigma : float
        Sigma of the Gaussian matched filter, px (close to the PSF sigma is best).
    min_area, max_area : int
        Accepted footprint areas (pixels above threshold).
    saturation : float, optional
        Saturation level, DN. Default: the dtype's maximum for integer images, none for floats.
    border : int
        Stars whose peak lies within ``border`` pixels of the edge are flagged ``BORDER``.
    mesh : int
        Background cell size, px (see :func:`estimate_background`).
    sharpness_ratio : float
        Hot-pixel / cosmic-ray test (:func:`starlog.detect.screening.is_spike`); 0.2 accepts
        Gaussian PSFs with sigma >= ~0.55 px.
    max_elongation, elongation_flag : float
        Reject candidates with a larger axis ratio (cosmic-ray tracks; blends are exempt) /
        flag ``ELONGATED`` above the second.
    deblend : bool
        Split components with several significant peaks.
    deblend_nsigma, deblend_contrast : float
        A secondary peak is kept when it rises above the saddle towards a brighter peak by
        more than ``deblend_nsigma`` filtered-noise sigma and ``deblend_contrast`` of its value.
    max_stars : int, optional
        Keep only the brightest ``max_stars`` detections.
    background : Background, optional
        A precomputed background; estimated otherwise.
    opening : bool
        Open the foreground by a 3x3 cross (step 4). An under-sampled faint star (PSF sigma
        well below a pixel) can have a footprint of one or two pixels, which the opening
        would erase: turn it off (with ``min_area=1``) for such stars.

    Returns
    -------
    ndarray of DETECTION_DTYPE, shape (n,)
        Detections sorted by decreasing flux (``star`` = row index). Empty (shape (0,))
        for a frame without stars, a constant frame, or (with a :class:`DetectionWarning`)
        a frame without finite pixels.
    """
    arr = np.asarray(image)
    _check_parameters(arr, threshold, filter_sigma, min_area, max_area, border, sharpness_ratio, max_elongation,
                      elongation_flag)
    saturation = _default_saturation(arr) if saturation is None else saturation
    frame = _prepare(arr, background, mesh)
    if frame is None:
        return empty_detections()
    work, bg, missing = frame
    filtered, k1 = matched_filter(work, filter_sigma)
    knorm = float(np.sum(k1**2))  # filtered white-noise sigma = noise * sum(k1^2)
    knorm *= filtered_noise_factor(filtered, bg, k1)
    comp = find_components(_foreground(filtered, bg, threshold * knorm, opening=opening), min_area, max_area)
    if comp.count == 0:
        return empty_detections()
    cx, cy = comp.box_centres()
    peaks = component_peaks(comp, filtered, work, bg.level_at(cx, cy), bg.noise_at(cx, cy) * knorm,
                            deblend=deblend, nsigma=deblend_nsigma, contrast=deblend_contrast)
    table, keep = _candidates(peaks, comp, work, filtered, bg, k1, knorm, saturation=saturation,
                              sharpness_ratio=sharpness_ratio, max_elongation=max_elongation,
                              elongation_flag=elongation_flag, threshold=threshold, border=border)
    if missing is not None:
        masked = gather(missing.view(np.uint8), table["y_peak"], table["x_peak"], 2).reshape(table.size, -1)
        table["flags"][masked.any(axis=1)] |= np.uint16(StarFlag.MASKED)
    out = table[keep]
    out = out[np.argsort(-out["flux"], kind="stable")][: None if max_stars is None else max(0, int(max_stars))]
    out["star"] = np.arange(out.size, dtype=np.int32)
    return out


def _foreground(filtered: npt.NDArray[np.float32], bg: Background, filtered_threshold: float, *,
                opening: bool = True) -> npt.NDArray[np.uint8]:
    """Pixels of the filtered frame above level + k * filtered noise, opened by a 3x3 cross.

    The smooth background passes through the filter unchanged, so the threshold map is the
    level plus ``filtered_threshold`` times the noise (both interpolated from the cell grids);
    the opening removes one-pixel bridges and specks.
    """
    above = bg.above(filtered, filtered_threshold)
    return cv2.morphologyEx(above, cv2.MORPH_OPEN, _CROSS) if opening else above


def _default_saturation(arr: npt.NDArray[Any]) -> float:
    return float(np.iinfo(arr.dtype).max) if np.issubdtype(arr.dtype, np.integer) else np.inf


def _check_parameters(arr: npt.NDArray[Any], threshold: float, filter_sigma: float, min_area: int, max_area: int,
                      border: int, sharpness_ratio: float, max_elongation: float, elongation_flag: float) -> None:
    if arr.ndim != 2 or arr.size == 0:
        raise InvalidInputError(f"image must be a non-empty 2-D array; got shape {arr.shape}.")
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise InvalidInputError(f"image must hold integers or floats; got dtype {arr.dtype}.")
    if not (threshold > 0 and filter_sigma > 0 and 1 <= min_area <= max_area and border >= 0):
        raise InvalidParameterError(
            "threshold and filter_sigma must be > 0, 1 <= min_area <= max_area and border >= 0; got "
            f"threshold={threshold!r}, filter_sigma={filter_sigma!r}, min_area={min_area!r}, "
            f"max_area={max_area!r}, border={border!r}."
        )
    if not (0 <= sharpness_ratio < 1 and max_elongation >= 1 and elongation_flag >= 1):
        raise InvalidParameterError(
            "sharpness_ratio must be in [0, 1) and the elongation limits >= 1; got "
            f"{sharpness_ratio!r}, {max_elongation!r}, {elongation_flag!r}."
        )


def _prepare(arr: npt.NDArray[Any], background: Background | None, mesh: int
             ) -> tuple[npt.NDArray[np.float32], Background, npt.NDArray[np.bool_] | None] | None:
    """float32 working copy (holes filled by the background level), the background, and the
    mask of non-finite pixels (None when there is none); None when no star can be detected."""
    finite = None if np.issubdtype(arr.dtype, np.integer) else np.isfinite(arr)
    all_finite = finite is None or bool(finite.all())
    if not all_finite and not finite.any():
        warnings.warn("the frame has no finite pixel; no star detected.", DetectionWarning, stacklevel=3)
        return None
    bg = background
    if bg is None:
        bg = estimate_background(arr if all_finite else np.where(finite, arr, np.nan), mesh=mesh)
    if tuple(bg.shape) != arr.shape:
        raise InvalidInputError(f"the background is for shape {bg.shape}, the image is {arr.shape}.")
    if not np.isfinite(bg.global_level):
        warnings.warn("the frame has no usable background; no star detected.", DetectionWarning, stacklevel=3)
        return None
    if not all_finite:  # never touch the caller's array: a copy with holes filled by the level
        return np.where(finite, arr, bg.level).astype(np.float32), bg, ~finite
    return (arr if arr.dtype == np.float32 else arr.astype(np.float32)), bg, None  # cv2 filters float32 fastest


def matched_filter(work: npt.NDArray[np.float32],
                   filter_sigma: float) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float64]]:
    """The frame smoothed by a Gaussian of ``filter_sigma`` px (reflected at the edges), and the 1-D kernel."""
    k1 = matched_filter_kernel(filter_sigma)
    return cv2.sepFilter2D(work, cv2.CV_32F, k1, k1, borderType=cv2.BORDER_REFLECT), k1


def matched_filter_kernel(filter_sigma: float) -> npt.NDArray[np.float64]:
    """The matched filter's 1-D kernel (2 sigma each side, at least one pixel, unit sum), read-only; the 2-D
    filter is its outer product with itself."""
    return _gaussian_kernel(float(filter_sigma))


@functools.lru_cache(maxsize=8)
def _gaussian_kernel(filter_sigma: float) -> npt.NDArray[np.float64]:
    """:func:`matched_filter_kernel`, made once per sigma."""
    r = max(1, int(np.ceil(2.0 * filter_sigma)))
    k1 = cv2.getGaussianKernel(2 * r + 1, filter_sigma, cv2.CV_64F).ravel()
    k1.flags.writeable = False
    return k1


def _candidates(peaks: Peaks, comp: Components, work: npt.NDArray[np.float32], filtered: npt.NDArray[np.float32],
                bg: Background, k1: npt.NDArray[np.float64], knorm: float, *, saturation: float,
                sharpness_ratio: float, max_elongation: float, elongation_flag: float, threshold: float,
                border: int) -> tuple[npt.NDArray[np.void], npt.NDArray[np.bool_]]:
    """Every peak as a detection row (``star`` not yet set), and which rows pass the screening.

    Compiled (:func:`starlog.detect.peak_kernels.candidate_rows`, then numpy's logarithms for
    the log-parabola, then :func:`~starlog.detect.peak_kernels.coarse_positions`);
    :func:`_candidates_vectorised` is the numpy form, the reference it is tested against.
    """
    from starlog.detect.peak_kernels import candidate_rows, coarse_positions  # numba: compiled on first use

    n = peaks.y.shape
    count = comp.area.shape
    if (len(n) != 1 or any(a.shape != n for a in (peaks.x, peaks.fval, peaks.flux, peaks.blended, peaks.component))
            or any(a.shape != count for a in (comp.x_min, comp.x_max, comp.y_min, comp.y_max))
            or work.ndim != 2 or filtered.shape != work.shape or np.ndim(bg.mesh_level) != 2
            or np.ndim(bg.mesh_noise) != 2 or np.ndim(k1) != 1 or np.size(k1) == 0):
        raise InvalidInputError("_candidates: the peaks', components' or images' arrays have mismatched shapes.")
    out = np.zeros(n, dtype=DETECTION_DTYPE)
    keep = np.empty(n, np.bool_)
    three, moments = np.empty(n + (6,)), np.empty(n + (2,))
    bits = np.array([StarFlag.SATURATED, StarFlag.ELONGATED, StarFlag.BLENDED, StarFlag.BORDER, StarFlag.LOW_SNR],
                    np.uint16)
    i64 = [np.ascontiguousarray(a, np.intp) for a in (peaks.y, peaks.x, peaks.component)]
    f64 = [np.ascontiguousarray(a, np.float64) for a in (peaks.fval, peaks.flux)]
    boxes = [np.ascontiguousarray(a, np.intp) for a in (comp.area, comp.x_min, comp.x_max, comp.y_min, comp.y_max)]
    bad = candidate_rows(
        np.ascontiguousarray(work, np.float32), np.ascontiguousarray(filtered, np.float32),
        np.ascontiguousarray(bg.mesh_level, np.float64), np.ascontiguousarray(bg.mesh_noise, np.float64),
        float(bg.mesh), _edge_noise_table(np.ascontiguousarray(k1, np.float64).tobytes()), *i64, *f64,
        np.ascontiguousarray(peaks.blended, np.bool_), *boxes, float(saturation), float(sharpness_ratio),
        float(max_elongation), float(elongation_flag), float(threshold), float(knorm), int(border), bits,
        *(out[name] for name in ("background", "noise", "peak", "snr", "elongation", "flags")), keep,
        *(out[name] for name in ("x_peak", "y_peak", "flux", "area", "x_min", "x_max", "y_min", "y_max")),
        three, moments)
    if bad >= 0:
        raise InvalidInputError(f"_candidates: peak {bad} belongs to no component.")
    coarse_positions(np.log(three), moments, i64[1], i64[0], out["x"], out["y"])
    return out, keep


def _candidates_vectorised(peaks: Peaks, comp: Components, work: npt.NDArray[np.float32],
                           filtered: npt.NDArray[np.float32], bg: Background, k1: npt.NDArray[np.float64],
                           knorm: float, *, saturation: float, sharpness_ratio: float, max_elongation: float,
                           elongation_flag: float, threshold: float,
                           border: int) -> tuple[npt.NDArray[np.void], npt.NDArray[np.bool_]]:
    """:func:`_candidates` vectorised over the peaks in numpy."""
    py, px, c = peaks.y, peaks.x, peaks.component
    rows, cols = work.shape
    level = bg.level_at(px, py)
    noise = bg.noise_at(px, py)
    raw = gather(work, py, px, 2).astype(np.float64)
    filtered7 = gather(filtered, py, px, 3).astype(np.float64)
    keep, flags, elong = screen(raw, filtered7, level, noise, peaks.blended,
                                saturation=saturation, sharpness_ratio=sharpness_ratio,
                                max_elongation=max_elongation, elongation_flag=elongation_flag)
    # near the frame edge the reflected filter has more noise: apply the true noise there
    fx = _edge_noise_factor(k1, np.minimum(px, cols - 1 - px))
    fy = _edge_noise_factor(k1, np.minimum(py, rows - 1 - py))
    filtered_noise = noise * knorm * fx * fy
    keep &= peaks.fval > threshold * filtered_noise
    box = raw - level[:, None, None]
    dx, dy = coarse_offsets(box, filtered7[:, 2:5, 2:5] - level[:, None, None])
    out = np.zeros(py.size, dtype=DETECTION_DTYPE)
    out["x"], out["y"] = px + dx, py + dy
    out["x_peak"], out["y_peak"] = px, py
    out["flux"] = peaks.flux
    out["peak"] = box[:, 1:4, 1:4].reshape(py.size, 9).max(axis=1)
    out["background"] = level
    out["noise"] = noise
    out["snr"] = peaks.fval / filtered_noise
    out["area"] = comp.area[c]
    out["x_min"], out["x_max"], out["y_min"], out["y_max"] = comp.x_min[c], comp.x_max[c], comp.y_min[c], comp.y_max[c]
    out["elongation"] = elong
    flags[peaks.blended] |= np.uint16(StarFlag.BLENDED)
    flags[(px < border) | (py < border) | (px >= cols - border) | (py >= rows - border)] |= np.uint16(StarFlag.BORDER)
    flags[out["snr"] < 5.0] |= np.uint16(StarFlag.LOW_SNR)
    out["flags"] = flags
    return out, keep


def _edge_noise_factor(k1: npt.NDArray[np.float64], dist: npt.NDArray[np.intp]) -> npt.NDArray[np.float64]:
    """Filtered-noise inflation at ``dist`` px from an edge with BORDER_REFLECT (1 = none).

    Reflection folds the kernel onto the frame, so near an edge the same pixels are counted
    twice and the filtered noise is larger than ``noise * sum(k1^2)`` along that axis.
    """
    fac = _edge_noise_table(k1.tobytes())
    r = fac.size - 1
    return np.where(dist <= r, fac[np.minimum(np.maximum(dist, 0), r)], 1.0)


@functools.lru_cache(maxsize=8)
def _edge_noise_table(kernel: bytes) -> npt.NDArray[np.float64]:
    """:func:`_edge_noise_factor` at 0..r px from the edge for the 1-D kernel (float64 bytes); one per filter."""
    k1 = np.frombuffer(kernel, np.float64)
    r = k1.size // 2
    base = np.sqrt(np.sum(k1**2))
    fac = np.ones(r + 1)
    for d in range(r + 1):
        w = np.zeros(d + r + 1)
        for j in range(-r, r + 1):
            i = d + j
            w[i if i >= 0 else -i - 1] += k1[j + r]
        fac[d] = np.sqrt(np.sum(w**2)) / base
    fac.setflags(write=False)
    return fac
