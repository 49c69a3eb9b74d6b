"""The paper's experiments, regenerated with one call (paper §3; docs/PAPER.md, "Experiments").

:func:`run_experiment` simulates the two "laboratory" datasets (300 Hz × 3248 frames and
200 Hz × 3027 frames, :mod:`~starlog.experiment.datasets`), runs the ``centroid``, ``track``
and ``compensate`` stages, and writes the paper's Tables 2–4 and Figure 5 — under the paper's
protocol with its published numbers beside ours (:mod:`~starlog.experiment.paper_tables`), and
again under the ``truth`` and ``leakfree`` protocols — as Markdown and Parquet, with PNG plots
and a ``report.md``.  Independent runs go to any ``concurrent.futures.Executor``
(:mod:`~starlog.experiment.runner`); :func:`experiment_command` is what the CLI calls.
"""

from __future__ import annotations

from starlog.experiment.datasets import SIGMA_FLOOR_PX, Dataset, paper_datasets
from starlog.experiment.experiment import experiment_command, run_experiment
from starlog.experiment.runner import RESULT_FIELDS, WINDOW_S
from starlog.experiment.summary import ExperimentSummary
from starlog.experiment.tables import TABLE_FIELDS

__all__ = [
    "RESULT_FIELDS",
    "SIGMA_FLOOR_PX",
    "TABLE_FIELDS",
    "WINDOW_S",
    "Dataset",
    "ExperimentSummary",
    "experiment_command",
    "paper_datasets",
    "run_experiment",
]
