"""``starlog info``: what a log holds — its files (a chain: the base and each layer), channels, time range,
provenance."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from starlog.io.chain import base_reference
from starlog.io.frames import stamp_disagreement
from starlog.io.images import is_image_schema
from starlog.io.mcap_file import McapFile
from starlog.io.reader import LogReader
from starlog.io import topics

__all__ = ["describe_log", "evidence_summaries", "format_description", "solve_summaries", "trust_lines",
           "trust_summary"]


def describe_log(path: str | os.PathLike[str]) -> dict[str, Any]:
    """A JSON-ready description of the log at ``path`` (reads only its summary and metadata)."""
    with LogReader(path) as log:
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

    Read from the record's own fields (:data:`starlog.io.topics.EPSF_METADATA`); the grid is not decoded.
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
    method, methods declined; :data:`starlog.io.topics.PHASE_METADATA`); none: {}."""
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
    evidence, and the method recommended with its reason; :data:`starlog.io.topics.EVIDENCE_METADATA`); none: {}."""
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
    (:data:`starlog.io.topics.SOLVE_METADATA`); none: {}."""
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


def trust_lines(decision: dict[str, Any], indent: str = "           ") -> list[str]:
    """``trust      METHOD (evidence)`` and the reason; or that none is named and why."""
    if decision.get("method") is None:
        return ["trust      no method named", f"{indent}{decision['reason']}"]
    return [f"trust      {decision['method']} (by {decision['evidence']} evidence)", f"{indent}{decision['reason']}"]


def _solve_lines(records: list[dict[str, Any]]) -> list[str]:
    """Per centroid method: frames solved, stars matched, catalogue residuals, the fitted camera, the attitude
    error against the truth when known."""
    lines = []
    for r in records:
        if "error" in r:
            lines.append(f"solve      {r['error']}")
            continue
        lines.append("solve      per centroid method: frames solved, stars matched / frame, catalogue residual RMS "
                     "px (arcsec), camera focal length px, field of view deg, distortion k")
        for method, m in r["methods"].items():
            cam = m["camera"]
            lines.append(f"           {method:<10} {m['solved']}/{m['frames']}  {m['matched_per_frame']:.1f}  "
                         f"{m['residual_px']:.4f} ({m['residual_arcsec']:.2f})  {cam['focal_px']:.1f}  "
                         f"{cam['fov_deg']:.4f}  {cam['distortion']:+.5f}")
            e = m.get("attitude_error")
            if e:
                a = e["rms_arcsec"]
                lines.append(f"           {'':<10} attitude error RMS arcsec x {a['x']:.3f}, y {a['y']:.3f}, roll "
                             f"{a['roll']:.2f}; / q-method sigma: cross-boresight {e['ratio']['cross_boresight']:.2f}, "
                             f"roll {e['ratio']['roll']:.2f}")
        lines += _sky_lines(r.get("sky_evidence") or {})
    return lines


def _sky_lines(sky: dict[str, Any]) -> list[str]:
    """Per centroid method its catalogue residual on the stars every method identified (one camera per log), its
    95 % interval and the share of bootstrap draws in which it is the least."""
    if not sky:
        return []
    first = next(iter(sky.values()))
    lines = [f"sky        per centroid method: catalogue residual px per axis on the {first.get('stars', 0)} stars every "
             f"method identified in {first.get('frames', 0)} frames (one camera model per log), 95 % bootstrap over "
             "stars, least in % of draws"]
    for method, e in sky.items():
        if e.get("residual_px") is None:
            lines.append(f"           {method:<15} -")
            continue
        lo, hi = e["interval_px"]
        lines.append(f"           {method:<15}{e['residual_px']:>9.4f}  ({lo:.4f}-{hi:.4f})  {100 * e['p_best']:>3.0f} %")
    return lines


def _px(value: Any, width: int = 9) -> str:
    return f"{value:>{width}.4f}" if isinstance(value, (int, float)) else f"{'-':>{width}}"


def evidence_lines(records: list[dict[str, Any]], indent: str = "           ") -> list[str]:
    """Lines on which centroid method to trust: per method its frame-to-frame noise, median reported sigma,
    difference to the other methods, phase S-curve applied +- standard error; then the method recommended."""
    lines = []
    for r in records:
        if "error" in r:
            lines.append(f"trust      {r['error']}")
            continue
        lines.append("evidence   which centroid method (per axis, px): frame-to-frame noise (95 % bootstrap over stars), "
                     "median own sigma, RMS apart from the others' median, S-curve applied x/y +- error")
        for method, e in r["methods"].items():
            amp, err = e.get("phase_amplitude_px"), e.get("phase_error_px")
            phase = (f"{amp[0]:+.4f}/{amp[1]:+.4f} +- {max(err):.4f}" if amp and err else "no calibration")
            span = e.get("interval_px")
            span_text = f" ({span[0]:.4f}-{span[1]:.4f})" if span else f"{'':>16}"
            lines.append(f"{indent}{method:<15}{_px(e.get('noise_px'))}{span_text}{_px(e.get('median_sigma_px'))}"
                         f"{_px(e.get('apart_px'))}   {phase}")
        lines.append(f"{indent}recommended: {r['reason']}")
    return lines


def _phase_lines(records: list[dict[str, Any]]) -> list[str]:
    """``info``'s lines for the phase-correction records: the S-curve amplitude applied per method and axis."""
    lines = []
    for r in records:
        if "error" in r:
            lines.append(f"phase      {r['error']}")
            continue
        lines.append(f"phase      pixel-phase correction ({r['source']}); S-curve amplitude px applied "
                     "(estimate +- error), distinct star positions")
        for c in r["calibrations"]:
            try:
                a, e, s = c["amplitude_px"], c["estimate_px"], c["error_px"]
                axes = "  ".join(f"{k} {a[k][0]:+.4f} ({e[k][0]:+.4f} +- {s[k][0]:.4f})" for k in ("x", "y"))
                lines.append(f"           {c['method']:<15} {axes}  {c.get('n_stars', 0)} positions")
            except (KeyError, IndexError, TypeError):
                lines.append(f"           unreadable calibration {c!r:.60}")
        for method, why in r["declined"].items():
            lines.append(f"           {method:<15} not corrected: {why}")
    return lines


def _chain_lines(files: list[dict[str, Any]]) -> list[str]:
    """``info``'s lines for a chain: each file, the first log first, with what it adds (none for one file)."""
    if len(files) < 2:
        return []
    lines = [f"chain      {len(files)} files, read as one log (the first is the base, each next one a layer on "
             "the one before it)"]
    for i, f in enumerate(files, 1):
        topics = ", ".join(f["topics"]) or "no channel"
        lines.append(f"  {i}. {f['path']}  ({f['size_bytes'] / 2**20:.1f} MiB, {f['message_count']} messages): "
                     f"{topics}")
        if f["base"]:
            lines.append(f"     on {f['base']['path']} ({f['base']['sha256']})")
    return lines


def _short(value: Any, limit: int = 80) -> str:
    """A parameter's value on one line: scalars as they are, lists and maps as compact JSON, cut at ``limit``."""
    text = json.dumps(value, separators=(",", ":"), default=str) if isinstance(value, (dict, list)) else str(value)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def format_description(info: dict[str, Any]) -> str:
    """Human-readable text of :func:`describe_log`'s result."""
    lines = [
        f"log        {info['path']}  ({info['size_bytes'] / 2**20:.1f} MiB, {info['chunk_count']} chunks, "
        f"{'/'.join(info['compression']) or 'no data'})",
        *_chain_lines(info.get("files", [])),
        f"time       {info['start_log_time']} .. {info['end_log_time']} ns  ({info['duration_s']:.3f} s)",
        f"messages   {info['message_count']}",
        "",
        f"{'topic':<40} {'schema':<28} {'encoding':<9} {'count':>8} {'rate Hz':>9}",
    ]
    for ch in info["channels"]:
        lines.append(
            f"{ch['topic']:<40} {ch['schema']:<28} {ch['message_encoding']:<9} {ch['message_count']:>8} "
            f"{ch['rate_hz']:>9.2f}"
        )
        for part in ch.get("per_channel", []):  # a topic of several channels: each one under it
            lines.append(f"{'  channel ' + str(part['channel_ids'][0]):<40} {part['schema']:<28} "
                         f"{part['message_encoding']:<9} {part['message_count']:>8} {part['rate_hz']:>9.2f}")
    lines.append("")
    lines.append("provenance")
    if not info["provenance"]:
        lines.append("  (none recorded)")
    for i, p in enumerate(info["provenance"], 1):
        params = ", ".join(f"{k}={_short(v)}" for k, v in sorted(p["parameters"].items()) if k != "range")
        lines.append(f"  {i}. {p['stage']} (starlog {p['version']}) -> {', '.join(p['channels']) or 'no new channel'}")
        if p["input_digest"]:
            lines.append(f"     input {p['input_digest']}")
        if params:
            lines.append(f"     {params}")
        time_range = p["parameters"].get("range")
        if isinstance(time_range, dict):  # a stage run on a time slice (--start/--end)
            span = (f"log_time from {time_range.get('start_ns')} ns" if time_range.get("end_ns") is None else
                    f"log_time {time_range.get('start_ns')} to {time_range['end_ns']} ns (end exclusive)")
            lines.append(f"     range [{time_range.get('start') or 'start'}, {time_range.get('end') or 'end'}): {span}")
    for e in info.get("epsf", []):
        if "error" in e:
            lines.append(f"epsf       {e['error']}")
        else:
            lines.append(f"epsf       {e['size_px']}x{e['size_px']} px, oversampling {e['oversampling']} "
                         f"(grid {e['grid'][0]}x{e['grid'][1]}), {e['n_stars']} stars, FWHM {e['fwhm_px']:.3f} px")
    lines += _phase_lines(info.get("phase_correction", []))
    lines += evidence_lines(info.get("centroid_evidence", []))
    lines += _solve_lines(info.get("solve", []))
    if info.get("trust"):
        lines += trust_lines(info["trust"])
    return "\n".join(lines)
