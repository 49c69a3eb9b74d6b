"""Nearest-frame decimation: every nominal rate of Figure 5 is reached, with the expected sample counts."""

from __future__ import annotations

import numpy as np
import pytest

from starlog.compensation import decimation_indices, effective_rate, sampled_rate

FIGURE5_RATES = [float(r) for r in range(10, 101, 10)]


@pytest.mark.parametrize(("native", "n"), [(300.0, 3248), (200.0, 3027)])
def test_figure5_rates_are_distinct_and_within_one_percent(native: float, n: int) -> None:
    chosen = [tuple(decimation_indices(n, native_rate=native, target_rate=r).tolist()) for r in FIGURE5_RATES]
    assert len(set(chosen)) == len(FIGURE5_RATES)
    for rate in FIGURE5_RATES:
        got = effective_rate(native_rate=native, target_rate=rate, n=n)
        assert abs(got / rate - 1.0) < 0.01, (rate, got)


@pytest.mark.parametrize(("native", "n"), [(300.0, 3248), (200.0, 3027), (300.0, 960), (200.0, 640)])
@pytest.mark.parametrize("rate", [5.0, *FIGURE5_RATES])
def test_sample_count_is_the_ideal_times_inside_the_sequence(native: float, n: int, rate: float) -> None:
    idx = decimation_indices(n, native_rate=native, target_rate=rate)
    # ideal times m / rate whose nearest frame index floor(m * native / rate + 0.5) is < n
    expected = sum(1 for m in range(n + 1) if np.floor(m * native / rate + 0.5) < n)
    assert idx.size == expected
    assert np.all(np.diff(idx) > 0) and idx[0] == 0 and idx[-1] < n
    steps = set(np.diff(idx).tolist())
    assert steps <= {int(np.floor(native / rate)), int(np.ceil(native / rate))}


def test_six_second_window_counts() -> None:
    # The paper's image numbers: 60 at 10 Hz, 300 at 50 Hz; a 6 s window of 70 Hz has 420 samples.
    for native in (300.0, 200.0):
        for rate, count in ((10.0, 60), (50.0, 300), (70.0, 420)):
            idx = decimation_indices(3000, native_rate=native, target_rate=rate)[:count]
            assert abs(sampled_rate(idx, native_rate=native) / rate - 1.0) < 0.01


def test_start_offsets_the_selection() -> None:
    assert decimation_indices(20, native_rate=300.0, target_rate=70.0, start=3).tolist() == [3, 7, 12, 16]
    assert decimation_indices(5, native_rate=300.0, target_rate=70.0, start=5).size == 0


def test_sampled_rate_of_too_few_samples_is_the_native_rate() -> None:
    assert sampled_rate([4], native_rate=300.0) == 300.0
    assert sampled_rate([0, 6, 12], native_rate=300.0) == 50.0
