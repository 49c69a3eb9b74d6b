"""Every report starlog writes: the HTML report of a log (``starlog report``, the end of ``starlog run``) and the
Markdown and HTML reports of ``starlog experiment``, with their figures.

An HTML report needs nothing at view time (inline CSS and SVG, the frame as a ``data:`` URI, no
script, no font or network fetch). matplotlib draws every figure, as PNG files or inline SVG
(:mod:`starlog.report.figures`). The experiment's reports are rendered from the data the
experiment hands them (:mod:`starlog.report.experiment_data`); this package imports nothing of
:mod:`starlog.experiment`.
"""

from starlog.report.collect import ReportData, collect_report_data
from starlog.report.log_report import render_report, write_report

__all__ = ["ReportData", "collect_report_data", "render_report", "write_report"]
