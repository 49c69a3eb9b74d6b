"""starlog: star-tracker centroid extraction with every step kept in MCAP logs.

Conventions used everywhere in starlog (functions, messages, tables):

* pixel coordinates are ``x`` = column and ``y`` = row, 0-based, with (0, 0) at the
  *centre* of the top-left pixel (the numpy / OpenCV / photutils convention);
* times are integer nanoseconds named ``log_time``.

Subpackages: :mod:`starlog.io` (the MCAP log layer), :mod:`starlog.sim` (star-image
simulator), :mod:`starlog.detect` and :mod:`starlog.centroiding` (single-frame extraction),
:mod:`starlog.tracking` (UKF tracking), :mod:`starlog.compensation` (error decomposition and
compensation), :mod:`starlog.stages` (the stages that join algorithms and logs),
:mod:`starlog.replay` (what the stages share to replay a log), :mod:`starlog.excerpt` (``filter`` and ``cat``),
:mod:`starlog.pipeline` (several stages from one config), :mod:`starlog.parquet` (Parquet),
:mod:`starlog.batch` (many logs on Dask), :mod:`starlog.experiment` (the paper's tables) and
:mod:`starlog.cli` (the command line).
"""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["StarlogError", "__version__"]


def __getattr__(name: str) -> object:
    """``StarlogError``, imported on first use: ``import starlog`` stays instant (the command line starts with it)."""
    if name == "StarlogError":
        from starlog.errors import StarlogError

        return StarlogError
    raise AttributeError(f"module 'starlog' has no attribute {name!r}")
