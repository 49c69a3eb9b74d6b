"""The text ``starlog info`` and ``starlog cat`` print: a log's facts (:func:`starlog.facts.log_facts`) as
lines for people, and each message (:class:`starlog.codecs.plain_values.PlainValues`) as one strict JSON line."""

from __future__ import annotations

import base64
import hashlib
import json
import math
from typing import Any

__all__ = ["evidence_lines", "info_text", "json_line", "json_safe", "trust_lines"]

#: Byte fields up to this size print as base64 text; longer ones as ``{bytes, sha256}``.
INLINE_BYTES = 1024


def json_safe(value: Any) -> Any:
    """Plain values → strict-JSON values (bytes as base64 text, or ``{bytes, sha256}`` when longer than
    :data:`INLINE_BYTES`; NaN and infinities → None)."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list):
        return [json_safe(v) for v in value]
    if isinstance(value, (bytes, bytearray, memoryview)):
        data = bytes(value)
        if len(data) <= INLINE_BYTES:
            return base64.b64encode(data).decode("ascii")
        return {"bytes": len(data), "sha256": "sha256:" + hashlib.sha256(data).hexdigest()}
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def json_line(value: Any) -> str:
    """One line of ``starlog cat``: ``value`` (a message and where it is) as compact strict JSON, ``jq`` reads it."""
    return json.dumps(json_safe(value), separators=(",", ":"), allow_nan=False)


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


def info_text(facts: dict[str, Any]) -> str:
    """``starlog info``'s text of :func:`starlog.facts.log_facts`' result."""
    lines = [
        f"log        {facts['path']}  ({facts['size_bytes'] / 2**20:.1f} MiB, {facts['chunk_count']} chunks, "
        f"{'/'.join(facts['compression']) or 'no data'})",
        *_chain_lines(facts.get("files", [])),
        f"time       {facts['start_log_time']} .. {facts['end_log_time']} ns  ({facts['duration_s']:.3f} s)",
        f"messages   {facts['message_count']}",
        "",
        *_channel_lines(facts["channels"]),
        "",
        *_provenance_lines(facts["provenance"]),
        *_epsf_lines(facts.get("epsf", [])),
        *_phase_lines(facts.get("phase_correction", [])),
        *evidence_lines(facts.get("centroid_evidence", [])),
        *_solve_lines(facts.get("solve", [])),
        *(trust_lines(facts["trust"]) if facts.get("trust") else []),
    ]
    return "\n".join(lines)


def _channel_lines(channels: list[dict[str, Any]]) -> list[str]:
    """The table of channels: topic, schema, encoding, messages, rate; a topic of several channels, each under it."""
    lines = [f"{'topic':<40} {'schema':<28} {'encoding':<9} {'count':>8} {'rate Hz':>9}"]
    for ch in channels:
        lines.append(
            f"{ch['topic']:<40} {ch['schema']:<28} {ch['message_encoding']:<9} {ch['message_count']:>8} "
            f"{ch['rate_hz']:>9.2f}"
        )
        for part in ch.get("per_channel", []):
            lines.append(f"{'  channel ' + str(part['channel_ids'][0]):<40} {part['schema']:<28} "
                         f"{part['message_encoding']:<9} {part['message_count']:>8} {part['rate_hz']:>9.2f}")
    return lines


def _provenance_lines(records: list[dict[str, Any]]) -> list[str]:
    """Each stage: what ran and made which channels, its input, its parameters, the time slice it ran on."""
    lines = ["provenance"]
    if not records:
        lines.append("  (none recorded)")
    for i, p in enumerate(records, 1):
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
    return lines


def _epsf_lines(records: list[dict[str, Any]]) -> list[str]:
    """Each stored empirical PSF: size, oversampling, grid, stars used, FWHM."""
    lines = []
    for e in records:
        if "error" in e:
            lines.append(f"epsf       {e['error']}")
        else:
            lines.append(f"epsf       {e['size_px']}x{e['size_px']} px, oversampling {e['oversampling']} "
                         f"(grid {e['grid'][0]}x{e['grid'][1]}), {e['n_stars']} stars, FWHM {e['fwhm_px']:.3f} px")
    return lines
