"""Table 2 over realisations: seeds, one realisation end to end, the summary against hand-worked numbers."""

from __future__ import annotations

import math
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from starlog.experiment import realisations
from starlog.experiment.datasets import MIN_SEPARATION_PX, min_separation, paper_datasets
# private _Sweep: which realisations a run adds shows publicly only in a full experiment (minutes); checked directly
from starlog.experiment.experiment import _Sweep
from dataclasses import replace


def test_seeds_follow_the_datasets_own_and_keep_its_stars_apart():
    ds = paper_datasets(quick=True, regime="modern")[0]  # 2 stars: not every seed separates them
    seeds = realisations.realisation_seeds(ds.config, 5)
    assert len(seeds) == 5 and len(set(seeds)) == 5
    assert all(s > ds.config.seed for s in seeds) and seeds == sorted(seeds)
    assert all(min_separation(replace(ds.config, seed=s)) >= MIN_SEPARATION_PX for s in seeds)


@pytest.fixture(scope="module")
def realisation(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[dict], Path]:
    """One realisation of the 200 Hz dataset (740 frames) with the tables' own seed, scored over 3 s: its rows and
    the folder it worked in (run once for the two tests that read it)."""
    work = tmp_path_factory.mktemp("realisation")
    ds = paper_datasets(quick=True, regime="paper")[1]
    return realisations.run_realisation(ds.to_dict(), ds.config.seed, str(work), window_s=3.0), work


def test_one_realisation_scores_table2s_cells_and_leaves_no_log(realisation: tuple[list[dict], Path],
                                                                 tmp_path: Path):
    rows, work = realisation
    ds = paper_datasets(quick=True, regime="paper")[1]
    assert [r["rate_hz"] for r in rows] == [5.0, 10.0]
    for r in rows:
        assert (r["regime"], r["dataset"], r["seed"]) == ("paper", "200Hz", ds.config.seed)
        assert r["n_samples"] == int(math.floor(3.0 * r["rate_hz"] + 0.5))
        assert 0.05 < r["rmse"] < 2.0  # a faint star's scatter, px
    assert list(work.iterdir()) == []
    path = realisations.write_parquet(rows, tmp_path / "r.parquet")
    assert pq.read_table(path).column("rmse").to_pylist() == [r["rmse"] for r in rows]


def test_the_run_is_as_long_as_a_numeric_burn_in_and_the_window_need(tmp_path: Path):
    ds = paper_datasets(quick=True, regime="paper")[1]  # 200 Hz, 740 frames = 3.7 s
    rows = realisations.run_realisation(ds.to_dict(), ds.config.seed + 1, str(tmp_path), window_s=1.0, burn_in=1.5)
    assert [r["n_samples"] for r in rows] == [5, 10]  # 1.5 s skipped, then the whole 1 s window


def test_the_tables_seed_reproduces_the_tables_cell(realisation: tuple[list[dict], Path], tmp_path: Path):
    from starlog.experiment.runner import simulate_and_centroid, track_and_score

    ds = paper_datasets(quick=True, regime="paper")[1]
    d = ds.to_dict()
    simulate_and_centroid(d, str(tmp_path / "s.mcap"), str(tmp_path / "c.mcap"), methods=["NONE", "GAUSSFIT"])
    result = track_and_score(str(tmp_path / "c.mcap"), str(tmp_path / "t.mcap"), dataset=ds.name, regime="paper",
                             method="NONE", models=["STATIC", "RANDOM_WALK"], tracker=ds.tracker, motion=ds.motion,
                             rates_uncompensated=[5.0, 10.0], rates_compensated=[], window_s=3.0)
    table = {r["rate_hz"]: r["rmse_before"] for r in result["rows"] if r["model"] == "STATIC"
             and r["window"] == "3s" and r["burn_in"] == "skipped" and r["protocol"] == "paper"}
    again, _ = realisation  # run_realisation(d, ds.config.seed, ..., window_s=3.0)
    assert {r["rate_hz"]: r["rmse"] for r in again} == table


def _row(ds: str, seed: int, rate: float, rmse: float) -> dict:
    return {"regime": "paper", "dataset": ds, "seed": seed, "rate_hz": rate, "n_samples": 30, "rmse": rmse}


def test_summary_against_hand_worked_numbers():
    rows = [_row("300Hz", 301, 5.0, 0.40), _row("300Hz", 302, 5.0, 0.50), _row("300Hz", 303, 5.0, 0.45),
            _row("200Hz", 201, 5.0, 0.30)]
    table2 = [{"regime": "paper", "dataset": "300Hz", "rate_hz": 5.0, "protocol": "paper", "reference": "global_mean",
               "model": "STATIC", "method": "NONE", "rmse_before": 0.56},
              {"regime": "paper", "dataset": "300Hz", "rate_hz": 5.0, "protocol": "truth", "reference": "truth_fixed",
               "model": "STATIC", "method": "NONE", "rmse_before": 9.9}]
    out = realisations.summarise(rows, table2)
    assert [(r["dataset"], r["rate_hz"]) for r in out] == [("300Hz", 5.0), ("200Hz", 5.0)]  # the paper's order
    first = out[0]
    assert first["single_run"] == 0.56 and first["paper"] == 0.4481 and first["n"] == 3
    assert first["mean"] == pytest.approx(0.45)
    assert first["se"] == pytest.approx(0.05 / math.sqrt(3))  # sample SD 0.05 over 3
    assert (first["min"], first["max"]) == (0.40, 0.50)
    assert math.isnan(out[1]["se"]) and out[1]["single_run"] is None
    md = realisations.markdown(out)
    assert "| 0.5600 | 1.25 ✗ |" in md  # the single run, outside ±15 %
    assert "| 3 | 0.4500 ± 0.0289 | 1.00 |" in md


def test_a_realisation_that_lost_its_star_is_counted_and_left_out_of_the_mean():
    rows = [_row("300Hz", 301, 5.0, 0.40), _row("300Hz", 302, 5.0, 0.50),
            {**_row("300Hz", 303, 5.0, 0.90), "n_samples": 12},  # its track ended early
            {**_row("300Hz", 304, 5.0, 0.0), "n_samples": 0, "rmse": None}]  # no track at all
    (cell,) = realisations.summarise(rows, [], window_s=6.0)
    assert (cell["n"], cell["short"]) == (2, 2) and cell["mean"] == pytest.approx(0.45)
    assert "| 2 (2 lost the star, left out) |" in realisations.markdown([cell])


def test_the_full_run_adds_realisations_for_the_paper_regime_only(tmp_path: Path):
    datasets = [*paper_datasets(regime="paper"), *paper_datasets(regime="modern")]
    full = _Sweep(datasets, tmp_path, window_s=6.0, compensation={}, quick=False)
    tasks = full._realisation_tasks()
    assert len(tasks) == 2 * realisations.REALISATIONS
    assert {ds.regime for ds, _ in tasks} == {"paper"}
    quick = _Sweep(list(paper_datasets(quick=True, regime="paper")), tmp_path, window_s=6.0,
                   compensation={}, quick=True)
    assert quick._realisation_tasks() == []


def test_the_html_report_shows_the_realisations_of_a_full_run():
    from starlog.report.experiment_data import ExperimentReportData
    from starlog.report.experiment_html import render_experiment_html

    summary = {"output_dir": "/tmp/x", "datasets": [], "quick": False, "regimes": ["paper"], "wall_time_s": 1.0,
               "executor": "serial", "window_note": "6 s", "headline": [], "null_checks": [], "files": {},
               "realisations": realisations.summarise([_row("300Hz", 301, 5.0, 0.40), _row("300Hz", 302, 5.0, 0.50)],
                                                      [])}
    html = render_experiment_html(ExperimentReportData(summary))
    assert "Table 2 over realisations" in html and "0.4000–0.5000" in html
    assert "Table 2 over realisations" not in render_experiment_html(ExperimentReportData({**summary,
                                                                                           "realisations": []}))
