"""Batches of logs on a local Dask cluster: same results as serial; a broken log does not stop the others."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from starlog.batch import BatchTask, run_batch
from starlog.cli import cli
from starlog.stages import simulate_log
from tests.helpers import small_config

CONFIG = ('[centroid]\nmethods = ["GAUSSFIT"]\n[track]\nmethods = ["GAUSSFIT"]\nmodels = "STATIC"\n'
          '[track.tracker]\nsigma_floor = 0.05\n[compensate]\nrates = [50]\nprotocols = "paper"\n')


@pytest.fixture(scope="module")
def four_logs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    folder = tmp_path_factory.mktemp("batch")
    logs = []
    for seed in range(4):
        path = folder / f"log{seed}.mcap"
        simulate_log(small_config(n_frames=40, seed=seed), path)
        logs.append(path)
    return logs


def _divide(a: float, b: float) -> float:
    return a / b


def test_run_batch_reports_failures_in_task_order() -> None:
    tasks = [BatchTask(str(b), _divide, (1.0, float(b))) for b in (1, 0, 4)]
    outcomes = run_batch(tasks)
    assert [o.ok for o in outcomes] == [True, False, True]
    assert outcomes[1].error.startswith("ZeroDivisionError") and outcomes[2].result == 0.25


def test_local_dask_cluster_gives_the_serial_results(four_logs: list[Path], tmp_path: Path) -> None:
    config = tmp_path / "p.toml"
    config.write_text(CONFIG)
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(four_logs[0].read_bytes()[:3000])
    runner = CliRunner()
    serial = runner.invoke(cli, ["run", *map(str, four_logs), "-o", str(tmp_path / "serial"), "--config",
                                 str(config), "--workers", "1", "-q"])
    assert serial.exit_code == 0, serial.output
    parallel = runner.invoke(cli, ["run", *map(str, four_logs), str(broken), "-o", str(tmp_path / "dask"),
                                   "--config", str(config), "--workers", "2", "-q"])
    assert parallel.exit_code == 1  # the broken log failed ...
    assert "broken.mcap: FAILED" in parallel.output and "starlog recover" in parallel.output
    assert "4 of 5 logs done, 1 failed." in parallel.output  # ... and the others completed
    for log in four_logs:
        assert (tmp_path / "serial" / log.name).read_bytes() == (tmp_path / "dask" / log.name).read_bytes()


def test_export_batch(four_logs: list[Path], tmp_path: Path) -> None:
    result = CliRunner().invoke(cli, ["export", *map(str, four_logs[:2]), "-o", str(tmp_path), "--workers", "2",
                                      "-q"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "log0" / "truth.parquet").is_file() and (tmp_path / "log1" / "frames.parquet").is_file()
