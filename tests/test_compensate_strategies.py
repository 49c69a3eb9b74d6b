"""The five compensation strategies (§2.3) against hand-worked numbers, plus properties."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from numpy.testing import assert_allclose, assert_array_equal

from starlog.compensation import strategies as S
from starlog.compensation.strategies import Strategy
from starlog.errors import InvalidInputError, InvalidParameterError


def _xaxis(values: list[float]) -> np.ndarray:
    """An (N, 2) series moving along x only."""
    return np.column_stack([np.asarray(values, dtype=float), np.zeros(len(values))])


# --- 1. adaptive window trend (eq. 1-3) --------------------------------------------------------


@pytest.mark.parametrize(
    ("rate_hz", "fd", "expected"),
    [
        (100.0, 10.0, 5),  # 100 / 20 = 5 -> 5
        (100.0, 20.0, 3),  # 2.5 -> nearest odd 3
        (100.0, 1.0, 11),  # 50 -> clipped to 11
        (100.0, 0.0, 11),  # no dominant frequency -> widest window
        (10.0, 4.0, 3),  # 1.25 -> 1 -> clipped to 3
        (100.0, 40.0, 3),  # 1.25 -> 1 -> clipped to 3
        (100.0, 100.0 / 14.0, 7),  # exactly 7
        (100.0, 12.5, 5),  # 4: tie between 3 and 5 -> the larger, 5
        (100.0, 100.0 / 12.0, 7),  # 6: tie between 5 and 7 -> 7
        (100.0, 6.25, 9),  # 8: tie -> 9
        (100.0, 5.0, 11),  # 10: tie -> 11
        (100.0, 100.0 / 11.8, 5),  # 5.9 -> 5
        (30.0, 3.0, 5),  # 5 -> 5
    ],
)
def test_trend_window_eq1(rate_hz: float, fd: float, expected: int) -> None:
    assert S.trend_window(rate_hz=rate_hz, dominant_frequency=fd) == expected


@pytest.mark.parametrize("fd", [-1.0, float("nan"), float("inf")])
def test_trend_window_rejects_bad_frequency(fd: float) -> None:
    with pytest.raises(InvalidParameterError, match="dominant_frequency"):
        S.trend_window(rate_hz=100.0, dominant_frequency=fd)


def test_trend_window_rejects_bad_rate() -> None:
    with pytest.raises(InvalidParameterError, match="rate_hz"):
        S.trend_window(rate_hz=0.0, dominant_frequency=1.0)


def test_moving_average_eq2_truncated_edges() -> None:
    # W = 3: interior (x[n-1] + x[n] + x[n+1]) / 3; ends average the samples that exist.
    x = _xaxis([0.0, 1.0, 2.0, 3.0, 10.0])
    t = S.moving_average(x, window=3)
    assert_allclose(t[:, 0], [0.5, 1.0, 2.0, 5.0, 6.5], rtol=0, atol=1e-12)
    assert_allclose(t[:, 1], 0.0, rtol=0, atol=0)


def test_adaptive_window_trend_eq3_by_hand() -> None:
    # rate_hz = 100, f_d = 20 -> W = 3; T = [0.5, 1, 2, 5, 6.5]; M = (1, 0); y = x - (T - M).
    x = _xaxis([0.0, 1.0, 2.0, 3.0, 10.0])
    y = S.adaptive_window_trend(x, rate_hz=100.0, dominant_frequency=20.0, reference=[1.0, 0.0])
    assert_allclose(y[:, 0], [0.5, 1.0, 1.0, -1.0, 4.5], rtol=0, atol=1e-12)
    assert_allclose(y[:, 1], 0.0, rtol=0, atol=1e-12)


# --- 2. adaptive median (eq. 4) ----------------------------------------------------------------


@pytest.mark.parametrize(
    ("level", "window"),
    [
        (0.0, 3),  # floor(3) = 3
        (0.05, 3),  # floor(3.5) = 3
        (0.1, 5),  # floor(4) = 4 -> even, raised to 5
        (0.25, 5),  # floor(5.5) = 5
        (0.35, 7),  # floor(6.5) = 6 -> 7
        (0.5, 9),  # 8 -> 9
        (0.75, 11),  # floor(10.5) = 10 -> 11
        (0.8, 11),  # 11
        (5.0, 11),  # clipped to 11
    ],
)
def test_median_window_eq4(level: float, window: int) -> None:
    assert int(S.median_window(np.array([level]))[0]) == window


def test_local_noise_level_estimates_white_noise() -> None:
    rng = np.random.default_rng(11)
    xy = rng.normal(0.0, 0.3, size=(2000, 2)) + np.linspace(0, 5, 2000)[:, None]  # + slow trend
    level = S.local_noise_level(xy)
    assert_allclose(np.median(level, axis=0), [0.3, 0.3], rtol=0, atol=0.03)


def test_adaptive_median_removes_impulse_and_leaves_edges() -> None:
    # Constant zeros: local noise (MAD of differences) 0 -> W = 3 everywhere.
    x = _xaxis([5.0, 0, 0, 0, 0, 7.0, 0, 0, 0, 0, 0, -4.0])
    y = S.adaptive_median(x)
    expected = [5.0, 0, 0, 0, 0, 0.0, 0, 0, 0, 0, 0, -4.0]  # spikes at the ends untouched
    assert_allclose(y[:, 0], expected, rtol=0, atol=0)


def test_adaptive_median_wide_window_edges_unchanged() -> None:
    rng = np.random.default_rng(3)
    xy = rng.normal(0.0, 50.0, size=(40, 2))  # noise level >> 0.8 px -> W = 11, h = 5
    windows = S.median_window(S.local_noise_level(xy))
    assert (windows == 11).all()
    y = S.adaptive_median(xy)
    assert_array_equal(y[:5], xy[:5])
    assert_array_equal(y[-5:], xy[-5:])
    for n in range(5, 35):
        assert_allclose(y[n], np.median(xy[n - 5 : n + 6], axis=0), rtol=0, atol=0)


# --- 3. local smoothing (eq. 5-6) --------------------------------------------------------------


def test_local_smoothing_eq6_by_hand() -> None:
    # x = [0, 0, 1, 0, 0], y = 0.  5-sample windows (truncated at the ends), ddof = 0:
    #   n = 2: var{0,0,1,0,0} = 0.2 - 0.04 = 0.16,  alpha = 1 - e^-0.16 = 0.147856211
    #          y[2] = (1 - alpha) * 1 + alpha/2 * (0 + 0) = 0.852143789
    #   n = 1: var{0,0,1,0} = 0.25 - 0.0625 = 0.1875, alpha = 0.170970882
    #          y[1] = (1 - alpha) * 0 + alpha/2 * (0 + 1) = 0.085485441;  n = 3 likewise
    #   n = 0, 4: unchanged.
    x = _xaxis([0.0, 0.0, 1.0, 0.0, 0.0])
    assert_allclose(S.local_variance(x)[1:4], [0.1875, 0.16, 0.1875], rtol=0, atol=1e-12)
    y = S.local_smoothing(x)
    assert_allclose(
        y[:, 0], [0.0, 0.0854854409, 0.8521437890, 0.0854854409, 0.0], rtol=0, atol=1e-9
    )
    assert_allclose(y[:, 1], 0.0, rtol=0, atol=0)


# --- 4. AR(2) prediction (eq. 7-9) -------------------------------------------------------------


def test_ar_weights_eq8() -> None:
    assert_allclose(S.AR_THETA, [0.6225, 0.3775], rtol=0, atol=1e-4)
    assert_allclose(S.AR_THETA.sum(), 1.0, rtol=0, atol=1e-15)
    assert_allclose(S.AR_THETA[0], 1.0 / (1.0 + np.exp(-0.5)), rtol=0, atol=1e-15)


def test_ar_prediction_eq9_by_hand() -> None:
    # M = 0, e = x = [1, 2, 4]; e_hat[2] = theta1 * 2 + theta2 * 1 = 1 + theta1 = 1.6224593
    # y[2] = 0.7 * (0 + 1.6224593) + 0.3 * 4 = 2.3357215;  y[0], y[1] unchanged.
    y = S.ar_prediction(_xaxis([1.0, 2.0, 4.0]), reference=[0.0, 0.0])
    assert_allclose(y[:, 0], [1.0, 2.0, 2.3357215318], rtol=0, atol=1e-9)


def test_ar_prediction_per_sample_reference() -> None:
    # With M[n] = x[n] - c for all n: e = c, e_hat = c, y = 0.7 (M + c) + 0.3 x = x.
    rng = np.random.default_rng(5)
    xy = rng.normal(size=(20, 2))
    y = S.ar_prediction(xy, reference=xy - np.array([0.2, -0.1]))
    assert_allclose(y, xy, rtol=0, atol=1e-12)


# --- 5. confidence weighting (eq. 10-11) -------------------------------------------------------


def test_confidence_weighted_eq11_by_hand() -> None:
    # G = (0.3, 0.4), M = 0: D = 0.5; I = 1 (no flux); A = 0
    # gamma = (1/100 + 1) * 1/2 * e^-0.5 = 0.505 * 0.60653066 = 0.30629798
    # output = gamma * G = (0.09188939, 0.12251919)
    g = S.confidence(np.array([[0.3, 0.4]]), reference=[0.0, 0.0])
    assert_allclose(g, [0.3062979832], rtol=0, atol=1e-9)
    out = S.confidence_weighted(np.array([[0.3, 0.4]]), reference=[0.0, 0.0])
    assert_allclose(out, [[0.0918893949, 0.1225191933]], rtol=0, atol=1e-9)


def test_confidence_intensity_normalised_by_max() -> None:
    # D = 0: gamma = (I/100 + 1) / 2 with I = flux / max(flux) = [0.5, 1]
    xy = np.zeros((2, 2))
    g = S.confidence(xy, reference=[0.0, 0.0], flux=[50.0, 100.0])
    assert_allclose(g, [0.5025, 0.505], rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    ("point", "accuracy", "expected"),
    [
        ((3.0, 0.0), 0.0, 0.1),  # 0.505 e^-3 = 0.025 -> clipped up to 0.1
        ((0.0, 0.0), 0.2, 0.1),  # 1 - 10 A = -1 -> negative -> 0.1
        ((0.0, 0.0), 0.05, 0.255),  # (0.01 + 0.5) / 2
        ((0.0, 0.0), 0.0, 0.505),  # the largest gamma valid input can give (< 0.9 clip)
    ],
)
def test_confidence_clipped(point: tuple[float, float], accuracy: float, expected: float) -> None:
    g = S.confidence(np.array([point]), reference=[0.0, 0.0], accuracy=[accuracy])
    assert_allclose(g, [expected], rtol=0, atol=1e-12)


def test_confidence_rejects_negative_accuracy() -> None:
    with pytest.raises(InvalidInputError, match="accuracy"):
        S.confidence(np.zeros((1, 2)), reference=[0.0, 0.0], accuracy=[-0.1])


# --- validation, empty input, dispatch ---------------------------------------------------------


def _run(strategy: Strategy, xy: np.ndarray, reference: np.ndarray) -> np.ndarray:
    return S.apply_strategy(
        strategy, xy, rate_hz=50.0, reference=reference, dominant_frequency=7.0,
        flux=np.ones(len(xy)), accuracy=np.zeros(len(xy)),
    )


@pytest.mark.parametrize("strategy", list(Strategy))
def test_empty_series_gives_empty_result(strategy: Strategy) -> None:
    out = _run(strategy, np.zeros((0, 2)), np.zeros(2))
    assert out.shape == (0, 2)


@pytest.mark.parametrize("strategy", list(Strategy))
def test_nan_rejected(strategy: Strategy) -> None:
    xy = np.zeros((10, 2))
    xy[4, 1] = np.nan
    with pytest.raises(InvalidInputError, match="NaN"):
        _run(strategy, xy, np.zeros(2))


@pytest.mark.parametrize("shape", [(10,), (10, 3), (2, 10)])
def test_bad_shape_rejected(shape: tuple[int, ...]) -> None:
    with pytest.raises(InvalidInputError, match=r"shape \(N, 2\)"):
        S.local_smoothing(np.zeros(shape))


def test_reference_shape_mismatch_rejected() -> None:
    with pytest.raises(InvalidInputError, match="reference"):
        S.ar_prediction(np.zeros((10, 2)), reference=np.zeros((9, 2)))


def test_unknown_strategy_rejected() -> None:
    with pytest.raises(InvalidParameterError, match="unknown strategy"):
        S.apply_strategy("KALMAN", np.zeros((5, 2)), rate_hz=10.0, reference=[0.0, 0.0])


# --- hypothesis properties ---------------------------------------------------------------------

_series = hnp.arrays(
    np.float64,
    st.tuples(st.integers(0, 40), st.just(2)),
    elements=st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False),
)


@settings(max_examples=60, deadline=None)
@given(xy=_series, strategy=st.sampled_from(list(Strategy)))
def test_shape_finite_and_no_mutation(xy: np.ndarray, strategy: Strategy) -> None:
    original = xy.copy()
    reference = xy.mean(axis=0) if len(xy) else np.zeros(2)
    ref_copy = reference.copy()
    out = _run(strategy, xy, reference)
    assert out.shape == xy.shape
    assert np.isfinite(out).all()
    assert out is not xy
    assert_array_equal(xy, original)
    assert_array_equal(reference, ref_copy)


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(0, 40),
    point=st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)),
    strategy=st.sampled_from(list(Strategy)),
)
def test_constant_series_is_fixed_point(
    n: int, point: tuple[float, float], strategy: Strategy
) -> None:
    # The reference of a constant series is its own mean, i.e. the constant.
    xy = np.tile(np.asarray(point, dtype=float), (n, 1))
    out = _run(strategy, xy, np.asarray(point, dtype=float))
    assert_allclose(out, xy, rtol=0, atol=1e-9 * (1.0 + np.abs(xy).max(initial=0.0)))
