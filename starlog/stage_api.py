"""Your own stages: declare what a stage reads and writes; starlog runs it like its built-in stages.

A stage is a function called once per message of the channel it reads, with numpy arrays in
and records (dicts) out::

    from starlog.stage_api import stage

    @stage(name="brightest", version="1.0", reads="centroids",
           writes={"/stars/brightest/{name}": {"title": "demo.Brightest", "type": "object",
                                               "properties": {"flux": {"type": "number"}}}})
    def brightest(message, *, min_snr=5.0):
        stars = message.data[message.data["snr"] >= min_snr]
        return {"flux": float(stars["flux"].max())} if stars.size else None

The function's keyword-only parameters are the stage's options (``--set K=V``, or the keys of
its ``run`` config table); their defaults are recorded with them in the provenance.
:func:`run_stage` (or ``starlog run`` with ``uses = "module:function"``, or an installed entry
point of the group :data:`ENTRY_POINT_GROUP`) runs it with the guarantees of every stage: it
streams, the output is written atomically and carries the stage's provenance (name, version,
options, input digest), every record is checked against its channel's JSON Schema, reruns give
the same bytes, and ``workers`` processes give the same bytes as one. See ``docs/STAGES.md``.
"""

from __future__ import annotations

from starlog.replay.plugins import ENTRY_POINT_GROUP
from starlog.replay.declaration import KINDS, Message, Output, Stage, stage
from starlog.stages.custom import StageSummary, run_stage

__all__ = ["ENTRY_POINT_GROUP", "KINDS", "Message", "Output", "Stage", "StageSummary", "run_stage", "stage"]
