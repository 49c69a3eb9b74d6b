"""RMSE (eq. 15), references, decimation and the paper / truth / leakfree protocols."""

from __future__ import annotations

import json

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from starlog.compensation.decimate import (
    decimate,
    decimation_indices,
)
from starlog.compensation.protocols import FIGURE_DTYPE, evaluate, rmse
from starlog.compensation.references import (
    ScoringProtocol,
    global_mean_reference,
    running_mean_reference,
)
from starlog.errors import InvalidInputError, InvalidParameterError

# --- eq. 15 and references ---------------------------------------------------------------------


def test_rmse_about_point() -> None:
    # sqrt(((0 + 0) + (9 + 16)) / 2) = sqrt(12.5)
    assert_allclose(rmse([[0.0, 0.0], [3.0, 4.0]], [0.0, 0.0]), np.sqrt(12.5), rtol=0, atol=1e-15)


def test_rmse_about_series() -> None:
    xy = np.array([[1.0, 1.0], [2.0, 2.0]])
    ref = np.array([[1.0, 0.0], [2.0, 2.0]])
    assert_allclose(rmse(xy, ref), np.sqrt(0.5), rtol=0, atol=1e-15)


def test_rmse_about_mean_is_eq15() -> None:
    rng = np.random.default_rng(0)
    xy = rng.normal(size=(50, 2))
    m = global_mean_reference(xy)
    expected = np.sqrt(np.mean((xy[:, 0] - m[0]) ** 2 + (xy[:, 1] - m[1]) ** 2))
    assert_allclose(rmse(xy, m), expected, rtol=0, atol=1e-15)


@pytest.mark.parametrize(
    ("xy", "ref", "match"),
    [
        (np.zeros((0, 2)), [0.0, 0.0], "empty"),
        (np.array([[np.nan, 0.0]]), [0.0, 0.0], "NaN"),
        (np.zeros((3, 2)), np.zeros((2, 2)), "reference"),
        (np.zeros((3, 3)), [0.0, 0.0], "shape"),
    ],
)
def test_rmse_rejects(xy: np.ndarray, ref: object, match: str) -> None:
    with pytest.raises(InvalidInputError, match=match):
        rmse(xy, ref)  # type: ignore[arg-type]


def test_running_mean_uses_only_the_past() -> None:
    xy = np.array([[1.0, 0.0], [3.0, 2.0], [5.0, 4.0], [7.0, 0.0]])
    m = running_mean_reference(xy)
    assert_allclose(m, [[1.0, 0.0], [1.0, 0.0], [2.0, 1.0], [3.0, 2.0]], rtol=0, atol=1e-15)


# --- decimation --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("native", "target", "first"),
    [
        (300.0, 100.0, [0, 3, 6, 9]),
        (300.0, 50.0, [0, 6, 12, 18]),
        (300.0, 40.0, [0, 8, 15, 23, 30]),  # 7.5 frames per sample: nearest frame, ties later
        (300.0, 70.0, [0, 4, 9, 13, 17, 21, 26, 30]),  # 30 frames per 7 samples
        (200.0, 30.0, [0, 7, 13, 20, 27]),
        (300.0, 300.0, [0, 1, 2, 3]),
    ],
)
def test_decimation_takes_the_nearest_frame(native: float, target: float, first: list[int]) -> None:
    idx = decimation_indices(len(first) * 10, native_rate=native, target_rate=target)
    assert idx[: len(first)].tolist() == first
    ideal = np.arange(idx.size) * native / target
    assert np.abs(idx - ideal).max() <= 0.5 + 1e-9


def test_decimation_rejects_upsampling() -> None:
    with pytest.raises(InvalidParameterError, match="above the native rate"):
        decimation_indices(10, native_rate=200.0, target_rate=300.0)


@pytest.mark.parametrize("rate", [0.0, -10.0, float("nan")])
def test_decimation_rejects_bad_rates(rate: float) -> None:
    with pytest.raises(InvalidParameterError):
        decimation_indices(10, native_rate=300.0, target_rate=rate)


def test_decimate_keeps_every_kth_sample() -> None:
    values = np.arange(40.0).reshape(20, 2)
    original = values.copy()
    out = decimate(values, native_rate=300.0, target_rate=50.0)  # k = 6
    assert_array_equal(out, values[[0, 6, 12, 18]])
    assert_array_equal(values, original)
    assert_array_equal(
        decimation_indices(20, native_rate=300.0, target_rate=50.0, start=2), [2, 8, 14]
    )
    assert decimate(np.zeros((0, 2)), native_rate=300.0, target_rate=50.0).shape == (0, 2)


def test_decimate_keeps_dtype() -> None:
    log_time = np.arange(10, dtype=np.int64) * 3_333_333
    out = decimate(log_time, native_rate=300.0, target_rate=100.0)
    assert out.dtype == np.int64
    assert_array_equal(out, log_time[[0, 3, 6, 9]])


def test_decimate_rejects_non_numeric() -> None:
    with pytest.raises(InvalidInputError, match="numeric"):
        decimate(np.array(["a", "b"]), native_rate=300.0, target_rate=100.0)


# --- protocols on a simulated static star ------------------------------------------------------


def _static_star(seed: int, n: int = 300, rate_hz: float = 50.0):  # type: ignore[no-untyped-def]
    """White centroid noise (0.3 px) + small platform jitter (0.05 px) about a fixed point."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate_hz
    fixed = np.array([512.37, 300.81])
    jitter = 0.05 * np.column_stack(
        [np.sin(2 * np.pi * 3.1 * t), np.cos(2 * np.pi * 3.1 * t + 0.4)]
    )
    truth = fixed + jitter
    xy = truth + rng.normal(0.0, 0.3, size=(n, 2))
    return xy, fixed, truth, rate_hz


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_paper_protocol_improves_static_star(seed: int) -> None:
    xy, _, _, rate_hz = _static_star(seed)
    ev = evaluate(xy, rate_hz=rate_hz, protocol="paper")
    assert ev.protocol is ScoringProtocol.PAPER
    assert [f.reference for f in ev.figures] == ["global_mean"]
    assert_allclose(ev.rmse_before, rmse(xy, xy.mean(axis=0)), rtol=0, atol=1e-12)
    assert ev.rmse_after < ev.rmse_before  # the paper's claim
    assert ev.n_scored == len(xy) and ev.scored_start == 0
    assert ev.result.protocol is ScoringProtocol.PAPER


@pytest.mark.parametrize("seed", [0, 1])
def test_truth_and_leakfree_figures_are_computed(seed: int) -> None:
    xy, fixed, truth, rate_hz = _static_star(seed)
    paper = evaluate(xy, rate_hz=rate_hz, protocol="paper")
    tr = evaluate(xy, rate_hz=rate_hz, protocol="truth", truth_fixed=fixed, truth_series=truth)
    lf = evaluate(xy, rate_hz=rate_hz, protocol="leakfree", truth_fixed=fixed, truth_series=truth)
    lf_run = evaluate(xy, rate_hz=rate_hz, protocol="leakfree", leakfree_reference="running_mean",
                      truth_series=truth)
    assert [f.reference for f in tr.figures] == ["truth_fixed", "truth_series"]
    assert [f.reference for f in lf.figures] == ["heldout_mean", "truth_fixed", "truth_series"]
    assert [f.reference for f in lf_run.figures] == ["heldout_mean", "truth_series"]
    for ev in (tr, lf, lf_run):
        for f in ev.figures:
            assert np.isfinite([f.rmse_before, f.rmse_after, f.effective]).all()
            assert f.rmse_before > 0
    # truth: same strategy run as the paper (global mean), scored against the truth
    assert_array_equal(tr.result.compensated, paper.result.compensated)
    assert tr.result.protocol is ScoringProtocol.TRUTH
    assert_allclose(tr.figure("truth_fixed").rmse_before, rmse(xy, fixed), rtol=0, atol=1e-12)
    assert_allclose(tr.figure("truth_series").rmse_after,
                    rmse(tr.result.compensated, truth), rtol=0, atol=1e-12)
    # leakfree: scored on the held-out half only
    assert lf.scored_start == 150 and lf.n_scored == 150
    held = xy[150:]
    assert_allclose(lf.figure("heldout_mean").rmse_before, rmse(held, held.mean(axis=0)),
                    rtol=0, atol=1e-12)
    assert_allclose(lf.figure("truth_series").rmse_after,
                    rmse(lf.result.compensated[150:], truth[150:]), rtol=0, atol=1e-12)
    assert lf.result.protocol is ScoringProtocol.LEAKFREE


def test_evaluation_record_json_and_table() -> None:
    xy, fixed, truth, rate_hz = _static_star(3)
    ev = evaluate(xy, rate_hz=rate_hz, protocol="leakfree", truth_fixed=fixed, truth_series=truth)
    d = ev.to_dict()
    assert json.loads(json.dumps(d, allow_nan=False)) == d
    assert d["protocol"] == "leakfree"
    assert d["compensation"]["protocol"] == "leakfree"
    assert d["compensation"]["reference_mode"] == "calibration"
    table = ev.figures_table()
    assert table.dtype == FIGURE_DTYPE
    assert list(table["reference"]) == ["heldout_mean", "truth_fixed", "truth_series"]


def test_truth_protocol_needs_truth() -> None:
    xy, _, _, rate_hz = _static_star(4)
    with pytest.raises(InvalidParameterError, match="truth"):
        evaluate(xy, rate_hz=rate_hz, protocol="truth")


@pytest.mark.parametrize(
    ("kwargs", "error"),
    [
        ({"protocol": "oracle"}, InvalidParameterError),
        ({"protocol": "truth", "truth_series": np.zeros((10, 2))}, InvalidInputError),
        ({"protocol": "truth", "truth_fixed": np.zeros(3)}, InvalidInputError),
        ({"protocol": "leakfree", "leakfree_reference": "global_mean"}, InvalidParameterError),
    ],
)
def test_evaluate_rejects(kwargs: dict[str, object], error: type) -> None:
    xy, _, _, rate_hz = _static_star(5, n=60, rate_hz=10.0)
    with pytest.raises(error):
        evaluate(xy, rate_hz=rate_hz, **kwargs)  # type: ignore[arg-type]
