"""What one ``starlog experiment`` run produced: :class:`ExperimentSummary` (``summary.json`` and the command's lines)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from starlog.experiment.datasets import JITTER, REGIMES, jitter_rms_px

__all__ = ["ExperimentSummary"]


@dataclass
class ExperimentSummary:
    """What :func:`run_experiment` produced.

    Attributes
    ----------
    output_dir : Path
        Where everything was written.
    quick : bool
        CI-sized datasets.
    wall_time_s : float
        Wall time of the whole run, s.
    executor : str
        ``serial`` or the executor's class name.
    files : dict
        Output name → path relative to ``output_dir`` (tables, Parquet, PNGs, logs, report).
    rows : list of dict
        Every result row (:data:`starlog.experiment.runner.RESULT_FIELDS`), canonical order.
    tables : dict
        ``table2`` / ``table3`` / ``table4`` / ``figure5`` → long-format rows
        (:data:`starlog.experiment.tables.TABLE_FIELDS`).
    headline : list of dict
        :func:`starlog.experiment.tables.headline_rows`.
    """

    output_dir: Path
    quick: bool
    wall_time_s: float
    executor: str
    datasets: list[dict[str, Any]]
    sigma_floor_px: float
    window_s: float | None
    files: dict[str, str] = field(default_factory=dict)
    tracks: dict[str, Any] = field(default_factory=dict)
    rows: list[dict[str, Any]] = field(default_factory=list)
    tables: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    headline: list[dict[str, Any]] = field(default_factory=list)
    showcase_check: float | None = None
    regimes: tuple[str, ...] = REGIMES
    table3_models: dict[str, str] = field(default_factory=dict)
    null_checks: list[dict[str, Any]] = field(default_factory=list)
    realisations: list[dict[str, Any]] = field(default_factory=list)
    compensation: dict[str, Any] = field(default_factory=dict)
    burn_in: str = "auto"

    @property
    def window_note(self) -> str:
        if self.window_s is None:
            return "every decimated sample (whole sequence)"
        short = " (fewer in --quick, whose datasets last 3.7 s)" if self.quick else ""
        return (f"the first {self.window_s:g} s of each decimated sequence (floor({self.window_s:g} s × f + 0.5) "
                f"samples: 60 at 10 Hz, 300 at 50 Hz — the paper's 'Image number'){short}; results.parquet also has "
                "every run scored over the whole sequence (window = full)")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no per-row data; see ``results.parquet`` for that)."""
        return {
            "output_dir": str(self.output_dir), "quick": self.quick, "wall_time_s": self.wall_time_s,
            "executor": self.executor, "datasets": self.datasets, "sigma_floor_px": self.sigma_floor_px,
            "jitter_rms_px": jitter_rms_px(JITTER), "window_s": self.window_s, "window_note": self.window_note,
            "files": dict(self.files), "tracks": self.tracks, "headline": self.headline,
            "showcase_check": self.showcase_check, "n_rows": len(self.rows), "regimes": list(self.regimes),
            "table3_models": dict(self.table3_models), "null_checks": self.null_checks,
            "realisations": self.realisations,
            "compensation": dict(self.compensation), "burn_in": self.burn_in,
        }

    def text(self) -> str:
        """A short plain-text summary for the command line: Table 3's headline per regime, and where the report is."""
        lines = [f"experiment ({'quick' if self.quick else 'full'}, regimes {', '.join(self.regimes)}) in "
                 f"{self.wall_time_s:.0f} s [{self.executor}] -> {self.output_dir}"]

        def f(v: float | None) -> str:
            return "—" if v is None else f"{v:.4f}"

        for h in self.headline:
            if h["table"] == "table3" and (h["protocol"], h["reference"]) in (("paper", "global_mean"),
                                                                             ("truth", "truth_fixed")):
                paper = f" (paper: {f(h['paper_before'])} -> {f(h['paper_after'])})" if h["protocol"] == "paper" else ""
                lines.append(f"  {h['regime']} regime, Table 3, {h['protocol']}/{h['reference']}: median RMSE "
                             f"{f(h['before'])} -> {f(h['after'])} px{paper}")
        lines.append(f"report: {self.output_dir / self.files.get('report_html', 'report.html')} (open it in a browser; "
                     f"Markdown: {self.files.get('report', 'report.md')}, tables: table2-4.md, figure5.md)")
        return "\n".join(lines)
