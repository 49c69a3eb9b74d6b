"""The few lines ``starlog run`` prints at the end, pointing to the report instead of listing every row."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["run_summary_lines"]


def _best(records: list[dict[str, Any]], trusted: str | None = None) -> list[dict[str, Any]]:
    """The records of one track channel (the ``trusted`` method's STATIC track if run, else GAUSSFIT/STATIC, else
    the first), at its highest rate, keep mode."""
    if not records:
        return []
    channels = list(dict.fromkeys((r["method"], r["model"]) for r in records))
    chosen = next((c for c in ((trusted, "STATIC"), ("GAUSSFIT", "STATIC")) if c in channels), channels[0])
    mine = [r for r in records if (r["method"], r["model"]) == chosen and r.get("motion", "keep") == "keep"]
    top = max((r["rate_hz"] for r in mine), default=None)
    return [r for r in mine if r["rate_hz"] == top]


def _trust_text(decision: dict[str, Any] | None) -> str:
    """``; trust M (least catalogue residual, 0.0992 px, 95 % 0.0937-0.1042)``, or why none is named."""
    if not decision:
        return ""
    if decision.get("evidence") is None:
        return "; trust: no method named (" + decision["reason"].split(":", 1)[0] + ")"
    what = "least catalogue residual" if decision["evidence"] == "sky" else "least frame-to-frame noise"
    span = decision.get("interval_px")
    figure = f"{decision['figure_px']:.4f} px" + (f", 95 % {span[0]:.4f}-{span[1]:.4f}" if span else "")
    return f"; trust {decision['method']} ({what}, {figure})"


def run_summary_lines(output: Path, stages: list[tuple[str, dict[str, Any]]], report: Path | None,
                      skipped: Sequence[dict[str, Any]] = (), trusted: dict[str, Any] | None = None) -> list[str]:
    """What ran, the method trusted (``trusted``: what ``"trusted"`` in ``[track]`` stood for, else the centroid
    stage's own recommendation), the headline compensation figures of one track channel, what was ``skipped``
    because the log is too short (:meth:`starlog.compensation.Shortfall.to_dict` each), and where the report and
    the rows are."""
    lines = [f"{output}: " + ", ".join(name for name, _ in stages)]
    for name, result in stages:
        if name == "centroid":
            decision = trusted
            if decision is None and (result.get("recommended") or {}).get("method"):
                method = result["recommended"]["method"]
                figures = result.get("evidence", {}).get(method, {})
                decision = {"method": method, "evidence": "frame-to-frame", "figure_px": figures.get("noise_px"),
                            "interval_px": figures.get("interval_px"), "reason": result["recommended"]["reason"]}
            lines.append(f"  centroid: {result['frames']} frames, {result['detections_per_frame']:.1f} stars/frame"
                         + _trust_text(decision))
        elif name.startswith("track") and result.get("models"):
            model, figures = next(iter(result["models"].items()))
            lines.append(f"  {name}: {len(result['models'])} models, brightest star = track "
                         f"{figures['brightest_track']} ({model}: {figures['confirmed_tracks']} confirmed tracks)")
    if trusted is not None and trusted.get("evidence") is None:
        lines.append(f"  trusted: {trusted['reason']}")
    records = next((r["records"] for n, r in stages if n == "compensate"), [])
    best = _best(records, trusted["method"] if trusted else None)
    if best:
        figures = ", ".join(f"{r['protocol']} {r['figures'][0]['rmse_before']:.3g} -> {r['figures'][0]['rmse_after']:.3g}"
                            for r in best)
        f_d = best[0]["compensation"]["decomposition"]["dominant_frequency"]
        lines.append(f"  compensate: {len(records)} runs; {best[0]['method']}/{best[0]['model']} at "
                     f"{best[0]['rate_hz']:g} Hz, RMSE px {figures}; f_d = {f_d:.3g} Hz")
    if skipped:
        lines.append("  skipped, log too short: compensate " + ", ".join(
            f"{s['rate_hz']:g} Hz {s['protocol']} (needs {s['seconds_needed']:.2f} s)" for s in skipped))
    if report is not None:
        lines.append(f"report: {report} (open it in a browser)")
    if records:
        lines.append("every row: --table (text) or --json")
    return lines
