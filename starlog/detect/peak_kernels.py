"""Compiled (numba): the per-candidate glue of star detection.

The numpy forms work on a few thousand pixels or a few dozen peaks a frame, so their time is
the fixed cost of many small array operations, not arithmetic. Here each pixel or peak is a
plain loop, giving the same bits as the numpy forms, which stay as the references the tests
compare with:

- :func:`member_pixels` — the pixel listing of
  :func:`starlog.detect.components.find_components_vectorised` (boxes' foreground pixels,
  seed-connected ones where boxes overlap);
- :func:`local_maxima` — :func:`starlog.detect.components._local_maxima_vectorised`;
- :func:`candidate_rows` and :func:`coarse_positions` —
  :func:`starlog.detect.detection._candidates_vectorised`: the background at the peak
  (:meth:`Background.level_at <starlog.detect.background.Background.level_at>`, ``noise_at``),
  the windows of :func:`~starlog.detect.screening.gather`,
  :func:`~starlog.detect.screening.screen`, the edge noise factor and
  :func:`~starlog.detect.position.coarse_offsets`.

Same bits: float64 sums over a window add its values in the order of numpy's pairwise
summation (:func:`starlog.compiled_numpy.block_sum`), float32 values are widened where numpy widens them, maxima
and minima propagate NaN as ``np.maximum`` does, and the logarithms of the log-parabola are
taken by numpy itself between the two kernels (numpy's SIMD ``log`` and the C library's
differ in the last bit for a fraction of values).

One module: numba's cache is refreshed when a function's own file changes, not when a function it
calls in another file does (after editing :mod:`starlog.compiled_numpy`, delete the cached code:
``find starlog -name '*.nb[ic]' -delete``). Divisions follow numpy (``error_model="numpy"``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from starlog.compiled_numpy import block_sum, maximum, minimum


@njit(cache=True, nogil=True, error_model="numpy")
def local_maxima(filtered, y, x, label, x_min, x_max, y_min, y_max, peak):  # type: ignore[no-untyped-def]
    """``peak[i]``: pixel ``(y[i], x[i])`` of component ``label[i]`` is not below any 8-neighbour
    inside the component's box; a component without such a pixel gets its brightest (first in
    pixel order; NaN counts as the faintest). Returns -1, or the index of a component
    whose box is not inside the frame or of a pixel outside its box (nothing is read from there)."""
    rows, cols = filtered.shape
    count = x_min.size
    for c in range(count):
        if not (0 <= x_min[c] <= x_max[c] < cols and 0 <= y_min[c] <= y_max[c] < rows):
            return c
    has_peak = np.zeros(count, np.bool_)
    lonely = count
    for i in range(y.size):
        c, yi, xi = label[i], y[i], x[i]
        if not (0 <= c < count and y_min[c] <= yi <= y_max[c] and x_min[c] <= xi <= x_max[c]):
            return i
        # the 3 x 3 neighbourhood clamped to the box: a clamped index repeats a pixel of the
        # neighbourhood, which changes no maximum (one tree of comparisons, no branch per neighbour)
        r0, r2 = max(yi - 1, y_min[c]), min(yi + 1, y_max[c])
        c0, c2 = max(xi - 1, x_min[c]), min(xi + 1, x_max[c])
        up, mid, down = filtered[r0], filtered[yi], filtered[r2]
        f = mid[xi]
        top = maximum(maximum(maximum(up[c0], up[xi]), maximum(up[c2], mid[c0])),
                      maximum(maximum(mid[c2], down[c0]), maximum(down[xi], down[c2])))
        peak[i] = f >= maximum(top, f)
        if peak[i] and not has_peak[c]:
            has_peak[c] = True
            lonely -= 1
    if lonely == 0:
        return -1
    best = np.full(count, -1, np.intp)
    for i in range(y.size):
        c = label[i]
        if has_peak[c]:
            continue
        b = best[c]
        if b < 0:
            best[c] = i
            continue
        f, fb = filtered[y[i], x[i]], filtered[y[b], x[b]]
        if f > fb or (fb != fb and f == f):  # the brightest, NaN the faintest; ties: the first
            best[c] = i
    for c in range(count):
        if best[c] >= 0:
            peak[best[c]] = True
    return -1


@njit(cache=True, nogil=True, error_model="numpy")
def _axis_weights(c, n, mesh, extrapolate):  # type: ignore[no-untyped-def]
    """:func:`starlog.detect.background._axis_weights` for one coordinate."""
    if n == 1:
        return 0, 0, 1.0, 0.0
    f = (c + 0.5) / mesh - 0.5
    if not extrapolate:
        f = min(max(f, 0.0), n - 1.0)
    i0 = min(max(int(math.floor(f)), 0), n - 2)
    t = f - i0
    return i0, i0 + 1, np.float64(np.float32(1.0 - t)), np.float64(np.float32(t))


@njit(cache=True, nogil=True, error_model="numpy")
def _interp(grid, mesh, x, y, extrapolate):  # type: ignore[no-untyped-def]
    """:meth:`starlog.detect.background.Background._interp` at one point (``grid`` in float64)."""
    y0, y1, a0, a1 = _axis_weights(y, grid.shape[0], mesh, extrapolate)
    x0, x1, b0, b1 = _axis_weights(x, grid.shape[1], mesh, extrapolate)
    return (((a0 * grid[y0, x0]) * b0 + (a0 * grid[y0, x1]) * b1) + (a1 * grid[y1, x0]) * b0
            + (a1 * grid[y1, x1]) * b1)


@njit(cache=True, nogil=True, error_model="numpy")
def _window(img, yc, xc, r, out):  # type: ignore[no-untyped-def]
    """:func:`starlog.detect.screening.gather` for one centre, widened to float64, row by row into ``out``."""
    rows, cols = img.shape
    w = 2 * r + 1
    for a in range(w):
        yy = min(max(yc + a - r, 0), rows - 1)
        for b in range(w):
            out[a * w + b] = np.float64(img[yy, min(max(xc + b - r, 0), cols - 1)])


@njit(cache=True, nogil=True, error_model="numpy")
def _saturation_and_spike(raw, box, saturation, nse, sharpness_ratio):  # type: ignore[no-untyped-def]
    """:func:`~starlog.detect.screening.screen`'s saturation and spike tests on the 5 x 5 window (``raw``, and
    ``box`` above the background): (saturated, the 3 x 3 core's maximum, a spike)."""
    sat = False
    top = box[6]
    for a in range(1, 4):
        for b in range(1, 4):
            sat = sat or raw[a * 5 + b] >= saturation
            v = box[a * 5 + b]
            if top == top and not (v <= top):
                top = v
    centre = box[12]
    lowest = minimum(0.5 * (box[11] + box[13]), 0.5 * (box[7] + box[17]))
    spike = (centre - lowest > 8.0 * nse) and (lowest < sharpness_ratio * centre) and not sat
    return sat, top, spike


@njit(cache=True, nogil=True, error_model="numpy")
def _elongation(fil, level, fb, term):  # type: ignore[no-untyped-def]
    """:func:`~starlog.detect.screening.screen`'s elongation: the axis ratio of the second moments of the 7 x 7
    filtered window ``fil`` above ``level`` (``fb`` and ``term``: scratch of 49 values)."""
    for k in range(49):
        fb[k] = maximum(fil[k] - level, 0.0)
    s0 = 0.0 + block_sum(fb, 0, 49)
    s0 = s0 if s0 > 0 else 1.0
    for k in range(49):
        term[k] = fb[k] * (k % 7 - 3.0)
    mx = (0.0 + block_sum(term, 0, 49)) / s0
    for k in range(49):
        term[k] = fb[k] * (k // 7 - 3.0)
    my = (0.0 + block_sum(term, 0, 49)) / s0
    for k in range(49):
        d = k % 7 - 3.0 - mx
        term[k] = fb[k] * d * d
    sxx = (0.0 + block_sum(term, 0, 49)) / s0
    for k in range(49):
        d = k // 7 - 3.0 - my
        term[k] = fb[k] * d * d
    syy = (0.0 + block_sum(term, 0, 49)) / s0
    for k in range(49):
        term[k] = fb[k] * (k % 7 - 3.0 - mx) * (k // 7 - 3.0 - my)
    sxy = (0.0 + block_sum(term, 0, 49)) / s0
    tr, det = sxx + syy, sxx * syy - sxy * sxy
    disc = math.sqrt(maximum(tr * tr / 4 - det, 0.0))
    l1, l2 = tr / 2 + disc, maximum(tr / 2 - disc, 1e-12)
    return maximum(math.sqrt(l1 / l2), 1.0)


@njit(cache=True, nogil=True, error_model="numpy")
def _moment_offsets(box, term, fb, out):  # type: ignore[no-untyped-def]
    """``out`` = the moment offsets (x, y) of the 5 x 5 window ``box`` above the background
    (:func:`~starlog.detect.position.coarse_offsets`; ``term`` and ``fb``: scratch of 25 values)."""
    for k in range(25):
        term[k] = maximum(box[k], 0.0)
    w0 = 0.0 + block_sum(term, 0, 25)
    w0s = w0 if w0 > 0 else 1.0
    for k in range(25):
        fb[k] = term[k] * (k % 5 - 2.0)
    out[0] = (0.0 + block_sum(fb, 0, 25)) / w0s if w0 > 0 else 0.0
    for k in range(25):
        fb[k] = term[k] * (k // 5 - 2.0)
    out[1] = (0.0 + block_sum(fb, 0, 25)) / w0s if w0 > 0 else 0.0


@njit(cache=True, nogil=True, error_model="numpy")
def _parabola_values(fil, level, out):  # type: ignore[no-untyped-def]
    """``out`` = the log-parabola's three filtered values above ``level`` through the centre of the 7 x 7 window
    ``fil``, in x then in y (1 where one is not positive, as in :func:`~starlog.detect.position.log_parabola`)."""
    fm, f0, fp = fil[3 * 7 + 2] - level, fil[3 * 7 + 3] - level, fil[3 * 7 + 4] - level
    ok = fm > 0 and f0 > 0 and fp > 0
    out[0], out[1], out[2] = (fm, f0, fp) if ok else (1.0, 1.0, 1.0)
    fm, fp = fil[2 * 7 + 3] - level, fil[4 * 7 + 3] - level
    ok = fm > 0 and f0 > 0 and fp > 0
    out[3], out[4], out[5] = (fm, f0, fp) if ok else (1.0, 1.0, 1.0)


@njit(cache=True, nogil=True, error_model="numpy")
def candidate_rows(work, filtered, level_grid, noise_grid, mesh, edge_factor, py, px, component, fval, flux,
                   blended, area, x_min, x_max, y_min, y_max, saturation, sharpness_ratio, max_elongation,
                   elongation_flag, threshold, knorm, border, bits, background, noise_out, peak, snr, elong,
                   flags, keep, x_peak, y_peak, flux_out, area_out, x_min_out, x_max_out, y_min_out, y_max_out,
                   three, moments):  # type: ignore[no-untyped-def]
    """Every field of :func:`~starlog.detect.detection._candidates_vectorised`'s rows but x and y,
    and its keep mask.

    ``bits`` holds the flag values SATURATED, ELONGATED, BLENDED, BORDER, LOW_SNR. For the
    coarse position, ``three[i]`` gets the log-parabola's three filtered values in x then in
    y (1 where one is not positive, as in :func:`~starlog.detect.position.log_parabola`), and
    ``moments[i]`` the 5 x 5 window's moment offsets (x, y). Returns -1, or the index of the
    first peak whose component does not exist (nothing is written then).
    """
    rows, cols = work.shape
    n = py.size
    count = area.size
    for i in range(n):
        if not (0 <= component[i] < count):
            return i
    radius = edge_factor.size - 1
    raw = np.empty(25)
    box = np.empty(25)
    fil = np.empty(49)
    fb = np.empty(49)
    term = np.empty(49)
    for i in range(n):
        y, x, c = py[i], px[i], component[i]
        level = _interp(level_grid, mesh, np.float64(x), np.float64(y), True)
        nse = _interp(noise_grid, mesh, np.float64(x), np.float64(y), False)
        _window(work, y, x, 2, raw)
        _window(filtered, y, x, 3, fil)
        for k in range(25):
            box[k] = raw[k] - level
        # screening: saturation, spike, elongation (screening.screen)
        sat, top, spike = _saturation_and_spike(raw, box, saturation, nse, sharpness_ratio)
        e = _elongation(fil, level, fb, term)
        too_long = e > max_elongation and not blended[i] and not sat
        # significance with the filter's larger noise near the edges (detection._edge_noise_factor)
        dist = min(x, cols - 1 - x)
        fx = edge_factor[min(max(dist, 0), radius)] if dist <= radius else 1.0
        dist = min(y, rows - 1 - y)
        fy = edge_factor[min(max(dist, 0), radius)] if dist <= radius else 1.0
        filtered_noise = nse * knorm * fx * fy
        keep[i] = not spike and not too_long and fval[i] > threshold * filtered_noise
        # coarse position (position.coarse_offsets): moments here, the log-parabola after numpy's log
        _moment_offsets(box, term, fb, moments[i])
        _parabola_values(fil, level, three[i])
        s = fval[i] / filtered_noise
        flag = 0
        if sat:
            flag |= bits[0]
        if e > elongation_flag:
            flag |= bits[1]
        if blended[i]:
            flag |= bits[2]
        if x < border or y < border or x >= cols - border or y >= rows - border:
            flag |= bits[3]
        if s < 5.0:
            flag |= bits[4]
        background[i], noise_out[i], peak[i], snr[i], elong[i], flags[i] = level, nse, top, s, e, flag
        x_peak[i], y_peak[i], flux_out[i], area_out[i] = x, y, flux[i], area[c]
        x_min_out[i], x_max_out[i], y_min_out[i], y_max_out[i] = x_min[c], x_max[c], y_min[c], y_max[c]
    return -1


@njit(cache=True, nogil=True, error_model="numpy")
def coarse_positions(logs, moments, px, py, x, y):  # type: ignore[no-untyped-def]
    """``x``, ``y`` = peak pixel + offset: the log-parabola's vertex through the logarithms ``logs[i]``
    (x then y, of :func:`candidate_rows`' ``three``) where valid, else the moment offset."""
    for i in range(px.size):
        for axis in range(2):
            lm, l0, lp = logs[i, 3 * axis], logs[i, 3 * axis + 1], logs[i, 3 * axis + 2]
            den = lm - 2.0 * l0 + lp
            off = 0.5 * (lm - lp) / den
            d = off if (den < 0 and abs(off) <= 1.0) else moments[i, axis]
            if axis == 0:
                x[i] = px[i] + d
            else:
                y[i] = py[i] + d
    return -1


@njit(cache=True, nogil=True, error_model="numpy")
def member_pixels(binary, rects, seeds, shared, box, y, x):  # type: ignore[no-untyped-def]
    """The foreground pixels of each box ``(x, y, w, h)`` in raster order, box after box, into
    ``box``, ``y``, ``x``: all of them, or for a ``shared`` box those 8-connected to its seed
    inside the box (:func:`starlog.detect.components._member_pixels_vectorised`).

    The outputs hold at least the boxes' total area. Returns the number of pixels, or
    ``-1 - b`` for the first box ``b`` not inside the frame or whose seed is not in it.
    """
    rows, cols = binary.shape
    largest = 0
    for b in range(rects.shape[0]):
        bx, by, bw, bh = rects[b, 0], rects[b, 1], rects[b, 2], rects[b, 3]
        if not (bx >= 0 and by >= 0 and bw >= 1 and bh >= 1 and bx + bw <= cols and by + bh <= rows
                and bx <= seeds[b, 0] < bx + bw and by <= seeds[b, 1] < by + bh):
            return -1 - b
        if shared[b]:
            largest = max(largest, bw * bh)
    reached = np.zeros(largest, np.bool_)
    stack = np.empty(largest, np.intp)
    n = 0
    for b in range(rects.shape[0]):
        bx, by, bw, bh = rects[b, 0], rects[b, 1], rects[b, 2], rects[b, 3]
        if not shared[b]:
            for r in range(by, by + bh):
                for c in range(bx, bx + bw):
                    if binary[r, c] != 0:
                        box[n], y[n], x[n] = b, r, c
                        n += 1
            continue
        reached[: bw * bh] = False
        s = (seeds[b, 1] - by) * bw + seeds[b, 0] - bx
        if binary[seeds[b, 1], seeds[b, 0]] != 0:
            reached[s] = True
            stack[0] = s
            top = 1
            while top:
                top -= 1
                r, c = divmod(stack[top], bw)
                for dr in range(max(r - 1, 0), min(r + 2, bh)):
                    for dc in range(max(c - 1, 0), min(c + 2, bw)):
                        k = dr * bw + dc
                        if not reached[k] and binary[by + dr, bx + dc] != 0:
                            reached[k] = True
                            stack[top] = k
                            top += 1
        for k in range(bw * bh):
            if reached[k]:
                box[n], y[n], x[n] = b, by + k // bw, bx + k % bw
                n += 1
    return n
