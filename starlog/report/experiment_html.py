"""``report.html`` of ``starlog experiment``: the headline, Figure 5 as inline SVG, Tables 2-4, Table 2 over
realisations and the null check.

Rendered from :class:`~starlog.report.experiment_data.ExperimentReportData`, the same data as
``report.md`` (:mod:`starlog.report.experiment_markdown`), so it shows exactly what the Markdown
and Parquet files hold; Figure 5's panels are drawn as the PNG file's are
(:mod:`starlog.report.experiment_figures`). Like the log report it needs no network to view.
"""

from __future__ import annotations

from collections.abc import Sequence
from html import escape
from pathlib import Path
from typing import Any

from starlog.report.experiment_data import ExperimentReportData
from starlog.report.experiment_figures import FIGURE5_PANELS, figure5_panel_svg
from starlog.report.page import figure, html_page, missing, table

__all__ = ["render_experiment_html"]

_TABLE_COLUMNS = ("regime", "dataset", "method", "model", "rate_hz", "protocol", "reference", "n_scored",
                  "rmse_before", "rmse_after", "effective", "paper_rmse_before", "paper_rmse_after")


def _pct(v: float | None) -> str:
    return "—" if v is None else f"{100 * v:+.0f} %"


def _num(v: float | None) -> str | float:
    return "—" if v is None else v


def _overview(summary: dict[str, Any]) -> str:
    rows = []
    for d in summary["datasets"]:
        c = d["config"]
        jitter = ", ".join(f"{j['frequency_hz']:g} Hz × {j['amplitude_px']:g} px" for j in c["jitter"])
        rows.append([d["regime"], d["name"], c["n_frames"], c["fps"], f"{c['width']}×{c['height']}", c["n_stars"],
                     c["psf_sigma"], jitter])
    return (f'<p class="stat">{"quick" if summary["quick"] else "full"} run, regimes '
            f'{escape(", ".join(summary["regimes"]))}, {summary["wall_time_s"]:.0f} s ({escape(summary["executor"])}); '
            f"scored samples: {escape(summary['window_note'])}. Table 3's model per regime: "
            f"{escape(', '.join(f'{g}: {m}' for g, m in summary.get('table3_models', {}).items()) or '—')}.</p>"
            + table(["regime", "dataset", "frames", "fps (Hz)", "size (px)", "stars", "PSF σ (px)", "jitter"], rows))


def _headline(summary: dict[str, Any]) -> str:
    rows = [[h["regime"], h["table"], h["protocol"], h["reference"], f"{h['cells_with_paper']}/{h['cells']}",
             _num(h["before"]), _num(h["after"]), _pct(h["gain"]), _num(h["paper_before"]), _num(h["paper_after"]),
             _pct(h["paper_gain"])] for h in summary["headline"] if h["table"] != "table2"]
    if not rows:
        return missing("No compensated table in this experiment: Tables 3 and 4 come from `starlog experiment` "
                       "without --sweep.")
    return ("<p>Medians over each table's cells that the paper also reports; gain = eq. 13.</p>"
            + table(["regime", "table", "protocol", "reference", "cells", "ours before (px)", "ours after (px)",
                     "ours gain", "paper before (px)", "paper after (px)", "paper gain"], rows))


def _figure5(rows: Sequence[dict[str, Any]]) -> str:
    if not rows:
        return missing("No Figure 5 rows: `starlog experiment` (without --sweep) writes them.")
    out = []
    for regime in dict.fromkeys(r["regime"] for r in rows):
        mine = [r for r in rows if r["regime"] == regime]
        for dataset in dict.fromkeys(r["dataset"] for r in mine):
            for protocol, reference in FIGURE5_PANELS:
                if not any((r["dataset"], r["protocol"], r["reference"]) == (dataset, protocol, reference)
                           and r["rmse_after"] is not None for r in mine):
                    continue
                title = f"Figure 5, {regime} regime, {dataset}: {protocol} / {reference}"
                svg = figure5_panel_svg(mine, dataset=dataset, protocol=protocol, reference=reference, title=title)
                out.append(figure(svg, f"{escape(title)}. Solid: after compensation, dashed: before; one colour per "
                                       "UKF model.", f"figure5_{regime}_{dataset}_{protocol}_{reference}"))
    return "".join(out)


def _table(rows: Sequence[dict[str, Any]], title: str) -> str:
    if not rows:
        return missing(f"{title}: no rows in this experiment.")
    body = [[_num(r.get(c)) if c not in ("effective",) else _pct(r.get(c)) for c in _TABLE_COLUMNS] for r in rows]
    return (f"<details><summary>{escape(title)} ({len(rows)} rows)</summary>"
            f"{table([c.replace('_', ' ') for c in _TABLE_COLUMNS], body)}</details>")


def _null_check(summary: dict[str, Any]) -> str:
    rows = [[r["regime"], r["case"], r["rate_hz"], r["protocol"], r["reference"], r["rmse_before"], r["rmse_after"],
             _pct(r["effective"])] for r in summary.get("null_checks", [])]
    if not rows:
        return missing("No null check in this experiment.")
    return ("<p>Datasets with nothing to correct: a compensation that helps here fits noise.</p>"
            + table(["regime", "case", "rate (Hz)", "protocol", "reference", "RMSE before (px)", "RMSE after (px)",
                     "gain"], rows))


def _realisations(summary: dict[str, Any]) -> str:
    rows = [[r["regime"], r["dataset"], r["rate_hz"], _num(r["paper"]), _num(r["single_run"]), r["n"], r["mean"],
             r["se"], f"{r['min']:.4f}–{r['max']:.4f}"] for r in summary.get("realisations", [])]
    return ("<p>Table 2's STATIC cells (NONE, paper protocol) of the tables' datasets and of the same datasets "
            "simulated again with other seeds: one 6 s window's cell scatters by 7–12 %, so the mean is what the "
            "conditions predict. n: realisations in the mean (those that lost the star are left out).</p>"
            + table(["regime", "dataset", "rate (Hz)", "paper (px)", "tables' run (px)", "n",
                     "mean (px)", "standard error (px)", "range (px)"], rows))


def _files(summary: dict[str, Any], output_dir: Path) -> str:
    rows = [[name, path] for name, path in sorted(summary["files"].items()) if not path.startswith("logs/")]
    return (f"<p>In {escape(str(output_dir))}; the logs are in logs/ (open one with `starlog report LOG -o "
            "LOG.html`).</p>" + table(["output", "file"], rows))


def render_experiment_html(data: ExperimentReportData) -> str:
    """The HTML document of ``report.html``."""
    summary, tables = data.summary, data.tables
    sections = [
        ("run", "What was run", _overview(summary)),
        ("headline", "Headline: ours beside the paper's", _headline(summary)),
        ("figure5", "Figure 5: RMSE before/after against the rate", _figure5(tables.get("figure5", []))),
        ("tables", "Tables 2–4", "".join(_table(tables.get(n, []), data.table_titles.get(n, n))
                                         for n in ("table2", "table3", "table4"))),
        ("null", "Null check", _null_check(summary)),
        ("files", "Files", _files(summary, Path(summary["output_dir"]))),
    ]
    if summary.get("realisations"):  # full runs only
        sections.insert(-2, ("realisations", "Table 2 over realisations", _realisations(summary)))
    return html_page("starlog experiment: the paper's Tables 2–4 and Figure 5", escape(summary["output_dir"]),
                     sections)
