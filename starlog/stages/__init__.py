"""Replay stages: each reads the channels it needs from a log and writes a new log with its channels added.

The algorithms live in :mod:`starlog.sim`, :mod:`starlog.detect`, :mod:`starlog.centroiding`,
:mod:`starlog.tracking` and :mod:`starlog.compensation` and know nothing of MCAP; the functions
here join them to the log layer (:mod:`starlog.io`) and record provenance.

The names below are imported on first use, so a command running one stage does not pay for
importing the others (simulation and ingest pull in scipy.special, OpenCV, image readers).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from starlog.stages.ingest import IngestSummary, ingest_folder, ingest_source
    from starlog.stages.simulate import simulate_log

__all__ = ["IngestSummary", "ingest_folder", "ingest_source", "simulate_log"]

_MODULE_OF = {
    "IngestSummary": "starlog.stages.ingest",
    "ingest_folder": "starlog.stages.ingest",
    "ingest_source": "starlog.stages.ingest",
    "simulate_log": "starlog.stages.simulate",
}


def __getattr__(name: str) -> Any:
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
