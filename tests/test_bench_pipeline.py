"""The stage benchmark's own arithmetic: the marginal rate and start-up, and where sampled time is attributed."""

from __future__ import annotations

import math
import sys

import pytest

from tests.tool_modules import tool_module



@pytest.fixture(scope="module")
def bench():
    with tool_module("bench_pipeline") as module:
        yield module


def test_marginal_rate_and_start_up_of_a_known_line(bench):
    # 2.5 s of start-up, then 150 frames/s
    rate, start_up = bench.marginal_fit([300, 3000], [2.5 + 300 / 150, 2.5 + 3000 / 150])
    assert rate == pytest.approx(150.0)
    assert start_up == pytest.approx(2.5)
    rate, start_up = bench.marginal_fit([100, 200, 400], [1.0 + 0.01 * 100, 1.0 + 0.01 * 200, 1.0 + 0.01 * 400])
    assert rate == pytest.approx(100.0)
    assert start_up == pytest.approx(1.0)


def test_marginal_rate_is_nan_when_the_longer_log_is_not_slower(bench):
    rate, _ = bench.marginal_fit([300, 3000], [5.0, 4.9])
    assert math.isnan(rate)
    with pytest.raises(ValueError):
        bench.marginal_fit([300, 300], [1.0, 2.0])


def test_paired_repeats_keep_a_speed_drift_out_of_the_marginal_rate(bench):
    """Repeat 2 ran on a machine 1.5x slower than repeat 1 and 3 (start-up and frames alike): the
    median of each repeat's own line is still 150 frames/s; the best time per length would mix
    repeats and say otherwise."""
    timing = lambda s: bench.Timing(s, s, 100.0)  # noqa: E731
    line = lambda slow, n: slow * (2.5 + n / 150)  # noqa: E731
    runs = [[timing(line(slow, 300)), timing(line(slow, 3000))] for slow in (1.0, 1.5, 1.0)]
    result = bench.StageResult("centroid GAUSSFIT", 1)
    result.add_pairs([300, 3000], runs, {300: ["a"] * 3, 3000: ["b"] * 3})
    fit = result.fit()
    assert fit["rate"] == pytest.approx(150.0)
    assert fit["start_up"] == pytest.approx(2.5)
    assert result.seconds == pytest.approx([line(1.0, 300), line(1.0, 3000)])
    # one repeat whose longer log ran faster (a line that does not rise) counts as the slowest
    runs[0][1] = timing(0.1)
    result.add_pairs([300, 3000], runs, {300: ["a"] * 3, 3000: ["b"] * 3})
    assert result.fit()["rate"] == pytest.approx(150.0 / 1.5)


def _stack(modules: list[tuple[str, str]]):
    """A real call stack through functions defined in the given (module, function) namespaces, outermost first."""
    source_of = "def {name}(inner):\n    return inner()\n"
    call = lambda: sys._getframe()  # noqa: E731 (innermost: the frame that is "interrupted")
    for module, name in reversed(modules):
        namespace = {"__name__": module}
        exec(compile(source_of.format(name=name), f"<{module}>", "exec"), namespace)
        call = (lambda f, inner: lambda: f(inner))(namespace[name], call)
    return call()


@pytest.mark.parametrize("modules, expected", [
    ([("starlog.stages.centroid", "centroid_log"), ("starlog.centroid.gaussfit", "fit")], "algorithm"),
    ([("starlog.stages.track", "track_log"), ("starlog.io.reader", "messages"), ("starlog.io.messages", "check")],
     "read"),
    ([("starlog.stages.track", "track_log"), ("starlog.io.writer", "write"), ("starlog.io.messages", "check")],
     "write"),
    ([("starlog.stages.centroid", "__call__"), ("starlog.io.messages", "encode_json")], "write"),
    ([("starlog.stages.centroid", "rows")], "stage"),
    ([("starlog.stages.centroid", "centroid_log"), ("starlog.io.schemas", "json_message_type")], "other"),
    ([("click.core", "invoke")], "other"),
])
def test_sampled_time_goes_to_the_innermost_starlog_frame(bench, modules, expected):
    assert bench.classify(_stack(modules), {}) == expected


def test_output_growth_a_frame_and_the_disk_floor_it_sets(bench):
    result = bench.StageResult("track STATIC", 2)
    timing = bench.Timing(1.0, 1.0, 100.0)
    result.add_pairs([300, 3000], [[timing, timing]], {300: ["a"], 3000: ["b"]})
    assert math.isnan(result.bytes_per_frame())  # sizes not recorded
    result.output_bytes = [1_000_000 + 300 * 800_000, 1_000_000 + 3000 * 800_000]
    assert result.bytes_per_frame() == pytest.approx(800_000)
    # 800 kB a frame at 400 MB/s: 2 ms a frame
    assert bench.write_floor(800_000, 400e6) == pytest.approx(2e-3)
    assert math.isnan(bench.write_floor(math.nan, 400e6))
    assert math.isnan(bench.write_floor(800_000, 0.0))


def test_a_target_below_the_disk_floor_says_so(bench):
    size = {"disk_rate": 400e6}
    stage = {"bytes_per_frame": 800_000}
    assert bench.disk_note(size, stage, 0.7e-3).endswith("BELOW THE DISK'S ESTIMATED FLOOR")  # 2 ms > 0.7 ms allowed
    above = bench.disk_note(size, {"bytes_per_frame": 40_000}, 0.7e-3)  # 0.1 ms
    assert "0.10 ms a frame, 0.70 allowed" in above and "FLOOR" not in above
    assert bench.disk_note({"disk_rate": math.nan}, stage, 0.7e-3) == ""


def test_the_disk_probe_writes_syncs_and_removes_its_file(bench, tmp_path):
    rate = bench.disk_write_rate(tmp_path, 16, block_mib=8)
    assert math.isfinite(rate) and rate > 0
    assert list(tmp_path.iterdir()) == []
