"""A frame's stars: detection, the PSF width, sub-pixel centroids by several methods, artefacts flagged.

:func:`extract_stars` detects the stars of a frame (:func:`starlog.detect.detect_stars`, the detector's options
set for the PSF width: :mod:`starlog.centroiding.psf_width`), measures them with each method
(:func:`starlog.centroiding.measure.measure_methods`) and flags the detections that exist only because of an
artefact (:func:`artefact_candidates`, :func:`~starlog.centroiding.measure.artefact_detections`).

Coordinates: x = column, y = row, 0-based, (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.centroiding.artefacts import light_reach
from starlog.centroiding.epsf import EPSF
from starlog.centroiding.hotpixels import without_hot_pixels
from starlog.centroiding.measure import artefact_detections, measure_methods
from starlog.centroiding.psf_width import detect_options_for_psf, estimate_psf_sigma, window_half_size
from starlog.centroiding.stamps import default_saturation
from starlog.centroiding.table import CentroidFlag, CentroidMethod
from starlog.detect import detect_stars

# measure_methods, window_half_size and detect_options_for_psf are imported from here by the stages too
__all__ = ["artefact_candidates", "detect_options_for_psf", "extract_stars", "measure_methods", "window_half_size"]


def extract_stars(
    image: npt.ArrayLike,
    *,
    methods: Iterable[CentroidMethod | str] = (CentroidMethod.GAUSSFIT,),
    gain: float = 1.0,
    read_noise: float | None = None,
    psf_sigma: float | None = None,
    window: int | None = None,
    saturation: float | None = None,
    detect_options: Mapping[str, Any] | None = None,
    centroid_options: Mapping[str, Any] | None = None,
    epsf: EPSF | None = None,
    hot_pixels: npt.NDArray[np.bool_] | None = None,
    drop_artefacts: bool = True,
) -> tuple[npt.NDArray[np.void], dict[CentroidMethod, npt.NDArray[np.void]]]:
    """Detect the stars of a frame and centroid them with each method.

    Parameters
    ----------
    image : (rows, cols) array_like
        Frame, DN.
    methods : iterable of CentroidMethod or str
        Methods to run (each once).
    gain, read_noise, psf_sigma, window, saturation
        As in :func:`~starlog.centroiding.measure.measure_centroids` (``saturation`` is passed to detection
        too). The PSF sigma is estimated once per frame when not given.
    detect_options : mapping, optional
        Extra keyword options of :func:`starlog.detect.detect_stars` (threshold, ...). On a frame
        whose PSF is undersampled the spike test is relaxed unless these set it
        (:func:`detect_options_for_psf`; with the PSF sigma estimated, the frame is detected again).
    centroid_options : mapping, optional
        Extra keyword options of :func:`~starlog.centroiding.measure.measure_centroids` (debias, weighting, ...).
    epsf : EPSF, optional
        The empirical PSF PSFFIT fits (see :func:`~starlog.centroiding.measure.measure_centroids`).
    hot_pixels : (rows, cols) bool array, optional
        Hot-pixel map (:mod:`starlog.centroiding.hotpixels`): these pixels are never detections
        and are left out of every star's window (counted in ``n_masked``).
    drop_artefacts : bool
        Leave the detections that exist only because of an artefact (flag ``ARTEFACT``,
        :mod:`starlog.centroiding.artefacts`) out of the centroids. They are flagged either way.

    Returns
    -------
    detections : ndarray of DETECTION_DTYPE
        Every detection, ``ARTEFACT`` flagged.
    centroids : dict
        ``{CentroidMethod: ndarray of CENTROID_DTYPE}`` with one row per detection (per detection
        not flagged ``ARTEFACT`` with ``drop_artefacts``), ``star`` naming its detection.
    """
    meths = [CentroidMethod(m) for m in methods]
    if hot_pixels is not None:
        raw = np.asarray(image)
        saturation = default_saturation(raw, saturation)  # of the frame's own type, before the float copy
        image = without_hot_pixels(raw, hot_pixels)
    arr = np.asarray(image)
    det, psf_sigma, detect_options = _detect(arr, psf_sigma, gain, saturation, detect_options)
    out = measure_methods(arr, det, meths, gain=gain, read_noise=read_noise, psf_sigma=psf_sigma, window=window,
                          saturation=saturation, **dict(centroid_options or {}),
                          **({"epsf": epsf} if epsf is not None else {}))
    if det.size:
        artefact = artefact_detections(arr, det, psf_sigma=float(psf_sigma), gain=gain, read_noise=read_noise,
                                       window=window, saturation=saturation, detect_options=detect_options,
                                       candidates=artefact_candidates(det, out.values()))
        det["flags"][artefact] |= np.uint16(CentroidFlag.ARTEFACT)
        for rows in out.values():
            rows["flags"][artefact] |= np.uint16(CentroidFlag.ARTEFACT)
        if drop_artefacts and artefact.any():
            out = {m: rows[~artefact] for m, rows in out.items()}
    return det, out


def _detect(arr: npt.NDArray[Any], psf_sigma: float | None, gain: float, saturation: float | None,
            detect_options: Mapping[str, Any] | None) -> tuple[npt.NDArray[Any], float | None, dict[str, Any]]:
    """The frame's detections, its PSF sigma (estimated from them when not given) and the detector's options
    used (:func:`detect_options_for_psf`: a frame found undersampled is detected again with them)."""
    options = dict(detect_options or {}) if psf_sigma is None else detect_options_for_psf(psf_sigma, detect_options)
    det = detect_stars(arr, saturation=saturation, **options)
    if det.size and psf_sigma is None:
        psf_sigma = estimate_psf_sigma(arr, det, gain=gain, saturation=saturation)
        relaxed = detect_options_for_psf(psf_sigma, options)
        if relaxed != options:
            options, det = relaxed, detect_stars(arr, saturation=saturation, **relaxed)
            psf_sigma = estimate_psf_sigma(arr, det, gain=gain, saturation=saturation) if det.size else psf_sigma
    return det, psf_sigma, options


def artefact_candidates(detections: npt.NDArray[Any], centroids: Iterable[npt.NDArray[Any]]) -> npt.NDArray[np.bool_]:
    """The detections that can exist because of an artefact, from their centroids by any method (tables
    of one row per detection): the window lost pixels (``n_masked`` > 0), the centroid strayed beyond a
    star's light from the detection (:func:`~starlog.centroiding.artefacts.light_reach`), or the fit failed.
    A window with none of these is explained by its star's profile."""
    det = np.asarray(detections)
    out = np.zeros(det.size, np.bool_)
    for rows in centroids:
        off = np.hypot(rows["x"] - det["x"], rows["y"] - det["y"])
        out |= ((np.asarray(rows["n_masked"]) > 0) | ~(off <= light_reach(rows["psf_sigma"]))
                | ((rows["flags"] & CentroidFlag.FIT_FAILED) != 0))
    return out
