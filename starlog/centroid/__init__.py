"""Sub-pixel star centroids: methods NONE, MOMENT(_SQUARED), BICUBIC, GAUSSFIT, GRADIENT.

Entry points: :func:`measure_centroids` (centroid given detections), :func:`extract_stars`
(detect + centroid, detections only an artefact made left out), :func:`artefact_detections`
(which those are), :func:`centroid_crb` (the Cramer-Rao bound). Results are structured
arrays of :data:`CENTROID_DTYPE`. Coordinates: x = column, y = row, 0-based, (0, 0) at the
centre of the top-left pixel.
"""

from __future__ import annotations

from starlog.centroid.crb import centroid_crb
from starlog.centroid.extract import (
    EFFICIENCY,
    artefact_detections,
    estimate_psf_sigma,
    extract_stars,
    measure_centroids,
)
from starlog.centroid.table import CENTROID_DTYPE, CentroidFlag, CentroidMethod, empty_centroids

__all__ = [
    "CENTROID_DTYPE",
    "EFFICIENCY",
    "CentroidFlag",
    "CentroidMethod",
    "artefact_detections",
    "centroid_crb",
    "empty_centroids",
    "estimate_psf_sigma",
    "extract_stars",
    "measure_centroids",
]
