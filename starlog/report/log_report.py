"""The report of one log: its frame and centroids, tracks, the brightest star's error and spectrum, the
error decomposition, compensation before/after per protocol, the strategy decisions, the attitude per centroid
method and the provenance."""

from __future__ import annotations

import os
from collections.abc import Iterable
from html import escape
from pathlib import Path
from typing import Any

import numpy as np

from starlog.io.output_files import atomic_output
from starlog.report.attitude import attitude_section
from starlog.report.collect import ReportData, collect_report_data
from starlog.report.page import Raw, figure, html_page, missing, table
from starlog.report.figures import PALETTE, Bars, Series, bar_chart, frame_figure, line_chart

__all__ = ["amplitude_spectrum", "render_report", "write_report", "write_text_atomic"]

CATEGORIES = ("SYSTEMATIC_LOW_FREQ", "SYSTEMATIC_HIGH_FREQ", "MEASUREMENT_NOISE", "RANDOM_QUANTIZATION",
              "MODEL_MISMATCH")
STRATEGIES = ("ADAPTIVE_WINDOW_TREND", "ADAPTIVE_MEDIAN", "LOCAL_SMOOTHING", "AR_PREDICTION", "CONFIDENCE_WEIGHTED")


def amplitude_spectrum(error: np.ndarray, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Single-sided amplitude spectrum ``2 |FFT| / N`` (px) of a mean-removed series sampled at ``rate_hz``."""
    e = np.asarray(error, float) - np.mean(error)
    amp = 2.0 * np.abs(np.fft.rfft(e)) / max(e.size, 1)
    return np.fft.rfftfreq(e.size, 1.0 / rate_hz), amp


def _words(names: Iterable[str]) -> list[str]:
    """``SYSTEMATIC_LOW_FREQ`` -> ``systematic low freq`` (table headers that wrap)."""
    return [n.replace("_", " ").lower() for n in names]


def _label(record: dict[str, Any]) -> str:
    motion = record.get("motion", "keep")
    return f"{record['rate_hz']:g} Hz {record['protocol']}" + ("" if motion == "keep" else f" {motion}")


def _overview(data: ReportData) -> str:
    t0, t1 = data.time_range
    rows = [[c.topic, c.schema_name, c.message_count, round(c.rate_hz, 3)] for c in data.channels]
    notes = "".join(f"<p>note: {escape(n)}</p>" for n in data.notes)
    return (f'<p class="stat">{len(data.channels)} channels, {(t1 - t0) * 1e-9:.3f} s of log time '
            f"(log_time {t0} .. {t1} ns), {len(data.provenance)} stages recorded.</p>{notes}"
            f"<details><summary>channels</summary>{table(['topic', 'schema', 'messages', 'rate (Hz)'], rows)}"
            "</details>")


def _frame_section(data: ReportData) -> str:
    if data.frame is None:
        return missing(data.missing["frame"])
    f = data.frame
    h, w = f.image.shape[:2]
    what = f"frame {f.index}" if f.index is not None else "the middle frame"
    caption = (f"{escape(what)} of {escape(f.topic)} (log_time {f.log_time} ns, {w}×{h} px, contrast-stretched"
               f"{', downscaled' if max(w, h) > 512 else ''}); red circles: {len(f.points)} centroids from "
               f"{escape(f.overlay_topic or 'no centroid channel')}.")
    out = figure(frame_figure(f.image, f.points, title=caption), caption, "frame")
    if "overlay" in data.missing:
        out += missing(data.missing["overlay"])
    return out


def _tracks_section(data: ReportData) -> str:
    if data.tracks is None:
        return missing(data.missing["tracks"])
    tp = data.tracks
    if not tp.tracks:
        return missing(f"{tp.topic} has no confirmed track: the tracker confirmed no star (see `starlog track --help`).")
    shown = (f"{len(tp.tracks)} of {tp.total_tracks} confirmed tracks (the longest)" if tp.total_tracks > len(tp.tracks)
             else f"all {tp.total_tracks} confirmed tracks")
    sampled = f", every {tp.stride}th frame" if tp.stride > 1 else ""
    caption = (f"{shown} of {escape(tp.topic)}{sampled}, each about its own mean; the thick line is the brightest "
               f"star (track {tp.brightest}). The y range leaves out the top and bottom 1 % (the filter's start-up).")
    charts = []
    for axis, k in (("x", 1), ("y", 2)):
        series = [Series(f"track {i}" + (" (brightest)" if i == tp.brightest else ""), v[0], v[k] - np.mean(v[k]),
                         PALETTE[n % len(PALETTE)], 2.2 if i == tp.brightest else 1.0)
                  for n, (i, v) in enumerate(tp.tracks.items())]
        title = f"{axis} of every star minus its mean, {tp.topic}"
        charts.append(figure(line_chart(series, title=title, x_label="time (s)", y_label=f"{axis} − mean (px)",
                                        legend=len(series) <= 6, robust=True), caption, f"tracks_{axis}"))
    return "".join(charts)


def _error_section(data: ReportData) -> str:
    if data.error is None:
        return missing(data.missing["error"])
    e = data.error
    series = [Series("x error", e.t, e.ex), Series("y error", e.t, e.ey)]
    out = figure(line_chart(series, title=f"brightest star: position minus its mean ({e.source})", x_label="time (s)",
                            y_label="error (px)"),
                 f"The brightest star's filtered position about its mean, {e.t.size} samples at {e.rate_hz:.4g} Hz"
                 f"{' (the first samples only: the series is long)' if e.truncated else ''}.", "error_series")
    if e.t.size < 4 or e.rate_hz <= 0:
        return out + missing(f"{e.source} has too few samples ({e.t.size}) for a spectrum.")
    freq, ax = amplitude_spectrum(e.ex, e.rate_hz)
    _, ay = amplitude_spectrum(e.ey, e.rate_hz)
    total = np.hypot(ax, ay)
    peak = float(freq[1 + int(np.argmax(total[1:]))]) if freq.size > 1 else 0.0
    if e.dominant_frequency is not None:
        fd, source = e.dominant_frequency, e.dominant_from
    else:
        fd, source = peak, "the spectrum's highest peak (no decomposition in this log: `starlog compensate` makes one)"
    marker = [(fd, f"f_d = {fd:.3g} Hz")] if fd > 0 else []
    out += figure(line_chart([Series("x", freq, ax), Series("y", freq, ay)], title="amplitude spectrum of the error",
                             x_label="frequency (Hz)", y_label="amplitude (px)", markers=marker),
                  "Single-sided amplitude spectrum 2|FFT|/N of each axis; dashed: the dominant frequency.",
                  "error_spectrum")
    stated = (f"Dominant frequency f_d = <b>{fd:.4g} Hz</b>, from {escape(source).replace('`', '')}"
              if fd > 0 else f"No spectral peak stands out (f_d = 0, from {escape(source)})")
    return out + f'<p class="stat">{stated}; the spectrum\'s highest peak is at {peak:.4g} Hz.</p>'


def _decomposition_section(data: ReportData) -> str:
    records = data.primary_records
    if not records:
        return missing(data.missing["decisions"])
    groups = [c.replace("_", " ").lower() for c in CATEGORIES]
    bars = [Bars(_label(r), [r["compensation"]["decomposition"]["magnitudes"][c] for c in CATEGORIES]) for r in records]
    title = f"error decomposition (paper §2.2), {data.primary_decisions}"
    rows = [[_label(r), *[r["compensation"]["decomposition"]["magnitudes"][c] for c in CATEGORIES],
             r["compensation"]["decomposition"]["dominant_frequency"],
             ", ".join(_words(c for c in CATEGORIES if r["compensation"]["decomposition"].get("significant", {}).get(c)))]
            for r in records]
    return (figure(bar_chart(groups, bars, title=title, y_label="RMS magnitude (px)"),
                   "RMS magnitude of each error category per rate and protocol.", "decomposition")
            + table(["run", *_words(CATEGORIES), "f_d (Hz)", "significant"], rows))


def _compensation_section(data: ReportData) -> str:
    records = data.primary_records
    if not records:
        return missing(data.missing["decisions"])
    groups = [_label(r) for r in records]
    bars = [Bars("before", [r["figures"][0]["rmse_before"] for r in records], "#888888"),
            Bars("after", [r["figures"][0]["rmse_after"] for r in records], "#0072B2")]
    out = figure(bar_chart(groups, bars, title=f"RMSE before/after compensation (eq. 15), {data.primary_decisions}",
                           y_label="RMSE (px)"),
                 "Each protocol's primary figure: the RMSE against its own reference, before and after.", "compensation")
    for protocol, (t, before, after) in data.compensated.items():
        centre = before.mean(axis=0)
        title = f"{protocol} protocol: distance from the mean position, before/after"
        series = [Series("before", t, np.hypot(*(before - centre).T), "#888888", 1.0),
                  Series("after", t, np.hypot(*(after - centre).T), "#0072B2", 1.6)]
        out += figure(line_chart(series, title=title, x_label="time (s)", y_label="distance (px)", width=540,
                                 height=240),
                      f"The brightest star's series at {data.compensated_rate_hz:g} Hz under the {escape(protocol)} "
                      "protocol, before and after its kept passes, as distance from the mean position before.",
                      f"compensated_{protocol}")
    rows = [[r["_topic"].split("/")[2] + "/" + r["_topic"].split("/")[3], _label(r), f["reference"], f["rmse_before"],
             f["rmse_after"], f"{100 * f['effective']:+.1f} %", f["n_scored"]]
            for r in data.records for f in r["figures"]]
    header = ["track", "run", "reference", "RMSE before (px)", "RMSE after (px)", "gain (eq. 13)", "scored"]
    primary = [row for row in rows if row[0] == "/".join(data.primary_decisions.split("/")[2:4])]  # type: ignore[union-attr]
    out += table(header, primary)
    if len(rows) > len(primary):
        out += f"<details><summary>every track channel ({len(rows)} rows)</summary>{table(header, rows)}</details>"
    return out


def _passes(record: dict[str, Any]) -> Raw:
    items = []
    for p in record["compensation"]["passes"]:
        state = '<span class="kept">kept</span>' if p["kept"] else '<span class="rolled">rolled back</span>'
        items.append(f"{p['rank'] + 1}. {escape(p['strategy'])} (score {p['score']:.3g}): {p['rmse_before']:.4g} → "
                     f"{p['rmse_after']:.4g} px, {100 * p['effective']:+.1f} % {state}")
    return Raw("<br>".join(items) or "none run (no strategy scored above 0)")


def _decisions_section(data: ReportData) -> str:
    records = data.primary_records
    if not records:
        return missing(data.missing["decisions"])
    rows = [[_label(r), r["n_samples"], r["compensation"]["decomposition"]["dominant_frequency"],
             *[r["compensation"]["scores"][s] for s in STRATEGIES], _passes(r),
             " > ".join(r["compensation"]["kept"]) or "—"] for r in records]
    return (f"<p>Eq. 12 scores of each strategy, the passes run in score order and the eq. 13 rollback "
            f"(a pass improving by less than the threshold is undone), {escape(data.primary_decisions or '')}.</p>"
            + table(["run", "samples", "f_d (Hz)", *_words(STRATEGIES), "passes (eq. 13)", "kept"], rows))


def _rounded(value: Any) -> Any:
    return round(value, 5) if isinstance(value, (int, float)) else "—"


def _trust_section(data: ReportData) -> str:
    """Which centroid method to trust (:func:`starlog.centroiding.evidence.trust`): the method named and why, then the
    evidence per method: the catalogue residual on the stars every method identified (``starlog solve``) and the
    frame-to-frame noise (:mod:`starlog.centroiding.evidence`)."""
    if not data.evidence and not data.sky:
        return missing("This log holds no centroid evidence: `starlog centroid` records it.")
    out = ""
    if data.trust is not None:
        named = data.trust["method"] or "no method named"
        out += f'<p class="stat">Trust: {escape(named)}. {escape(data.trust["reason"])}</p>'
    if data.sky:
        rows = [[method, _rounded(e.get("residual_px")),
                 f"{e['interval_px'][0]:.4f} – {e['interval_px'][1]:.4f}" if e.get("interval_px") else "—",
                 f"{100 * e['p_best']:.0f} %" if e.get("p_best") is not None else "—", e.get("stars", 0)]
                for method, e in data.sky.items()]
        out += ("<p>The sky as the judge: each method's residual against the catalogue on the stars every method "
                "identified, one camera model per log; 95 % bootstrap interval over the stars, and how often each "
                "is the least in the draws.</p>"
                + table(["method", "catalogue residual (px per axis)", "95 % interval (px)", "least in",
                         "stars"], rows))
    for r in data.evidence:
        if "error" in r:
            out += missing(r["error"])
            continue
        rows = []
        for method, e in r["methods"].items():
            amp, err = e.get("phase_amplitude_px"), e.get("phase_error_px")
            span = e.get("interval_px")
            rows.append([method, _rounded(e.get("noise_px")), f"{span[0]:.4f} – {span[1]:.4f}" if span else "—",
                         _rounded(e.get("median_sigma_px")), _rounded(e.get("apart_px")),
                         f"{amp[0]:+.4f} / {amp[1]:+.4f} ± {max(err):.4f}" if amp and err else "—"])
        out += (f'<p>{escape(r["reason"])}</p><p>The frame-to-frame rule: the method of least frame-to-frame noise '
                "(a star's displacement between consecutive frames minus the median displacement of all stars, "
                "divided by √2), from the log alone; the other columns are evidence beside it.</p>"
                + table(["method", "frame-to-frame noise (px)", "95 % interval (px)", "median own sigma (px)",
                         "RMS apart from the others' median (px)", "S-curve applied x / y ± error (px)"], rows))
    return out


def _provenance_section(data: ReportData) -> str:
    if not data.provenance:
        return missing("This log holds no provenance record: it was not written by a starlog stage.")
    rows = [[k + 1, p.stage, p.version, Raw("<br>".join(escape(c) for c in p.channels) or "—"),
             p.input_digest[:23] + "…" if p.input_digest else "—", p.parameters] for k, p in enumerate(data.provenance)]
    return table(["#", "stage", "version", "channels added", "input", "parameters"], rows)


def render_report(data: ReportData) -> str:
    """The HTML document of :class:`~starlog.report.collect.ReportData`."""
    sections = [
        ("overview", "Log", _overview(data)),
        ("frame", "A frame and its centroids", _frame_section(data)),
        ("trust", "Which centroid method to trust", _trust_section(data)),
        ("tracks", "Tracks of every star", _tracks_section(data)),
        ("error", "The brightest star's error and its spectrum", _error_section(data)),
        ("decomposition", "Error decomposition", _decomposition_section(data)),
        ("compensation", "Before/after compensation per protocol", _compensation_section(data)),
        ("decisions", "Strategy decisions", _decisions_section(data)),
        ("provenance", "Provenance of every stage", _provenance_section(data)),
    ]
    if data.attitude:  # solve is optional (it needs cedar-solve): its section only where it ran
        sections.insert(-1, ("attitude", "Attitude and catalogue residuals per centroid method",
                             attitude_section(data.attitude)))
    return html_page(f"starlog report: {data.path.name}", f"{escape(str(data.path))}", sections)


def write_text_atomic(path: Path, text: str, *, force: bool = True) -> Path:
    """Write ``text`` to ``path`` through a temporary file put in its place when complete (never a half-written
    file; see :func:`~starlog.io.output_files.atomic_output`)."""
    with atomic_output(path, force=force) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


def write_report(log: str | os.PathLike[str], output: str | os.PathLike[str], *, force: bool = True) -> Path:
    """Write the self-contained HTML report of ``log`` to ``output``; returns its path."""
    return write_text_atomic(Path(output), render_report(collect_report_data(log)), force=force)
