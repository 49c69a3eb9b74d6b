"""What :func:`~starlog.experiment.run_experiment` writes once the sweep is done: the tables, the figures, and
the reports with the data collected for them (:func:`collect_report_data`).

The reports are drawn by :mod:`starlog.report` from that data: ``report.md`` and ``report.html``
from the same collection, the PNG figures and the HTML's SVG by the same drawing functions.
"""

from __future__ import annotations

import json
from concurrent.futures import Executor
from pathlib import Path
from typing import Any

import pyarrow as pa

from starlog.experiment import null_check, paper_tables, realisations, tables
from starlog.experiment.datasets import Dataset
from starlog.experiment.parquet import write_rows
from starlog.experiment.runner import METHODS, RESULT_FIELDS
from starlog.experiment.summary import ExperimentSummary
from starlog.report import experiment_figures
from starlog.report.experiment_data import ExperimentReportData
from starlog.report.experiment_html import render_experiment_html
from starlog.report.experiment_markdown import render_experiment_markdown
from starlog.report.log_report import write_text_atomic

__all__ = ["TRAJECTORY", "collect_report_data", "log_files", "write_plots", "write_realisations", "write_reports",
           "write_results", "write_tables"]

#: The series drawn as trajectories: dataset, centroid method, UKF models, rate (Hz).
TRAJECTORY = ("300Hz", "NONE", ("STATIC", "RANDOM_WALK"), 50.0)


def write_tables(summary: ExperimentSummary, out: Path, files: dict[str, str]) -> dict[str, str]:
    """Tables 2-4 and Figure 5 as Parquet and Markdown; returns the Markdown by table name."""
    tables_md: dict[str, str] = {}
    for name in ("table2", "table3", "table4", "figure5"):
        trows = tables.build_table(name, summary.rows, table3_models=summary.table3_models)
        summary.tables[name] = trows
        tables.write_parquet(trows, out / f"{name}.parquet", description=tables.TABLE_TITLES[name])
        tables_md[name] = tables.table_markdown(name, trows, note=f"Scored samples: {summary.window_note}.",
                                                table3_models=summary.table3_models)
        write_text_atomic(out / f"{name}.md", tables_md[name])
        files[f"{name}.parquet"] = f"{name}.parquet"
        files[f"{name}.md"] = f"{name}.md"
    return tables_md


def write_realisations(summary: ExperimentSummary, rows: list[dict[str, Any]], out: Path,
                        files: dict[str, str]) -> None:
    """``table2_realisations.parquet`` (every realisation's cells) and the summary beside Table 2."""
    if not rows:
        return
    rows = realisations.sort_records(rows)
    files["table2_realisations"] = realisations.write_parquet(rows, out / "table2_realisations.parquet").name
    summary.realisations = realisations.summarise(rows, summary.tables["table2"], window_s=summary.window_s)


def write_plots(summary: ExperimentSummary, series: dict[str, Any], out: Path, files: dict[str, str],
                 executor: Executor | None = None) -> None:
    """Per regime: Figures 4 and 5, and the trajectory of the brightest star (before/after) per model.

    With an ``executor`` the plots are drawn on its workers, in parallel (the same files)."""
    ds_name, method, models, rate = TRAJECTORY
    window_s = summary.window_s
    out = out.resolve()  # the workers' working directory may differ
    jobs: list[tuple[str, Any, tuple[Any, ...], dict[str, Any]]] = []
    for regime in summary.regimes:
        t3 = [r for r in summary.tables["table3"] if r["regime"] == regime]
        f5 = [r for r in summary.tables["figure5"] if r["regime"] == regime]
        jobs.append((f"figure4_{regime}", experiment_figures.plot_figure4, (t3, out / f"figure4_{regime}.png"),
                     {"model": summary.table3_models.get(regime, "STATIC"), "label": f"regime {regime}"}))
        jobs.append((f"figure5_{regime}", experiment_figures.plot_figure5, (f5, out / f"figure5_{regime}.png"), {}))
        for m in models:
            key = f"{regime}/{ds_name}/{method}/{m}/{rate:g}Hz/{window_s:g}s" if window_s is not None else ""
            if key not in series:
                continue
            name = f"trajectory_{regime}_{m.lower()}"
            jobs.append((name, experiment_figures.plot_trajectory, (series[key], out / f"{name}.png"),
                         {"title": f"{regime} {ds_name} dataset, {method} centroids, {m} UKF, {rate:g} Hz — brightest star"}))
    if executor is None:
        for name, fn, args, kwargs in jobs:
            files[name] = fn(*args, **kwargs).name
        return
    futures = [(name, executor.submit(fn, *args, **kwargs)) for name, fn, args, kwargs in jobs]
    for name, future in futures:
        files[name] = future.result().name


def log_files(datasets: list[Dataset]) -> dict[str, str]:
    """Output name → path of every log the experiment writes."""
    files: dict[str, str] = {}
    for ds in datasets:
        for kind in ("sim", "centroids"):
            files[f"{ds.stem}_{kind}"] = f"logs/{ds.stem}_{kind}.mcap"
        for method in METHODS:
            files[f"{ds.stem}_track_{method}"] = f"logs/{ds.stem}_track_{method}.mcap"
        files[f"{ds.stem}_compensated"] = f"logs/{ds.stem}_compensated.mcap"
    for regime in sorted({d.regime for d in datasets}):
        for kind in ("sim", "centroids", "track"):
            files[f"{regime}_null_{kind}"] = f"logs/{regime}_null_{kind}.mcap"
    return files


def write_results(rows: list[dict[str, Any]], path: Path) -> None:
    """Every result row as ``results.parquet`` (:data:`~starlog.experiment.runner.RESULT_FIELDS`)."""
    types = {"burn_in_samples": pa.int64(), "rate_hz": pa.float64(), "effective_rate_hz": pa.float64(), "n_samples": pa.int64(),
             "compensated": pa.bool_(), "n_scored": pa.int64(), "rmse_before": pa.float64(),
             "rmse_after": pa.float64(), "effective": pa.float64(), "dominant_frequency_hz": pa.float64()}
    write_rows(rows, {n: (types.get(n, pa.string()), d) for n, d in RESULT_FIELDS.items()}, path)


def collect_report_data(summary: ExperimentSummary, tables_md: dict[str, str]) -> ExperimentReportData:
    """What both reports show, collected once: the summary, the tables' rows and their Markdown."""
    data = summary.to_dict()
    markdown = dict(tables_md)
    if data["realisations"]:
        markdown["realisations"] = realisations.markdown(data["realisations"])
    if data["null_checks"]:
        markdown["null_check"] = null_check.markdown(data["null_checks"])
    return ExperimentReportData(summary=data, tables=summary.tables, table_titles=dict(tables.TABLE_TITLES),
                                markdown=markdown, paper_reference=paper_tables.PAPER_REFERENCE)


def write_reports(summary: ExperimentSummary, tables_md: dict[str, str], out: Path) -> None:
    """``summary.json``, ``report.md`` and ``report.html``, the two reports rendered from one collection."""
    data = collect_report_data(summary, tables_md)
    write_text_atomic(out / "summary.json", json.dumps(data.summary, indent=1))
    write_text_atomic(out / "report.md", render_experiment_markdown(data))
    write_text_atomic(out / "report.html", render_experiment_html(data))
