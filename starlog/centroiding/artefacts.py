"""Detections that exist only because of an artefact.

A hot pixel or a cosmic-ray hit that the detector's spike and elongation tests let through (a
track with soft edges, a hot pixel on the frame's edge or beside a star) is detected like a star.
Its window's robust masking (:mod:`starlog.centroiding.robust`) then leaves out the pixels the star's
profile cannot explain, and often what remains is noise: without the artefact, the detector would
not have found anything there. Such a detection is flagged ``ARTEFACT``.

The rule reuses the detector's own threshold. The detector keeps a peak of the matched-filtered
frame when ``filtered > threshold * noise * sum(k1^2)`` (:func:`starlog.detect.detect_stars`:
``k1`` the filter's 1-D Gaussian kernel of ``filter_sigma``, ``noise`` the background's per-pixel
sigma, ``sum(k1^2)`` the filtered noise's factor). Applied to the pixels a window keeps, the same
matched filter at pixel ``p`` is

    S(p) = sum_q w_q k(q - p) d_q / (noise * sqrt(sum_q w_q k(q - p)^2)),

with ``d`` the background-subtracted pixels (saturated ones at their clipped value, as the
detector sees them), ``k`` the 2-D kernel ``k1 k1^T`` and ``w_q`` 1 for a pixel kept, 0 for a
masked, missing or outside one. With every pixel kept, ``S`` is the detector's SNR; with some left
out it is the matched filter over the pixels kept, still in units of its own noise.

A detection is an artefact when its window holds pixels its star's model cannot explain
(:func:`starlog.centroiding.robust.suspect_pixels`) and, however the window is read as a star plus
artefacts, once the artefact's pixels are masked ``S(p) <= threshold`` at every pixel within the
reach of a star's light from the detection (:func:`light_reach`, ``max(2, 1.5 psf_sigma)`` px,
the distance beyond which a centroid is taken as drawn off by an artefact). Two readings are
tried (:func:`starlog.centroiding.robust.mask_outliers`, the Gaussian of the frame's PSF): started
from the star's centre of symmetry (the robust windows' own start, which an artefact does not
pull) and from the detection's own model (which an artefact next to a faint star does not capture
either, where the centre of symmetry can land on the artefact and mask the star). Pure noise passes
5 sigma within the reach with a chance of about 1e-5; a star the detector would find without the
artefact's light stays above the threshold in at least one reading, and is kept.

The readings are made once per frame from the detections' coarse positions, whatever the centroid
methods: every method's table loses the same detections. Only the windows where some method's
robust pass masked pixels, its centroid strayed or its fit failed are judged
(:func:`starlog.centroiding.extract.artefact_candidates`): any other window is explained by its star's
profile, so a clean frame costs nothing here.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.ndimage import correlate1d

from starlog.centroiding.stamps import Stamps, model, with_saturated
from starlog.centroiding.robust import (
    ModelError,
    gaussian_predictor,
    mask_outliers,
    mask_windows,
    suspect_pixels,
    take_stamps,
)
from starlog.detect import detect_stars
from starlog.detect.detection import matched_filter_kernel

__all__ = ["detection_threshold", "find_artefacts", "light_reach", "remaining_snr"]

F64 = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]


def light_reach(psf_sigma: F64) -> F64:
    """How far from its detection a star's light reaches, px: ``max(2, 1.5 psf_sigma)``."""
    return np.maximum(2.0, 1.5 * np.asarray(psf_sigma, np.float64))


def detection_threshold(detect_options: Mapping[str, Any] | None = None) -> tuple[float, float]:
    """The detector's ``(threshold, filter_sigma)`` under ``detect_options`` (its defaults for the keys not given)."""
    defaults = inspect.signature(detect_stars).parameters
    options = dict(detect_options or {})
    return (float(options.get("threshold", defaults["threshold"].default)),
            float(options.get("filter_sigma", defaults["filter_sigma"].default)))


def remaining_snr(st: Stamps, dx: F64, dy: F64, noise: F64, filter_sigma: float, reach: F64) -> F64:
    """Each window's highest matched-filter SNR ``S(p)`` (module docstring) over its valid pixels, at the
    pixels within ``reach`` px of ``(dx, dy)`` (offsets from the window centre); ``noise``: per-pixel sigma, DN."""
    k1 = matched_filter_kernel(filter_sigma)
    kept = st.valid.astype(np.float64)
    signal = st.data * kept
    for axis in (1, 2):  # the 2-D kernel is separable, and so is its square
        signal = correlate1d(signal, k1, axis=axis, mode="constant")
        kept = correlate1d(kept, k1 * k1, axis=axis, mode="constant")
    usable = kept > 1e-12 * float(np.sum(k1 * k1)) ** 2
    snr = signal / (np.asarray(noise, np.float64)[:, None, None] * np.sqrt(np.where(usable, kept, 1.0)))
    u = st.u
    near = ((u[None, None, :] - dx[:, None, None]) ** 2 + (u[None, :, None] - dy[:, None, None]) ** 2
            <= (np.asarray(reach, np.float64) ** 2)[:, None, None])
    return np.where(near & usable, snr, -np.inf).max(axis=(1, 2))


def find_artefacts(st: Stamps, dx0: F64, dy0: F64, flux: F64, psf: F64, noise: F64, *, threshold: float,
                   filter_sigma: float, candidates: Mask | None = None) -> Mask:
    """Which detections exist only because of an artefact (module docstring).

    ``st``: the detections' windows; ``(dx0, dy0)``: their coarse positions (offsets from the
    window centres); ``flux``: a first flux there; ``psf``: the PSF sigma per star, px; ``noise``:
    the detector's background sigma per star, DN; ``threshold``, ``filter_sigma``: the detector's
    (:func:`detection_threshold`); ``candidates``: the only detections that may be artefacts (default
    all; the frame's model error is measured on every window either way).
    """
    unit = model(st, dx0, dy0, psf)
    suspect, error = suspect_pixels(st, np.maximum(flux, 0.0)[:, None, None] * unit)
    out = np.zeros(dx0.size, np.bool_)
    rows = np.flatnonzero(suspect.any(axis=(1, 2)) & (True if candidates is None else candidates))
    if rows.size == 0:
        return out
    reach = light_reach(psf[rows])
    remaining = np.full(rows.size, -np.inf)
    for kept, mask in _readings(st, rows, dx0, dy0, unit, flux, psf, error):
        snr = remaining_snr(with_saturated(kept), dx0[rows], dy0[rows], noise[rows], filter_sigma, reach)
        remaining = np.maximum(remaining, np.where(mask.any(axis=(1, 2)), snr, np.inf))
    out[rows] = remaining <= threshold
    return out


def _readings(st: Stamps, rows: npt.NDArray[np.intp], dx0: F64, dy0: F64, unit: F64, flux: F64, psf: F64,
              error: ModelError) -> list[tuple[Stamps, Mask]]:
    """The windows ``rows`` read as a star plus artefacts, two ways: masked by the robust windows
    (:func:`~starlog.centroiding.robust.mask_windows`, from the star's centre of symmetry) and by the same
    clipping started from the detection's own model. Each masked, kept window and its mask."""
    symmetric = mask_windows(st, rows, psf, error)[:2]
    sub = take_stamps(st, rows)
    start = np.maximum(flux[rows], 0.0)[:, None, None] * unit[rows]
    coarse = mask_outliers(sub, gaussian_predictor(psf[rows]), dx0[rows], dy0[rows], start, error=error)[:2]
    return [symmetric, coarse]
