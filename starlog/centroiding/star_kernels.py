"""Compiled (numba) inner loops of the centroid methods, one star window at a time.

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
- :func:`gather_windows` — the star windows (:func:`~starlog.centroiding.stamps.gather_stamps`);
- :func:`symmetry_shifts` — the robust windows' centre of symmetry (:mod:`starlog.centroiding.robust`), the 25
  reflections of each window tried in turn.

The tracked frame's kernels (:mod:`starlog.centroiding.tracked_search_kernel`,
:mod:`starlog.centroiding.tracked_measure_kernel`) call the fit, the Cramer-Rao sigma, :func:`pixel_profile` and the
window cutter. numba's cache is refreshed when a function's own file changes, not when a function it calls in another
file does: after editing a kernel that others call, delete the cached code (``find starlog -name '*.nb[ic]'
-delete``, docs/DEVELOPMENT.md). Compiled on first use and cached beside this file
(``__pycache__``), or in numba's user cache when the package folder is read-only. Divisions follow numpy
(``error_model="numpy"``): a zero denominator gives inf or nan, not an exception. No function here calls itself
(numba does not load a cached recursive function safely).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from starlog.compiled_numpy import pairwise_sum

__all__ = ["GAUSSIAN", "NONE", "OPTIMAL", "fisher_sigmas", "fit_stars", "gather_windows", "pixel_profile",
           "symmetry_shifts", "weighted_centres"]

_INV_SQ2 = 1.0 / math.sqrt(2.0)
_ISQ2PI = 1.0 / math.sqrt(2.0 * math.pi)
_MAX_PAR = 5


@njit(cache=True, nogil=True, error_model="numpy")
def pixel_profile(edges, c, s, out):  # type: ignore[no-untyped-def]
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
def _damped_step(a_mat, grad, lam, npar, fit_sigma, s, damped, step):  # type: ignore[no-untyped-def]
    """The Levenberg-damped Gauss-Newton step into ``step``: non-finite parts zeroed, the centre's move limited to
    half a pixel and the width's to 30 %; False when the damped system is singular (the step is zero)."""
    for p in range(npar):
        for q in range(npar):
            damped[p, q] = a_mat[p, q] * (1.0 + lam) if p == q else a_mat[p, q]
    solved = _solve(damped, grad, npar, step)
    if not solved:
        step[:npar] = 0.0
    for p in range(npar):
        if not math.isfinite(step[p]):
            step[p] = 0.0
    step[0] = min(max(step[0], -0.5), 0.5)
    step[1] = min(max(step[1], -0.5), 0.5)
    if fit_sigma:
        step[npar - 1] = min(max(step[npar - 1], -0.3 * s), 0.3 * s)
    return solved


@njit(cache=True, nogil=True, error_model="numpy")
def fit_stars(data, valid, noise, gain, edges, cx, cy, flux, background, width, fit_background, fit_sigma,
              iterations, tol, sigma, flux_err, good_var, active):  # type: ignore[no-untyped-def]
    """Fit every window in place: ``cx``, ``cy``, ``flux``, ``background``, ``width`` start at the first guess
    and end at the solution; ``sigma``, ``flux_err``, ``good_var`` (the Fisher covariance could be inverted)
    and ``active`` (no singular step) are filled. Arrays as in :class:`~starlog.centroiding.stamps.Stamps`."""
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
            pixel_profile(edges, x, s, ex)
            pixel_profile(edges, y, s, ey)
            _slopes(edges, x, s, dex, dsx)
            _slopes(edges, y, s, dey, dsy)
            c0 = _normal(data[k], valid[k], var0, gain, f, b, ex, ey, dex, dey, dsx, dsy, fit_background, fit_sigma,
                         fitted, a_mat, grad)
            if not _damped_step(a_mat, grad, lam, npar, fit_sigma, s, damped, step):
                active[k] = False
            nx, ny = x + step[0], y + step[1]
            nf = max(f + step[2], 1e-6 * noise[k] + 1e-12)
            nb = b + step[3] if fit_background else b
            ns = min(max(s + step[npar - 1], 0.2), 20.0) if fit_sigma else s
            pixel_profile(edges, nx, ns, tx)
            pixel_profile(edges, ny, ns, ty)
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
        pixel_profile(edges, x, s, ex)
        pixel_profile(edges, y, s, ey)
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
        pixel_profile(edges, cx[k], width[k], ex)
        pixel_profile(edges, cy[k], width[k], ey)
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
        pixel_profile(edges, cx, s, ex)
        pixel_profile(edges, cy, s, ey)
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
    :func:`~starlog.centroiding.stamps.gather_stamps_vectorised` cuts them.

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
                cost = (0.0 + pairwise_sum(terms, 0, w * w)) / max(count, 1)
                if cost < best:
                    best, bx, by = cost, sx, sy
        shift_x[k], shift_y[k] = bx, by
