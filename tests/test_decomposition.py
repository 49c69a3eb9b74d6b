"""Error decomposition (§2.2) on synthetic error series with a known mix."""

from __future__ import annotations

import json

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.signal import lfilter

from starlog.compensation.decomposition import (
    MIN_SAMPLES,
    ErrorCategory,
    ErrorDecomposition,
    decompose,
)
from starlog.errors import InvalidInputError, InvalidParameterError

FS = 100.0


def _radial(c: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(c**2, axis=1))))


def _known_mix(seed: int, n: int) -> tuple[np.ndarray, np.ndarray, dict[ErrorCategory, float]]:
    """Drift + 20.3 Hz vibration + S-curve + white noise about a dithered true position.

    The true position dithers over 3 px (so the sub-pixel phase is sampled), drift and
    vibration move the image (the S-curve follows the physical position), the white noise
    does not.  Returns (measured xy, reference = true positions, true magnitudes).
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n) / FS
    truth = np.array([100.0, 50.0]) + rng.uniform(0.0, 3.0, size=(n, 2))
    u = np.linspace(-1.0, 1.0, n)
    drift = np.column_stack([0.15 * u + 0.05 * u**2, -0.10 * u])
    vib = np.column_stack(
        [0.08 * np.sin(2 * np.pi * 20.3 * t + 0.3), 0.05 * np.sin(2 * np.pi * 20.3 * t + 1.1)]
    )
    physical = truth + drift + vib
    phase = physical - np.round(physical)
    scurve = np.column_stack(
        [0.06 * np.sin(2 * np.pi * phase[:, 0]), 0.04 * np.sin(2 * np.pi * phase[:, 1])]
    )
    noise = rng.normal(0.0, 0.04, size=(n, 2))
    expected = {
        ErrorCategory.SYSTEMATIC_LOW_FREQ: _radial(drift),
        ErrorCategory.SYSTEMATIC_HIGH_FREQ: _radial(vib),
        ErrorCategory.RANDOM_QUANTIZATION: _radial(scurve),
        ErrorCategory.MEASUREMENT_NOISE: _radial(noise),
    }
    return physical + scurve + noise, truth, expected


@pytest.mark.parametrize(("seed", "n"), [(0, 500), (1, 1000), (2, 2000), (3, 3000)])
def test_known_mix_recovered_within_20_percent(seed: int, n: int) -> None:
    xy, truth, expected = _known_mix(seed, n)
    d = decompose(xy, rate_hz=FS, reference=truth)
    for category, value in expected.items():
        assert_allclose(d.magnitudes[category], value, rtol=0.2, atol=0)
    assert d.magnitudes[ErrorCategory.MODEL_MISMATCH] < 0.2 * expected[
        ErrorCategory.MEASUREMENT_NOISE
    ]
    assert_allclose(d.dominant_frequency, 20.3, rtol=0, atol=0.05)
    assert d.significant[ErrorCategory.SYSTEMATIC_HIGH_FREQ]


@pytest.mark.parametrize("seed", [4, 5, 6])
def test_white_noise_is_only_measurement_noise(seed: int) -> None:
    rng = np.random.default_rng(seed)
    xy = np.array([200.3, 10.7]) + rng.normal(0.0, 0.1, size=(1000, 2))
    d = decompose(xy, rate_hz=50.0)  # reference: global mean
    assert_allclose(d.magnitudes[ErrorCategory.MEASUREMENT_NOISE], 0.1 * np.sqrt(2), rtol=0.1)
    for category in (
        ErrorCategory.SYSTEMATIC_LOW_FREQ,
        ErrorCategory.SYSTEMATIC_HIGH_FREQ,
        ErrorCategory.RANDOM_QUANTIZATION,
        ErrorCategory.MODEL_MISMATCH,
    ):
        assert d.magnitudes[category] == 0.0
    assert d.dominant_frequency == 0.0  # documented: no peak stands out
    assert d.peaks == ()


@pytest.mark.parametrize("seed", [7, 8])
def test_ar_noise_is_model_mismatch(seed: int) -> None:
    # e[n] = 0.8 e[n-1] + u[n], u ~ N(0, 0.05^2): the AR-predictable part 0.8 e[n-1] has RMS
    # 0.8 * 0.05 / sqrt(1 - 0.64) per axis, the white innovation 0.05 per axis.
    rng = np.random.default_rng(seed)
    e = lfilter([1.0], [1.0, -0.8], rng.normal(0.0, 0.05, size=(2000, 2)), axis=0)
    d = decompose(e + 30.0, rate_hz=100.0, reference=[30.0, 30.0])
    expected_mm = 0.8 * 0.05 / 0.6 * np.sqrt(2)
    assert_allclose(d.magnitudes[ErrorCategory.MODEL_MISMATCH], expected_mm, rtol=0.2)
    assert_allclose(d.magnitudes[ErrorCategory.MEASUREMENT_NOISE], 0.05 * np.sqrt(2), rtol=0.2)
    assert d.peaks == ()  # a red spectrum is not a periodic peak
    assert_allclose(d.ar_coefficients[0][0], 0.8, rtol=0, atol=0.1)


def test_bias_against_truth_is_low_frequency() -> None:
    rng = np.random.default_rng(9)
    xy = np.array([10.2, 20.4]) + rng.normal(0.0, 0.05, size=(400, 2))
    d = decompose(xy, rate_hz=20.0, reference=[10.0, 20.0])  # bias (0.2, 0.4)
    assert_allclose(d.magnitudes[ErrorCategory.SYSTEMATIC_LOW_FREQ], np.hypot(0.2, 0.4), rtol=0.05)


def test_static_star_without_phase_spread_has_no_scurve() -> None:
    # A star that sits still on one sub-pixel phase: the S-curve cannot be identified.
    rng = np.random.default_rng(10)
    xy = np.array([100.3, 50.6]) + rng.normal(0.0, 0.02, size=(500, 2))
    d = decompose(xy, rate_hz=50.0)
    assert d.magnitudes[ErrorCategory.RANDOM_QUANTIZATION] == 0.0


def test_to_dict_is_json_ready() -> None:
    xy, truth, _ = _known_mix(11, 500)
    d = decompose(xy, rate_hz=FS, reference=truth)
    out = d.to_dict()
    text = json.dumps(out, allow_nan=False)
    assert json.loads(text) == out
    assert set(out["magnitudes"]) == {c.value for c in ErrorCategory}
    assert out["peaks"][0]["frequency"] == pytest.approx(20.3, abs=0.05)
    assert isinstance(d, ErrorDecomposition)


def test_error_category_names() -> None:
    assert [c.value for c in ErrorCategory] == [
        "SYSTEMATIC_LOW_FREQ",
        "SYSTEMATIC_HIGH_FREQ",
        "MEASUREMENT_NOISE",
        "RANDOM_QUANTIZATION",
        "MODEL_MISMATCH",
    ]


def test_input_not_mutated() -> None:
    xy, truth, _ = _known_mix(12, 300)
    xy_copy, truth_copy = xy.copy(), truth.copy()
    decompose(xy, rate_hz=FS, reference=truth)
    np.testing.assert_array_equal(xy, xy_copy)
    np.testing.assert_array_equal(truth, truth_copy)


def test_too_short_rejected() -> None:
    with pytest.raises(InvalidInputError, match=f"at least {MIN_SAMPLES}"):
        decompose(np.zeros((MIN_SAMPLES - 1, 2)), rate_hz=10.0)


def test_minimum_length_accepted() -> None:
    rng = np.random.default_rng(13)
    d = decompose(rng.normal(size=(MIN_SAMPLES, 2)), rate_hz=10.0)
    assert all(np.isfinite(v) for v in d.magnitudes.values())


def test_constant_series() -> None:
    d = decompose(np.full((50, 2), 3.25), rate_hz=10.0)
    assert all(v == 0.0 for v in d.magnitudes.values())
    assert d.dominant_frequency == 0.0


def test_nan_rejected() -> None:
    xy = np.zeros((40, 2))
    xy[3, 0] = np.nan
    with pytest.raises(InvalidInputError, match="NaN"):
        decompose(xy, rate_hz=10.0)


@pytest.mark.parametrize(
    "kwargs",
    [{"rate_hz": 0.0}, {"rate_hz": 10.0, "trend_degree": -1}, {"rate_hz": 10.0, "false_alarm": 0.7},
     {"rate_hz": 10.0, "ar_order": 0}],
)
def test_bad_parameters_rejected(kwargs: dict[str, float]) -> None:
    with pytest.raises(InvalidParameterError):
        decompose(np.zeros((40, 2)), **kwargs)
