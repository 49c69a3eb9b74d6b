"""Star detection: matched filter, k-sigma threshold, connected components, screening.

Steps (paper §2.1, read as docs/PAPER.md "Single-frame extraction" says; the paper's "denoising, background estimation, foreground
extraction, connected components, morphology, screening, moments + second-order fit"):

1. background level and noise maps (:func:`starlog.detect.estimate_background`);
2. denoising: the background-subtracted frame is smoothed with a Gaussian of
   ``filter_sigma`` px (a matched filter for a Gaussian PSF);
3. foreground: pixels whose filtered value exceeds ``threshold`` times the filtered noise;
4. morphology: a 3x3 cross opening removes one-pixel bridges and specks;
5. connected components (external contours for the boxes, then ``cv2.connectedComponents``
   with 8-connectivity inside each box), screened by
   area; each component's local maxima of the filtered image are peaks, and a component with
   several peaks separated by a significant saddle is split (flag ``BLENDED``);
6. screening: hot pixels and cosmic-ray hits are rejected because they are sharper than any
   PSF (the mean of the two horizontal, or the two vertical, neighbours of the peak pixel
   is below ``sharpness_ratio`` of it and more than 8 noise sigma below it), and so are
   footprints elongated beyond
   ``max_elongation``; saturated stars are kept and flagged ``SATURATED``; stars within
   ``border`` pixels of the edge are flagged ``BORDER``;
7. coarse position: the intensity moments of the peak's 5x5 neighbourhood, refined by a
   three-point log-parabola (second-order Gaussian) fit through the filtered image's peak
   pixel and its neighbours in x and in y (the moment is kept when the fit is not possible).

Coordinates: x = column, y = row, 0-based, (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import numpy.typing as npt

from starlog.detect._flags import StarFlag
from starlog.detect.background import Background, estimate_background
from starlog.errors import InvalidInputError, InvalidParameterError

__all__ = ["DETECTION_DTYPE", "DetectionWarning", "detect_stars", "empty_detections"]

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
    LOW_SNR, MASKED).
"""


_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))


class DetectionWarning(UserWarning):
    """A frame cannot hold stars (no finite pixel): the result is empty."""


def empty_detections() -> npt.NDArray[np.void]:
    """Return a (0,) array of :data:`DETECTION_DTYPE`."""
    return np.zeros(0, dtype=DETECTION_DTYPE)


def _gather(img: npt.NDArray[np.float32], yc: npt.NDArray[np.intp], xc: npt.NDArray[np.intp], r: int) -> npt.NDArray[np.float32]:
    """(n, 2r+1, 2r+1) boxes of ``img`` around (yc, xc), edge pixels replicated."""
    d = np.arange(-r, r + 1)
    rr = np.clip(yc[:, None] + d, 0, img.shape[0] - 1)
    cc = np.clip(xc[:, None] + d, 0, img.shape[1] - 1)
    return img[rr[:, :, None], cc[:, None, :]]


def _edge_noise_factor(k1: npt.NDArray[np.float64], dist: npt.NDArray[np.intp]) -> npt.NDArray[np.float64]:
    """Filtered-noise inflation at ``dist`` px from an edge with BORDER_REFLECT (1 = none).

    Reflection folds the kernel onto the frame, so near an edge the same pixels are counted
    twice and the filtered noise is larger than ``noise * sum(k1^2)`` along that axis.
    """
    r = k1.size // 2
    base = np.sqrt(np.sum(k1**2))
    fac = np.ones(r + 1)
    for d in range(r + 1):
        w = np.zeros(d + r + 1)
        for j in range(-r, r + 1):
            i = d + j
            w[i if i >= 0 else -i - 1] += k1[j + r]
        fac[d] = np.sqrt(np.sum(w**2)) / base
    return np.where(dist <= r, fac[np.clip(dist, 0, r)], 1.0)


def _log_parabola(fm: npt.NDArray[np.float64], f0: npt.NDArray[np.float64], fp: npt.NDArray[np.float64]) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_]]:
    """Vertex offset of the parabola through (-1, ln fm), (0, ln f0), (1, ln fp)."""
    ok = (fm > 0) & (f0 > 0) & (fp > 0)
    with np.errstate(all="ignore"):
        lm, l0, lp = np.log(np.where(ok, fm, 1)), np.log(np.where(ok, f0, 1)), np.log(np.where(ok, fp, 1))
        den = lm - 2.0 * l0 + lp
        off = 0.5 * (lm - lp) / den
    ok &= (den < 0) & (np.abs(off) <= 1.0)
    return np.where(ok, off, 0.0), ok


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
        Hot-pixel / cosmic-ray test: reject a candidate whose peak pixel (the filtered image's
        maximum) stands more than 8 noise sigma above the mean of its two horizontal or of its
        two vertical neighbours, that mean being below this fraction of it. 0.2 accepts Gaussian PSFs with
        sigma >= ~0.55 px.
    max_elongation : float
        Reject candidates with a larger axis ratio (cosmic-ray tracks); blends are exempt.
    elongation_flag : float
        Flag ``ELONGATED`` above this axis ratio.
    deblend : bool
        Split components with several significant peaks.
    deblend_nsigma, deblend_contrast : float
        A secondary peak is kept when it rises above the saddle towards a brighter peak by
        more than ``deblend_nsigma`` filtered-noise sigma and ``deblend_contrast`` of its value.
    max_stars : int, optional
        Keep only the brightest ``max_stars`` detections.
    background : Background, optional
        A precomputed background; estimated otherwise.

    Returns
    -------
    ndarray of DETECTION_DTYPE, shape (n,)
        Detections sorted by decreasing flux (``star`` = row index). Empty (shape (0,))
        for a frame without stars, a constant frame, or (with a :class:`DetectionWarning`)
        a frame without finite pixels.
    """
    arr = np.asarray(image)
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
    if saturation is None:
        saturation = float(np.iinfo(arr.dtype).max) if np.issubdtype(arr.dtype, np.integer) else np.inf
    integer = np.issubdtype(arr.dtype, np.integer)
    finite = None if integer else np.isfinite(arr)
    all_finite = integer or bool(finite.all())
    if not all_finite and not finite.any():
        warnings.warn("the frame has no finite pixel; no star detected.", DetectionWarning, stacklevel=2)
        return empty_detections()
    if background is None:
        src = arr if all_finite else np.where(finite, arr, np.nan)
        background = estimate_background(src, mesh=mesh)
    bg = background
    if tuple(bg.shape) != arr.shape:
        raise InvalidInputError(f"the background is for shape {bg.shape}, the image is {arr.shape}.")
    if not np.isfinite(bg.global_level):
        warnings.warn("the frame has no usable background; no star detected.", DetectionWarning, stacklevel=2)
        return empty_detections()
    work = arr
    if not all_finite:  # never touch the caller's array: a copy with holes filled by the level
        work = np.where(finite, arr, bg.level).astype(np.float32)
    elif arr.dtype != np.float32:
        work = arr.astype(np.float32)  # cv2 filters float32 fastest
    rows, cols = arr.shape
    r = max(1, int(np.ceil(2.0 * filter_sigma)))
    k1 = cv2.getGaussianKernel(2 * r + 1, filter_sigma, cv2.CV_64F).ravel()
    knorm = float(np.sum(k1**2))  # filtered white-noise sigma = noise * sum(k1^2)
    # matched filter on the raw frame; the smooth background passes through unchanged, so the
    # threshold map is level + k * filtered noise (both interpolated from the cell grids)
    gimg = cv2.sepFilter2D(work, cv2.CV_32F, k1, k1, borderType=cv2.BORDER_REFLECT)
    thr_map = bg.map(bg.mesh_level, plus=np.float32(threshold * knorm) * bg.mesh_noise)
    binary = cv2.compare(gimg, thr_map, cv2.CMP_GT)
    binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, _CROSS)
    # connected components: external contours give each component's bounding box cheaply;
    # inside the box the component is relabelled (8-connectivity) to separate neighbours
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return empty_detections()
    rects = np.array([cv2.boundingRect(c) for c in contours], dtype=np.intp).reshape(-1, 4)
    seeds = np.array([c[0].ravel()[:2] for c in contours], dtype=np.intp).reshape(-1, 2)
    big = rects[:, 2] * rects[:, 3] >= min_area
    rects, seeds = rects[big], seeds[big]
    if rects.shape[0] == 0:
        return empty_detections()
    # boxes that overlap another box need relabelling inside (a neighbour may poke in)
    x0s, y0s = rects[:, 0], rects[:, 1]
    x1s, y1s = x0s + rects[:, 2], y0s + rects[:, 3]
    if rects.shape[0] <= 2000:
        ov = (x0s[:, None] < x1s[None, :]) & (x0s[None, :] < x1s[:, None]) & (y0s[:, None] < y1s[None, :]) & (y0s[None, :] < y1s[:, None])
        shared = ov.sum(axis=1) > 1
    else:
        shared = np.ones(rects.shape[0], bool)
    cx = rects[:, 0] + 0.5 * (rects[:, 2] - 1)
    cy = rects[:, 1] + 0.5 * (rects[:, 3] - 1)
    clev = bg.level_at(cx, cy)
    cnf = bg.noise_at(cx, cy) * knorm
    kernel3 = np.ones((3, 3), np.uint8)
    P_y: list[int] = []
    P_x: list[int] = []
    P_f: list[float] = []
    P_bl: list[bool] = []
    P_share: list[float] = []
    P_area: list[int] = []
    P_box: list[tuple[int, int, int, int]] = []
    for i in range(rects.shape[0]):
        x0, y0, wd, ht = (int(v) for v in rects[i])
        x1, y1 = x0 + wd, y0 + ht
        bcrop = binary[y0:y1, x0:x1]
        if shared[i]:
            nl, lcrop = cv2.connectedComponents(bcrop, connectivity=8)
            lm = lcrop == lcrop[seeds[i, 1] - y0, seeds[i, 0] - x0] if nl > 2 else bcrop > 0
        else:
            lm = bcrop > 0
        area = int(np.count_nonzero(lm))
        if area < min_area or area > max_area:
            continue
        f = gimg[y0:y1, x0:x1]
        lev = np.float32(clev[i])
        comp_flux = float(np.sum(work[y0:y1, x0:x1][lm], dtype=np.float64)) - area * float(clev[i])
        if area == 1:
            yy = np.zeros(1, np.intp)
            xx = np.zeros(1, np.intp)
            yy[0], xx[0] = np.argwhere(lm)[0]
            fv = np.array([float(f[yy[0], xx[0]] - lev)])
            kept = [0]
        else:
            yy, xx = np.nonzero((f >= cv2.dilate(f, kernel3)) & lm)
            if yy.size == 0:  # the maximum sits on a pixel the opening removed: take the top one
                j = int(np.argmax(np.where(lm, f, -np.inf)))
                yy, xx = np.array([j // wd]), np.array([j % wd])
            fv = f[yy, xx].astype(np.float64) - float(lev)
            if yy.size > 1:
                order = np.argsort(-fv, kind="stable")
                yy, xx, fv = yy[order], xx[order], fv[order]
            kept = [0]
            if deblend and yy.size > 1:
                fl = f - lev
                for j in range(1, yy.size):
                    ok = True
                    for m in kept:
                        n = int(max(abs(yy[j] - yy[m]), abs(xx[j] - xx[m]))) + 1
                        t = np.linspace(0.0, 1.0, n + 1)
                        ys = np.rint(yy[j] + t * (yy[m] - yy[j])).astype(np.intp)
                        xs = np.rint(xx[j] + t * (xx[m] - xx[j])).astype(np.intp)
                        prom = fv[j] - float(fl[ys, xs].min())
                        if prom <= max(deblend_nsigma * cnf[i], deblend_contrast * fv[j]):
                            ok = False
                            break
                    if ok:
                        kept.append(j)
        tot = float(np.sum(fv[kept]))
        for j in kept:
            P_y.append(y0 + int(yy[j]))
            P_x.append(x0 + int(xx[j]))
            P_f.append(float(fv[j]))
            P_bl.append(len(kept) > 1)
            P_share.append(comp_flux * (fv[j] / tot if tot > 0 else 1.0 / len(kept)))
            P_area.append(area)
            P_box.append((x0, x1 - 1, y0, y1 - 1))
    if not P_y:
        return empty_detections()
    py = np.asarray(P_y, np.intp)
    px = np.asarray(P_x, np.intp)
    areas = np.asarray(P_area, np.int32)
    boxes = np.asarray(P_box, np.int32).reshape(-1, 4)
    fval = np.asarray(P_f, np.float64)
    blended = np.asarray(P_bl, bool)
    flux = np.asarray(P_share, np.float64)
    n = py.size
    flags = np.zeros(n, np.uint16)
    flags[blended] |= np.uint16(StarFlag.BLENDED)
    level = bg.level_at(px, py)
    noise = bg.noise_at(px, py)
    # raw neighbourhood tests (hot pixels, cosmic rays, saturation)
    raw = _gather(work, py, px, 2).astype(np.float64)  # (n, 5, 5)
    box = raw - level[:, None, None]
    c3 = box[:, 1:4, 1:4].reshape(n, 9)
    jmax = np.argmax(c3, axis=1)
    ar = np.arange(n)
    peak = c3[ar, jmax]
    # sharpness at the filtered image's peak pixel (where a hot pixel or a track is; for a star
    # it is the pixel nearest its centre, more robust than the brightest noisy pixel)
    cval = box[:, 2, 2]
    hmean = 0.5 * (box[:, 2, 1] + box[:, 2, 3])
    vmean = 0.5 * (box[:, 1, 2] + box[:, 3, 2])
    nmin = np.minimum(hmean, vmean)
    # a spike far above what noise can do (any detectable hot pixel is > 10 sigma) and narrower
    # than any PSF; noise spikes on faint stars are left alone by the significance condition
    sharp = (cval - nmin > 8.0 * noise) & (nmin < sharpness_ratio * cval)
    sat = (raw[:, 1:4, 1:4] >= saturation).reshape(n, 9).any(axis=1)
    flags[sat] |= np.uint16(StarFlag.SATURATED)
    sharp &= ~sat
    # elongation from second moments of the filtered image (7x7, positive part)
    fb = np.clip(_gather(gimg, py, px, 3).astype(np.float64) - level[:, None, None], 0, None)
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
    elong = np.maximum(np.sqrt(l1 / l2), 1.0)
    too_long = (elong > max_elongation) & ~blended & ~sat
    flags[elong > elongation_flag] |= np.uint16(StarFlag.ELONGATED)
    keep = ~sharp & ~too_long
    if not keep.all():
        py, px, areas, boxes, fval, blended, flags, box, peak, noise, elong, level, flux = (
            a[keep] for a in (py, px, areas, boxes, fval, blended, flags, box, peak, noise, elong, level, flux)
        )
        n = py.size
    if n == 0:
        return empty_detections()
    # near the frame edge the reflected filter has more noise: apply the true noise there
    fx = _edge_noise_factor(k1, np.minimum(px, cols - 1 - px))
    fy = _edge_noise_factor(k1, np.minimum(py, rows - 1 - py))
    nf = noise * knorm * fx * fy
    edge_ok = fval > threshold * nf
    if not edge_ok.all():
        py, px, areas, boxes, fval, blended, flags, box, peak, noise, elong, level, flux, nf = (
            a[edge_ok] for a in (py, px, areas, boxes, fval, blended, flags, box, peak, noise, elong, level, flux, nf)
        )
        n = py.size
        if n == 0:
            return empty_detections()
    # coarse position: moments of the 5x5 raw box, refined by a 3-point log-parabola on filt
    d5 = np.arange(-2, 3, dtype=np.float64)
    pb = np.clip(box, 0, None)
    w0 = pb.sum(axis=(1, 2))
    w0s = np.where(w0 > 0, w0, 1.0)
    mx = np.where(w0 > 0, (pb * d5[None, None, :]).sum(axis=(1, 2)) / w0s, 0.0)
    my = np.where(w0 > 0, (pb * d5[None, :, None]).sum(axis=(1, 2)) / w0s, 0.0)
    f3 = _gather(gimg, py, px, 1).astype(np.float64) - level[:, None, None]
    ox, okx = _log_parabola(f3[:, 1, 0], f3[:, 1, 1], f3[:, 1, 2])
    oy, oky = _log_parabola(f3[:, 0, 1], f3[:, 1, 1], f3[:, 2, 1])
    x = px + np.where(okx, ox, mx)
    y = py + np.where(oky, oy, my)
    if not all_finite:
        mbox = _gather((~finite).view(np.uint8), py, px, 2).reshape(n, -1).any(axis=1)
        flags[mbox] |= np.uint16(StarFlag.MASKED)
    near = (px < border) | (py < border) | (px >= cols - border) | (py >= rows - border)
    flags[near] |= np.uint16(StarFlag.BORDER)
    snrv = fval / nf
    flags[snrv < 5.0] |= np.uint16(StarFlag.LOW_SNR)
    out = np.zeros(n, dtype=DETECTION_DTYPE)
    out["x"], out["y"] = x, y
    out["x_peak"], out["y_peak"] = px, py
    out["flux"] = flux
    out["peak"] = peak
    out["background"] = level
    out["noise"] = noise
    out["snr"] = snrv
    out["area"] = areas
    out["x_min"], out["x_max"], out["y_min"], out["y_max"] = boxes.T
    out["elongation"] = elong
    out["flags"] = flags
    out = out[np.argsort(-out["flux"], kind="stable")]
    if max_stars is not None:
        out = out[: max(0, int(max_stars))]
    out["star"] = np.arange(out.size, dtype=np.int32)
    return out
