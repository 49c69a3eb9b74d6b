"""Compiled (numba): the second of a tracked frame's two calls, :func:`track_measure` — what its stars measure.

After :func:`~starlog.centroiding.tracked_search_kernel.track_search` and numpy's ``erf`` (the model at the coarse
position): GAUSSFIT in the measurement windows (:func:`~starlog.centroiding.star_kernels.fit_stars` itself), the
robust pass's test, the fallback of a failed fit, the centroid rows, the lost-star tests and the state's advance.
The numpy forms (``measure.measure_methods`` for GAUSSFIT, tracking's ``lost_stars`` and ``advance``) are the
references: the same bits, sums over a window in numpy's pairwise order (:mod:`starlog.compiled_numpy`). The inputs
come in the named tuples built by :mod:`~starlog.centroiding.tracked_frame` (``_Stars``, ``_Fit``, ``_Windows``,
``_Rule``, ``_Next``).

numba's cache is refreshed when a function's own file changes, not when a function it calls in another
file does: after editing a kernel that others call, delete the cached code (``find starlog -name '*.nb[ic]'
-delete``, docs/DEVELOPMENT.md). Divisions follow numpy (``error_model="numpy"``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from starlog.centroiding.star_kernels import fisher_sigmas, fit_stars, pixel_profile
from starlog.centroiding.tracked_search_kernel import FINISH, MEASURED, SEARCH
from starlog.compiled_numpy import maximum, pairwise_sum
from starlog.detect.flags import StarFlag

__all__ = ["track_measure"]

_FIT_FAILED, _LOW_SNR, _SATURATED = int(StarFlag.FIT_FAILED), int(StarFlag.LOW_SNR), int(StarFlag.SATURATED)
_BORDER, _MASKED = int(StarFlag.BORDER), int(StarFlag.MASKED)


@njit(cache=True, nogil=True, error_model="numpy")
def _coarse_model(cdf, k, w, out):  # type: ignore[no-untyped-def]
    """Star ``k``'s unit model at its coarse position from the error function at its pixel edges (``cdf``,
    numpy's ``erf``, as :func:`starlog.centroiding.stamps.model` evaluates it)."""
    for i in range(w):
        ey = 0.5 * (cdf[k, 1, i + 1] - cdf[k, 1, i])
        for j in range(w):
            out[i, j] = ey * (0.5 * (cdf[k, 0, j + 1] - cdf[k, 0, j]))


@njit(cache=True, nogil=True, error_model="numpy")
def _linear_flux(data, valid, noise, gain, unit, flux, iterations, terms):  # type: ignore[no-untyped-def]
    """:func:`starlog.centroiding.stamps.linear_flux` of one window (same bits): flux and its error."""
    w = unit.shape[0]
    f = maximum(flux, 0.0)
    den = 1.0
    for _ in range(iterations):
        for i in range(w):
            for j in range(w):
                weight = valid[i, j] / (noise * noise + maximum(f * unit[i, j], 0.0) / gain)
                terms[i * w + j] = weight * unit[i, j] * data[i, j]
                terms[w * w + i * w + j] = weight * unit[i, j] * unit[i, j]
        num = 0.0 + pairwise_sum(terms, 0, w * w)
        den = 0.0 + pairwise_sum(terms, w * w, w * w)
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
            var = noise * noise + maximum(mu[i, j], 0.0) / gain
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
    pixel_profile(fit.edges, cx, width, ex)
    pixel_profile(fit.edges, cy, width, ey)
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
            peak = maximum(peak, v)
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
        fitted.flux[k] = maximum(fitted.f0[k], 1.0 * windows.noise[k])
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
    the PSF width it fitted: then numpy finishes the rows from the fit (``measure.gaussfit_rows``)."""
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
                                          maximum(fitted.f0[k], 0.0), 2, terms)
            fisher_sigmas(windows.valid_f[k:k + 1], windows.noise[k:k + 1], fit.gain, fit.edges,
                          windows.dx0[k:k + 1], windows.dy0[k:k + 1], np.array([maximum(flux, 0.0)]),
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

