"""Burn-in detection: the first sample whose position variance is within 2x of the steady state."""

from __future__ import annotations

import numpy as np
import pytest

from starlog.compensate import BurnIn, burn_in
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
    from starlog.compensate import burn_in_cap

    assert burn_in_cap(3248, native_rate=300.0) == 150
    assert burn_in_cap(3027, native_rate=200.0) == 100
    assert burn_in_cap(160, native_rate=100.0) == 16
