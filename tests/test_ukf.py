"""Batched UKF: oracles (linear KF, filterpy), gate, masks, PSD property."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from starlog.errors import InvalidInputError, InvalidParameterError
from starlog.tracking import (
    BatchUKF,
    MotionModel,
    MotionModelConfig,
    SigmaPoints,
    discretize,
    filterpy_step,
    gate_threshold,
    initial_covariance,
    make_filterpy_ukf,
    state_dim,
)
from starlog.tracking.ukf import sigma_points, ukf_update

MODELS = list(MotionModel)
N_STEPS = 150


def assert_cov_close(actual: np.ndarray, desired: np.ndarray, rel: float = 1e-9) -> None:
    """Covariances equal to ``rel`` of each element's scale ``sqrt(P_ii P_jj)`` (units differ)."""
    s = np.sqrt(np.abs(np.diagonal(desired)))
    scale = np.maximum(np.outer(s, s), 1e-300)
    assert_allclose((actual - desired) / scale, 0.0, rtol=0, atol=rel)


def inputs(model: MotionModel, seed: int):
    rng = np.random.default_rng(seed)
    dts = rng.uniform(0.5, 2.0, N_STEPS) / 300
    sig = rng.uniform(0.03, 0.3, N_STEPS)
    z = np.array([512.3, 100.7]) + rng.normal(size=(N_STEPS, 2)) * sig[:, None]
    return dts, sig, z


def linear_kf(model, x, P, dts, sig, z):
    """A plain linear Kalman filter, written independently of starlog's UKF."""
    d = state_dim(model)
    H = np.zeros((2, d))
    H[0, 0] = H[1, 1] = 1.0
    xs, ps, niss = [], [], []
    for dt, s, zk in zip(dts, sig, z, strict=True):
        F, Q = discretize(model, dt)
        x = F @ x
        P = F @ P @ F.T + Q
        S = H @ P @ H.T + s**2 * np.eye(2)
        nu = zk - H @ x
        K = P @ H.T @ np.linalg.inv(S)
        x = x + K @ nu
        P = (np.eye(d) - K @ H) @ P
        xs.append(x)
        ps.append(P)
        niss.append(nu @ np.linalg.solve(S, nu))
    return np.array(xs), np.array(ps), np.array(niss)


@pytest.mark.parametrize(
    "points",
    [SigmaPoints(), SigmaPoints(alpha=0.5, beta=2.0, kappa=1.0)],
    ids=["default", "scaled"],
)
@pytest.mark.parametrize("model", MODELS)
def test_equals_linear_kalman_filter(model: MotionModel, points: SigmaPoints) -> None:
    dts, sig, z = inputs(model, 1)
    ukf = BatchUKF.from_centroids(
        model, x=[512.0], y=[101.0], sigma=[0.2], points=points, gate_probability=1.0
    )
    x_ref, p_ref, nis_ref = linear_kf(model, ukf.x[0], ukf.P[0], dts, sig, z)
    for k in range(N_STEPS):
        res = ukf.step(dts[k], z[k][None], sig[k : k + 1])
        assert_allclose(res.x[0, :2], x_ref[k, :2], rtol=0, atol=1e-9)
        s = np.sqrt(np.diagonal(p_ref[k]))
        assert_allclose(res.x[0] / s, x_ref[k] / s, rtol=0, atol=1e-6)
        assert_cov_close(res.P[0], p_ref[k])
        assert_allclose(res.nis[0], nis_ref[k], rtol=0, atol=1e-9 * max(1.0, nis_ref[k]))


@pytest.mark.parametrize("model", MODELS)
def test_equals_filterpy(model: MotionModel) -> None:
    dts, sig, z = inputs(model, 2)
    ukf = BatchUKF.from_centroids(model, x=[512.0], y=[101.0], sigma=[0.2])
    ref = make_filterpy_ukf(model, x=ukf.x[0], P=ukf.P[0])
    for k in range(N_STEPS):
        res = ukf.step(dts[k], z[k][None], sig[k : k + 1])
        nis, applied = filterpy_step(ref, model, dts[k], z[k], sig[k])
        assert applied == bool(res.applied[0])
        assert_allclose(res.x[0, :2], ref.x[:2], rtol=0, atol=1e-9)
        assert_cov_close(res.P[0], ref.P)
        assert_allclose(res.nis[0], nis, rtol=0, atol=1e-9 * max(1.0, nis))


@pytest.mark.parametrize("model", MODELS)
def test_batch_equals_one_by_one(model: MotionModel) -> None:
    """Vectorisation across stars (with per-star dt) changes nothing."""
    rng = np.random.default_rng(3)
    n = 5
    x0 = rng.uniform(0, 1000, n)
    y0 = rng.uniform(0, 1000, n)
    s0 = rng.uniform(0.05, 0.2, n)
    batch = BatchUKF.from_centroids(model, x=x0, y=y0, sigma=s0)
    singles = [BatchUKF.from_centroids(model, x=x0[i : i + 1], y=y0[i : i + 1], sigma=s0[i : i + 1])
               for i in range(n)]
    for _ in range(20):
        dt = rng.uniform(1 / 400, 1 / 100, n)
        z = np.stack([x0, y0], 1) + rng.normal(0, 0.1, (n, 2))
        s = rng.uniform(0.05, 0.2, n)
        res = batch.step(dt, z, s)
        for i, one in enumerate(singles):
            r1 = one.step(dt[i], z[i : i + 1], s[i : i + 1])
            assert_allclose(res.x[i, :2], r1.x[0, :2], rtol=0, atol=1e-12)
            assert_cov_close(res.P[i], r1.P[0], 1e-12)


def test_gate_threshold() -> None:
    assert_allclose(gate_threshold(0.9999), 18.420680743952367, rtol=0, atol=1e-12)
    assert_allclose(gate_threshold(0.95), 5.991464547107979, rtol=0, atol=1e-12)
    assert gate_threshold(1.0) == math.inf
    with pytest.raises(InvalidParameterError, match="gate probability"):
        gate_threshold(0.0)


def test_outlier_is_gated_and_not_applied() -> None:
    ukf = BatchUKF.from_centroids("STATIC", x=[10.0, 50.0], y=[20.0, 60.0], sigma=[0.1, 0.1])
    for _ in range(20):
        ukf.step(1 / 300, [[10.0, 20.0], [50.0, 60.0]], [0.1, 0.1])
    before = ukf.x
    ukf.predict(1 / 300)
    prior_x, prior_p = ukf.x, ukf.P
    res = ukf.update([[11.5, 20.0], [50.01, 60.0]], [0.1, 0.1])
    assert res.applied.tolist() == [False, True]
    assert res.nis[0] > gate_threshold(0.9999)
    assert_allclose(res.innovation[0], [1.5, 0.0], rtol=0, atol=1e-6)
    assert_allclose(res.x[0], prior_x[0], rtol=0, atol=0)
    assert_allclose(res.P[0], prior_p[0], rtol=0, atol=0)
    assert_allclose(ukf.x[0], before[0], rtol=0, atol=1e-12)


def test_mask_leaves_unmeasured_at_prior() -> None:
    ukf = BatchUKF.from_centroids("CONSTANT_VELOCITY", x=[1.0, 2.0], y=[3.0, 4.0], sigma=[0.1, 0.1])
    ukf.predict(0.01)
    prior_x, prior_p = ukf.x, ukf.P
    res = ukf.update([[1.05, 3.0], [0.0, 0.0]], [0.1, 0.1], mask=[True, False])
    assert res.applied.tolist() == [True, False]
    assert res.nis[1] == 0.0
    assert_allclose(res.x[1], prior_x[1], rtol=0, atol=0)
    assert_allclose(res.P[1], prior_p[1], rtol=0, atol=0)
    assert not np.allclose(res.x[0], prior_x[0])


@pytest.mark.parametrize(
    ("z", "sigma", "match"),
    [
        ([[1.0, 2.0, 3.0]], [0.1], "shape"),
        ([[np.nan, 2.0]], [0.1], "finite"),
        ([[1.0, 2.0]], [0.0], "sigma"),
        ([[1.0, 2.0]], [0.1, 0.2], "shape"),
    ],
)
def test_update_rejects_bad_input(z: list, sigma: list, match: str) -> None:
    ukf = BatchUKF.from_centroids("STATIC", x=[1.0], y=[2.0], sigma=[0.1])
    with pytest.raises(InvalidInputError, match=match):
        ukf.update(z, sigma)


def test_constructor_rejects_wrong_state_size() -> None:
    with pytest.raises(InvalidInputError, match=r"shape \(n, 4\)"):
        BatchUKF("CONSTANT_VELOCITY", x=np.zeros((1, 2)), P=np.eye(2)[None])


@pytest.mark.parametrize(("kw", "match"), [({"alpha": 0.0}, "alpha"), ({"beta": -1.0}, "beta"),
                                            ({"kappa": -3.0}, "kappa")])
def test_sigma_points_validation(kw: dict, match: str) -> None:
    with pytest.raises(InvalidParameterError, match=match):
        SigmaPoints(**kw)


@pytest.mark.parametrize("n", [2, 4, 6])
def test_sigma_point_moments(n: int) -> None:
    rng = np.random.default_rng(n)
    a = rng.normal(size=(3, n, n))
    P = a @ a.swapaxes(1, 2) + np.eye(n)
    x = rng.normal(size=(3, n))
    pts = SigmaPoints(alpha=0.3, beta=2.0, kappa=0.5)
    wm, wc = pts.weights(n)
    assert_allclose(wm.sum(), 1.0, rtol=0, atol=1e-12)
    sig = sigma_points(x, P, points=pts)
    mean = np.einsum("s,nsd->nd", wm, sig)
    dev = sig - mean[:, None]
    cov = np.einsum("s,nsi,nsj->nij", wc, dev, dev)
    assert_allclose(mean, x, rtol=0, atol=1e-12)
    assert_allclose(cov, P, rtol=0, atol=1e-10)


def test_rounding_indefinite_covariance_is_repaired() -> None:
    P = np.array([[[1.0, 1.0], [1.0, 1.0 - 1e-15]]])  # PSD up to rounding, not PD
    sig = sigma_points(np.zeros((1, 2)), P, points=SigmaPoints())
    assert np.isfinite(sig).all()
    res = ukf_update(np.zeros((1, 2)), P, np.zeros((1, 2)), 0.01 * np.eye(2)[None],
                     points=SigmaPoints())
    assert np.isfinite(res.P).all()


@settings(max_examples=40, deadline=None)
@given(
    model=st.sampled_from(MODELS),
    dts=st.lists(st.floats(1e-5, 0.1), min_size=1, max_size=25),
    sigmas=st.lists(st.floats(1e-3, 3.0), min_size=25, max_size=25),
    measure=st.lists(st.booleans(), min_size=25, max_size=25),
)
def test_covariance_stays_symmetric_psd(
    model: MotionModel, dts: list[float], sigmas: list[float], measure: list[bool]
) -> None:
    cfg = MotionModelConfig()
    P0 = initial_covariance(model, [sigmas[0]], config=cfg)
    ukf = BatchUKF(model, x=np.zeros((1, state_dim(model))), P=P0, config=cfg, gate_probability=1.0)
    for k, dt in enumerate(dts):
        ukf.predict(dt)
        if measure[k]:
            ukf.update([[0.01 * k, -0.02 * k]], [sigmas[k]])
        P = ukf.P[0]
        assert np.isfinite(P).all()
        assert_allclose(P, P.T, rtol=0, atol=0)
        s = np.sqrt(np.diagonal(P))
        corr = P / np.outer(s, s)
        assert np.linalg.eigvalsh(corr).min() > -1e-9
