"""Tables 2–4 and Figure 5's data: long-format rows, Parquet and Markdown writers, headline medians.

Every table is one Parquet file in long format (one row per dataset × method × model × rate ×
protocol × reference, columns :data:`TABLE_FIELDS`, the paper's number beside ours on every row
where the paper has one) and one Markdown file with a section per protocol and reference, each
labelled with both.  The Markdown puts the paper's numbers beside ours in the ``paper``
protocol's section (the only protocol the paper used).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa

from starlog.experiment.parquet import write_rows
from starlog.experiment import paper_tables
from starlog.experiment.runner import (
    FIGURE5_RATES,
    METHODS,
    MODELS,
    PROTOCOL_REFERENCES,
    TABLE2_RATES,
    TABLE3_RATES,
    TABLE4_RATE,
)

__all__ = [
    "REFERENCE_TEXT",
    "TABLE_FIELDS",
    "TABLE_TITLES",
    "build_table",
    "headline_rows",
    "primary_window",
    "table_markdown",
    "write_parquet",
]

TABLE_FIELDS: dict[str, tuple[pa.DataType, str]] = {
    "table": (pa.string(), "table2, table3, table4 or figure5"),
    "regime": (pa.string(), "dataset regime: paper (derived from the paper's numbers) or modern"),
    "protocol": (pa.string(), "evaluation protocol: paper, truth, leakfree"),
    "reference": (pa.string(), "RMSE reference: global_mean, truth_fixed, truth_series, heldout_mean"),
    "dataset": (pa.string(), "300Hz or 200Hz"),
    "method": (pa.string(), "sub-pixel centroid method"),
    "model": (pa.string(), "UKF motion model"),
    "window": (pa.string(), "scored samples: first N seconds ('6s') or 'full'"),
    "rate_hz": (pa.float64(), "requested down-sample rate, Hz"),
    "effective_rate_hz": (pa.float64(), "mean rate of the kept samples (nearest-frame decimation), Hz"),
    "burn_in_samples": (pa.int64(), "native frames skipped as the filter's start-up before the first sample"),
    "n_samples": (pa.int64(), "decimated samples in the window"),
    "n_scored": (pa.int64(), "samples scored"),
    "compensated": (pa.bool_(), "whether compensation was run"),
    "rmse_before": (pa.float64(), "ours, eq. 15 before compensation, px"),
    "rmse_after": (pa.float64(), "ours, eq. 15 after compensation, px (null: not compensated)"),
    "effective": (pa.float64(), "ours, eq. 13 improvement, fraction (null: not compensated)"),
    "paper_rmse_before": (pa.float64(), "the paper's RMSE before (its protocol), px; null where it has none"),
    "paper_rmse_after": (pa.float64(), "the paper's RMSE after (its protocol), px; null where it has none"),
    "paper_n_samples": (pa.int64(), "the paper's 'Image number' for this rate; null where it gives none"),
    "order": (pa.string(), "strategies run, '>'-separated"),
    "kept": (pa.string(), "strategies kept after rollback, '>'-separated"),
}
"""Columns of every table's Parquet file: name -> (Arrow type, description with unit)."""

TABLE_TITLES: dict[str, str] = {
    "table2": "Table 2 — uncompensated RMSE of the five UKF models (sub-pixel method NONE), 5 and 10 Hz",
    "table3": "Table 3 — Table 2's best UKF model, sub-pixel methods × 10–50 Hz, RMSE before/after compensation",
    "table4": "Table 4 — five UKF models at 50 Hz (sub-pixel method NONE), RMSE before/after compensation",
    "figure5": "Figure 5 — RMSE before/after compensation, 10–100 Hz, five UKF models (NONE)",
}

REFERENCE_TEXT: dict[str, str] = {
    "global_mean": "RMSE about the global mean of the scored sequence (the paper's eq. 15 and 'truth')",
    "truth_fixed": "RMSE about the simulator's fixed true star position",
    "truth_series": "RMSE about the simulator's instantaneous (jittered) true position",
    "heldout_mean": "RMSE of the held-out half about its own raw mean; the compensation only saw the "
                    "calibration half",
}


def primary_window(rows: Sequence[dict[str, Any]]) -> str:
    """The window the tables use: the first non-``full`` window, else ``full``."""
    windows = {r["window"] for r in rows}
    short = sorted(w for w in windows if w != "full")
    return short[0] if short else "full"


def _select(table: str, r: dict[str, Any], table3_models: dict[str, str]) -> bool:
    if table == "table2":
        return r["method"] == "NONE" and r["rate_hz"] in TABLE2_RATES
    if table == "table3":
        return r["model"] == table3_models.get(r["regime"], "STATIC") and r["rate_hz"] in TABLE3_RATES
    if table == "table4":
        return r["method"] == "NONE" and r["rate_hz"] == TABLE4_RATE
    if table == "figure5":
        return r["method"] == "NONE" and r["rate_hz"] in FIGURE5_RATES
    raise KeyError(table)


def build_table(table: str, rows: Sequence[dict[str, Any]], *, window: str | None = None,
                table3_models: dict[str, str] | None = None) -> list[dict[str, Any]]:
    """Long-format rows of ``table`` (columns :data:`TABLE_FIELDS`) from the sweep's result rows.

    Burn-in skipped, scored ``window`` (default :func:`primary_window`); Table 3 uses each
    regime's ``table3_models`` entry (Table 2's best model; STATIC when not given).
    """
    window = window or primary_window(rows)
    models = dict(table3_models or {})
    out = []
    for r in rows:
        if r["window"] != window or r["burn_in"] != "skipped" or not _select(table, r, models):
            continue
        before = after = None
        n_paper = None
        if table != "figure5":
            before, after = paper_tables.paper_value(table, dataset=r["dataset"], model=r["model"],
                                                     method=r["method"], rate_hz=r["rate_hz"])
            if table == "table3":
                n_paper = paper_tables.TABLE3_IMAGE_NUMBER.get(int(r["rate_hz"])) if before is not None else None
            elif table == "table4":
                n_paper = paper_tables.TABLE3_IMAGE_NUMBER[paper_tables.TABLE4_RATE]
        out.append({
            "table": table, "regime": r["regime"], "protocol": r["protocol"], "reference": r["reference"], "dataset": r["dataset"],
            "method": r["method"], "model": r["model"], "window": r["window"], "rate_hz": r["rate_hz"],
            "effective_rate_hz": r["effective_rate_hz"], "burn_in_samples": r["burn_in_samples"], "n_samples": r["n_samples"], "n_scored": r["n_scored"],
            "compensated": r["compensated"], "rmse_before": r["rmse_before"], "rmse_after": r["rmse_after"],
            "effective": r["effective"], "paper_rmse_before": before, "paper_rmse_after": after,
            "paper_n_samples": n_paper, "order": r["order"], "kept": r["kept"],
        })
    return out


def write_parquet(rows: Sequence[dict[str, Any]], path: str | Path, *, description: str) -> Path:
    """Write long-format rows as zstd Parquet with :data:`TABLE_FIELDS` (descriptions as field metadata)."""
    return write_rows(rows, TABLE_FIELDS, path,
                      metadata={"description": description, "reference": paper_tables.PAPER_REFERENCE})


# ---------------------------------------------------------------------------------------------
# Markdown


def _f(value: float | None, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    return f"{value:.{digits}f}"


def _pct(value: float | None) -> str:
    return "—" if value is None else f"{100 * value:+.0f}%"


def _n(row: dict[str, Any] | None) -> str:
    """The number of scored samples of a cell ('—' when there is no cell)."""
    return "—" if row is None else str(row["n_scored"])


def _md(header: Sequence[str], body: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in body]
    return "\n".join(lines)


def _index(rows: Sequence[dict[str, Any]], *, any_model: bool) -> dict[tuple[Any, ...], dict[str, Any]]:
    """Rows by (protocol, reference, dataset, method, model, rate); model '' when ``any_model``
    (Table 3 has one model per regime)."""
    return {(r["protocol"], r["reference"], r["dataset"], r["method"], "" if any_model else r["model"],
             r["rate_hz"]): r for r in rows}


Cell = Callable[[str, str, str, float], "dict[str, Any] | None"]
"""``cell(dataset, method, model, rate)``: the result row of one section, or None."""


def _table2_lines(cell: Cell, datasets: Sequence[str], with_paper: bool) -> tuple[list[str], list[list[str]]]:
    header = ["UKF model"]
    for ds in datasets:
        for rate in TABLE2_RATES:
            header += [f"{ds} RMSE_{rate:g}Hz", "N"]
            if with_paper:
                header.append("paper")
    body = []
    for model in MODELS:
        line = [model]
        for ds in datasets:
            for rate in TABLE2_RATES:
                c = cell(ds, "NONE", model, rate)
                line += [_f(c and c["rmse_before"]), _n(c)]
                if with_paper:
                    line.append(_f(paper_tables.TABLE2[model][ds][int(rate)]))
        body.append(line)
    return header, body


def _before_after_header(first: list[str], datasets: Sequence[str], with_paper: bool) -> list[str]:
    """``first`` columns, then per dataset its N, before, after and gain (and the paper's before/after)."""
    header = list(first)
    for ds in datasets:
        header += [f"{ds} N", f"{ds} before", f"{ds} after", "gain"]
        if with_paper:
            header += ["paper before", "paper after"]
    return header


def _table3_lines(cell: Cell, datasets: Sequence[str], with_paper: bool) -> tuple[list[str], list[list[str]]]:
    header = _before_after_header(["Sub-pixel method", "Rate/Hz", "paper N"], datasets, with_paper)
    body = []
    for method in METHODS:
        for rate in TABLE3_RATES:
            cells = [cell(ds, method, "", rate) for ds in datasets]
            if not any(cells):
                continue
            paper_n = paper_tables.TABLE3_IMAGE_NUMBER.get(int(rate))
            has_paper = paper_tables.paper_value("table3", dataset=datasets[0], method=method,
                                                 rate_hz=rate)[0] is not None
            line = [method, f"{rate:g}", str(paper_n) if has_paper and paper_n else "—"]
            for ds, c in zip(datasets, cells):
                line += [_n(c), _f(c and c["rmse_before"]), _f(c and c["rmse_after"]), _pct(c and c["effective"])]
                if with_paper:
                    pb, pa_ = paper_tables.paper_value("table3", dataset=ds, method=method, rate_hz=rate)
                    line += [_f(pb), _f(pa_)]
            body.append(line)
    return header, body


def _table4_lines(cell: Cell, datasets: Sequence[str], with_paper: bool) -> tuple[list[str], list[list[str]]]:
    header = _before_after_header(["UKF model"], datasets, with_paper)
    body = []
    for model in MODELS:
        line = [model]
        for ds in datasets:
            c = cell(ds, "NONE", model, TABLE4_RATE)
            line += [_n(c), _f(c and c["rmse_before"]), _f(c and c["rmse_after"]), _pct(c and c["effective"])]
            if with_paper:
                pb, pa_ = paper_tables.TABLE4[model][ds]
                line += [_f(pb), _f(pa_)]
        body.append(line)
    return header, body


def _figure5_lines(cell: Cell, datasets: Sequence[str], with_paper: bool) -> tuple[list[str], list[list[str]]]:
    header = ["Dataset", "UKF model"] + [f"{r:g} Hz" for r in FIGURE5_RATES]
    body = []
    for ds in datasets:
        for model in MODELS:
            line = [ds, model]
            for rate in FIGURE5_RATES:
                c = cell(ds, "NONE", model, rate)
                line.append("—" if c is None else f"{_f(c['rmse_before'])}→{_f(c['rmse_after'])} ({_n(c)})")
            body.append(line)
    return header, body


_LINES = {"table2": _table2_lines, "table3": _table3_lines, "table4": _table4_lines, "figure5": _figure5_lines}


def _section(table: str, rows: Sequence[dict[str, Any]], protocol: str, reference: str,
             datasets: Sequence[str]) -> str | None:
    """Markdown of one table under one protocol and reference (None when it has no value)."""
    idx = _index(rows, any_model=table == "table3")

    def cell(ds: str, method: str, model: str, rate: float) -> dict[str, Any] | None:
        return idx.get((protocol, reference, ds, method, model, rate))

    header, body = _LINES[table](cell, datasets, protocol == "paper")
    if not any(any(v not in ("—",) for v in line[1:]) for line in body):
        return None
    title = f"#### Protocol `{protocol}` — reference `{reference}`\n\n{REFERENCE_TEXT[reference]}."
    return title + "\n\n" + _md(header, body)


def table_markdown(table: str, rows: Sequence[dict[str, Any]], *, note: str = "",
                   table3_models: dict[str, str] | None = None) -> str:
    """Markdown of one table: per regime, a section per protocol and reference (paper's numbers
    in ``paper``)."""
    parts = [f"## {TABLE_TITLES[table]}",
             f"Reproduction of the paper's {table.replace('table', 'Table ').replace('figure', 'Figure ')} "
             f"({paper_tables.PAPER_REFERENCE}). RMSE in pixels; N = samples scored per dataset."]
    if note:
        parts.append(note)
    regimes = sorted({r["regime"] for r in rows}, key=lambda g: ({"paper": 0, "modern": 1}.get(g, 9), g))
    for regime in regimes:
        sub = [r for r in rows if r["regime"] == regime]
        head = f"### Regime `{regime}`"
        if table == "table3" and table3_models and regime in table3_models:
            head += f"\n\nUKF model: {table3_models[regime]} (the best of Table 2 in this run)."
        parts.append(head)
        datasets = [d for d in paper_tables.DATASETS if any(r["dataset"] == d for r in sub)]
        for protocol, references in PROTOCOL_REFERENCES.items():
            for reference in references:
                section = _section(table, sub, protocol, reference, datasets)
                if section:
                    parts.append(section)
    return "\n\n".join(parts) + "\n"


# ---------------------------------------------------------------- headline medians
def _median(values: Sequence[float | None]) -> float | None:
    vals = [v for v in values if v is not None]
    return statistics.median(vals) if vals else None


def headline_rows(tables: dict[str, list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Per regime × table × protocol × reference: medians of our before/after/gain and of the paper's numbers.

    Medians over every cell of the table (datasets, methods/models, rates) that the paper also
    reports, plus the median over all our cells (``*_all``).
    """
    out = []
    regimes = sorted({r["regime"] for t in tables.values() for r in t},
                     key=lambda g: ({"paper": 0, "modern": 1}.get(g, 9), g))
    for regime, name in ((g, n) for g in regimes for n in ("table2", "table3", "table4")):
        rows = [r for r in tables.get(name, []) if r["regime"] == regime]
        for protocol, references in PROTOCOL_REFERENCES.items():
            for reference in references:
                sel = [r for r in rows if r["protocol"] == protocol and r["reference"] == reference]
                if not sel:
                    continue
                both = [r for r in sel if r["paper_rmse_before"] is not None]
                if name == "table2":  # uncompensated: only the before figures belong to it
                    sel = [{**r, "rmse_after": None, "effective": None} for r in sel]
                    both = [{**r, "rmse_after": None, "effective": None} for r in both]
                out.append({
                    "regime": regime, "table": name, "protocol": protocol, "reference": reference, "cells": len(sel),
                    "before_all": _median([r["rmse_before"] for r in sel]),
                    "after_all": _median([r["rmse_after"] for r in sel]),
                    "gain_all": _median([r["effective"] for r in sel]),
                    "cells_with_paper": len(both),
                    "before": _median([r["rmse_before"] for r in both]),
                    "after": _median([r["rmse_after"] for r in both]),
                    "gain": _median([r["effective"] for r in both]),
                    "paper_before": _median([r["paper_rmse_before"] for r in both]),
                    "paper_after": _median([r["paper_rmse_after"] for r in both]),
                    "paper_gain": _median([
                        (r["paper_rmse_before"] - r["paper_rmse_after"]) / r["paper_rmse_before"]
                        for r in both if r["paper_rmse_after"] is not None and r["paper_rmse_before"]
                    ]),
                })
    return out
