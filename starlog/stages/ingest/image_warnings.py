"""The warnings ingest gives about the frames it reads: colour converted to mono, lossy compression.

Shared by every ingest source (:mod:`starlog.stages.ingest.sources`, :mod:`starlog.stages.ingest.tiff`);
it imports none of them.
"""

from __future__ import annotations

__all__ = ["ColourImageWarning", "LossyImageWarning", "lossy_warning"]


class ColourImageWarning(UserWarning):
    """A colour image was converted to mono (luma) on ingest."""


class LossyImageWarning(UserWarning):
    """Lossy-compressed frames were ingested; their compression biases sub-pixel centroids."""


def lossy_warning(what: str) -> LossyImageWarning:
    """The warning for ``what`` (a file, or a file and its codec), which is lossy-compressed."""
    return LossyImageWarning(f"{what} is lossy: its compression biases sub-pixel centroids "
                             "(prefer PNG, TIFF, FITS or SER from the camera).")
