"""Motion models: discretisation against Van Loan, and filter consistency on each model."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.linalg import expm
from scipy.stats import chi2

from starlog.errors import InvalidInputError, InvalidParameterError
from starlog.tracking import (
    BatchUKF,
    MotionModel,
    MotionModelConfig,
    discretize,
    initial_covariance,
    state_dim,
)

MODELS = list(MotionModel)
CFG = MotionModelConfig()


def continuous(model: MotionModel, cfg: MotionModelConfig) -> tuple[np.ndarray, np.ndarray]:
    """Continuous-time (A, G Qc Gᵀ) per axis, written independently of the module."""
    if model is MotionModel.STATIC:
        a1, qc = np.zeros((1, 1)), np.diag([cfg.q_floor])
    elif model is MotionModel.RANDOM_WALK:
        a1, qc = np.zeros((1, 1)), np.diag([cfg.q_position + cfg.q_floor])
    elif model is MotionModel.BROWNIAN_MOTION:
        a1 = np.array([[0.0, 1.0], [0.0, -1.0 / cfg.tau]])
        qc = np.diag([cfg.q_floor, cfg.q_velocity])
    elif model is MotionModel.CONSTANT_VELOCITY:
        a1 = np.array([[0.0, 1.0], [0.0, 0.0]])
        qc = np.diag([cfg.q_floor, cfg.q_acceleration])
    else:
        a1 = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
        qc = np.diag([cfg.q_floor, 0.0, cfg.q_jerk])
    return np.kron(a1, np.eye(2)), np.kron(qc, np.eye(2))


def van_loan(
    model: MotionModel, dt: float, cfg: MotionModelConfig
) -> tuple[np.ndarray, np.ndarray]:
    a, qc = continuous(model, cfg)
    d = a.shape[0]
    m = np.zeros((2 * d, 2 * d))
    m[:d, :d] = -a
    m[:d, d:] = qc
    m[d:, d:] = a.T
    e = expm(m * dt)
    f = e[d:, d:].T
    return f, f @ e[:d, d:]


def test_parse_names() -> None:
    assert MotionModel.parse("constant-velocity") is MotionModel.CONSTANT_VELOCITY
    assert MotionModel.parse("static") is MotionModel.STATIC
    assert MotionModel.STATIC == "STATIC"
    with pytest.raises(InvalidParameterError, match="unknown motion model 'JERK'"):
        MotionModel.parse("JERK")


@pytest.mark.parametrize(
    ("field", "value"),
    [("q_floor", 0.0), ("tau", -1.0), ("q_jerk", -1.0), ("q_position", float("nan")),
     ("init_velocity_sigma", 0.0), ("q_velocity", "big")],
)
def test_config_rejects(field: str, value: object) -> None:
    with pytest.raises(InvalidParameterError, match=f"MotionModelConfig.{field}"):
        MotionModelConfig(**{field: value})


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("dt", [1e-4, 1 / 300, 1 / 200, 0.05])  # Van Loan overflows for dt >> tau
def test_discretize_matches_van_loan(model: MotionModel, dt: float) -> None:
    f, q = discretize(model, dt)
    f_ref, q_ref = van_loan(model, dt, CFG)
    assert f.shape == (state_dim(model),) * 2
    assert_allclose(f, f_ref, rtol=0, atol=1e-12 * max(1.0, np.abs(f_ref).max()))
    assert_allclose(q, q_ref, rtol=0, atol=1e-9 * np.abs(q_ref).max())


@pytest.mark.parametrize("u", [1e-4, 0.0099, 0.0101, 0.05])
def test_ou_small_step_series(u: float) -> None:
    """The Taylor branch of the OU position variance joins the closed form smoothly."""
    dt = u * CFG.tau
    _, q = discretize(MotionModel.BROWNIAN_MOTION, dt)
    _, q_ref = van_loan(MotionModel.BROWNIAN_MOTION, dt, CFG)
    assert_allclose(q[0, 0], q_ref[0, 0], rtol=1e-8, atol=0)


@pytest.mark.parametrize("model", MODELS)
def test_discretize_semigroup_and_batch(model: MotionModel) -> None:
    dt1, dt2 = 0.0021, 0.0047
    f1, q1 = discretize(model, dt1)
    f2, q2 = discretize(model, dt2)
    f12, q12 = discretize(model, dt1 + dt2)
    assert_allclose(f12, f2 @ f1, rtol=0, atol=1e-12 * np.abs(f12).max())
    assert_allclose(q12, f2 @ q1 @ f2.T + q2, rtol=0, atol=1e-10 * np.abs(q12).max())
    fb, qb = discretize(model, np.array([dt1, dt2]))
    assert_allclose(fb, np.stack([f1, f2]), rtol=0, atol=0)
    assert_allclose(qb, np.stack([q1, q2]), rtol=0, atol=0)
    f0, q0 = discretize(model, 0.0)
    assert_allclose(f0, np.eye(state_dim(model)), rtol=0, atol=0)
    assert_allclose(q0, 0.0, rtol=0, atol=0)


@pytest.mark.parametrize("dt", [-1e-3, float("nan"), [[0.1]]])
def test_discretize_rejects_bad_dt(dt: object) -> None:
    with pytest.raises(InvalidInputError, match="dt must be"):
        discretize(MotionModel.STATIC, dt)  # type: ignore[arg-type]


def test_initial_covariance() -> None:
    p = initial_covariance(MotionModel.POLYNOMIAL_TREND, [0.1, 0.2])
    assert p.shape == (2, 6, 6)
    assert_allclose(
        np.diagonal(p[1]), [0.04, 0.04, 100.0, 100.0, 1e6, 1e6], rtol=0, atol=1e-12
    )


# ---------------------------------------------------------------------- filter consistency
N_STARS = 8
N_STEPS = 400
SEEDS = {
    MotionModel.STATIC: 11,
    MotionModel.RANDOM_WALK: 12,
    MotionModel.BROWNIAN_MOTION: 13,
    MotionModel.POLYNOMIAL_TREND: 14,
    MotionModel.CONSTANT_VELOCITY: 15,
}


def simulate(model: MotionModel, rng: np.random.Generator):
    """Truth drawn from the model itself, irregular 200-300 Hz frames, per-frame sigma."""
    d = state_dim(model)
    dts = rng.uniform(1 / 300, 1 / 200, N_STEPS)
    sig = rng.uniform(0.05, 0.15, (N_STEPS, N_STARS))
    p0 = initial_covariance(model, np.ones(N_STARS), config=CFG)
    truth = np.zeros((N_STEPS, N_STARS, d))
    state = np.zeros((N_STARS, d))
    state[:, :2] = rng.uniform(50, 1000, (N_STARS, 2))
    state[:, 2:] = rng.normal(size=(N_STARS, d - 2)) * np.sqrt(np.diagonal(p0[0])[2:])
    for k in range(N_STEPS):
        if k:
            f, q = discretize(model, dts[k], config=CFG)
            w = rng.multivariate_normal(np.zeros(d), q, size=N_STARS, method="cholesky")
            state = state @ f.T + w
        truth[k] = state
    z = truth[:, :, :2] + rng.normal(size=(N_STEPS, N_STARS, 2)) * sig[:, :, None]
    return dts, sig, truth, z


@pytest.mark.parametrize("model", MODELS)
def test_filter_beats_raw_and_is_consistent(model: MotionModel) -> None:
    rng = np.random.default_rng(SEEDS[model])
    dts, sig, truth, z = simulate(model, rng)
    ukf = BatchUKF.from_centroids(model, x=z[0, :, 0], y=z[0, :, 1], sigma=sig[0])
    est = np.zeros((N_STEPS, N_STARS, 2))
    est[0] = z[0]
    nis = np.zeros((N_STEPS - 1, N_STARS))
    for k in range(1, N_STEPS):
        res = ukf.step(dts[k], z[k], sig[k])
        est[k] = res.x[:, :2]
        nis[k - 1] = res.nis
    burn = 10
    rmse_filter = np.sqrt(np.mean((est[burn:] - truth[burn:, :, :2]) ** 2))
    rmse_raw = np.sqrt(np.mean((z[burn:] - truth[burn:, :, :2]) ** 2))
    assert rmse_filter < 0.9 * rmse_raw
    n = nis.size
    low, high = chi2.ppf([0.025, 0.975], 2 * n) / n
    assert low < nis.mean() < high
