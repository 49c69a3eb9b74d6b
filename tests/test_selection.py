"""Adaptive selection (§2.4): eq. 12 scores, top-three order, eq. 13 rollback, the record."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from numpy.testing import assert_allclose, assert_array_equal

from starlog.compensation.decomposition import ErrorCategory
from starlog.compensation.references import ReferenceMode, ScoringProtocol
from starlog.compensation.selection import (
    StrategyProfile,
    PASS_DTYPE,
    TABLE_1,
    compensate,
    rank_strategies,
    strategy_scores,
)
from starlog.compensation.strategies import Strategy, apply_strategy
from starlog.errors import InvalidInputError, InvalidParameterError

C = ErrorCategory


def test_table_1() -> None:
    rows = {r.strategy: (r.effect, r.cost, r.targets) for r in TABLE_1}
    assert rows[Strategy.ADAPTIVE_WINDOW_TREND] == (0.7, 0.3, {C.SYSTEMATIC_LOW_FREQ})
    assert rows[Strategy.ADAPTIVE_MEDIAN] == (
        0.6, 0.2, {C.SYSTEMATIC_HIGH_FREQ, C.MEASUREMENT_NOISE})
    assert rows[Strategy.LOCAL_SMOOTHING] == (
        0.5, 0.1, {C.RANDOM_QUANTIZATION, C.MEASUREMENT_NOISE})
    assert rows[Strategy.AR_PREDICTION] == (0.8, 0.4, {C.MODEL_MISMATCH})
    assert rows[Strategy.CONFIDENCE_WEIGHTED] == (
        0.9, 0.5, {C.SYSTEMATIC_LOW_FREQ, C.MODEL_MISMATCH})


def test_scores_eq12_by_hand() -> None:
    mags = {
        C.SYSTEMATIC_LOW_FREQ: 0.1,
        C.SYSTEMATIC_HIGH_FREQ: 0.2,
        C.MEASUREMENT_NOISE: 0.3,
        C.RANDOM_QUANTIZATION: 0.05,
        C.MODEL_MISMATCH: 0.4,
    }
    scores = strategy_scores(mags)
    expected = {
        Strategy.ADAPTIVE_WINDOW_TREND: 0.1 * 0.7 * 0.7,  # 0.049
        Strategy.ADAPTIVE_MEDIAN: (0.2 + 0.3) * 0.6 * 0.8,  # 0.24
        Strategy.LOCAL_SMOOTHING: (0.05 + 0.3) * 0.5 * 0.9,  # 0.1575
        Strategy.AR_PREDICTION: 0.4 * 0.8 * 0.6,  # 0.192
        Strategy.CONFIDENCE_WEIGHTED: (0.1 + 0.4) * 0.9 * 0.5,  # 0.225
    }
    for s, v in expected.items():
        assert_allclose(scores[s], v, rtol=0, atol=1e-12)
    assert rank_strategies(scores) == (
        Strategy.ADAPTIVE_MEDIAN,
        Strategy.CONFIDENCE_WEIGHTED,
        Strategy.AR_PREDICTION,
        Strategy.LOCAL_SMOOTHING,
        Strategy.ADAPTIVE_WINDOW_TREND,
    )


def test_scores_accept_names_and_missing_categories() -> None:
    scores = strategy_scores({"MODEL_MISMATCH": 1.0})
    assert_allclose(scores[Strategy.AR_PREDICTION], 0.48, rtol=0, atol=1e-12)
    assert scores[Strategy.ADAPTIVE_MEDIAN] == 0.0


def test_ties_keep_table_order() -> None:
    scores = strategy_scores({})
    assert rank_strategies(scores) == tuple(r.strategy for r in TABLE_1)


def test_unknown_category_rejected() -> None:
    with pytest.raises(InvalidParameterError, match="category"):
        strategy_scores({"VIBRATION": 1.0})


def _noise_series(seed: int, sigma: float, n: int = 300) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.array([512.3, 300.8]) + rng.normal(0.0, sigma, size=(n, 2))


def _replay(xy: np.ndarray, result) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Apply the kept passes by hand, in order, about the global mean."""
    out = xy
    ref = xy.mean(axis=0)
    for p in result.passes:
        if p.kept:
            out = apply_strategy(
                p.strategy, out, rate_hz=result.rate_hz, reference=ref,
                dominant_frequency=result.decomposition.dominant_frequency,
            )
    return out


def test_top_three_run_in_score_order_and_record_matches() -> None:
    xy = _noise_series(0, 0.3)
    res = compensate(xy, rate_hz=50.0, select_positive=False)  # the top three whatever their score
    ranked = rank_strategies(res.scores)
    assert res.order == ranked[:3]
    assert tuple(p.strategy for p in res.passes) == res.order
    assert [p.rank for p in res.passes] == [0, 1, 2]
    scores = [p.score for p in res.passes]
    assert scores == sorted(scores, reverse=True)
    assert scores == [res.scores[s] for s in res.order]
    # The record matches what ran: each pass starts from the last kept output ...
    current_rmse = res.rmse_before
    for p in res.passes:
        assert_allclose(p.rmse_before, current_rmse, rtol=0, atol=1e-12)
        assert_allclose(p.effective, (p.rmse_before - p.rmse_after) / p.rmse_before, rtol=0,
                        atol=1e-12)
        assert p.kept == (p.effective >= 0.01)
        if p.kept:
            current_rmse = p.rmse_after
    assert_allclose(res.rmse_after, current_rmse, rtol=0, atol=1e-12)
    # ... and replaying the kept passes gives the compensated series.
    assert_allclose(res.compensated, _replay(xy, res), rtol=0, atol=1e-12)
    assert res.protocol is ScoringProtocol.PAPER
    assert res.reference_mode is ReferenceMode.GLOBAL_MEAN
    assert res.n_selection == res.n_samples == len(xy)


def test_pass_below_one_percent_is_rolled_back() -> None:
    # 0.01 px white noise: the median filter (first) helps a lot; afterwards the local
    # variance is ~1e-4 px^2, so eq. 5 gives alpha ~ 1e-4 and local smoothing changes the
    # RMSE by far less than 1 %: it must be rolled back.
    xy = _noise_series(1, 0.01)
    res = compensate(xy, rate_hz=50.0)
    by_name = {p.strategy: p for p in res.passes}
    assert res.order[:2] == (Strategy.ADAPTIVE_MEDIAN, Strategy.LOCAL_SMOOTHING)
    smoothing = by_name[Strategy.LOCAL_SMOOTHING]
    assert 0.0 <= smoothing.effective < 0.01
    assert not smoothing.kept
    assert Strategy.LOCAL_SMOOTHING not in res.kept
    assert by_name[Strategy.ADAPTIVE_MEDIAN].kept
    assert_allclose(res.compensated, _replay(xy, res), rtol=0, atol=1e-12)


def test_everything_rolled_back_returns_input() -> None:
    xy = _noise_series(2, 0.2)
    res = compensate(xy, rate_hz=50.0, rollback_threshold=1.0)
    assert res.kept == ()
    assert_array_equal(res.compensated, xy)
    assert res.rmse_after == res.rmse_before


def test_constant_series_rolls_everything_back() -> None:
    xy = np.full((40, 2), 7.5)
    res = compensate(xy, rate_hz=10.0)
    assert res.kept == ()
    assert all(p.effective == 0.0 for p in res.passes)
    assert_array_equal(res.compensated, xy)


def test_top_k() -> None:
    res = compensate(_noise_series(3, 0.2), rate_hz=50.0, top_k=5, select_positive=False)
    assert len(res.passes) == 5
    assert set(res.order) == set(Strategy)


def test_record_is_json_ready_and_table() -> None:
    xy = _noise_series(4, 0.2)
    res = compensate(xy, rate_hz=50.0, flux=np.linspace(100, 200, len(xy)), select_positive=False)
    d = res.to_dict()
    text = json.dumps(d, allow_nan=False)
    assert json.loads(text) == d
    assert d["protocol"] == "paper"
    assert d["order"] == [str(s) for s in res.order]
    assert set(d["scores"]) == {s.value for s in Strategy}
    assert len(d["passes"]) == 3
    table = res.passes_table()
    assert table.dtype == PASS_DTYPE
    assert list(table["strategy"]) == [str(s) for s in res.order]
    assert list(table["kept"]) == [p.kept for p in res.passes]


def test_input_not_mutated() -> None:
    xy = _noise_series(5, 0.2)
    flux = np.linspace(1.0, 2.0, len(xy))
    sigma = np.full(len(xy), 0.01)
    copies = (xy.copy(), flux.copy(), sigma.copy())
    res = compensate(xy, rate_hz=50.0, flux=flux, sigma=sigma, accuracy_source="sigma")
    for a, b in zip((xy, flux, sigma), copies):
        assert_array_equal(a, b)
    assert res.compensated is not xy


@pytest.mark.parametrize("mode", [ReferenceMode.CALIBRATION, ReferenceMode.RUNNING_MEAN])
def test_leakfree_selection_never_sees_held_out_samples(mode: ReferenceMode) -> None:
    xy = _noise_series(6, 0.3, n=200)
    other = xy.copy()
    rng = np.random.default_rng(60)
    other[100:] += rng.normal(0.0, 1.0, size=(100, 2)) + 5.0  # change only the held-out part
    a = compensate(xy, rate_hz=50.0, reference_mode=mode, calibration_fraction=0.5)
    b = compensate(other, rate_hz=50.0, reference_mode=mode, calibration_fraction=0.5)
    assert a.n_selection == b.n_selection == 100
    assert a.decomposition.n_samples == 100
    assert a.scores == b.scores
    assert a.passes == b.passes
    assert a.reference_point == b.reference_point
    assert a.protocol is ScoringProtocol.LEAKFREE
    if mode is ReferenceMode.CALIBRATION:
        assert_allclose(a.reference_point, xy[:100].mean(axis=0), rtol=0, atol=1e-12)
    else:
        assert a.reference_point is None


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"top_k": 0}, InvalidParameterError, "top_k"),
        ({"top_k": 6}, InvalidParameterError, "top_k"),
        ({"reference_mode": "median"}, InvalidParameterError, "reference_mode"),
        ({"accuracy_source": "sigma"}, InvalidParameterError, "sigma"),
        ({"protocol": "leakfree"}, InvalidParameterError, "does not go with"),
        ({"reference_mode": "calibration", "protocol": "paper"}, InvalidParameterError,
         "does not go with"),
        ({"flux": np.ones(10)}, InvalidInputError, "flux"),
        ({"reference_mode": "calibration", "calibration_fraction": 0.05}, InvalidInputError,
         "calibration"),
        ({"reference_mode": "calibration", "calibration_fraction": 1.0}, InvalidParameterError,
         "calibration_fraction"),
    ],
)
def test_bad_arguments(kwargs: dict[str, object], error: type, match: str) -> None:
    with pytest.raises(error, match=match):
        compensate(_noise_series(7, 0.1, n=60), rate_hz=10.0, **kwargs)  # type: ignore[arg-type]


def test_too_short_rejected() -> None:
    with pytest.raises(InvalidInputError, match="at least 16"):
        compensate(np.zeros((15, 2)), rate_hz=10.0)


@settings(max_examples=30, deadline=None)
@given(
    xy=hnp.arrays(
        np.float64,
        st.tuples(st.integers(16, 80), st.just(2)),
        elements=st.floats(-100.0, 100.0, allow_nan=False, allow_infinity=False),
    )
)
def test_compensate_properties(xy: np.ndarray) -> None:
    original = xy.copy()
    res = compensate(xy, rate_hz=25.0)
    assert res.compensated.shape == xy.shape
    assert np.isfinite(res.compensated).all()
    assert_array_equal(xy, original)
    # Rollback keeps only improving passes: the RMSE about M never grows.
    assert res.rmse_after <= res.rmse_before * (1.0 + 1e-12) + 1e-12
    json.dumps(res.to_dict(), allow_nan=False)


def test_zero_score_strategies_are_not_run() -> None:
    # Only measurement noise: AR_PREDICTION and the trend strategies target categories the
    # decomposition sets to 0, so only positive-score strategies run (fewer than three here).
    xy = _noise_series(7, 0.2)
    res = compensate(xy, rate_hz=50.0, top_k=5)
    positive = tuple(s for s in rank_strategies(res.scores) if res.scores[s] > 0.0)
    assert res.order == positive
    assert all(res.scores[s] > 0.0 for s in res.order)
    assert res.select_positive and res.to_dict()["select_positive"] is True
    forced = compensate(xy, rate_hz=50.0, top_k=5, select_positive=False)
    assert len(forced.order) == 5 and not forced.select_positive


def test_nothing_to_run_when_every_score_is_zero() -> None:
    zero = tuple(StrategyProfile(row.strategy, 0.0, row.cost, row.targets) for row in TABLE_1)
    xy = _noise_series(8, 0.2)
    res = compensate(xy, rate_hz=50.0, table=zero)
    assert res.order == () and res.passes == () and res.kept == ()
    assert_array_equal(res.compensated, xy)
    assert compensate(xy, rate_hz=50.0, table=zero, select_positive=False).order != ()
