"""The benchmarks' targets: verdicts, one line per reason, and the exit status."""

from __future__ import annotations

import pytest

from tests.tool_modules import tool_module


@pytest.fixture(scope="module")
def targets():
    with tool_module("bench_targets") as module:
        yield module.Targets


def test_a_failed_target_fails_the_run(targets, capsys):
    run = targets()
    run.check("accuracy 0.9 <= 1.0", True)
    run.check("memory growth 12 % <= 10 %", False)
    assert run.report() == 1
    out = capsys.readouterr().out
    assert "PASS  accuracy" in out and "FAIL  memory growth" in out
    assert "# 1/2 targets met, 1 failed, 0 informational missed, 0 not judged in this run" in out


def test_informational_and_unjudged_targets_do_not_fail_the_run(targets, capsys):
    run = targets()
    run.check("speed-up 1.2x >= 1.6x", False, informational="wall clock on a shared machine")
    run.check("speed-up 0.9x >= 1.6x", False, not_judged="--quick: too few frames")
    run.check("rate 3 <= 2", False, not_judged="--quick: too few frames")
    assert run.report() == 0
    out = capsys.readouterr().out
    assert "MISS  speed-up 1.2x" in out and "n/a   speed-up 0.9x" in out
    assert out.count("# n/a: --quick: too few frames") == 1  # each reason once
    assert "# informational (a miss does not fail the run): wall clock on a shared machine" in out
    assert "# 0/1 targets met, 0 failed, 1 informational missed, 2 not judged in this run" in out


def test_check_returns_whether_the_target_was_met(targets):
    run = targets()
    assert run.check("a", True) is True
    assert run.check("b", 0) is False


def test_a_run_that_judges_nothing_says_so(targets, capsys):
    run = targets()
    run.check("verify 1.2 x <= 1.5", True, not_judged="--quick: too short")
    assert run.report() == 0
    assert "# no target judged, 0 failed, 0 informational missed, 1 not judged in this run" in capsys.readouterr().out
