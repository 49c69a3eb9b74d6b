"""What ``starlog experiment`` hands its reports: one collection of plain data, rendered as ``report.md``
(:mod:`starlog.report.experiment_markdown`) and ``report.html`` (:mod:`starlog.report.experiment_html`).

The experiment fills it (:func:`starlog.experiment.outputs.collect_report_data`); the report package
imports nothing of :mod:`starlog.experiment`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

__all__ = ["ExperimentReportData"]


@dataclass(frozen=True)
class ExperimentReportData:
    """Everything the experiment's two reports show.

    Attributes
    ----------
    summary : dict
        ``ExperimentSummary.to_dict()``: the run, its datasets, tracks, headline medians, null
        checks, realisations and output files.
    tables : dict
        ``table2`` / ``table3`` / ``table4`` / ``figure5`` → their long-format rows.
    table_titles : dict
        The title of each table.
    markdown : dict
        Markdown the experiment wrote or formats itself: each table as written beside its Parquet
        file (``table2`` ... ``figure5``), ``realisations`` and ``null_check`` (empty when absent).
    paper_reference : str
        The paper, as the tables cite it.
    """

    summary: dict[str, Any]
    tables: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    table_titles: dict[str, str] = field(default_factory=dict)
    markdown: dict[str, str] = field(default_factory=dict)
    paper_reference: str = ""
