"""Tracking mode's frame in compiled code: the light check, the window search, GAUSSFIT in the windows, the
lost-star tests and the state's advance of every tracked star, in two compiled calls a frame.

:func:`track_frame` gives what :func:`starlog.centroiding.tracking.track_frame_vectorised` gives (the numpy form,
kept as the reference the tests compare with): the frame's cells, the located detection rows, the first method's
centroid rows and the state after the frame. Between its two calls
(:func:`starlog.centroiding.tracked_search_kernel.track_search`,
:func:`starlog.centroiding.tracked_measure_kernel.track_measure`) numpy's ``erf`` evaluates each star's model at its
coarse position, the one number of the measurement the compiled loops do not take from the full mode's code, so a star
measured here gets full mode's bytes for the same detection row (:func:`starlog.centroiding.measure.measure_methods`).

What it leaves to numpy: a frame whose first method is not GAUSSFIT or whose PSF width is not given
(:class:`WindowFit`) is only located (``centroids`` None: the caller measures the located rows and ends the frame
with :func:`~starlog.centroiding.tracking.finish_tracked`); a frame where a star's window holds a pixel its model
cannot explain or its centroid strayed (the robust re-measurement, which judges every window of the frame
together), or a fit failed while the PSF width is fitted, has its rows finished by numpy from the compiled windows
and fit (:func:`~starlog.centroiding.measure.gaussfit_rows`: the robust pass, the fallback and the table, frame-wide
numpy calls, a star's own only for the windows re-measured; ``remeasured`` in the result).

Same numbers as the numpy form: the light check's cells, medians and thresholds and the window search's filter,
peak and flags bit for bit; the coarse positions to the last bit of a logarithm (the C library's here, numpy's
there); the measurement bit for bit given the detection rows (the fit is
:func:`~starlog.centroiding.star_kernels.fit_stars` itself, sums run in numpy's pairwise order); the robust test's
model takes the C library's ``erf``, so a pixel within a rounding error of its clip level could be judged apart.

Coordinates: x = column, y = row, 0-based, (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt
from scipy.special import erf

from starlog.centroiding.gaussfit import GaussFitResult
from starlog.centroiding.measure import gaussfit_rows
from starlog.centroiding.robust import clip_level
from starlog.centroiding.stamps import SHOULDER, Stamps
from starlog.centroiding.table import CENTROID_DTYPE
from starlog.centroiding.tracking import TrackedFrame, TrackingSettings, TrackState, finish_tracked
from starlog.detect import DETECTION_DTYPE
from starlog.detect.detection import matched_filter_kernel

__all__ = ["WindowFit", "track_frame"]

F64 = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class WindowFit:
    """How the compiled frame measures its stars: GAUSSFIT as :func:`~starlog.centroiding.measure.measure_methods`
    runs it with these options (windows of ``half_size``, the PSF width ``psf_sigma`` given)."""

    half_size: int
    psf_sigma: float
    gain: float
    read_noise: float | None = None
    fit_psf_sigma: bool = False
    robust: bool = True


_NO_FIT = WindowFit(half_size=3, psf_sigma=1.0, gain=1.0)
"""Settings the kernels take when no window is measured."""


class _Light(NamedTuple):
    cells: F64  # the acquisition's cell means ((0, 0): no check)
    excess: F64  # TrackState.excess
    before: Mask  # the frame before's risen cells ((0, 0): none)
    steps: F64  # offsets from a star, px, whose cells are near it
    cell: int
    sigma: float
    exact: bool  # pixels summed exactly in integers
    risen: Mask  # out: this frame's risen cells


class _Search(NamedTuple):
    kernel: F64
    power: float  # sum of the kernel's squares: the filtered noise's factor
    half: int
    threshold: float
    border: int
    just_acquired: bool


class _Stars(NamedTuple):
    reference: npt.NDArray[np.void]
    flux: F64
    x: F64
    y: F64
    vx: F64
    vy: F64
    quiet: Mask
    acquired_x: F64
    acquired_y: F64


class _Fit(NamedTuple):
    half: int
    psf: float
    gain: float
    noise_floor: float  # read noise in DN (-inf: none)
    saturation: float
    shoulder: float  # stamps.SHOULDER: a saturated core's shoulders are saturated too
    fit_background: bool
    fit_sigma: bool
    robust: bool
    iterations: int
    tol: float
    edges: F64  # pixel edges of a window
    clip: F64  # clip_level of each count of valid pixels


class _Windows(NamedTuple):
    data: F64
    valid: Mask
    valid_f: F64
    satpix: Mask
    flags: Mask  # (n, 3): saturated, cut, masked
    left_out: npt.NDArray[np.int32]
    xc: npt.NDArray[np.intp]
    yc: npt.NDArray[np.intp]
    noise: F64
    background: F64
    dx0: F64
    dy0: F64
    flux0: F64  # the detections' flux
    arguments: F64  # (n, 2, w + 1) of erf at the pixel edges, x then y
    cdf: F64


class _Fitted(NamedTuple):  # gaussfit.GaussFitResult's columns, and the first flux
    f0: F64
    dx: F64
    dy: F64
    flux: F64
    flux_err: F64
    background: F64
    width: F64
    sigma: F64
    ok: Mask


class _Rule(NamedTuple):
    flux_change: float
    flux_sigma: float
    reach: float
    margin: float
    just_acquired: bool


class _Next(NamedTuple):
    lost: Mask
    x: F64
    y: F64
    vx: F64
    vy: F64
    stay: Mask


def _windows(n: int, w: int) -> _Windows:
    return _Windows(np.empty((n, w, w)), np.empty((n, w, w), np.bool_), np.empty((n, w, w)),
                    np.empty((n, w, w), np.bool_), np.empty((n, 3), np.bool_), np.empty(n, np.int32),
                    np.empty(n, np.intp), np.empty(n, np.intp), np.empty(n), np.empty(n), np.empty(n), np.empty(n),
                    np.empty(n), np.empty((n, 2, w + 1)), np.empty((n, 2, w + 1)))


@functools.lru_cache(maxsize=16)
def _fit_settings(fit: WindowFit, saturation: float) -> _Fit:
    """The kernels' form of ``fit`` (made once per fit and saturation level)."""
    h, w = fit.half_size, 2 * fit.half_size + 1
    edges = (-h - 0.5) + np.arange(w + 1, dtype=np.float64)  # as stamps.pixel_edges
    floor = fit.read_noise / fit.gain if fit.read_noise is not None else -np.inf
    return _Fit(h, float(fit.psf_sigma), float(fit.gain), float(floor), float(saturation), SHOULDER, True,
                fit.fit_psf_sigma, fit.robust, 12, 1e-4, edges, clip_level(np.arange(w * w + 1)))


@functools.lru_cache(maxsize=16)
def _search_settings(settings: TrackingSettings) -> tuple[F64, float]:
    k1 = matched_filter_kernel(settings.filter_sigma)
    return k1, float(np.sum(k1 * k1))


def _frame_image(image: npt.NDArray[Any]) -> npt.NDArray[Any]:
    """The frame as the compiled loops read it (native byte order; float16 widened)."""
    if image.dtype.kind == "f" and image.dtype.itemsize not in (4, 8):
        image = image.astype(np.float64)
    if not image.dtype.isnative:
        image = image.astype(image.dtype.newbyteorder("="))
    return image


def _light(image: npt.NDArray[Any], state: TrackState, settings: TrackingSettings, before: Mask | None,
           reach: int) -> _Light | None:
    """The light check's inputs; None when the frame's cells are not the acquisition's (another size)."""
    c = settings.cell
    cells = state.cells if state.cells is not None else np.zeros((0, 0))
    rows, cols = image.shape[0] // c, image.shape[1] // c
    if state.cells is not None and cells.shape != ((rows, cols) if rows and cols else (0, 0)):  # as cell_means
        return None
    excess = state.excess if state.excess is not None else np.zeros(cells.shape)
    before = before if before is not None else np.zeros((0, 0), np.bool_)
    exact = image.dtype.kind in "ui" and image.dtype.itemsize <= 2 and c <= 256
    return _Light(cells, excess, before, _steps(reach, c), c, float(settings.new_light_sigma), exact,
                  np.zeros(cells.shape, np.bool_))


@functools.lru_cache(maxsize=16)
def _steps(reach: int, cell: int) -> F64:
    """Offsets from a star whose cells are near it (:func:`~starlog.centroiding.tracking.new_light`'s)."""
    return np.clip(np.arange(-reach, reach + cell, cell), -reach, reach).astype(np.float64)


@functools.lru_cache(maxsize=16)
def _default_saturation(dtype: np.dtype[Any]) -> float:
    """The saturation level of a frame of ``dtype`` without one given: the type's maximum for integers."""
    return float(np.iinfo(dtype).max) if dtype.kind in "ui" else np.inf


def track_frame(image: npt.NDArray[Any], state: TrackState, settings: TrackingSettings, before: Mask | None,
                half_size: int, fit: WindowFit | None = None, saturation: float | None = None) -> TrackedFrame:
    """One tracked frame, compiled: :func:`~starlog.centroiding.tracking.track_frame_vectorised`'s result, measured by
    ``fit`` (None: located only). ``image``: the frame as measured (hot pixels missing); ``saturation``: its level
    (None: the type's maximum for integers, none for floats); ``half_size``: the windows' half-size the light check
    and the lost-star tests keep clear."""
    from starlog.centroiding.tracked_measure_kernel import track_measure
    from starlog.centroiding.tracked_search_kernel import LOCATED, MEASURED, SEARCH, track_search

    image = _frame_image(np.asarray(image))
    light = _light(image, state, settings, before, half_size + settings.search + 1)
    if light is None:
        return TrackedFrame(search=True, risen=None)
    n = state.x.size
    k1, power = _search_settings(settings)
    just_acquired = state.since_acquisition == 0
    search = _Search(k1, power, settings.search, float(settings.threshold), settings.border, just_acquired)
    stars = _Stars(state.reference, state.flux, state.x, state.y, state.vx, state.vy, state.quiet_stars,
                   state.acquired_x, state.acquired_y)
    level = _default_saturation(image.dtype) if saturation is None else float(saturation)
    kernel_fit = _fit_settings(fit if fit is not None else _NO_FIT, level)
    windows = _windows(n if fit is not None else 0, 2 * kernel_fit.half + 1)  # no rows: no windows cut
    detections, found = np.zeros(n, DETECTION_DTYPE), np.zeros(n, np.bool_)
    risen = light.risen if state.cells is not None else np.zeros((0, 0), np.bool_)
    if track_search(image, light, search, stars, kernel_fit, windows, detections, found) != LOCATED:
        return TrackedFrame(search=True, risen=risen)
    located = TrackedFrame(search=False, risen=risen, detections=detections, found=found)
    if fit is None:
        return located
    erf(windows.arguments, out=windows.cdf)
    centroids = np.zeros(n, CENTROID_DTYPE)
    fitted = _Fitted(*(np.empty(n) for _ in range(8)), np.empty(n, np.bool_))
    after = _Next(np.zeros(n, np.bool_), np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n, np.bool_))
    rule = _Rule(float(settings.flux_change), float(settings.flux_sigma), float(half_size), float(settings.search),
                 just_acquired)
    status = track_measure(image.shape, detections, found, stars, kernel_fit, windows, rule, fitted, centroids, after)
    if status == SEARCH:
        return TrackedFrame(search=True, risen=risen)
    if status != MEASURED:  # a window needs the robust re-measurement: numpy finishes the rows
        rows = _finished_in_numpy(detections, kernel_fit, windows, fitted, fit)
        return replace(finish_tracked(located, rows, state, settings, half_size, image.shape), remeasured=True)
    stay = after.stay
    state = replace(state, reference=state.reference[stay], flux=state.flux[stay], x=after.x[stay], y=after.y[stay],
                    vx=after.vx[stay], vy=after.vy[stay], quiet=(stars.quiet | after.lost)[stay],
                    since_acquisition=state.since_acquisition + 1)
    return TrackedFrame(search=False, risen=risen, detections=detections, found=found, centroids=centroids,
                        lost=after.lost, state=state)


def _finished_in_numpy(detections: npt.NDArray[np.void], kernel_fit: _Fit, windows: _Windows, fitted: _Fitted,
                       fit: WindowFit) -> npt.NDArray[np.void]:
    """The first method's rows from the compiled windows and fit, finished as full mode finishes them
    (:func:`~starlog.centroiding.measure.gaussfit_rows`: the robust re-measurement, a failed fit's fallback)."""
    stamps = Stamps(data=windows.data, valid=windows.valid, xc=windows.xc, yc=windows.yc, h=kernel_fit.half,
                    background=windows.background, noise=windows.noise, gain=kernel_fit.gain,
                    saturated=windows.flags[:, 0], cut=windows.flags[:, 1], masked=windows.flags[:, 2],
                    satpix=windows.satpix, clip=kernel_fit.saturation - windows.background)
    result = GaussFitResult(dx=fitted.dx, dy=fitted.dy, flux=fitted.flux, flux_err=fitted.flux_err,
                            background=fitted.background, psf_sigma=fitted.width, sigma=fitted.sigma, ok=fitted.ok)
    return gaussfit_rows(detections, stamps, windows.dx0, windows.dy0, fitted.f0, result, windows.left_out,
                         psf_sigma=fit.psf_sigma, gain=fit.gain, fit_psf_sigma=fit.fit_psf_sigma, robust=fit.robust)
