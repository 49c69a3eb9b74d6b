"""Logs too short for some compensation rates and protocols: the rule (starlog.compensation.lengths), ``run`` with
the built-in config (skips them) and with a config file (refuses at once), and ``compensate`` (refuses, or skips
with --skip-short)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from starlog.cli import cli
from starlog.compensation import (
    MIN_SAMPLES,
    ScoringProtocol,
    burn_in_cap,
    compensate,
    decimation_indices,
    enough_samples,
    fewest_samples,
    frames_needed,
    samples_needed,
    shortfalls,
)
from starlog.errors import InvalidInputError, InvalidParameterError
from starlog.io import LogReader
from starlog.pipeline import DEFAULT_CONFIG_TOML
from starlog.stages import simulate_log
from starlog.stages.compensate import compensate_log
from starlog.stages.track import track_log
from starlog.stages.centroid import centroid_log
from tests.helpers import small_config

FPS = 50.0  # a "1 s log" of 50 frames: the built-in rates (10, 50 Hz) meet the same limits as at 300 Hz
PROTOCOLS = list(ScoringProtocol)


# ---------------------------------------------------------------- the rule
@given(protocol=st.sampled_from(PROTOCOLS), fraction=st.floats(0.05, 0.95), n=st.integers(0, 400))
def test_enough_samples_is_what_compensate_accepts(protocol: ScoringProtocol, fraction: float, n: int) -> None:
    mode = "global_mean" if protocol is not ScoringProtocol.LEAKFREE else "calibration"
    xy = np.random.default_rng(n).normal(size=(n, 2))
    try:
        compensate(xy, rate_hz=10.0, reference_mode=mode, calibration_fraction=fraction)
        accepted = True
    except InvalidInputError:
        accepted = False
    assert enough_samples(protocol, n, calibration_fraction=fraction) == accepted


@given(protocol=st.sampled_from(PROTOCOLS), fraction=st.floats(0.01, 0.99))
def test_samples_needed_is_the_fewest_accepted(protocol: ScoringProtocol, fraction: float) -> None:
    needed = samples_needed(protocol, calibration_fraction=fraction)
    assert needed >= MIN_SAMPLES
    assert enough_samples(protocol, needed, calibration_fraction=fraction)
    assert not enough_samples(protocol, needed - 1, calibration_fraction=fraction)


@settings(max_examples=60)
@given(native=st.sampled_from([50.0, 100.0, 200.0, 300.0]), rate=st.sampled_from([5.0, 10.0, 25.0, 50.0]),
       samples=st.integers(1, 60))
def test_frames_needed_is_the_shortest_log_that_gives_the_samples(native: float, rate: float, samples: int) -> None:
    frames = frames_needed(samples, native_rate=native, rate_hz=rate)
    assert fewest_samples(frames, native_rate=native, rate_hz=rate) >= samples
    assert frames == 1 or fewest_samples(frames - 1, native_rate=native, rate_hz=rate) < samples


@given(n=st.integers(1, 3000), native=st.sampled_from([50.0, 100.0, 300.0]), rate=st.sampled_from([10.0, 50.0]),
       burn_in=st.integers(0, 200))
def test_fewest_samples_is_a_lower_bound_for_any_auto_burn_in(n: int, native: float, rate: float,
                                                              burn_in: int) -> None:
    """The stage keeps at least as many samples whatever start-up the variance rule finds (it is capped)."""
    start = min(burn_in, burn_in_cap(n, native_rate=native))
    kept = decimation_indices(n, native_rate=native, target_rate=rate, start=start).size
    assert fewest_samples(n, native_rate=native, rate_hz=rate) <= kept
    assert fewest_samples(n, native_rate=native, rate_hz=rate, burn_in="off") == \
        decimation_indices(n, native_rate=native, target_rate=rate).size


def test_shortfalls_of_one_and_two_seconds_at_300_hz() -> None:
    one = shortfalls(300, native_rate=300.0, rates=[10, 50], protocols=PROTOCOLS[:3])
    assert [(s.rate_hz, s.protocol.value, s.samples, s.needed) for s in one] == [
        (10.0, "paper", 9, 16), (10.0, "truth", 9, 16), (10.0, "leakfree", 9, 31)]
    two = shortfalls(600, native_rate=300.0, rates=[10, 50], protocols=PROTOCOLS[:3])
    assert len(two) == 1 and two[0].describe() == (
        "10 Hz leakfree: 18 samples, needs 31 (a log of at least 3.34 s: 1001 frames at 300 Hz)")
    assert shortfalls(1001, native_rate=300.0, rates=[10, 50], protocols=PROTOCOLS) == []
    assert shortfalls(600, native_rate=300.0, rates=[10], protocols=PROTOCOLS[:1]) == []
    assert shortfalls(600, native_rate=300.0, rates=[400, 0], protocols=PROTOCOLS) == []  # left to the stage


# ---------------------------------------------------------------- the commands
@pytest.fixture(scope="module")
def short_logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Simulated logs of 1 s and 2 s at 50 Hz (64x64 px, one star: the built-in config runs every centroid method
    on it)."""
    folder = tmp_path_factory.mktemp("short")
    logs = {}
    for seconds in (1, 2):
        logs[f"{seconds}s"] = folder / f"{seconds}s.mcap"
        simulate_log(small_config(width=64, height=64, n_stars=1, fps=FPS, n_frames=int(seconds * FPS)),
                     logs[f"{seconds}s"])
    return logs


def _run(*args: str) -> tuple[int, str, str]:
    result = CliRunner().invoke(cli, list(args))
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise result.exception
    return result.exit_code, result.stdout, result.stderr


def test_run_with_the_built_in_config_skips_what_a_1_s_log_is_too_short_for(short_logs: dict[str, Path],
                                                                            tmp_path: Path) -> None:
    code, out, err = _run("run", str(short_logs["1s"]), "-o", str(tmp_path / "r.mcap"), "--workers", "1")
    assert code == 0, err
    skips = [line for line in err.splitlines() if line.startswith("skipped")]
    assert skips == [f"skipped, log too short: compensate 10 Hz {p}: 9 samples, needs {n} (a log of at least "
                     f"{s} s: {f} frames at 50 Hz)" for p, n, s, f in
                     [("paper", 16, "1.68", 84), ("truth", 16, "1.68", 84), ("leakfree", 31, "3.34", 167)]]
    assert "  skipped, log too short: compensate 10 Hz paper (needs 1.68 s), 10 Hz truth (needs 1.68 s), " \
           "10 Hz leakfree (needs 3.34 s)" in out.splitlines()
    with LogReader(tmp_path / "r.mcap") as log:
        rates = {m.payload["rate_hz"] for m in log.messages("/compensated/GAUSSFIT/STATIC/decisions")}
    assert rates == {50.0}


def test_run_with_the_built_in_config_on_a_2_s_log_leaves_out_only_leakfree_at_10_hz(short_logs: dict[str, Path],
                                                                                     tmp_path: Path) -> None:
    code, out, err = _run("run", str(short_logs["2s"]), "-o", str(tmp_path / "r.mcap"), "--workers", "1", "--json")
    assert code == 0, err
    assert [line for line in err.splitlines() if line.startswith("skipped")] == [
        "skipped, log too short: compensate 10 Hz leakfree: 18 samples, needs 31 (a log of at least 3.34 s: "
        "167 frames at 50 Hz)"]
    result = json.loads(out)
    assert [(s["rate_hz"], s["protocol"]) for s in result["skipped"]] == [(10.0, "leakfree")]
    records = result["stages"][-1]["records"]
    assert {(r["rate_hz"], r["protocol"]) for r in records} == {
        (10.0, "paper"), (10.0, "truth"), (50.0, "paper"), (50.0, "truth"), (50.0, "leakfree")}


def test_run_with_a_config_that_asks_for_too_much_fails_at_once(short_logs: dict[str, Path], tmp_path: Path) -> None:
    config = tmp_path / "pipeline.toml"
    config.write_text(DEFAULT_CONFIG_TOML, encoding="utf-8")
    out = tmp_path / "out"
    out.mkdir()
    began = time.monotonic()
    code, _, err = _run("run", str(short_logs["2s"]), "-o", str(out / "r.mcap"), "--config", str(config))
    assert time.monotonic() - began < 5
    assert code != 0 and "pipeline.toml, [compensate]: /camera/image (100 frames, 1.98 s) is too short" in err
    assert "10 Hz leakfree: 18 samples, needs 31 (a log of at least 3.34 s: 167 frames at 50 Hz)" in err
    assert list(out.iterdir()) == []


def test_compensate_refuses_a_short_track_or_skips_with_skip_short(short_logs: dict[str, Path],
                                                                   tmp_path: Path) -> None:
    centroid_log(short_logs["1s"], tmp_path / "cen.mcap", methods=["MOMENT"])
    track_log(tmp_path / "cen.mcap", tmp_path / "trk.mcap", method="MOMENT", models=["STATIC"])
    args = ["compensate", str(tmp_path / "trk.mcap"), "-o", str(tmp_path / "c.mcap"), "--rate", "10,50"]
    code, _, err = _run(*args, "--protocol", "paper,leakfree")
    assert code != 0 and "/track/MOMENT/STATIC (50 messages, 0.98 s) is too short for 2 of the rates" in err
    assert "10 Hz leakfree: 9 samples, needs 31 (a log of at least 3.34 s: 167 frames at 50 Hz)" in err
    assert "--skip-short" in err and not (tmp_path / "c.mcap").exists()
    code, out, err = _run(*args, "--protocol", "paper,leakfree", "--skip-short", "--json")
    assert code == 0, err
    assert "skipped (track too short): 10 Hz paper: 9 samples, needs 16" in err
    assert {(r["rate_hz"], r["protocol"]) for r in json.loads(out)["records"]} == {(50.0, "paper"), (50.0, "leakfree")}
    with pytest.raises(InvalidParameterError, match=r"too short for 1 of .*\n  10 Hz paper: 9 samples.*\n.*--rate"):
        compensate_log(tmp_path / "trk.mcap", tmp_path / "c.mcap", rates=[10], protocols="paper", skip_short=True,
                       force=True)
