"""tools/bench_attitude.py's targets, judged by small runs (skipped without cedar-solve, import name tetra3)."""

from __future__ import annotations

import pytest

from tests.tool_modules import tool_module

pytest.importorskip("tetra3")


@pytest.fixture(scope="module")
def bench():
    with tool_module("bench_attitude") as module:
        yield module


@pytest.fixture
def targets():
    with tool_module("bench_targets") as module:
        yield module.Targets()


def test_angle_between_two_sky_directions(bench):
    assert bench.angle_between(10.0, 0.0, 10.0, 1.0) == pytest.approx(3600.0)
    assert bench.angle_between(0.0, 89.0, 180.0, 89.0) == pytest.approx(7200.0, rel=1e-6)


def test_simulated_sky_error_is_within_the_q_method_bound(bench, targets, tmp_path):
    bench.simulated_sky(tmp_path, bench.SKY_FIELDS[:1], 12, targets)
    assert [t.verdict for t in targets.items] == ["PASS", "PASS"], [t.text for t in targets.items]


def test_tracking_identifies_every_frame_and_states_its_rate(bench, targets, capsys):
    bench.tracking_speed(200, targets)
    (target,) = targets.items
    assert "frames/s >= 1000" in target.text and target.informational
    assert "200 tracked" in capsys.readouterr().out


def test_real_sky_frames_are_solved_and_agree_with_cedar_solve(bench, targets, tmp_path):
    images = bench.default_images()
    if bench.missing_images(images):
        pytest.skip(bench.missing_images(images))
    solved = bench.real_sky(images, tmp_path, targets)
    assert targets.items and all(t.verdict == "PASS" for t in targets.items), [t.text for t in targets.items]
    bench.lost_in_space_time(bench.list_images(images), solved, targets)
    mirrored = targets.items[-1]
    assert mirrored.text.startswith("mirrored frames 8/8") and mirrored.verdict == "PASS", mirrored.text
