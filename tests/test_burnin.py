"""Burn-in detection: the first sample whose position variance is within 2x of the steady state."""

from __future__ import annotations

import numpy as np
import pytest

from starlog.compensation import BurnIn, burn_in
from starlog.errors import InvalidInputError, InvalidParameterError


def _settling_variance(n: int, *, steady: float, tau: float) -> np.ndarray:
    """A filter settling exponentially from 100x its steady variance."""
    k = np.arange(n, dtype=np.float64)
    return steady * (1.0 + 99.0 * np.exp(-k / tau))


def test_settling_filter_ends_where_the_variance_is_twice_the_steady_state() -> None:
    var = _settling_variance(3000, steady=1e-3, tau=10.0)
    expected = int(np.ceil(10.0 * np.log(99.0)))  # 99 exp(-k/10) <= 1
    got = burn_in(var, max_samples=150)
    assert got == BurnIn(samples=expected, steady_variance=pytest.approx(1e-3), capped=False)
    assert var[got.samples] <= 2e-3 < var[got.samples - 1]


def test_running_mean_never_settles_and_is_capped() -> None:
    # STATIC: P[n] = sigma^2 / (n + 1), no steady state inside the sequence.
    var = 0.01 / np.arange(1, 3249, dtype=np.float64)
    got = burn_in(var, max_samples=150)
    assert got.capped and got.samples == 150


def test_settled_from_the_start_and_edge_cases() -> None:
    assert burn_in(np.full(100, 4e-4), max_samples=10) == BurnIn(0, 4e-4, False)
    assert burn_in(np.zeros(0), max_samples=10) == BurnIn(0, 0.0, False)
    # a gated spike after settling does not move the burn-in
    var = _settling_variance(500, steady=1e-3, tau=5.0)
    var[300] = 1.0
    assert burn_in(var, max_samples=100).samples == int(np.ceil(5.0 * np.log(99.0)))


@pytest.mark.parametrize(("kwargs", "error"), [
    ({"variance": [1.0, -1.0], "max_samples": 1}, InvalidInputError),
    ({"variance": [1.0, np.nan], "max_samples": 1}, InvalidInputError),
    ({"variance": [1.0], "max_samples": -1}, InvalidParameterError),
    ({"variance": [1.0], "max_samples": 1, "ratio": 1.0}, InvalidParameterError),
])
def test_rejects(kwargs: dict[str, object], error: type) -> None:
    with pytest.raises(error):
        burn_in(**kwargs)  # type: ignore[arg-type]


def test_cap_is_half_a_second_or_a_tenth_of_the_log() -> None:
    from starlog.compensation import burn_in_cap

    assert burn_in_cap(3248, native_rate=300.0) == 150
    assert burn_in_cap(3027, native_rate=200.0) == 100
    assert burn_in_cap(160, native_rate=100.0) == 16


@pytest.mark.parametrize(("value", "expected"), [(None, "auto"), ("auto", "auto"), (" OFF ", "off"), ("0", "off"),
                                                 (0.0, "off"), ("0.25", 0.25), ("1.5 s", 1.5), (2, 2.0)])
def test_parse_burn_in(value: object, expected: object) -> None:
    from starlog.compensation import parse_burn_in

    assert parse_burn_in(value) == expected


@pytest.mark.parametrize("value", ["soon", "-1", -0.5, float("nan"), True])
def test_parse_burn_in_rejects(value: object) -> None:
    from starlog.compensation import parse_burn_in

    with pytest.raises(InvalidParameterError):
        parse_burn_in(value)


def _series(n: int = 400, rate: float = 100.0) -> object:
    from starlog.stages.compensate import BrightestSeries

    var = 1.0 / np.arange(1, n + 1) + 0.01  # a settling filter: within 2x of 0.01 after 100 samples
    return BrightestSeries(method="NONE", model="STATIC", track=0, log_time=np.arange(n, dtype=np.int64) * 10_000_000,
                           frame=np.arange(n, dtype=np.int64), xy=np.zeros((n, 2)), flux=np.ones(n),
                           sigma=np.full(n, 0.1), native_rate=rate, position_var=var)


def test_series_burn_in_settings_decide_the_first_sample() -> None:
    series = _series()
    auto = series.burn_in("auto")
    assert 0 < auto.samples <= 40  # the variance rule, capped at 10 % of 400 samples
    assert series.burn_in("off").samples == 0
    assert series.burn_in(0.25).samples == 25  # 0.25 s at 100 Hz
    assert series.burn_in(100.0).samples == 399  # never past the last sample
    assert series.indices(10.0, burn_in="off")[0] == 0
    assert series.indices(10.0, burn_in=0.25)[0] == 25
    assert series.indices(10.0)[0] == auto.samples
    assert series.indices(10.0, skip_burn_in=False, burn_in=0.25)[0] == 0


def test_label() -> None:
    from starlog.compensation import burn_in_label

    assert [burn_in_label(s) for s in ("auto", "off", 0.5)] == ["auto", "off", "0.5 s"]
