"""What a log holds, as plain data (``starlog info --json`` prints it; :mod:`starlog.cli.describe` its text).

:func:`log_facts` reads the container (:mod:`starlog.io`: files of the chain, channels, time range, the
provenance of every stage) and the records the stages leave in it, named in :mod:`starlog.topics`: the
empirical PSF, the pixel-phase calibrations, the evidence on which centroid method to trust, the solve
runs, and the method to trust from them (:func:`starlog.centroiding.evidence.trust`). It reads the log's
summary and metadata, and of its messages only the first 64 frames of each image channel (a note when their
own stamps disagree with their ``log_time``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from starlog import topics
from starlog.codecs.images import is_image_schema
from starlog.io.chain import base_reference
from starlog.io.frames import stamp_disagreement
from starlog.io.mcap_file import McapFile
from starlog.io.reader import LogReader

__all__ = ["evidence_summaries", "log_facts", "solve_summaries", "trust_summary"]


def log_facts(log: str | os.PathLike[str] | LogReader) -> dict[str, Any]:
    """What a log holds, JSON-ready: ``path``, ``size_bytes``, ``message_count``, ``chunk_count``,
    ``compression``, ``files`` (each file of the chain), ``start_log_time``, ``end_log_time``, ``duration_s``,
    ``channels``, ``provenance`` (one dict per stage), ``notes`` (how the log was read), and, when the log
    holds them, ``epsf``, ``phase_correction``, ``centroid_evidence``, ``solve`` and ``trust``.

    ``log`` is a path, or a log already open (left open; the notes found here are added to its own).
    """
    if isinstance(log, LogReader):
        return _facts(log, log.path)
    with LogReader(log) as reader:
        return _facts(reader, log)


def _facts(log: LogReader, path: str | os.PathLike[str]) -> dict[str, Any]:
    """:func:`log_facts` of an open log opened from ``path``."""
    channels = [c.to_dict() for c in log.channels()]
    start, end = log.time_range()
    for channel in log.channels():
        conflict = log.topic_conflict(channel.topic)
        if conflict is not None:
            log.add_note(conflict)
        elif is_image_schema(channel.schema_name):
            note = stamp_disagreement(log, channel.topic)
            if note:
                log.add_note(note)
    files = [_file_description(file) for file in log.files]
    return {
        "path": str(Path(path)),
        "size_bytes": sum(f["size_bytes"] for f in files),
        "message_count": log.message_count(),
        "chunk_count": sum(f["chunk_count"] for f in files),
        "compression": sorted({c for f in files for c in f["compression"]}),
        "files": files,
        "start_log_time": start,
        "end_log_time": end,
        "duration_s": (end - start) * 1e-9,
        "channels": channels,
        "provenance": [p.to_dict() for p in log.provenance()],
        "notes": list(log.notes),
    } | _epsf_summaries(log) | _phase_summaries(log) | evidence_summaries(log) | solve_summaries(log) | \
        trust_summary(log)


def _file_description(file: McapFile) -> dict[str, Any]:
    """One file of a chain: its path, size, what it holds and (for a layer) what it records of its base."""
    reference = base_reference(file)
    return {"path": str(file.path), "size_bytes": file.size,
            "topics": list(dict.fromkeys(c.topic for _, c in sorted(file.summary.channels.items()))),
            "message_count": sum(e[0] for e in file.channel_extents().values()),
            "chunk_count": len(file.summary.chunk_indexes),
            "compression": sorted({n or "none" for n in file.summary.chunk_indexes.compressions()}),
            "base": None if reference is None else reference.to_dict()}


def _epsf_summaries(log: LogReader) -> dict[str, Any]:
    """``{"epsf": [...]}``: size, oversampling, stars used and FWHM of each stored empirical PSF (none: {}).

    Read from the record's own fields (:data:`starlog.topics.EPSF_METADATA`); the grid is not decoded.
    """
    out = []
    for _, meta in log.metadata(topics.EPSF_METADATA):
        try:
            oversampling, half = int(meta["oversampling"]), int(meta["half_size"])
            side = 2 * half * oversampling + 1
            out.append({"size_px": 2 * half + 1, "grid": [side, side], "oversampling": oversampling,
                        "n_stars": int(meta.get("n_stars", 0)), "fwhm_px": round(float(meta["fwhm_px"]), 4)})
        except (ValueError, KeyError) as err:
            out.append({"error": f"unreadable ePSF record: {err}"})
    return {"epsf": out} if out else {}


def _phase_summaries(log: LogReader) -> dict[str, Any]:
    """``{"phase_correction": [...]}``: each stored pixel-phase calibration record (source, calibrations per
    method, methods declined; :data:`starlog.topics.PHASE_METADATA`); none: {}."""
    out = []
    for _, meta in log.metadata(topics.PHASE_METADATA):
        try:
            out.append({"source": meta.get("source", ""), "calibrations": json.loads(meta["calibrations"]),
                        "declined": json.loads(meta.get("declined", "{}"))})
        except (KeyError, ValueError) as err:
            out.append({"error": f"unreadable phase-correction record: {err!r}"})
    return {"phase_correction": out} if out else {}


def evidence_summaries(log: LogReader) -> dict[str, Any]:
    """``{"centroid_evidence": [...]}``: each stored record of which centroid method to trust (per method the
    evidence, and the method recommended with its reason; :data:`starlog.topics.EVIDENCE_METADATA`); none: {}."""
    out = []
    for _, meta in log.metadata(topics.EVIDENCE_METADATA):
        try:
            out.append({"methods": json.loads(meta["methods"]), "recommended": meta.get("recommended") or None,
                        "reason": meta.get("reason", "")})
        except (KeyError, ValueError) as err:
            out.append({"error": f"unreadable centroid-evidence record: {err!r}"})
    return {"centroid_evidence": out} if out else {}


def solve_summaries(log: LogReader) -> dict[str, Any]:
    """``{"solve": [...]}``: each ``starlog solve`` run's figures per centroid method
    (:data:`starlog.topics.SOLVE_METADATA`); none: {}."""
    out = []
    for _, meta in log.metadata(topics.SOLVE_METADATA):
        try:
            out.append({"methods": json.loads(meta["methods"]), "sky_evidence": json.loads(meta.get("sky_evidence", "{}"))})
        except (KeyError, ValueError) as err:
            out.append({"error": f"unreadable solve record: {err!r}"})
    return {"solve": out} if out else {}


def trust_summary(log: LogReader) -> dict[str, Any]:
    """``{"trust": {...}}``: the centroid method to trust from the evidence the log holds
    (:func:`starlog.centroiding.evidence.trust`: the last ``solve`` record's catalogue residuals, else the last
    centroid record's frame-to-frame noise, else none, saying why); {} for a log without centroids."""
    from starlog.centroiding.evidence import trust

    noise = [r for r in evidence_summaries(log).get("centroid_evidence", []) if "error" not in r]
    solved = [r for r in solve_summaries(log).get("solve", []) if "error" not in r]
    if not noise and not solved:
        return {}
    sky = solved[-1].get("sky_evidence") if solved else None
    missing = ("the log was not plate-solved (starlog solve --centroids all; it needs starlog[solve])" if not solved
               else "its solve record compares no two centroid methods (starlog solve --centroids all)")
    return {"trust": trust(noise[-1]["methods"] if noise else None, sky or None, sky_missing=missing)}
