"""The stages: each joins an algorithm to logs and records what it did in the log's provenance.

Two stages write a new log: ``simulate`` (:mod:`~starlog.stages.simulate`, frames from :mod:`starlog.sim`) and
``ingest`` (:mod:`~starlog.stages.ingest`: image files, SER, video). The others replay a log: each reads the
channels it needs and writes its own channels as a layer on its input (:mod:`starlog.io.chain`; with
``flatten``, the whole chain as one self-contained log): ``centroid`` (:mod:`~starlog.stages.centroid`,
:mod:`starlog.detect` and :mod:`starlog.centroiding`), ``track`` (:mod:`~starlog.stages.track`,
:mod:`starlog.tracking`), ``motion`` (:mod:`~starlog.stages.motion`, :mod:`starlog.platform_motion`),
``compensate`` (:mod:`~starlog.stages.compensate`, :mod:`starlog.compensation`), ``solve``
(:mod:`~starlog.stages.solve`, :mod:`starlog.attitude`) and your own stages (:mod:`~starlog.stages.custom`,
declared with :mod:`starlog.stage_api`). A stage with parts of its own is a package holding them
(``centroid/``, ``compensate/``, ``ingest/``).

The algorithms know nothing of MCAP; what the stages share to read and write logs (the layer and its
provenance, ``--start`` / ``--end``, worker pools, blocks, spools, progress) is :mod:`starlog.replay`.

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
