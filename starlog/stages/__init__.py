"""Replay stages: each reads the channels it needs from a log and writes a new log with its channels added.

The algorithms live in :mod:`starlog.sim`, :mod:`starlog.detect`, :mod:`starlog.centroid`,
:mod:`starlog.track` and :mod:`starlog.compensate` and know nothing of MCAP; the functions
here join them to the log layer (:mod:`starlog.io`) and record provenance.
"""

from __future__ import annotations

from starlog.stages.ingest import IngestSummary, ingest_folder, ingest_source
from starlog.stages.simulate import simulate_log

__all__ = ["IngestSummary", "ingest_folder", "ingest_source", "simulate_log"]
