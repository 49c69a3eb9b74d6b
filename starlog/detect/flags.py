"""Quality flags shared by detections and centroids (one IntFlag, two public names).

The class lives here (and not in :mod:`starlog.centroiding`) so that :mod:`starlog.detect`
does not import :mod:`starlog.centroiding`; it is re-exported as
:class:`starlog.detect.DetectionFlag` and :class:`starlog.centroiding.CentroidFlag`.
"""

from __future__ import annotations

import enum

__all__ = ["StarFlag"]


class StarFlag(enum.IntFlag):
    """Bit flags stored in the ``flags`` (uint16) field of detections and centroids.

    Attributes
    ----------
    SATURATED : 1
        At least one pixel of the star reached the saturation level. The star is kept;
        saturated pixels are left out of fits (GAUSSFIT) and moments.
    BORDER : 2
        The star's measurement window is cut by the image edge (or lies within the
        border margin); the missing pixels are left out.
    FIT_FAILED : 4
        The sub-pixel method did not converge or left the window; ``x``/``y`` fall back to
        the coarse (NONE) position and ``sigma`` to a noise-model value.
    BLENDED : 8
        The star was split from a connected component holding several separable peaks.
    ELONGATED : 16
        The footprint's axis ratio is above ``elongation_flag`` (kept, but suspicious).
    LOW_SNR : 32
        The star's SNR is below 5: the centroid is valid but its error is large.
    MASKED : 64
        Pixels of the star's window were left out: non-finite (NaN/inf) or hot pixels, or
        pixels its fitted profile plus noise cannot explain (a cosmic ray, a hot pixel, a
        neighbour's wing; :mod:`starlog.centroiding.robust`).
    ARTEFACT : 128
        The detection exists only because of an artefact: once the pixels its star's profile
        cannot explain are masked, nothing within the reach of a star's light passes the
        detector's own threshold (:mod:`starlog.centroiding.artefacts`). The centroid stage keeps
        it in the detections and leaves it out of the centroids.
    TRACKED : 256
        Tracking mode: the star was found in a window around its predicted position, not by a search of
        the whole frame (:mod:`starlog.centroiding.tracking`); without it, the frame was searched in full.
    """

    SATURATED = 1
    BORDER = 2
    FIT_FAILED = 4
    BLENDED = 8
    ELONGATED = 16
    LOW_SNR = 32
    MASKED = 64
    ARTEFACT = 128
    TRACKED = 256
