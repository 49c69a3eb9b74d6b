"""Self-contained HTML reports (``starlog report``): the figures of a log or an experiment in one file.

The report needs nothing at view time (inline CSS and SVG, the frame as a ``data:`` URI, no script,
no font or network fetch); numpy draws every figure (:mod:`starlog.report.svg`).
"""

from starlog.report.collect import ReportData, collect_report_data
from starlog.report.log_report import render_report, write_report

__all__ = ["ReportData", "collect_report_data", "render_report", "write_report"]
