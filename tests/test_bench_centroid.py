"""The centroid benchmark's verdicts: which targets --quick judges, and the exit status."""

from __future__ import annotations

import pytest

from tests.tool_modules import tool_module


@pytest.fixture(scope="module")
def bench():
    with tool_module("bench_centroid") as module:
        yield module


def test_a_missed_target_fails_the_run_and_a_missed_cost_is_informational(bench, capsys):
    assert bench.report_targets([("accuracy", False, "acc")], quick=False) == 1
    assert bench.report_targets([("accuracy", True, "acc"), ("masking cost", False, "cost")], quick=False) == 0
    out = capsys.readouterr().out
    assert "FAIL  accuracy" in out and "MISS  masking cost" in out


def test_targets_set_for_the_full_run_are_not_judged_at_quick_size(bench, capsys):
    targets = [("accuracy", True, "acc"), ("speed a", False, "speed"), ("speed b", False, "speed"),
               ("false", False, "false")]
    assert bench.report_targets(targets, quick=True) == 0
    out = capsys.readouterr().out
    assert "n/a   speed a" in out and "n/a   false" in out
    assert out.count("# n/a: --quick:") == 2  # one line of reason for each kind
    assert "# 1/1 targets met, 0 failed, 0 informational missed, 3 not judged in this run" in out


def test_the_full_run_judges_every_target(bench, capsys):
    targets = [(kind, False, kind) for kind in [*bench.NOT_AT_QUICK_SIZE, "acc", "compl", "art"]]
    assert bench.report_targets(targets, quick=False) == 1
    assert capsys.readouterr().out.count("FAIL  ") == len(targets)


def test_artefacts_keep_the_full_runs_density(bench):
    assert bench.artifact_counts(1024) == (200, 40)
    assert bench.artifact_counts(512) == (50, 10)
