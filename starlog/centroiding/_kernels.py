"""Compiled (numba) inner loops of the centroid methods, one star at a time, and tracking mode's frame.

The vectorised numpy forms (:func:`~starlog.centroiding.gaussfit.fit_gaussians_vectorised`,
:func:`~starlog.centroiding.moment.weighted_centroid_vectorised`) spend their time in the fixed
cost of dozens of small array operations an iteration, not in arithmetic: a 13 x 13 window
holds 169 pixels. Here each star's window is a plain loop. The mathematics is that of the
numpy forms, kept as the references the tests compare with, with one difference: a star stops
iterating at its own convergence, where the vectorised forms run every star until the slowest
has converged, so a star's result no longer depends on the other stars of its frame.

- :func:`fit_stars` — GAUSSFIT: damped Gauss-Newton fit of the pixel-integrated Gaussian plus
  background (model, weights, Levenberg damping, step limits, acceptance test, Fisher covariance
  as in :mod:`starlog.centroiding.gaussfit`);
- :func:`weighted_centres` — MOMENT: the re-weighted centre of gravity's fixed point, by the
  secant method from winpos' doubled first step (:mod:`starlog.centroiding.moment`);
- :func:`fisher_sigmas` — the Cramer-Rao sigma of a star of known flux and PSF;
- :func:`gather_windows` — the star windows;
- :func:`symmetry_shifts` — the robust windows' centre of symmetry (:mod:`starlog.centroiding.robust`), the 25
  reflections of each window tried in turn;
- :func:`evidence_sums` — the centroid stage's evidence of one frame (:mod:`starlog.centroiding.evidence`);
- :func:`track_search` and :func:`track_measure` — a tracked frame
  (:mod:`starlog.centroiding.tracked_frame`): one pass over the frame for the light check's cell means
  that copies each star's search window while its rows are in the cache, the window search, then the
  measurement windows, GAUSSFIT (:func:`fit_stars` itself), the robust pass's test, the fallback of
  a failed fit, the centroid rows, the lost-star tests and the state's advance. Same bits as the numpy
  forms: sums over a window in numpy's pairwise order (:func:`_pairwise_sum`), NaN propagating in
  maxima as ``np.maximum``, the star model at the coarse position from numpy's ``erf`` (between the two
  calls).

One module of over 500 lines: numba's cache is refreshed when a function's own file changes, not when a
function it calls in another file does, and the tracked frame calls the fit, the Cramer-Rao sigma and the
window cutter. Compiled on first use and cached beside this file (``__pycache__``), or in numba's user cache
when the package folder is read-only. Divisions follow numpy (``error_model="numpy"``): a zero denominator
gives inf or nan, not an exception. No function here calls itself (numba does not load a cached recursive
function safely).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_INV_SQ2 = 1.0 / math.sqrt(2.0)
_ISQ2PI = 1.0 / math.sqrt(2.0 * math.pi)
_MAX_PAR = 5


@njit(cache=True, nogil=True, error_model="numpy")
def _profile(edges, c, s, out):  # type: ignore[no-untyped-def]
    """Pixel-integrated unit Gaussian of centre ``c``, width ``s`` between the pixel ``edges``."""
    prev = math.erf((edges[0] - c) / s * _INV_SQ2)
    for j in range(out.size):
        cur = math.erf((edges[j + 1] - c) / s * _INV_SQ2)
        out[j] = 0.5 * (cur - prev)
        prev = cur


@njit(cache=True, nogil=True, error_model="numpy")
def _slopes(edges, c, s, d_centre, d_width):  # type: ignore[no-untyped-def]
    """d profile / d centre and d profile / d width."""
    t = (edges[0] - c) / s
    pdf = _ISQ2PI * math.exp(-0.5 * t * t)
    tpdf = t * pdf
    for j in range(d_centre.size):
        t = (edges[j + 1] - c) / s
        nxt = _ISQ2PI * math.exp(-0.5 * t * t)
        d_centre[j] = -(nxt - pdf) / s
        d_width[j] = -(t * nxt - tpdf) / s
        pdf, tpdf = nxt, t * nxt


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc", "contract"})
def _normal(data, valid, var0, gain, f, b, ex, ey, dex, dey, dsx, dsy, fit_background, fit_sigma, fitted,
            a_mat, grad):  # type: ignore[no-untyped-def]
    """Normal matrix J^T W J and gradient J^T W r at the profiles given; returns the weighted chi^2.

    W is the inverse model variance (read + sky noise + the star's shot noise), as in the vectorised
    fit. The sums run in scalars over all five parameters (cx, cy, F, B, s), a parameter not fitted
    having a zero derivative, and the fitted ones (indices ``fitted``, from :func:`_fitted`) are packed into
    ``a_mat`` and ``grad``.
    """
    d_b = 1.0 if fit_background else 0.0
    on_s = 1.0 if fit_sigma else 0.0
    a00 = a01 = a02 = a03 = a04 = a11 = a12 = a13 = a14 = a22 = a23 = a24 = a33 = a34 = a44 = 0.0
    g0 = g1 = g2 = g3 = g4 = 0.0
    chi2 = 0.0
    w_size = ex.size
    for i in range(w_size):
        for j in range(w_size):
            unit = ey[i] * ex[j]
            mu = f * unit
            w = valid[i, j] / (var0 + max(mu, 0.0) / gain)
            r = data[i, j] - b - mu
            j0 = f * ey[i] * dex[j]
            j1 = f * dey[i] * ex[j]
            j2 = unit
            j4 = on_s * f * (dsy[i] * ex[j] + ey[i] * dsx[j])
            w0, w1, w2, w3, w4 = w * j0, w * j1, w * j2, w * d_b, w * j4
            a00 += w0 * j0
            a01 += w0 * j1
            a02 += w0 * j2
            a03 += w0 * d_b
            a04 += w0 * j4
            a11 += w1 * j1
            a12 += w1 * j2
            a13 += w1 * d_b
            a14 += w1 * j4
            a22 += w2 * j2
            a23 += w2 * d_b
            a24 += w2 * j4
            a33 += w3 * d_b
            a34 += w3 * j4
            a44 += w4 * j4
            g0 += w0 * r
            g1 += w1 * r
            g2 += w2 * r
            g3 += w3 * r
            g4 += w4 * r
            chi2 += w * r * r
    sums = ((a00, a01, a02, a03, a04), (a01, a11, a12, a13, a14), (a02, a12, a22, a23, a24),
            (a03, a13, a23, a33, a34), (a04, a14, a24, a34, a44))
    gradients = (g0, g1, g2, g3, g4)
    for p in range(fitted.size):
        grad[p] = gradients[fitted[p]]
        for q in range(fitted.size):
            a_mat[p, q] = sums[fitted[p]][fitted[q]]
    return chi2


@njit(cache=True, nogil=True, error_model="numpy")
def _fitted(fit_background, fit_sigma):  # type: ignore[no-untyped-def]
    """Indices in (cx, cy, F, B, s) of the fitted parameters, in the order of the step."""
    if fit_background and fit_sigma:
        return np.array([0, 1, 2, 3, 4])
    if fit_background:
        return np.array([0, 1, 2, 3])
    if fit_sigma:
        return np.array([0, 1, 2, 4])
    return np.array([0, 1, 2])


@njit(cache=True, nogil=True, error_model="numpy")
def _chi2(data, valid, var0, gain, f, b, ex, ey, f_now, ex_now, ey_now):  # type: ignore[no-untyped-def]
    """Weighted chi^2 of the model (f, b, ex, ey), weighted by the variance of the current model (f_now, ...)."""
    chi2 = 0.0
    for i in range(ex.size):
        for j in range(ex.size):
            r = data[i, j] - b - f * ey[i] * ex[j]
            chi2 += valid[i, j] * r * r / (var0 + max(f_now * ey_now[i] * ex_now[j], 0.0) / gain)
    return chi2


@njit(cache=True, nogil=True, error_model="numpy")
def _solve(a_mat, rhs, npar, out):  # type: ignore[no-untyped-def]
    """``out`` = ``a_mat``^-1 ``rhs`` (Gaussian elimination, partial pivoting); False when singular."""
    m = np.empty((_MAX_PAR, _MAX_PAR + 1))
    for p in range(npar):
        for q in range(npar):
            m[p, q] = a_mat[p, q]
        m[p, npar] = rhs[p]
    for col in range(npar):
        pivot = col
        for r in range(col + 1, npar):
            if abs(m[r, col]) > abs(m[pivot, col]):
                pivot = r
        if m[pivot, col] == 0.0 or not math.isfinite(m[pivot, col]):
            return False
        if pivot != col:
            for q in range(npar + 1):
                m[col, q], m[pivot, q] = m[pivot, q], m[col, q]
        for r in range(col + 1, npar):
            factor = m[r, col] / m[col, col]
            for q in range(col, npar + 1):
                m[r, q] -= factor * m[col, q]
    for p in range(npar - 1, -1, -1):
        acc = m[p, npar]
        for q in range(p + 1, npar):
            acc -= m[p, q] * out[q]
        out[p] = acc / m[p, p]
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def _inverse_diagonal(a_mat, npar, out):  # type: ignore[no-untyped-def]
    """The diagonal of ``a_mat``^-1 into ``out``; False when ``a_mat`` is singular."""
    unit = np.zeros(_MAX_PAR)
    column = np.empty(_MAX_PAR)
    for p in range(npar):
        unit[:] = 0.0
        unit[p] = 1.0
        if not _solve(a_mat, unit, npar, column):
            return False
        out[p] = column[p]
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def fit_stars(data, valid, noise, gain, edges, cx, cy, flux, background, width, fit_background, fit_sigma,
              iterations, tol, sigma, flux_err, good_var, active):  # type: ignore[no-untyped-def]
    """Fit every window in place: ``cx``, ``cy``, ``flux``, ``background``, ``width`` start at the first guess
    and end at the solution; ``sigma``, ``flux_err``, ``good_var`` (the Fisher covariance could be inverted)
    and ``active`` (no singular step) are filled. Arrays as in :class:`~starlog.centroiding._stamps.Stamps`."""
    n, w_size, _ = data.shape
    npar = 3 + int(fit_background) + int(fit_sigma)
    ex, ey, dex, dey = np.empty(w_size), np.empty(w_size), np.empty(w_size), np.empty(w_size)
    dsx, dsy, tx, ty = np.empty(w_size), np.empty(w_size), np.empty(w_size), np.empty(w_size)
    a_mat, damped = np.empty((_MAX_PAR, _MAX_PAR)), np.empty((_MAX_PAR, _MAX_PAR))
    grad, step, diag = np.empty(_MAX_PAR), np.empty(_MAX_PAR), np.empty(_MAX_PAR)
    fitted = _fitted(fit_background, fit_sigma)
    for k in range(n):
        var0 = noise[k] * noise[k]
        lam = 1e-3
        active[k] = True
        f, b, s, x, y = flux[k], background[k], width[k], cx[k], cy[k]
        for _ in range(iterations):
            _profile(edges, x, s, ex)
            _profile(edges, y, s, ey)
            _slopes(edges, x, s, dex, dsx)
            _slopes(edges, y, s, dey, dsy)
            c0 = _normal(data[k], valid[k], var0, gain, f, b, ex, ey, dex, dey, dsx, dsy, fit_background, fit_sigma,
                         fitted, a_mat, grad)
            for p in range(npar):
                for q in range(npar):
                    damped[p, q] = a_mat[p, q] * (1.0 + lam) if p == q else a_mat[p, q]
            if not _solve(damped, grad, npar, step):
                step[:npar] = 0.0
                active[k] = False
            for p in range(npar):
                if not math.isfinite(step[p]):
                    step[p] = 0.0
            step[0] = min(max(step[0], -0.5), 0.5)
            step[1] = min(max(step[1], -0.5), 0.5)
            if fit_sigma:
                step[npar - 1] = min(max(step[npar - 1], -0.3 * s), 0.3 * s)
            nx, ny = x + step[0], y + step[1]
            nf = max(f + step[2], 1e-6 * noise[k] + 1e-12)
            nb = b + step[3] if fit_background else b
            ns = min(max(s + step[npar - 1], 0.2), 20.0) if fit_sigma else s
            _profile(edges, nx, ns, tx)
            _profile(edges, ny, ns, ty)
            trial = _chi2(data[k], valid[k], var0, gain, nf, nb, tx, ty, f, ex, ey)
            accepted = trial <= c0 * (1 + 1e-9) and active[k]
            # converged: an accepted step that moved the centre (and the width) by less than tol px
            # and the flux by less than tol of itself; a rejected (or damped-away) step proves nothing
            small = (abs(nx - x) < tol and abs(ny - y) < tol and abs(nf - f) <= tol * abs(f)
                     and (not fit_sigma or abs(ns - s) < tol))
            if accepted:
                x, y, f, b, s = nx, ny, nf, nb, ns
                lam = max(lam * 0.3, 1e-7)
            else:
                lam = lam * 10.0
            if (accepted and small) or not active[k]:
                break
        cx[k], cy[k], flux[k], background[k], width[k] = x, y, f, b, s
        _profile(edges, x, s, ex)
        _profile(edges, y, s, ey)
        _slopes(edges, x, s, dex, dsx)
        _slopes(edges, y, s, dey, dsy)
        _normal(data[k], valid[k], var0, gain, f, b, ex, ey, dex, dey, dsx, dsy, fit_background, fit_sigma, fitted,
                a_mat, grad)
        good_var[k] = False
        sigma[k] = flux_err[k] = np.inf
        if _inverse_diagonal(a_mat, npar, diag):
            var = 0.5 * (diag[0] + diag[1])
            if math.isfinite(var) and var > 0:
                good_var[k] = True
                sigma[k] = math.sqrt(var)
            if math.isfinite(diag[2]) and diag[2] > 0:
                flux_err[k] = math.sqrt(diag[2])



@njit(cache=True, nogil=True, error_model="numpy")
def fisher_sigmas(valid, noise, gain, edges, cx, cy, flux, width, out):  # type: ignore[no-untyped-def]
    """Per-axis Cramer-Rao sigma of each star of known flux, PSF width and background (the 2 x 2
    Fisher information of the centre, inverted); inf where it cannot be inverted."""
    w_size = edges.size - 1
    ex, ey, dex, dey = np.empty(w_size), np.empty(w_size), np.empty(w_size), np.empty(w_size)
    dsx, dsy = np.empty(w_size), np.empty(w_size)
    for k in range(cx.size):
        _profile(edges, cx[k], width[k], ex)
        _profile(edges, cy[k], width[k], ey)
        _slopes(edges, cx[k], width[k], dex, dsx)
        _slopes(edges, cy[k], width[k], dey, dsy)
        f = max(flux[k], 1e-12)
        var0 = noise[k] * noise[k]
        ixx = iyy = ixy = 0.0
        for i in range(w_size):
            for j in range(w_size):
                w = valid[k, i, j] / (var0 + max(f * ey[i] * ex[j], 0.0) / gain)
                jx, jy = ey[i] * dex[j], dey[i] * ex[j]
                ixx += w * jx * jx
                iyy += w * jy * jy
                ixy += w * jx * jy
        ixx, iyy, ixy = ixx * f * f, iyy * f * f, ixy * f * f
        det = ixx * iyy - ixy * ixy
        var = 0.5 * (ixx + iyy) / det if det != 0 else math.inf
        out[k] = math.sqrt(var) if math.isfinite(var) and var > 0 else math.inf


NONE, GAUSSIAN, OPTIMAL = 0, 1, 2
"""Weighting codes: the plain centre of gravity, the PSF (winpos), the noise-optimal weight."""


@njit(cache=True, nogil=True, error_model="numpy")
def _centre(data, valid, u, edges, cx, cy, s, var0, flux, gain, weighting, ex, ey, col, row):  # type: ignore[no-untyped-def]
    """One centre-of-gravity evaluation with the weights centred on (cx, cy): (x, y, any weight)."""
    w_size = u.size
    if weighting != NONE:
        _profile(edges, cx, s, ex)
        _profile(edges, cy, s, ey)
    col[:] = 0.0
    row[:] = 0.0
    for i in range(w_size):
        for j in range(w_size):
            if weighting == NONE:
                w = valid[i, j]
            else:
                m = ey[i] * ex[j]
                w = valid[i, j] * m
                if weighting == OPTIMAL:
                    w = w / (var0 + max(flux * m, 0.0) / gain)
            v = w * data[i, j]
            col[j] += v
            row[i] += v
    s0 = 0.0
    for j in range(w_size):
        s0 += col[j]
    ok = s0 > 0
    if not ok:
        s0 = 1.0
    x = y = 0.0
    for j in range(w_size):
        x += col[j] * u[j]
        y += row[j] * u[j]
    return x / s0, y / s0, ok


@njit(cache=True, nogil=True, error_model="numpy")
def weighted_centres(data, valid, u, edges, noise, gain, dx0, dy0, flux, psf_sigma, weighting, iterations, tol,
                     h, cx_out, cy_out, ok_out):  # type: ignore[no-untyped-def]
    """Fill ``cx_out``, ``cy_out``, ``ok_out`` for every window (arrays as in ``Stamps``; see the module)."""
    n, w_size, _ = data.shape
    ex, ey, col, row = np.empty(w_size), np.empty(w_size), np.empty(w_size), np.empty(w_size)
    for k in range(n):
        var0, f, s = noise[k] * noise[k], max(flux[k], 0.0), psf_sigma[k]
        tx, ty, ok = _centre(data[k], valid[k], u, edges, dx0[k], dy0[k], s, var0, f, gain, weighting, ex, ey,
                             col, row)
        if weighting == NONE:
            cx_out[k], cy_out[k] = tx, ty
            ok_out[k] = ok and abs(tx) < h and abs(ty) < h
            continue
        x_prev, y_prev = dx0[k], dy0[k]
        gx_prev, gy_prev = tx - x_prev, ty - y_prev
        cx = min(max(x_prev + 2.0 * gx_prev, -h), h)
        cy = min(max(y_prev + 2.0 * gy_prev, -h), h)
        for _ in range(iterations):
            tx, ty, good = _centre(data[k], valid[k], u, edges, cx, cy, s, var0, f, gain, weighting, ex, ey, col,
                                   row)
            ok = ok and good
            gx, gy = tx - cx, ty - cy
            if (abs(gx) < tol and abs(gy) < tol) or not ok:
                cx, cy = tx, ty
                break
            fx = _secant_factor(cx - x_prev, gx - gx_prev)
            fy = _secant_factor(cy - y_prev, gy - gy_prev)
            x_prev, y_prev, gx_prev, gy_prev = cx, cy, gx, gy
            cx = min(max(cx + fx * gx, -h), h)
            cy = min(max(cy + fy * gy, -h), h)
        cx_out[k], cy_out[k] = cx, cy
        ok_out[k] = ok and math.isfinite(cx) and math.isfinite(cy) and abs(cx) < h and abs(cy) < h


@njit(cache=True, nogil=True, error_model="numpy")
def _secant_factor(dx, dg):  # type: ignore[no-untyped-def]
    """The secant step's factor on g(x) = T(x) - x, kept within (0.5, 4); 2 (winpos) when undefined."""
    if abs(dg) <= 1e-12:
        return 2.0
    factor = -dx / dg
    return factor if math.isfinite(factor) and 0.5 < factor < 4.0 else 2.0


@njit(cache=True, nogil=True, error_model="numpy")
def gather_windows(image, xc, yc, h, background, saturation, data, valid, satpix, flags):  # type: ignore[no-untyped-def]
    """Star windows of ``image`` centred on the pixels (``xc``, ``yc``), as
    :func:`~starlog.centroiding._stamps.gather_stamps_vectorised` cuts them.

    Fills ``data`` (background-subtracted, 0 where invalid), ``valid`` (inside the frame, finite,
    below ``saturation``), ``satpix`` (saturated, inside) and ``flags[k]`` = (saturated, cut by the
    frame edge, non-finite pixel inside) of each star.
    """
    rows, cols = image.shape
    w = 2 * h + 1
    for k in range(xc.size):
        saturated, cut, masked = False, False, False
        for i in range(w):
            r = yc[k] - h + i
            row_in = 0 <= r < rows
            rr = min(max(r, 0), rows - 1)
            for j in range(w):
                c = xc[k] - h + j
                inside = row_in and 0 <= c < cols
                raw = np.float64(image[rr, min(max(c, 0), cols - 1)])
                finite = math.isfinite(raw)
                sat = raw >= saturation
                ok = inside and finite and not sat
                valid[k, i, j] = ok
                data[k, i, j] = raw - background[k] if ok else 0.0
                satpix[k, i, j] = sat and inside
                saturated |= sat and inside
                cut |= not inside
                masked |= inside and not finite
        flags[k, 0], flags[k, 1], flags[k, 2] = saturated, cut, masked


# ---------------------------------------------------------------- tracking mode's frame
# track_search and track_measure are starlog.centroiding.tracked_frame.track_frame; the numpy forms (tracking's
# new_light, lasting_light, locate_stars, extract's measure_methods for GAUSSFIT, lost_stars, advance) are the
# references. Their inputs come in the named tuples built there (_Light, _Search, _Stars, _Fit, _Windows, _Rule,
# _Next).

SEARCH, LOCATED, MEASURED, FINISH = 0, 1, 2, 3
"""Statuses: the frame must be searched in full; stars located (windows cut); measured and advanced; fitted, numpy
to finish the rows (a window needs the robust re-measurement)."""

_FIT_FAILED, _LOW_SNR, _SATURATED, _BORDER, _MASKED = 4, 32, 1, 2, 64
_TRACKED, _KEPT = 256, 8 | 16
""":class:`~starlog.detect._flags.StarFlag` bits (TRACKED; BLENDED | ELONGATED kept from the acquisition)."""


@njit(cache=True, nogil=True, error_model="numpy")
def _maximum(a, b):  # type: ignore[no-untyped-def]
    """``np.maximum(a, b)``: NaN propagates."""
    return a if (a > b or a != a) else b


@njit(cache=True, nogil=True, error_model="numpy")
def _block_sum(a, start, n):  # type: ignore[no-untyped-def]
    """numpy's pairwise sum of ``a[start:start + n]``, n <= 128: eight partial sums combined in a tree."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[start + i]
        return res
    r0, r1, r2, r3 = a[start], a[start + 1], a[start + 2], a[start + 3]
    r4, r5, r6, r7 = a[start + 4], a[start + 5], a[start + 6], a[start + 7]
    i = start + 8
    whole = start + n - n % 8
    while i < whole:
        r0 += a[i]
        r1 += a[i + 1]
        r2 += a[i + 2]
        r3 += a[i + 3]
        r4 += a[i + 4]
        r5 += a[i + 5]
        r6 += a[i + 6]
        r7 += a[i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < start + n:
        res += a[i]
        i += 1
    return res


@njit(cache=True, nogil=True, error_model="numpy")
def _pairwise_sum(a, start, n):  # type: ignore[no-untyped-def]
    """numpy's float64 sum of ``a[start:start + n]`` as ``sum(axis=(1, 2))`` takes one window: above 128 values
    the sum of its two halves (cut at a multiple of eight), :func:`_block_sum` below. numpy recurses; here a
    stack does (numba's cache does not load recursive functions safely)."""
    if n <= 128:
        return _block_sum(a, start, n)
    starts, counts, stages = np.empty(64, np.int64), np.empty(64, np.int64), np.empty(64, np.int64)
    sums = np.empty(64)
    top, done = 0, 0
    starts[0], counts[0], stages[0] = start, n, 0
    while top >= 0:
        s, m = starts[top], counts[top]
        if m <= 128:
            sums[done] = _block_sum(a, s, m)
            done += 1
            top -= 1
            continue
        half = m // 2
        half -= half % 8
        if stages[top] == 2:
            done -= 1
            sums[done - 1] = sums[done - 1] + sums[done]
            top -= 1
            continue
        stages[top] += 1
        top += 1
        starts[top], counts[top], stages[top] = (s, half, 0) if stages[top - 1] == 1 else (s + half, m - half, 0)
    return sums[0]


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
                cells[r, c] = (0.0 + _pairwise_sum(acc, c * cell, cell)) / (cell * cell)
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
        terms[p] = _maximum(raw[fy + r - 2 + p // 5, fx + r - 2 + p % 5], 0.0)
    w0 = 0.0 + _block_sum(terms, 0, 25)
    for p in range(25):
        terms[25 + p] = terms[p] * (p % 5 - 2.0)
        terms[50 + p] = terms[p] * (p // 5 - 2.0)
    mx = (0.0 + _block_sum(terms, 25, 25)) / w0 if w0 > 0 else 0.0
    my = (0.0 + _block_sum(terms, 50, 25)) / w0 if w0 > 0 else 0.0
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
    """:func:`starlog.centroiding._stamps.grown_saturation` of one saturated window: the valid pixels at least
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
        noise = _maximum(det.noise, fit.noise_floor)
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


@njit(cache=True, nogil=True, error_model="numpy")
def _coarse_model(cdf, k, w, out):  # type: ignore[no-untyped-def]
    """Star ``k``'s unit model at its coarse position from the error function at its pixel edges (``cdf``,
    numpy's ``erf``, as :func:`starlog.centroiding._stamps.model` evaluates it)."""
    for i in range(w):
        ey = 0.5 * (cdf[k, 1, i + 1] - cdf[k, 1, i])
        for j in range(w):
            out[i, j] = ey * (0.5 * (cdf[k, 0, j + 1] - cdf[k, 0, j]))


@njit(cache=True, nogil=True, error_model="numpy")
def _linear_flux(data, valid, noise, gain, unit, flux, iterations, terms):  # type: ignore[no-untyped-def]
    """:func:`starlog.centroiding._stamps.linear_flux` of one window (same bits): flux and its error."""
    w = unit.shape[0]
    f = _maximum(flux, 0.0)
    den = 1.0
    for _ in range(iterations):
        for i in range(w):
            for j in range(w):
                weight = valid[i, j] / (noise * noise + _maximum(f * unit[i, j], 0.0) / gain)
                terms[i * w + j] = weight * unit[i, j] * data[i, j]
                terms[w * w + i * w + j] = weight * unit[i, j] * unit[i, j]
        num = 0.0 + _pairwise_sum(terms, 0, w * w)
        den = 0.0 + _pairwise_sum(terms, w * w, w * w)
        f = num / den if den > 0 else 0.0
    err = 1.0 / math.sqrt(den) if den > 0 else 0.0
    return f, err if math.isfinite(err) else np.inf


@njit(cache=True, nogil=True, error_model="numpy")
def _suspect(data, valid, noise, gain, mu, clip):  # type: ignore[no-untyped-def]
    """Whether a pixel of the window passes :func:`starlog.centroiding.robust.suspect_pixels`' shot-noise level
    (its clean-frame test): the window then needs the robust re-measurement."""
    w = mu.shape[0]
    count = 0
    for i in range(w):
        for j in range(w):
            count += valid[i, j]
    k = clip[count]
    for i in range(w):
        for j in range(w):
            if not valid[i, j]:
                continue
            r = data[i, j] - mu[i, j]
            if not r > 0:
                continue
            var = noise * noise + _maximum(mu[i, j], 0.0) / gain
            if r * r > k * k * var:
                sd = math.sqrt(var)
                skew = min(1.0 / (gain * sd), 1.0)
                if r > (k + (k * k - 1.0) * skew / 6.0) * sd:
                    return True
    return False


@njit(cache=True, nogil=True, error_model="numpy")
def _needs_robust(windows, fit, k, cx, cy, flux, background, width, ex, ey, mu):  # type: ignore[no-untyped-def]
    """``_remeasure_robust``'s test of star ``k`` measured at (cx, cy) with ``flux``: a suspect pixel, or a
    centroid strayed beyond a star's light from the coarse position."""
    _profile(fit.edges, cx, width, ex)
    _profile(fit.edges, cy, width, ey)
    w = ex.size
    for i in range(w):
        for j in range(w):
            mu[i, j] = max(flux, 0.0) * (ey[i] * ex[j]) + background
    if _suspect(windows.data[k], windows.valid[k], windows.noise[k], fit.gain, mu, fit.clip):
        return True
    return math.hypot(cx - windows.dx0[k], cy - windows.dy0[k]) > max(2.0, 1.5 * width)


@njit(cache=True, nogil=True, error_model="numpy")
def _peak_near(windows, fit, k, dx, dy):  # type: ignore[no-untyped-def]
    """``_peak_near``: the highest pixel within one pixel of the centroid (saturated ones at their clip level)."""
    h = fit.half
    ix = min(max(int(np.rint(dx)) + h, 1), 2 * h - 1)
    iy = min(max(int(np.rint(dy)) + h, 1), 2 * h - 1)
    clip = fit.saturation - windows.background[k]
    peak = -np.inf
    for i in range(iy - 1, iy + 2):
        for j in range(ix - 1, ix + 2):
            if windows.satpix[k, i, j]:
                v = clip
            else:
                v = windows.data[k, i, j] if windows.valid[k, i, j] else -np.inf
            peak = _maximum(peak, v)
    return peak if math.isfinite(peak) else 0.0


@njit(cache=True, nogil=True, error_model="numpy")
def _fit_windows(windows, fit, fitted):  # type: ignore[no-untyped-def]
    """The first flux of every window at its coarse position (``_prepare``), then GAUSSFIT from there as
    ``fit_gaussians`` runs it, into ``fitted``; ``ok`` as it judges the fit."""
    n, w = fitted.dx.size, windows.data.shape[1]
    unit, terms = np.empty((w, w)), np.empty(2 * w * w)
    for k in range(n):
        _coarse_model(windows.cdf, k, w, unit)
        fitted.f0[k], _ = _linear_flux(windows.data[k], windows.valid_f[k], windows.noise[k], fit.gain, unit,
                                       windows.flux0[k], 1, terms)
        fitted.dx[k], fitted.dy[k] = windows.dx0[k], windows.dy0[k]
        fitted.flux[k] = _maximum(fitted.f0[k], 1.0 * windows.noise[k])
        fitted.background[k], fitted.width[k] = 0.0, fit.psf
    good_var, active = np.empty(n, np.bool_), np.empty(n, np.bool_)
    fit_stars(windows.data, windows.valid_f, windows.noise, fit.gain, fit.edges, fitted.dx, fitted.dy, fitted.flux,
              fitted.background, fitted.width, fit.fit_background, fit.fit_sigma, fit.iterations, fit.tol,
              fitted.sigma, fitted.flux_err, good_var, active)
    limit = fit.half - 0.5
    for k in range(n):
        fitted.ok[k] = (active[k] and math.isfinite(fitted.dx[k]) and math.isfinite(fitted.dy[k])
                        and abs(fitted.dx[k]) < limit and abs(fitted.dy[k]) < limit and fitted.flux[k] > 0
                        and good_var[k])


@njit(cache=True, nogil=True, error_model="numpy")
def _needs_numpy(windows, fit, fitted):  # type: ignore[no-untyped-def]
    """Whether a window needs the robust re-measurement (``_remeasure_robust``'s test), or a failed fit's fallback
    the PSF width it fitted: then numpy finishes the rows from the fit (``extract.gaussfit_rows``)."""
    w = windows.data.shape[1]
    mu, ex, ey = np.empty((w, w)), np.empty(w), np.empty(w)
    for k in range(fitted.dx.size):
        ok = fitted.ok[k]
        if not ok and fit.fit_sigma:
            return True
        if not fit.robust:
            continue
        dx, dy = (fitted.dx[k], fitted.dy[k]) if ok else (windows.dx0[k], windows.dy0[k])
        flux = fitted.flux[k] if ok and math.isfinite(fitted.flux[k]) else fitted.f0[k]
        if _needs_robust(windows, fit, k, dx, dy, flux, fitted.background[k] if ok else 0.0, fitted.width[k],
                         ex, ey, mu):
            return True
    return False


@njit(cache=True, nogil=True, error_model="numpy")
def _measured_rows(detections, fit, windows, fitted, centroids):  # type: ignore[no-untyped-def]
    """``_with_fallback`` and ``_centroid_table``: the centroid rows of the fitted windows (none needing the
    robust re-measurement), a failed fit at its coarse position with a flux fitted there and twice the bound."""
    w = windows.data.shape[1]
    unit, terms, one = np.empty((w, w)), np.empty(2 * w * w), np.empty(1)
    for k in range(detections.size):
        ok = fitted.ok[k]
        dx, dy = (fitted.dx[k], fitted.dy[k]) if ok else (windows.dx0[k], windows.dy0[k])
        flux, flux_err, sigma = fitted.flux[k], fitted.flux_err[k], fitted.sigma[k]
        if not ok:
            _coarse_model(windows.cdf, k, w, unit)
            flux, flux_err = _linear_flux(windows.data[k], windows.valid_f[k], windows.noise[k], fit.gain, unit,
                                          _maximum(fitted.f0[k], 0.0), 2, terms)
            fisher_sigmas(windows.valid_f[k:k + 1], windows.noise[k:k + 1], fit.gain, fit.edges,
                          windows.dx0[k:k + 1], windows.dy0[k:k + 1], np.array([_maximum(flux, 0.0)]),
                          fitted.width[k:k + 1], one)
            sigma = one[0] * 2.0
        _centroid_row(detections[k], windows, fit, k, dx, dy, ok, flux, flux_err, sigma,
                      fitted.background[k] if ok else 0.0, fitted.width[k], centroids[k])


@njit(cache=True, nogil=True, error_model="numpy")
def _centroid_row(det, windows, fit, k, dx, dy, ok, flux, flux_err, sigma, background, width, row):  # type: ignore[no-untyped-def]
    """``_with_fallback``'s last checks and ``_centroid_table``'s row of star ``k``."""
    sigma = sigma if math.isfinite(sigma) and sigma > 0 else width
    flux_err = flux_err if math.isfinite(flux_err) and flux_err > 0 else np.inf
    snr = flux / flux_err if math.isfinite(flux_err) else 0.0
    flags = det.flags & (~(_FIT_FAILED | _LOW_SNR) & 0xFFFF)
    if windows.flags[k, 0]:
        flags |= _SATURATED
    if windows.flags[k, 1]:
        flags |= _BORDER
    if windows.flags[k, 2] or windows.left_out[k] > 0:
        flags |= _MASKED
    if not ok:
        flags |= _FIT_FAILED
    if snr < 5.0:
        flags |= _LOW_SNR
    row.star, row.x, row.y = det.star, windows.xc[k] + dx, windows.yc[k] + dy
    row.flux, row.snr, row.sigma = flux, snr, sigma
    row.peak = _peak_near(windows, fit, k, dx, dy)
    row.background = det.background + background
    row.psf_sigma, row.flags, row.n_masked = width, flags, windows.left_out[k]


@njit(cache=True, nogil=True, error_model="numpy")
def _lost(centroids, found, stars, rule, lost):  # type: ignore[no-untyped-def]
    """``~found | lost_stars(...)`` into ``lost``."""
    n = stars.x.size
    for k in range(n):
        c = centroids[k]
        flux, reference = c.flux, stars.flux[k]
        error = abs(flux) / c.snr
        change = abs(flux - reference)
        changed = not math.isfinite(flux) or (change > rule.flux_change * abs(reference)
                                              and not change <= rule.flux_sigma * error)
        lost[k] = not found[k] or (c.flags & _FIT_FAILED) != 0 or changed
    reach2 = rule.reach * rule.reach
    for k in range(n):
        crowded = False
        for j in range(n):
            if j == k:
                continue
            for predicted in (True, False):
                if predicted:
                    dx = (stars.x[k] + stars.vx[k]) - (stars.x[j] + stars.vx[j])
                    dy = (stars.y[k] + stars.vy[k]) - (stars.y[j] + stars.vy[j])
                else:
                    dx, dy = centroids[k].x - centroids[j].x, centroids[k].y - centroids[j].y
                if dx ** 2 + dy ** 2 < reach2 and (not stars.quiet[j] or stars.quiet[k]):
                    crowded = True
        lost[k] = lost[k] or crowded


@njit(cache=True, nogil=True, error_model="numpy")
def _advance(centroids, stars, rule, rows, cols, nxt):  # type: ignore[no-untyped-def]
    """:func:`~starlog.centroiding.tracking.advance`'s positions, velocities and stars kept, into ``nxt``."""
    margin = rule.margin
    for k in range(stars.x.size):
        measured = not nxt.lost[k]
        x = centroids[k].x if measured else stars.x[k] + stars.vx[k]
        y = centroids[k].y if measured else stars.y[k] + stars.vy[k]
        vx = x - stars.x[k] if measured else stars.vx[k]
        vy = y - stars.y[k] if measured else stars.vy[k]
        nxt.x[k], nxt.y[k], nxt.vx[k], nxt.vy[k] = x, y, vx, vy
        nxt.stay[k] = measured or (x + vx > -margin and x + vx < cols - 1 + margin and y + vy > -margin
                                   and y + vy < rows - 1 + margin)


@njit(cache=True, nogil=True, error_model="numpy")
def track_measure(shape, detections, found, stars, fit, windows, rule, fitted, centroids, nxt):  # type: ignore[no-untyped-def]
    """The measurement, the lost-star tests and the state's advance of a frame :func:`track_search` located:
    FINISH when numpy must finish its rows from ``fitted`` (:func:`_needs_numpy`), SEARCH when a star is lost,
    else MEASURED."""
    _fit_windows(windows, fit, fitted)
    if _needs_numpy(windows, fit, fitted):
        return FINISH
    _measured_rows(detections, fit, windows, fitted, centroids)
    _lost(centroids, found, stars, rule, nxt.lost)
    if not rule.just_acquired:
        for k in range(stars.x.size):
            if nxt.lost[k] and not stars.quiet[k]:
                return SEARCH
    _advance(centroids, stars, rule, shape[0], shape[1], nxt)
    return MEASURED


# ---------------------------------------------------------------- the centroid stage's evidence
# evidence_sums is starlog.centroiding.evidence.evidence_sums; evidence_sums_vectorised there is its reference.


@njit(cache=True, nogil=True, error_model="numpy")
def _nearest_within(ax, ay, bx, by, order, radius, nearest):  # type: ignore[no-untyped-def]
    """For each point a, the index of its nearest point b when one lies within ``radius`` (else -1); ``order``:
    the points b sorted by x. Of equal distances the first in that order."""
    sorted_x = bx[order]
    for i in range(ax.size):
        nearest[i] = -1
        best = np.inf
        p = np.searchsorted(sorted_x, ax[i] - radius)
        while p < order.size and sorted_x[p] <= ax[i] + radius:
            j = order[p]
            d2 = (ax[i] - bx[j]) ** 2 + (ay[i] - by[j]) ** 2
            if d2 < best:
                nearest[i], best = j, d2
            p += 1
        if nearest[i] >= 0 and not math.sqrt(best) <= radius:
            nearest[i] = -1


@njit(cache=True, nogil=True, error_model="numpy")
def _matched(px, py, x, y, radius):  # type: ignore[no-untyped-def]
    """``evidence._matched_pairs``: stars of two frames each other's nearest within ``radius`` (first rows)."""
    ab, ba = np.empty(px.shape[1], np.int64), np.empty(x.shape[1], np.int64)
    _nearest_within(px[0], py[0], x[0], y[0], np.argsort(x[0], kind="mergesort"), radius, ab)
    _nearest_within(x[0], y[0], px[0], py[0], np.argsort(px[0], kind="mergesort"), radius, ba)
    count = 0
    for i in range(ab.size):
        count += ab[i] >= 0 and ba[ab[i]] == i
    before, after = np.empty(count, np.int64), np.empty(count, np.int64)
    count = 0
    for i in range(ab.size):
        if ab[i] >= 0 and ba[ab[i]] == i:
            before[count], after[count] = i, ab[i]
            count += 1
    return before, after


@njit(cache=True, nogil=True, error_model="numpy")
def _squares_about(values, centre, terms):  # type: ignore[no-untyped-def]
    """numpy's ``np.sum((values - centre) ** 2)`` (the pairwise order)."""
    for s in range(values.size):
        terms[s] = (values[s] - centre[s]) * (values[s] - centre[s])
    return 0.0 + _pairwise_sum(terms, 0, values.size)


@njit(cache=True, nogil=True, error_model="numpy")
def evidence_sums(px, py, x, y, radius, apart, steps):  # type: ignore[no-untyped-def]
    """One frame's sums for :class:`~starlog.centroiding.evidence.EvidenceAccumulator`: into ``apart`` each method's
    squared differences to the others' median, into ``steps`` its squared platform-free displacements from the
    frame before (``px``, ``py``; no columns: none); returns the star pairs matched (the stars' columns before and
    after; none when under three) and each pair's squared displacement, both axes, per method."""
    methods, n = x.shape
    terms, centre, others = np.empty(max(n, px.shape[1])), np.empty(max(n, px.shape[1])), np.empty(methods)
    if methods >= 2 and n:
        for k in range(methods):
            for axis in range(2):
                values = x if axis == 0 else y
                for s in range(n):
                    m = 0
                    for j in range(methods):
                        if j != k:
                            others[m] = values[j, s]
                            m += 1
                    centre[s] = np.median(others[:m])
                apart[k] = apart[k] + _squares_about(values[k], centre[:n], terms)
    none = np.empty(0, np.int64)
    if px.shape[1] == 0 or n == 0:
        return none, none, np.empty((methods, 0))
    before, after = _matched(px, py, x, y, radius)
    if before.size < 3:
        return none, none, np.empty((methods, 0))
    moves, squares = np.empty(before.size), np.zeros((methods, before.size))
    for k in range(methods):
        for axis in range(2):
            then, now = (px, x) if axis == 0 else (py, y)
            for p in range(before.size):
                moves[p] = now[k, after[p]] - then[k, before[p]]
            centre[: before.size] = np.median(moves)
            steps[k] = steps[k] + _squares_about(moves, centre[: before.size], terms)
            for p in range(before.size):
                squares[k, p] = terms[p] if axis == 0 else squares[k, p] + terms[p]
    return before, after, squares


# ---------------------------------------------------------------- the robust windows' centre of symmetry


@njit(cache=True, nogil=True, error_model="numpy")
def symmetry_shifts(data, valid, reach, shift_x, shift_y):  # type: ignore[no-untyped-def]
    """:func:`starlog.centroiding.robust.symmetry_shifts` of every window into ``shift_x``, ``shift_y`` (the numpy
    form's costs bit for bit: each pixel's absolute difference to its mirror where both are valid and the mirror
    inside the window, summed in numpy's pairwise order, over the pairs; the first least of the shifts in turn)."""
    n, w, _ = data.shape
    h = (w - 1) // 2
    terms = np.empty(w * w)
    for k in range(n):
        best, bx, by = np.inf, 0, 0
        for sy in range(-reach, reach + 1):
            for sx in range(-reach, reach + 1):
                count = 0
                for i in range(w):
                    mi = 2 * h + sy - i
                    ci = min(max(mi, 0), w - 1)
                    for j in range(w):
                        mj = 2 * h + sx - j
                        cj = min(max(mj, 0), w - 1)
                        pair = valid[k, i, j] and valid[k, ci, cj] and 0 <= mi < w and 0 <= mj < w
                        terms[i * w + j] = abs(data[k, i, j] - data[k, ci, cj]) * (1.0 if pair else 0.0)
                        count += pair
                cost = (0.0 + _pairwise_sum(terms, 0, w * w)) / max(count, 1)
                if cost < best:
                    best, bx, by = cost, sx, sy
        shift_x[k], shift_y[k] = bx, by
