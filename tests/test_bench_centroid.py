"""The centroid benchmark's verdicts: which targets --quick judges, and the exit status."""

from __future__ import annotations

import pytest

from tests.tool_modules import tool_module


@pytest.fixture(scope="module")
def bench():
    with tool_module("bench_centroid") as module:
        yield module


def test_a_missed_target_fails_the_run(bench, capsys):
    targets = [("accuracy", True, "acc"), ("masking cost", False, "cost")]
    assert bench.report_targets(targets, quick=False) == 1
    assert "FAIL  masking cost" in capsys.readouterr().out


def test_targets_set_for_the_full_run_are_not_judged_at_quick_size(bench, capsys):
    targets = [("accuracy", True, "acc"), ("speed", False, "speed"), ("false", False, "false")]
    assert bench.report_targets(targets, quick=True) == 0
    out = capsys.readouterr().out
    assert "n/a   speed" in out and "n/a   false" in out
    assert out.count("# n/a at --quick size") == 2  # one line of reason for each kind
    assert "# 1/1 targets met, 0 failed, 2 not applicable at --quick size" in out


def test_the_full_run_judges_every_target(bench):
    for kind in [*bench.NOT_AT_QUICK_SIZE, "acc", "compl", "art", "cost"]:
        assert bench.verdict(kind, False, quick=False) == "FAIL"
        assert bench.verdict(kind, True, quick=False) == "PASS"


def test_artefacts_keep_the_full_runs_density(bench):
    assert bench.artifact_counts(1024) == (200, 40)
    assert bench.artifact_counts(512) == (50, 10)
