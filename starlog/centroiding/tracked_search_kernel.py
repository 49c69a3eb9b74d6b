"""Compiled (numba): the first of a tracked frame's two calls, :func:`track_search` — where its stars are.

:func:`starlog.centroiding.tracked_frame.track_frame` calls it, then ``scipy.special.erf`` for
each star's model at its coarse position, then :func:`~starlog.centroiding.tracked_measure_kernel.track_measure`.
One pass over the frame for the light check's cell means copies each star's search window while its rows are in
the cache; then the window search and the measurement windows. The numpy forms (tracking's ``new_light``,
``lasting_light``, ``locate_stars``, the windows of ``measure.measure_methods``) are the references: the same
bits, sums over a window in numpy's pairwise order (:mod:`starlog.compiled_numpy`), NaN propagating in maxima as
``np.maximum``. The inputs come in the named tuples built by :mod:`~starlog.centroiding.tracked_frame` (``_Light``,
``_Search``, ``_Stars``, ``_Fit``, ``_Windows``).

numba's cache is refreshed when a function's own file changes, not when a function it calls in another
file does: after editing a kernel that others call, delete the cached code (``find starlog -name '*.nb[ic]'
-delete``, docs/DEVELOPMENT.md). Divisions follow numpy (``error_model="numpy"``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from starlog.centroiding.star_kernels import gather_windows
from starlog.compiled_numpy import block_sum, maximum, pairwise_sum
from starlog.detect.flags import StarFlag

__all__ = ["FINISH", "LOCATED", "MEASURED", "SEARCH", "track_search"]

SEARCH, LOCATED, MEASURED, FINISH = 0, 1, 2, 3
"""Statuses of a tracked frame's calls: the frame must be searched in full; stars located (windows cut); measured
and advanced; fitted, numpy to finish the rows (a window needs the robust re-measurement)."""

_INV_SQ2 = 1.0 / math.sqrt(2.0)
_BORDER, _TRACKED = int(StarFlag.BORDER), int(StarFlag.TRACKED)
_KEPT = int(StarFlag.BLENDED | StarFlag.ELONGATED)
""":class:`~starlog.detect.flags.StarFlag` bits (BLENDED | ELONGATED kept from the acquisition)."""


@njit(cache=True, nogil=True, error_model="numpy")
def _window_rows(rows, half, py):  # type: ignore[no-untyped-def]
    """Which search-window rows each frame row fills (windows of half-size ``half`` on rows ``py``, reflected at
    the frame's edges): entries ``start[i]:start[i + 1]`` of (``star``, ``row``), a counting sort by frame row."""
    side = 2 * half + 1
    start = np.zeros(rows + 1, np.int64)
    for k in range(py.size):
        for a in range(side):
            start[_reflect(py[k] - half + a, rows) + 1] += 1
    for i in range(rows):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    star, row = np.empty(py.size * side, np.int64), np.empty(py.size * side, np.int64)
    for k in range(py.size):
        for a in range(side):
            i = _reflect(py[k] - half + a, rows)
            star[fill[i]], row[fill[i]] = k, a
            fill[i] += 1
    return start, star, row


@njit(cache=True, nogil=True, error_model="numpy")
def _copy_rows(image, i, plan, px, bg, raws):  # type: ignore[no-untyped-def]
    """Frame row ``i`` into the search windows that hold it (``plan``: :func:`_window_rows`), reflected at the
    frame's edges, missing pixels at the star's background, minus it (``_search_windows``)."""
    start, star, row = plan
    cols, side = image.shape[1], raws.shape[1]
    half = side // 2
    for e in range(start[i], start[i + 1]):
        k, a = star[e], row[e]
        for j in range(side):
            v = np.float64(image[i, _reflect(px[k] - half + j, cols)])
            raws[k, a, j] = (v if math.isfinite(v) else bg[k]) - bg[k]


@njit(cache=True, nogil=True, error_model="numpy")
def _sweep(image, cell, exact, cells, plan, px, bg, raws):  # type: ignore[no-untyped-def]
    """One pass over the frame: :func:`starlog.centroiding.tracking.cell_means` into ``cells`` (``exact``: pixels
    summed in unsigned 32-bit integers, integers of up to 16 bits; else in float64 with missing pixels at the
    median of the others), and each row copied into the search windows that hold it while it is in the cache."""
    rows, cols = cells.shape
    width = cols * cell
    height = rows * cell if cells.size else 0
    if height and exact:
        acc = np.zeros(width, np.uint32)
        for r in range(rows):
            acc[:] = 0
            for i in range(r * cell, (r + 1) * cell):
                for j in range(width):
                    acc[j] = np.uint32(acc[j] + np.uint32(image[i, j]))
                _copy_rows(image, i, plan, px, bg, raws)
            for c in range(cols):
                total = np.uint32(0)
                for j in range(c * cell, (c + 1) * cell):
                    total = np.uint32(total + acc[j])
                cells[r, c] = np.float64(total) / (cell * cell)
    elif height:
        fill = _missing_value(image, height, width)
        acc = np.zeros(width)
        for r in range(rows):
            acc[:] = 0.0
            for i in range(r * cell, (r + 1) * cell):
                for j in range(width):
                    v = np.float64(image[i, j])
                    acc[j] += v if math.isfinite(v) else fill
                _copy_rows(image, i, plan, px, bg, raws)
            for c in range(cols):
                cells[r, c] = (0.0 + pairwise_sum(acc, c * cell, cell)) / (cell * cell)
    for i in range(height, image.shape[0]):
        _copy_rows(image, i, plan, px, bg, raws)


@njit(cache=True, nogil=True, error_model="numpy")
def _missing_value(image, height, width):  # type: ignore[no-untyped-def]
    """The median of the finite pixels of ``image[:height, :width]`` when some are not (0 when none is)."""
    finite = 0
    for i in range(height):
        for j in range(width):
            finite += math.isfinite(np.float64(image[i, j]))
    if finite == height * width:
        return 0.0
    if finite == 0:
        return 0.0
    values = np.empty(finite, image.dtype)
    k = 0
    for i in range(height):
        for j in range(width):
            if math.isfinite(np.float64(image[i, j])):
                values[k] = image[i, j]
                k += 1
    return np.float64(np.median(values))


@njit(cache=True, nogil=True, error_model="numpy")
def _new_light(cells, light, stars):  # type: ignore[no-untyped-def]
    """:func:`~starlog.centroiding.tracking.new_light` into ``light.risen``; returns the number of cells risen."""
    rows, cols = cells.shape
    change = cells - light.cells
    free = np.ones((rows, cols), np.bool_)
    n = stars.x.size
    for k in range(n + stars.acquired_x.size):
        x = stars.x[k] + stars.vx[k] if k < n else stars.acquired_x[k - n]
        y = stars.y[k] + stars.vy[k] if k < n else stars.acquired_y[k - n]
        for a in light.steps:
            row = int(min(max((y + a) // light.cell, 0), rows - 1))
            for b in light.steps:
                free[row, int(min(max((x + b) // light.cell, 0), cols - 1))] = False
    common = np.median(change)
    spread = 1.4826 * np.median(np.abs(change - common))
    floor = 0.0
    if n:
        noise = np.empty(n)
        for k in range(n):
            noise[k] = stars.reference[k].noise
        floor = np.median(noise) * math.sqrt(2.0) / light.cell
    level = spread
    if floor > level:
        level = floor
    if 1e-6 > level:
        level = 1e-6
    level = light.sigma * level
    count = 0
    for i in range(rows):
        for j in range(cols):
            light.risen[i, j] = free[i, j] and change[i, j] - common > level + light.excess[i, j]
            count += light.risen[i, j]
    return count


@njit(cache=True, nogil=True, error_model="numpy")
def _lasting(risen, count, before, tracked):  # type: ignore[no-untyped-def]
    """:func:`~starlog.centroiding.tracking.lasting_light` of ``count`` cells risen."""
    if count == 0:
        return False
    if tracked == 0 or count > 2:
        return True
    rows, cols = risen.shape
    if before.shape != risen.shape:
        return False
    for i in range(rows):
        for j in range(cols):
            if not risen[i, j]:
                continue
            for a in range(max(i - 1, 0), min(i + 2, rows)):
                for b in range(max(j - 1, 0), min(j + 2, cols)):
                    if before[a, b]:
                        return True
    return False


@njit(cache=True, nogil=True, error_model="numpy")
def _reflect(i, n):  # type: ignore[no-untyped-def]
    """An index beyond ``[0, n)`` reflected as OpenCV's ``BORDER_REFLECT``, then clipped."""
    if i < 0:
        i = -i - 1
    if i >= n:
        i = 2 * n - i - 1
    return min(max(i, 0), n - 1)


@njit(cache=True, nogil=True, error_model="numpy")
def _smooth(raw, k1, tmp, out):  # type: ignore[no-untyped-def]
    """The separable filter ``k1``, 'valid' part: rows, then columns, the taps added in turn (the numpy form's
    order, :func:`~starlog.centroiding.tracking._filtered`; the loop over pixels innermost, where it vectorises)."""
    taps = k1.size
    inner = raw.shape[0] - taps + 1
    for a in range(raw.shape[0]):
        for j in range(inner):
            tmp[a, j] = k1[0] * raw[a, j]
        for t in range(1, taps):
            for j in range(inner):
                tmp[a, j] = tmp[a, j] + k1[t] * raw[a, j + t]
    for i in range(inner):
        for j in range(inner):
            out[i, j] = k1[0] * tmp[i, j]
        for t in range(1, taps):
            for j in range(inner):
                out[i, j] = out[i, j] + k1[t] * tmp[i + t, j]


@njit(cache=True, nogil=True, error_model="numpy")
def _pick_peak(filt, s, px, py, rows, cols, level, dx, dy):  # type: ignore[no-untyped-def]
    """Index in the search area (2 s + 1)² of the local maximum above ``level`` nearest the offset (dx, dy) from
    its centre, else of its highest pixel (``_nearest_peak``); pixels outside the frame are neither."""
    side = 2 * s + 1
    nearest, best = -1, np.inf
    highest, high = 0, -np.inf
    for cy in range(side):
        out_row = py - s + cy < 0 or py - s + cy >= rows
        for cx in range(side):
            outside = out_row or px - s + cx < 0 or px - s + cx >= cols
            v = filt[cy + 2, cx + 2]
            if (-np.inf if outside else v) > high:
                highest, high = cy * side + cx, v
            if outside or not v >= level:
                continue
            peak = True
            for oy in range(-1, 2):
                for ox in range(-1, 2):
                    peak = peak and v >= filt[cy + 2 + oy, cx + 2 + ox]
            if peak:
                d = ((cy - s) - dy) ** 2 + ((cx - s) - dx) ** 2
                if d < best:
                    nearest, best = cy * side + cx, d
    return nearest if nearest >= 0 else highest


@njit(cache=True, nogil=True, error_model="numpy")
def _log_parabola(fm, f0, fp, fallback):  # type: ignore[no-untyped-def]
    """:func:`starlog.detect.position.log_parabola`'s vertex, or ``fallback`` where it is not valid."""
    if not (fm > 0 and f0 > 0 and fp > 0):
        return fallback
    lm, l0, lp = math.log(fm), math.log(f0), math.log(fp)
    den = lm - 2.0 * l0 + lp
    off = 0.5 * (lm - lp) / den
    return off if den < 0 and abs(off) <= 1.0 else fallback


@njit(cache=True, nogil=True, error_model="numpy")
def _coarse(raw, filt, fy, fx, r, terms):  # type: ignore[no-untyped-def]
    """:func:`starlog.detect.position.coarse_offsets` of the peak at (fy, fx) of the filtered window."""
    for p in range(25):
        terms[p] = maximum(raw[fy + r - 2 + p // 5, fx + r - 2 + p % 5], 0.0)
    w0 = 0.0 + block_sum(terms, 0, 25)
    for p in range(25):
        terms[25 + p] = terms[p] * (p % 5 - 2.0)
        terms[50 + p] = terms[p] * (p // 5 - 2.0)
    mx = (0.0 + block_sum(terms, 25, 25)) / w0 if w0 > 0 else 0.0
    my = (0.0 + block_sum(terms, 50, 25)) / w0 if w0 > 0 else 0.0
    ox = _log_parabola(filt[fy, fx - 1], filt[fy, fx], filt[fy, fx + 1], mx)
    oy = _log_parabola(filt[fy - 1, fx], filt[fy, fx], filt[fy + 1, fx], my)
    return ox, oy


@njit(cache=True, nogil=True, error_model="numpy")
def _locate(shape, k, px, py, search, stars, raw, tmp, filt, terms, row):  # type: ignore[no-untyped-def]
    """:func:`~starlog.centroiding.tracking.locate_stars` of star ``k``, its search window ``raw`` cut around pixel
    (px, py), into the detection ``row``; returns whether it was found."""
    rows, cols = shape
    s, r = search.half, search.kernel.size // 2
    ref = stars.reference[k]
    _smooth(raw, search.kernel, tmp, filt)
    level = search.threshold * ref.noise * search.power
    best = _pick_peak(filt, s, px, py, rows, cols, level,
                      stars.x[k] + stars.vx[k] - px, stars.y[k] + stars.vy[k] - py)
    iy, ix = best // (2 * s + 1), best % (2 * s + 1)
    x_peak, y_peak = px - s + ix, py - s + iy
    inside = 0 <= x_peak < cols and 0 <= y_peak < rows
    snr = (filt[iy + 2, ix + 2] if inside else -np.inf) / (ref.noise * search.power)
    ox, oy = _coarse(raw, filt, iy + 2, ix + 2, r, terms)
    b = search.border
    row.star, row.background, row.noise, row.area, row.elongation = ref.star, ref.background, ref.noise, ref.area, \
        ref.elongation
    row.x, row.y, row.x_peak, row.y_peak = x_peak + ox, y_peak + oy, x_peak, y_peak
    row.flux, row.peak, row.snr = ref.flux, raw[iy + r + 2, ix + r + 2], snr
    row.x_min, row.x_max, row.y_min, row.y_max = x_peak - 2, x_peak + 2, y_peak - 2, y_peak + 2
    flags = (ref.flags & _KEPT) | _TRACKED
    if x_peak < b or x_peak >= cols - b or y_peak < b or y_peak >= rows - b:
        flags |= _BORDER
    row.flags = flags
    on_edge = iy == 0 or iy == 2 * s or ix == 0 or ix == 2 * s
    return snr >= search.threshold and not on_edge and inside and math.isfinite(snr)


@njit(cache=True, nogil=True, error_model="numpy")
def _grow_saturation(data, valid, satpix, h, level):  # type: ignore[no-untyped-def]
    """:func:`starlog.centroiding.stamps.grown_saturation` of one saturated window: the valid pixels at least
    ``level`` joined to its saturated ones (8-neighbours, as many rings as it grows, ``2 h + 1`` at most) turn
    saturated, invalid and 0."""
    w = data.shape[0]
    sat, grown = satpix.copy(), np.empty_like(satpix)
    for _ in range(2 * h + 1):
        changed = False
        for i in range(w):
            for j in range(w):
                near = sat[i, j]
                for a in range(max(i - 1, 0), min(i + 2, w)):
                    for b in range(max(j - 1, 0), min(j + 2, w)):
                        near |= sat[a, b]
                grown[i, j] = sat[i, j] or (near and valid[i, j] and data[i, j] >= level)
                changed |= grown[i, j] != sat[i, j]
        if not changed:
            break
        sat[:, :] = grown
    for i in range(w):
        for j in range(w):
            if sat[i, j] and not satpix[i, j]:
                satpix[i, j], valid[i, j], data[i, j] = True, False, 0.0


@njit(cache=True, nogil=True, error_model="numpy")
def _cut_windows(image, detections, fit, windows):  # type: ignore[no-untyped-def]
    """The measurement windows of the located stars as ``measure_methods`` cuts them (``_star_stamps``, a saturated
    core's shoulders saturated too), the pixels each leaves out, and the error function's arguments of each star's
    model at its coarse position."""
    n, w = detections.size, windows.data.shape[1]
    rows, cols = image.shape
    h = fit.half
    for k in range(n):
        det = detections[k]
        noise = maximum(det.noise, fit.noise_floor)
        windows.noise[k] = noise if math.isfinite(noise) and noise > 0 else 1.0
        windows.background[k] = det.background if math.isfinite(det.background) else 0.0
        windows.flux0[k] = det.flux
        windows.xc[k], windows.yc[k] = int(np.rint(det.x)), int(np.rint(det.y))
        windows.dx0[k], windows.dy0[k] = det.x - windows.xc[k], det.y - windows.yc[k]
        for j in range(w + 1):
            windows.arguments[k, 0, j] = (fit.edges[j] - windows.dx0[k]) / fit.psf * _INV_SQ2
            windows.arguments[k, 1, j] = (fit.edges[j] - windows.dy0[k]) / fit.psf * _INV_SQ2
    gather_windows(image, windows.xc, windows.yc, h, windows.background, fit.saturation, windows.data, windows.valid,
                   windows.satpix, windows.flags)
    for k in range(n):
        if windows.flags[k, 0]:
            _grow_saturation(windows.data[k], windows.valid[k], windows.satpix[k], h,
                             fit.shoulder * (fit.saturation - windows.background[k]))
    for k in range(n):
        inside_rows = inside_cols = invalid = 0
        for d in range(-h, h + 1):
            inside_rows += 0 <= windows.yc[k] + d < rows
            inside_cols += 0 <= windows.xc[k] + d < cols
        for i in range(w):
            for j in range(w):
                windows.valid_f[k, i, j] = windows.valid[k, i, j]
                invalid += not windows.valid[k, i, j] and not windows.satpix[k, i, j]
        windows.left_out[k] = invalid - (w * w - inside_rows * inside_cols)


@njit(cache=True, nogil=True, error_model="numpy")
def track_search(image, light, search, stars, fit, windows, detections, found):  # type: ignore[no-untyped-def]
    """The light check and the window search of a tracked frame (and, when ``windows`` holds a row per star,
    the measurement windows): SEARCH when the frame must be searched in full, else LOCATED."""
    rows, cols = image.shape
    n = stars.x.size
    half = search.half + 2 + search.kernel.size // 2
    px, py, bg = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n)
    for k in range(n):
        px[k] = int(min(max(np.rint(stars.x[k] + stars.vx[k]), 0), cols - 1))
        py[k] = int(min(max(np.rint(stars.y[k] + stars.vy[k]), 0), rows - 1))
        bg[k] = stars.reference[k].background
    raws = np.empty((n, 2 * half + 1, 2 * half + 1))
    cells = np.empty(light.cells.shape)
    _sweep(image, light.cell, light.exact, cells, _window_rows(rows, half, py), px, bg, raws)
    if light.cells.size and _lasting(light.risen, _new_light(cells, light, stars), light.before, n):
        return SEARCH
    inner = 2 * half + 2 - search.kernel.size
    tmp, filt, terms = np.empty((2 * half + 1, inner)), np.empty((inner, inner)), np.empty(75)
    for k in range(n):
        found[k] = _locate(image.shape, k, px[k], py[k], search, stars, raws[k], tmp, filt, terms, detections[k])
        if not found[k] and not stars.quiet[k] and not search.just_acquired:
            return SEARCH
    if windows.data.shape[0] == n:
        _cut_windows(image, detections, fit, windows)
    return LOCATED

