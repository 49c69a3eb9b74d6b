"""starlog.experiment: the quick experiment produces every table and plot, with finite numbers, in layout."""

from __future__ import annotations

import math
import random
import re
import shutil
from concurrent.futures import ProcessPoolExecutor
from html import escape
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from numpy.testing import assert_allclose

from starlog.compensation import evaluate
from starlog.errors import InvalidParameterError, OutputExistsError
from starlog.experiment import TABLE_FIELDS, ExperimentSummary, experiment_command, paper_tables, run_experiment
from starlog.experiment.tables import TABLE_TITLES
from starlog.experiment.runner import (
    FIGURE5_RATES,
    METHODS,
    MODELS,
    PROTOCOL_REFERENCES,
    TABLE2_RATES,
    TABLE3_RATES,
    best_table2_model,
    sort_rows,
    uncompensated_figures,
)

pytest.importorskip("matplotlib")

DATASETS = ("300Hz", "200Hz")
REGIMES = ("paper", "modern")
N_REFERENCES = sum(len(v) for v in PROTOCOL_REFERENCES.values())


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory: pytest.TempPathFactory) -> ExperimentSummary:
    out = tmp_path_factory.mktemp("experiment")
    with ProcessPoolExecutor(max_workers=2) as pool:
        return run_experiment(out, quick=True, executor=pool, show_progress=False)


@pytest.mark.parametrize("name", ["table2", "table3", "table4", "figure5"])
def test_table_files_and_columns(quick_run: ExperimentSummary, name: str) -> None:
    out = quick_run.output_dir
    table = pq.read_table(out / f"{name}.parquet")
    assert table.column_names == list(TABLE_FIELDS)
    md = (out / f"{name}.md").read_text(encoding="utf-8")
    for protocol, references in PROTOCOL_REFERENCES.items():
        for reference in references:
            assert f"Protocol `{protocol}` — reference `{reference}`" in md
    rows = table.to_pylist()
    assert {(r["protocol"], r["reference"]) for r in rows} == {
        (p, ref) for p, refs in PROTOCOL_REFERENCES.items() for ref in refs}
    assert all(math.isfinite(r["rmse_before"]) and r["rmse_before"] >= 0 for r in rows)
    if name != "table2":
        assert all(r["compensated"] and math.isfinite(r["rmse_after"]) for r in rows)


@pytest.mark.parametrize(("name", "cells"), [
    ("table2", len(DATASETS) * len(MODELS) * len(TABLE2_RATES)),
    ("table3", len(DATASETS) * len(METHODS) * len(TABLE3_RATES)),
    ("table4", len(DATASETS) * len(MODELS)),
    ("figure5", len(DATASETS) * len(MODELS) * len(FIGURE5_RATES)),
])
def test_table_layout(quick_run: ExperimentSummary, name: str, cells: int) -> None:
    # both regimes by default, each with every cell
    rows = quick_run.tables[name]
    assert len(rows) == len(REGIMES) * cells * N_REFERENCES
    keys = {(r["regime"], r["dataset"], r["method"], r["model"], r["rate_hz"]) for r in rows}
    assert len(keys) == len(REGIMES) * cells


@pytest.mark.parametrize(("name", "dataset", "method", "model", "rate", "before", "after"), [
    ("table2", "300Hz", "NONE", "STATIC", 5.0, 0.4481, None),
    ("table2", "200Hz", "NONE", "CONSTANT_VELOCITY", 10.0, 0.3696, None),
    ("table3", "300Hz", "NONE", "STATIC", 10.0, 0.4374, 0.1281),
    ("table3", "200Hz", "BICUBIC", "STATIC", 30.0, 1.5380, 0.1548),
    ("table3", "200Hz", "GRADIENT", "STATIC", 50.0, 3.0936, 0.1693),
    ("table4", "300Hz", "NONE", "POLYNOMIAL_TREND", 50.0, 0.4904, 0.1730),
    ("table4", "200Hz", "NONE", "STATIC", 50.0, 0.3408, 0.1544),
])
def test_paper_numbers_beside_ours(quick_run: ExperimentSummary, name: str, dataset: str, method: str,
                                   model: str, rate: float, before: float, after: float | None) -> None:
    rows = [r for r in quick_run.tables[name] if (r["dataset"], r["method"], r["rate_hz"]) == (dataset, method, rate)
            and (r["model"] == model or name == "table3")]  # Table 3 uses Table 2's best model
    assert len(rows) == len(REGIMES) * N_REFERENCES
    for r in rows:
        assert r["paper_rmse_before"] == before
        assert r["paper_rmse_after"] == after
    md = (quick_run.output_dir / f"{name}.md").read_text(encoding="utf-8")
    paper_section = md.split("Protocol `truth`")[0]
    assert f"{before:.4f}" in paper_section


def test_plots_report_and_logs(quick_run: ExperimentSummary) -> None:
    out = quick_run.output_dir
    pngs = [rel for rel in quick_run.files.values() if rel.endswith(".png")]
    assert {f"{f}_{g}.png" for f in ("figure4", "figure5", "trajectory") for g in REGIMES
            if f != "trajectory"} <= set(pngs)
    assert {f"trajectory_{g}_static.png" for g in REGIMES} <= set(pngs)
    for rel in pngs:
        data = (out / rel).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and 1_000 < len(data) < 150_000
    for rel in quick_run.files.values():
        assert (out / rel).is_file(), rel
    report = (out / "report.md").read_text(encoding="utf-8")
    assert "sigma_floor" in report and "![figure5_paper](figure5_paper.png)" in report
    assert "## Null check" in report
    assert quick_run.showcase_check is not None and quick_run.showcase_check < 1e-12
    assert all(h["before"] is not None and math.isfinite(h["before"]) for h in quick_run.headline)


def test_results_have_both_windows(quick_run: ExperimentSummary) -> None:
    rows = pq.read_table(quick_run.output_dir / "results.parquet").to_pylist()
    assert {r["window"] for r in rows} == {"6s", "full"}
    assert rows == sort_rows(rows)


def test_refuses_to_overwrite(quick_run: ExperimentSummary) -> None:
    with pytest.raises(OutputExistsError):
        run_experiment(quick_run.output_dir, quick=True, show_progress=False)


def test_sort_rows_ignores_completion_order(quick_run: ExperimentSummary) -> None:
    rows = list(quick_run.rows)
    random.Random(4).shuffle(rows)
    assert sort_rows(rows) == quick_run.rows


@pytest.mark.parametrize("protocol", ["paper", "truth", "leakfree"])
def test_uncompensated_figures_match_evaluate(protocol: str) -> None:
    rng = np.random.default_rng(11)
    truth_series = np.array([40.0, 30.0]) + 0.05 * rng.standard_normal((48, 2))
    xy = truth_series + 0.02 * rng.standard_normal((48, 2))
    truth_fixed = np.array([40.0, 30.0])
    ours = uncompensated_figures(xy, truth_fixed=truth_fixed, truth_series=truth_series)[protocol]
    kw = {} if protocol == "paper" else {"truth_fixed": truth_fixed, "truth_series": truth_series}
    ev = evaluate(xy, rate_hz=10.0, protocol=protocol, **kw)
    assert [f[0] for f in ours] == [f.reference for f in ev.figures]
    assert_allclose([f[1] for f in ours], [f.rmse_before for f in ev.figures], rtol=0, atol=1e-12)
    assert [f[2] for f in ours] == [f.n_scored for f in ev.figures]


def test_paper_value_lookup() -> None:
    assert paper_tables.paper_value("table3", dataset="300Hz", method="GAUSSFIT", rate_hz=50.0) == (0.1097, 0.1097)
    assert paper_tables.paper_value("table3", dataset="300Hz", method="GAUSSFIT", rate_hz=20.0) == (None, None)
    assert paper_tables.paper_value("table4", dataset="200Hz", model="RANDOM_WALK", rate_hz=10.0) == (None, None)
    assert paper_tables.paper_value("table2", dataset="200Hz", model="STATIC", rate_hz=5.0) == (0.3173, None)


def test_experiment_command_rejects_bad_workers(tmp_path: Path) -> None:
    with pytest.raises(InvalidParameterError, match="workers"):
        experiment_command(tmp_path, quick=True, workers=0)


def test_a_failed_run_on_local_workers_leaves_no_partial_output(tmp_path: Path) -> None:
    (tmp_path / "logs").mkdir()
    left = [tmp_path / "logs" / ".paper_300Hz_sim.mcap.k2j4.partial", tmp_path / ".report.md.x1.partial"]
    for path in left:  # as a terminated worker leaves them
        path.write_bytes(b"unfinished")
    kept = tmp_path / "logs" / "notes.txt"
    kept.write_text("mine")
    with pytest.raises(InvalidParameterError, match="burn"):
        experiment_command(tmp_path, quick=True, workers=2, show_progress=False, burn_in="later")
    assert not any(path.exists() for path in left) and kept.read_text() == "mine"


def test_regimes_burn_in_and_rates_in_results(quick_run: ExperimentSummary) -> None:
    rows = pq.read_table(quick_run.output_dir / "results.parquet").to_pylist()
    assert {r["regime"] for r in rows} == set(REGIMES)
    assert {r["burn_in"] for r in rows} == {"skipped", "kept"}
    assert all(r["burn_in_samples"] == 0 for r in rows if r["burn_in"] == "kept")
    assert any(r["burn_in_samples"] > 0 for r in rows if r["burn_in"] == "skipped")
    for regime in REGIMES:
        for ds in DATASETS:
            f5 = [r for r in quick_run.tables["figure5"] if (r["regime"], r["dataset"], r["model"]) == (regime, ds, "STATIC")]
            rates = {r["rate_hz"]: r["effective_rate_hz"] for r in f5}
            assert sorted(rates) == list(FIGURE5_RATES)
            assert all(abs(eff / rate - 1.0) < 0.01 for rate, eff in rates.items())
    for name in ("table2", "table3", "table4", "figure5"):
        assert pq.read_table(quick_run.output_dir / f"{name}.parquet").column("regime").to_pylist()


def test_table3_uses_the_best_model_of_table2(quick_run: ExperimentSummary) -> None:
    for regime in REGIMES:
        rows = [r for r in quick_run.rows if r["regime"] == regime]
        best = best_table2_model(rows, window="6s")
        assert quick_run.table3_models[regime] == best
        assert {r["model"] for r in quick_run.tables["table3"] if r["regime"] == regime} == {best}


def test_null_check_covers_every_protocol(quick_run: ExperimentSummary) -> None:
    rows = pq.read_table(quick_run.output_dir / "null_check.parquet").to_pylist()
    for regime in REGIMES:
        for case in ("white_noise", "motionless_star"):
            got = {(r["protocol"], r["reference"]) for r in rows if (r["regime"], r["case"]) == (regime, case)}
            assert got == {(p, ref) for p, refs in PROTOCOL_REFERENCES.items() for ref in refs}
    assert all(math.isfinite(r["effective"]) for r in rows)


def test_html_report_and_short_summary(quick_run: ExperimentSummary) -> None:
    out = quick_run.output_dir
    html = (out / "report.html").read_text(encoding="utf-8")
    panels = re.findall(r'data-figure="(figure5_[^"]+)"', html)
    assert len(panels) == len(REGIMES) * len(DATASETS) * 4 and '<div class="missing">' not in html
    for name in ("table2", "table3", "table4"):
        assert escape(TABLE_TITLES[name]) in html
    text = quick_run.text().splitlines()
    assert len(text) == 2 + 2 * len(REGIMES) and text[-1].startswith(f"report: {out / 'report.html'} ")
    assert all("Table 3" in line for line in text[1:-1])


def test_html_report_renders_in_chromium(quick_run: ExperimentSummary) -> None:
    from tests.chromium import INSTALL_HINT, Browser, figures_drawn, find_chromium

    executable = find_chromium()
    if executable is None:
        pytest.skip(INSTALL_HINT)
    with Browser(executable, timeout=60) as browser:
        drawn = figures_drawn(browser, quick_run.output_dir / "report.html")
        assert len(drawn) == len(REGIMES) * len(DATASETS) * 4 and min(drawn.values()) > 0.02, drawn
        assert browser.errors() == []


def test_serial_run_gives_the_parallel_tables_even_running_every_task_twice(quick_run: ExperimentSummary,
                                                                            tmp_path: Path) -> None:
    """Dask runs a task twice at times (a lost worker, a work-stealing race): one regime, run serially in a copy of
    the module's parallel run, runs each of its tasks a second time over the files of the first attempt, and gives
    the same regime's rows of the parallel run."""
    shutil.copytree(quick_run.output_dir, tmp_path / "serial")
    serial = run_experiment(tmp_path / "serial", quick=True, show_progress=False, plot=False, regimes=["paper"],
                            force=True)
    for name in ("results", "table2", "table3", "table4", "figure5", "null_check"):
        ours = pq.read_table(serial.output_dir / f"{name}.parquet")
        theirs = pq.read_table(quick_run.output_dir / f"{name}.parquet")
        assert ours.schema == theirs.schema, name
        assert ours.to_pylist() == [r for r in theirs.to_pylist() if r["regime"] == "paper"], name


def test_burn_in_setting_is_recorded_and_checked(quick_run: ExperimentSummary, tmp_path: Path) -> None:
    rows = pq.read_table(quick_run.output_dir / "results.parquet").to_pylist()
    assert {r["burn_in_setting"] for r in rows} == {"auto"}
    assert quick_run.to_dict()["burn_in"] == "auto"
    with pytest.raises(InvalidParameterError):
        run_experiment(tmp_path, quick=True, show_progress=False, burn_in="later")



def test_best_table2_model_breaks_near_ties_in_table_order() -> None:
    def row(model: str, value: float) -> dict[str, object]:
        return {"method": "NONE", "rate_hz": 5.0, "window": "6s", "burn_in": "skipped", "protocol": "paper",
                "model": model, "rmse_before": value}

    near = [row("STATIC", 0.30006), row("RANDOM_WALK", 0.30000), row("CONSTANT_VELOCITY", 0.5)]
    assert best_table2_model(near, window="6s") == "STATIC"  # 2e-4 apart: rounding, not a better model
    clear = [row("STATIC", 0.31), row("RANDOM_WALK", 0.30)]
    assert best_table2_model(clear, window="6s") == "RANDOM_WALK"
