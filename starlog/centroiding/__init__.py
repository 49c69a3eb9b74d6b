"""Sub-pixel star centroids: methods NONE, MOMENT(_SQUARED), BICUBIC, GAUSSFIT, GRADIENT.

Entry points: :func:`measure_centroids` (centroid given detections), :func:`extract_stars`
(detect + centroid, detections only an artefact made left out), :func:`artefact_detections`
(which those are), :func:`centroid_crb` (the Cramer-Rao bound). Results are structured
arrays of :data:`CENTROID_DTYPE`. Coordinates: x = column, y = row, 0-based, (0, 0) at the
centre of the top-left pixel.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from starlog.centroiding.crb import centroid_crb
    from starlog.centroiding.extract import extract_stars
    from starlog.centroiding.measure import EFFICIENCY, artefact_detections, measure_centroids
    from starlog.centroiding.psf_width import estimate_psf_sigma
    from starlog.centroiding.table import CENTROID_DTYPE, CentroidFlag, CentroidMethod, empty_centroids

#: Each public name and the module that defines it, imported on first use: a command that needs only a light
#: module of this package (``info`` reading the evidence) does not load the fitting code and SciPy with it.
_DEFINED_IN = {
    "CENTROID_DTYPE": "table",
    "CentroidFlag": "table",
    "CentroidMethod": "table",
    "empty_centroids": "table",
    "EFFICIENCY": "measure",
    "artefact_detections": "measure",
    "estimate_psf_sigma": "psf_width",
    "extract_stars": "extract",
    "measure_centroids": "measure",
    "centroid_crb": "crb",
}

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


def __getattr__(name: str) -> Any:
    module = _DEFINED_IN.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_DEFINED_IN})
