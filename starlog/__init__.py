"""starlog: star-tracker centroid extraction with every step kept in MCAP logs.

Conventions used everywhere in starlog (functions, messages, tables):

* pixel coordinates are ``x`` = column and ``y`` = row, 0-based, with (0, 0) at the
  *centre* of the top-left pixel (the numpy / OpenCV / photutils convention);
* times are integer nanoseconds named ``log_time``.

From Python: :func:`starlog.open` reads a log as tables, frames and messages (:class:`Log`), and one
function per command runs it with the command's options and returns what it prints
(:func:`starlog.simulate`, :func:`starlog.ingest`, :func:`starlog.centroid`, :func:`starlog.track`,
:func:`starlog.motion`, :func:`starlog.compensate`, :func:`starlog.solve`, :func:`starlog.run`,
:func:`starlog.export`, :func:`starlog.flatten`, :func:`starlog.verify`; :mod:`starlog.api`).
Errors are :class:`StarlogError` subclasses with the command's one-line message.

Subpackages: :mod:`starlog.io` (the MCAP container), :mod:`starlog.codecs` (the payloads: star tables, images,
JSON messages, schemas, other tools' messages), :mod:`starlog.topics` (channel names), :mod:`starlog.facts`
(what a log holds, as data), :mod:`starlog.sim` (star-image simulator), :mod:`starlog.detect` and
:mod:`starlog.centroiding` (single-frame extraction), :mod:`starlog.tracking` (UKF tracking),
:mod:`starlog.platform_motion` (the platform's motion from all stars), :mod:`starlog.compensation` (error
decomposition and compensation), :mod:`starlog.stages` (the stages that join algorithms and logs),
:mod:`starlog.replay` (what the stages share to replay a log), :mod:`starlog.excerpt` (``filter`` and ``cat``),
:mod:`starlog.pipeline` (several stages from one config), :mod:`starlog.parquet` (Parquet), :mod:`starlog.batch`
(many logs on Dask), :mod:`starlog.experiment` (the paper's tables) and :mod:`starlog.cli` (the command line).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from starlog.version import __version__

__all__ = ["Log", "StarlogError", "__version__", "centroid", "compensate", "export", "flatten", "ingest", "motion",
           "open", "run", "simulate", "solve", "track", "verify"]

if TYPE_CHECKING:
    from starlog.api import (
        centroid,
        compensate,
        export,
        flatten,
        ingest,
        motion,
        open,
        run,
        simulate,
        solve,
        track,
        verify,
    )
    from starlog.errors import StarlogError
    from starlog.log import Log

_DEFINED_IN = {"StarlogError": "starlog.errors", "Log": "starlog.log"} | {
    name: "starlog.api" for name in ("centroid", "compensate", "export", "flatten", "ingest", "motion", "open", "run",
                                     "simulate", "solve", "track", "verify")}


def __getattr__(name: str) -> object:
    """The public face, imported on first use: ``import starlog`` stays instant (the command line starts with it)."""
    if name in _DEFINED_IN:
        import importlib

        value = getattr(importlib.import_module(_DEFINED_IN[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'starlog' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
