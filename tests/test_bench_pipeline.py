"""The stage benchmark's own arithmetic: the marginal rate and start-up, where sampled time is attributed, output
shares, the names of the stages' outputs (run's layers), the chain and flatten figures and the failed-targets line."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

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
    ([("starlog.stages.centroid", "centroid_log"), ("starlog.centroiding.gaussfit", "fit")], "algorithm"),
    ([("starlog.stages.track", "track_log"), ("starlog.io.reader", "messages"), ("starlog.codecs.json_schema", "check")],
     "read"),
    ([("starlog.stages.track", "track_log"), ("starlog.io.writer", "write"), ("starlog.codecs.json_schema", "check")],
     "write"),
    ([("starlog.stages.centroid", "__call__"), ("starlog.codecs.json_messages", "encode_json")], "write"),
    ([("starlog.stages.centroid", "rows")], "stage"),
    ([("starlog.stages.centroid", "centroid_log"), ("starlog.codecs.schemas", "json_message_type")], "other"),
    ([("click.core", "invoke")], "other"),
])
def test_sampled_time_goes_to_the_innermost_starlog_frame(bench, modules, expected):
    assert bench.classify(_stack(modules), {}) == expected


def test_output_growth_a_frame(bench):
    result = bench.StageResult("track STATIC", 2)
    timing = bench.Timing(1.0, 1.0, 100.0)
    result.add_pairs([300, 3000], [[timing, timing]], {300: ["a"], 3000: ["b"]})
    assert math.isnan(result.bytes_per_frame())  # sizes not recorded
    result.output_bytes = [1_000_000 + 300 * 8_000, 1_000_000 + 3000 * 8_000]
    assert result.bytes_per_frame() == pytest.approx(8_000)


def _size(input_bytes, stages):
    return {"size": 512, "lengths": [300, 3000], "input_bytes": input_bytes,
            "stages": [{"label": label, "workers": 2, "output_bytes": sizes} for label, sizes in stages]}


def test_output_share_is_of_the_input_on_the_longest_log(bench):
    s = _size([100e6, 1000e6], [("track STATIC", [9e6, 40e6])])
    assert bench.output_share(s, s["stages"][0]) == pytest.approx(0.04)


def test_output_size_targets_per_stage_and_none_for_run(bench):
    s = _size([100e6, 1000e6], [("centroid GAUSSFIT", [1e6, 99e6]), ("track STATIC", [1e6, 51e6]),
                                ("motion", [1e6, 49e6]), ("compensate 50 Hz paper", [1e6, 1e6]),
                                ("run (paper protocol)", [1e6, 200e6]), ("run --flatten (paper protocol)", [1e6, 1200e6])])
    results = bench.output_size_targets(s)
    assert [ok for _, ok in results] == [True, False, True, True]  # 9.9 % <= 10; 5.1 % > 5; 4.9 %; 0.1 %
    assert "<= 10 %" in results[0][0] and "<= 5 %" in results[1][0]
    assert bench.share_limit("run (paper protocol)") is None
    assert bench.share_limit("run --flatten (paper protocol)") is None
    assert bench.share_limit("centroid MOMENT") == pytest.approx(0.10)


def test_the_stages_one_by_one_are_named_as_runs_layers(bench, tmp_path):
    log = tmp_path / "sim.mcap"
    commands = {c.label: c for c in bench.pipeline_commands(log, tmp_path / "10/all", 2)}
    alone = [commands[label].outputs[0] for label in ("centroid GAUSSFIT", "track STATIC", "compensate 50 Hz paper")]
    assert [p.name for p in alone] == ["run.1-centroid.mcap", "run.2-track-GAUSSFIT.mcap", "run.mcap"]
    assert all(p.parent == tmp_path / "10/all" for p in alone)
    run = commands["run (paper protocol)"]
    assert [p.name for p in run.outputs] == [p.name for p in alone]
    flat = commands["run --flatten (paper protocol)"]
    assert [p.name for p in flat.outputs] == ["run.mcap"] and "--flatten" in flat.argv
    for other in (run.outputs[0].parent, flat.outputs[0].parent):  # siblings: a base path is relative
        assert other != tmp_path / "10/all" and other.parent == tmp_path / "10"
    # track, motion and compensate read the layer before them
    track, motion, compensate = (commands[k].argv for k in ("track STATIC", "motion", "compensate 50 Hz paper"))
    assert track[track.index("track") + 1] == str(alone[0])
    assert motion[motion.index("motion") + 1] == str(alone[1])
    assert compensate[compensate.index("compensate") + 1] == str(alone[1])


def test_runs_layer_names_come_from_the_pipeline(bench, tmp_path):
    from starlog.pipeline import layer_paths

    assert bench.pipeline_layers(tmp_path) == layer_paths(tmp_path / "run.mcap", ["centroid", "track GAUSSFIT",
                                                                                   "compensate"])


def test_several_outputs_have_one_digest_of_their_digests(bench, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.write_bytes(b"layer a")
    b.write_bytes(b"layer b")
    assert bench.outputs_digest([a]) == bench.sha256(a)
    assert bench.outputs_digest([a, b]) != bench.outputs_digest([b, a])


def test_a_topic_in_two_files_of_a_chain_is_found(bench):
    assert bench.repeated_topics([["/camera/image"], ["/stars/centroids/GAUSSFIT"], ["/track/GAUSSFIT/STATIC"]]) == []
    assert bench.repeated_topics([["/a", "/b"], ["/c"], ["/b", "/b"]]) == ["/b"]


def test_the_cost_of_the_copy_of_run_flatten(bench):
    # run at 400 frames/s (2.5 ms a frame), run --flatten at 250 (4 ms a frame)
    extra, ratio = bench.flatten_cost({"rate": 400.0}, {"rate": 250.0})
    assert extra == pytest.approx(1.5e-3)
    assert ratio == pytest.approx(0.625)
    assert math.isinf(bench.flatten_cost({"rate": 400.0}, {"rate": math.nan})[0])


def test_opening_a_chain_is_judged_on_the_cli_difference(bench):
    chain = {"info_pairs": [(0.4, 0.43)] * 9, "info_extra_s": 0.03, "open_base_s": 0.001, "open_layer_s": 0.004}
    text, ok = bench.chain_open_target({"size": 512, "chain": chain})
    assert ok and "30.0 ms more" in text and "median of 9" in text and "3.00 ms more" in text
    assert not bench.chain_open_target({"size": 512, "chain": {**chain, "info_extra_s": 0.051}})[1]


def test_failed_targets_are_named_in_one_line(bench):
    assert bench.failed_summary([("a", True), ("b", True), ("c (informational)", None)]) is None
    line = bench.failed_summary([("a", True), ("b fails", False), ("c fails", False), ("d (n/a)", None)])
    assert line == "FAILED 2/3 targets: b fails | c fails" and "\n" not in line
    assert [bench.verdict(ok) for ok in (True, False, None)] == ["PASS", "FAIL", "INFO"]


def test_the_centroid_stage_is_judged_against_the_decode_only_floor(bench, tmp_path):
    """The decode-only row writes nothing (no digest); the stage's default mode may take 1.5 times its time a frame;
    full mode's ratio is informational."""
    assert bench.outputs_digest([]) == ""
    command = bench.decode_command(tmp_path / "sim.mcap")
    assert command.label == bench.DECODE_LABEL and command.outputs == [] and "--decode-only" in command.argv
    stages = [{"label": bench.DECODE_LABEL, "rate": 250.0}, {"label": "centroid GAUSSFIT", "workers": 1, "rate": 170.0},
              {"label": bench.FULL_MODE_LABEL, "workers": 1, "rate": 100.0}]
    (text, ok), (info, verdict) = bench.decode_floor_targets({"size": 1024, "stages": stages})
    assert ok and "1.47x the decode-only floor 4.00 ms" in text  # 5.88 ms / 4 ms
    assert verdict is None and "2.50x the decode-only floor" in info and "1.70x as fast" in info
    stages[1]["rate"] = 160.0
    assert not bench.decode_floor_targets({"size": 1024, "stages": stages})[0][1]
    assert bench.decode_floor_targets({"size": 512, "stages": stages})[0][1] is None  # judged at 1024² only


def test_run_is_judged_at_each_size_it_has_a_target_for(bench):
    assert bench.RUN_TARGETS == {512: 1200.0, 1024: 600.0}


def test_run_is_judged_against_the_user_pipeline_and_the_code_before(bench):
    stages = [{"label": bench.RUN_LABEL, "rate": 1500.0}, {"label": bench.USER_LABEL, "rate": 90.0},
              {"label": bench.baseline_label("abc123"), "rate": 700.0}, {"label": bench.ZSTD_RUN_LABEL, "rate": 1200.0}]
    (user, ok_user), (before, ok_before), (zstd, info) = bench.comparison_targets({"size": 512, "stages": stages})
    assert ok_user and "16.67x" in user and ok_before and "2.14x code at abc123 700.0" in before
    assert info is None and "1.71x it" in zstd
    stages[0]["rate"] = 1300.0  # 14.4x the user pipeline, 1.86x the code before
    assert [ok for _, ok in bench.comparison_targets({"size": 512, "stages": stages})] == [False, False, None]
    (_, ok), (text, not_judged) = bench.comparison_targets({"size": 512, "stages": stages[:2]})
    assert not ok and not_judged is None and "no --baseline" in text


def test_the_baseline_rows_run_the_code_at_a_git_ref(bench, tmp_path):
    env = bench.baseline_source("HEAD", tmp_path / "src")
    assert env == {"PYTHONPATH": str(tmp_path / "src")} and (tmp_path / "src" / "starlog" / "cli").is_dir()
    before, today = bench.baseline_commands(tmp_path / "sim.mcap", tmp_path / "b", 2, "HEAD", env)
    assert before.env == env and today.env is None and before.label == bench.baseline_label("HEAD")
    assert before.outputs[0].parent != today.outputs[0].parent


def test_the_user_pipeline_tracks_every_star_of_a_log(tmp_path):
    """tools/user_pipeline.py (the row run is compared with) runs on a simulated log: one filter per star."""
    import numpy as np

    from starlog.stages import simulate_log
    from tests.helpers import small_config

    log = tmp_path / "sim.mcap"
    simulate_log(small_config(n_frames=12, n_stars=6, width=200, height=160), log)
    out = tmp_path / "user.npz"
    script = Path(__file__).resolve().parent.parent / "tools" / "user_pipeline.py"
    subprocess.run([sys.executable, str(script), str(log), str(out)], check=True)
    result = np.load(out)
    assert result["counts"].tolist() == [6] * 12 and result["positions"].shape == (72, 2)
