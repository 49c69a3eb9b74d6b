"""The five motion models of the tracking filter (paper §3.2.1; docs/PAPER.md, "Temporal filtering").

Every model is linear and time-invariant in continuous time; this module gives its exact
discretisation over a step ``dt`` (seconds): the transition matrix ``F(dt)`` and the process
noise covariance ``Q(dt)``. State layout, units px, px/s, px/s²:

=====================  ========================  ==========================================
model                  state                     dynamics (per axis, continuous time)
=====================  ========================  ==========================================
``STATIC``             (x, y)                    dx = 0 (only the ``q_floor`` diffusion)
``RANDOM_WALK``        (x, y)                    dx = sqrt(q_position) dW
``BROWNIAN_MOTION``    (x, y, vx, vy)            dx = v dt, dv = -v/tau dt + sqrt(q_velocity) dW
``POLYNOMIAL_TREND``   (x, y, vx, vy, ax, ay)    dx = v dt, dv = a dt, da = sqrt(q_jerk) dW
``CONSTANT_VELOCITY``  (x, y, vx, vy)            dx = v dt, dv = sqrt(q_acceleration) dW
=====================  ========================  ==========================================

``W`` is a unit Wiener process, so each ``q_*`` is the (two-sided) spectral density of the
white noise driving the model's highest state derivative. Every model also gets
``q_floor * dt`` on its position variances so that ``P`` stays positive definite.

Default intensities come from one picture of the data: a static star field imaged at
200–300 Hz whose centroids jitter with a micro-vibration of amplitude ``a = 0.05`` px at
``f = 20`` Hz (RMS ``a_rms = a / sqrt(2)``, ``omega = 2 pi f``). Each model's driven derivative
is allowed to change by its RMS value for that vibration within a quarter period
(``1 / (4 f)`` s), that is ``q = rms² * 4 f``:

* ``q_position = a_rms² * 4f ≈ 0.1 px²/s`` (RANDOM_WALK),
* ``q_acceleration = (omega a_rms)² * 4f ≈ 1.5e3 px²/s³`` (CONSTANT_VELOCITY),
* ``q_jerk = (omega² a_rms)² * 4f ≈ 2.5e7 px²/s⁵`` (POLYNOMIAL_TREND),
* ``tau = 1 / omega ≈ 8 ms`` and ``q_velocity = 2 (omega a_rms)² / tau ≈ 5e3 px²/s³``, which
  makes the stationary velocity RMS of the Ornstein–Uhlenbeck process ``sqrt(q tau / 2)``
  equal to the vibration's (BROWNIAN_MOTION),
* ``q_floor = 1e-9 px²/s``: over a 3248-frame, 300 Hz log the STATIC model's position
  uncertainty stays far below any centroid noise, so STATIC behaves as "no process noise".

Nothing here depends on the time origin; times are differences of integer-ns ``log_time``
values converted to seconds by the caller.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidInputError, InvalidParameterError

__all__ = [
    "MotionModel",
    "MotionModelConfig",
    "state_dim",
    "discretize",
    "initial_covariance",
]


class MotionModel(enum.StrEnum):
    """Motion model of a star track, by the paper's names (Table 2)."""

    STATIC = "STATIC"
    RANDOM_WALK = "RANDOM_WALK"
    BROWNIAN_MOTION = "BROWNIAN_MOTION"
    POLYNOMIAL_TREND = "POLYNOMIAL_TREND"
    CONSTANT_VELOCITY = "CONSTANT_VELOCITY"

    @classmethod
    def parse(cls, name: str | MotionModel) -> MotionModel:
        """Return the model named ``name`` (case-insensitive, ``-`` allowed for ``_``).

        Raises
        ------
        InvalidParameterError
            If no model has that name.
        """
        if isinstance(name, MotionModel):
            return name
        key = str(name).strip().upper().replace("-", "_")
        try:
            return cls(key)
        except ValueError:
            names = ", ".join(m.value for m in cls)
            raise InvalidParameterError(
                f"unknown motion model {name!r}; choose one of {names}."
            ) from None


_DIM = {
    MotionModel.STATIC: 2,
    MotionModel.RANDOM_WALK: 2,
    MotionModel.BROWNIAN_MOTION: 4,
    MotionModel.POLYNOMIAL_TREND: 6,
    MotionModel.CONSTANT_VELOCITY: 4,
}


def state_dim(model: MotionModel | str) -> int:
    """Length of the state vector of ``model`` (2, 4 or 6)."""
    return _DIM[MotionModel.parse(model)]


@dataclass(frozen=True)
class MotionModelConfig:
    """Process-noise intensities and initial uncertainties of the motion models.

    Each model reads only the fields named for it; see the module docstring for the
    dynamics and for where the defaults come from.

    Parameters
    ----------
    q_floor : float
        Position diffusion added to every model, px²/s, > 0 (keeps ``P`` positive definite;
        the whole process noise of STATIC).
    q_position : float
        RANDOM_WALK position diffusion, px²/s, >= 0.
    q_velocity : float
        BROWNIAN_MOTION spectral density of the noise driving the velocity, px²/s³, >= 0.
    tau : float
        BROWNIAN_MOTION velocity correlation time, s, > 0.
    q_acceleration : float
        CONSTANT_VELOCITY white-acceleration spectral density, px²/s³, >= 0.
    q_jerk : float
        POLYNOMIAL_TREND white-jerk spectral density, px²/s⁵, >= 0.
    init_velocity_sigma : float
        Standard deviation of the initial velocity (initial velocity is 0), px/s, > 0.
    init_acceleration_sigma : float
        Standard deviation of the initial acceleration (initially 0), px/s², > 0.
    """

    q_floor: float = 1e-9
    q_position: float = 0.1
    q_velocity: float = 5e3
    tau: float = 8e-3
    q_acceleration: float = 1.5e3
    q_jerk: float = 2.5e7
    init_velocity_sigma: float = 10.0
    init_acceleration_sigma: float = 1e3

    def __post_init__(self) -> None:
        positive = ("q_floor", "tau", "init_velocity_sigma", "init_acceleration_sigma")
        non_negative = ("q_position", "q_velocity", "q_acceleration", "q_jerk")
        for name in positive + non_negative:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)):
                raise InvalidParameterError(
                    f"MotionModelConfig.{name} must be a number, got {value!r}."
                )
            if not math.isfinite(value):
                raise InvalidParameterError(
                    f"MotionModelConfig.{name} must be finite, got {value!r}."
                )
            if name in positive and value <= 0:
                raise InvalidParameterError(
                    f"MotionModelConfig.{name} must be > 0, got {value!r}."
                )
            if name in non_negative and value < 0:
                raise InvalidParameterError(
                    f"MotionModelConfig.{name} must be >= 0, got {value!r}."
                )
            object.__setattr__(self, name, float(value))


def _axis_blocks(
    model: MotionModel, dt: npt.NDArray[np.float64], cfg: MotionModelConfig
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Per-axis ``F1`` and ``Q1`` of shape (n, k, k), k = 1, 2 or 3."""
    n = dt.shape[0]
    one = np.ones(n)
    zero = np.zeros(n)
    if model is MotionModel.STATIC:
        f1 = one[:, None, None]
        q1 = (cfg.q_floor * dt)[:, None, None]
    elif model is MotionModel.RANDOM_WALK:
        f1 = one[:, None, None]
        q1 = ((cfg.q_position + cfg.q_floor) * dt)[:, None, None]
    elif model is MotionModel.CONSTANT_VELOCITY:
        q = cfg.q_acceleration
        f1 = np.stack([np.stack([one, dt], -1), np.stack([zero, one], -1)], -2)
        q1 = q * np.stack(
            [np.stack([dt**3 / 3, dt**2 / 2], -1), np.stack([dt**2 / 2, dt], -1)], -2
        )
    elif model is MotionModel.POLYNOMIAL_TREND:
        q = cfg.q_jerk
        f1 = np.stack(
            [
                np.stack([one, dt, dt**2 / 2], -1),
                np.stack([zero, one, dt], -1),
                np.stack([zero, zero, one], -1),
            ],
            -2,
        )
        q1 = q * np.stack(
            [
                np.stack([dt**5 / 20, dt**4 / 8, dt**3 / 6], -1),
                np.stack([dt**4 / 8, dt**3 / 3, dt**2 / 2], -1),
                np.stack([dt**3 / 6, dt**2 / 2, dt], -1),
            ],
            -2,
        )
    else:  # BROWNIAN_MOTION: integrated Ornstein-Uhlenbeck velocity, exact discretisation
        tau, q = cfg.tau, cfg.q_velocity
        u = dt / tau
        one_m_e = -np.expm1(-u)  # 1 - exp(-u)
        one_m_e2 = -np.expm1(-2 * u)  # 1 - exp(-2u)
        # u - 2(1 - e^-u) + (1 - e^-2u)/2, with its Taylor series where it cancels
        g11 = u - 2 * one_m_e + one_m_e2 / 2
        small = u < 1e-2
        if np.any(small):
            us = u[small]
            g11[small] = us**3 * (
                1 / 3 + us * (-1 / 4 + us * (7 / 60 + us * (-1 / 24 + us * (31 / 2520))))
            )
        f1 = np.stack([np.stack([one, tau * one_m_e], -1), np.stack([zero, 1 - one_m_e], -1)], -2)
        q11 = q * tau**3 * g11
        q12 = q * tau**2 * one_m_e**2 / 2
        q22 = q * tau * one_m_e2 / 2
        q1 = np.stack([np.stack([q11, q12], -1), np.stack([q12, q22], -1)], -2)
    return f1, q1


def discretize(
    model: MotionModel | str,
    dt: float | npt.ArrayLike,
    *,
    config: MotionModelConfig | None = None,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Exact discrete transition matrix and process noise of ``model`` over ``dt``.

    Parameters
    ----------
    model : MotionModel or str
        The motion model.
    dt : float or (n,) array_like
        Step length(s) in seconds, finite and >= 0 (``dt = 0`` gives ``F = I, Q = 0``).
    config : MotionModelConfig, optional
        Noise intensities; defaults to ``MotionModelConfig()``.

    Returns
    -------
    F, Q : ndarray of float64
        Shape (d, d) each for a scalar ``dt``, (n, d, d) for an array, with
        ``d = state_dim(model)`` and the state ordered (x, y, vx, vy, ax, ay).
        ``Q = ∫₀^dt Φ(s) G q Gᵀ Φ(s)ᵀ ds`` (Van Loan), plus ``q_floor * dt`` on the positions.
    """
    model = MotionModel.parse(model)
    cfg = MotionModelConfig() if config is None else config
    dt_arr = np.asarray(dt, dtype=np.float64)
    scalar = dt_arr.ndim == 0
    dt1 = np.atleast_1d(dt_arr)
    if dt1.ndim != 1:
        raise InvalidInputError(f"dt must be a scalar or a 1-D array, got shape {dt_arr.shape}.")
    if not np.all(np.isfinite(dt1)) or np.any(dt1 < 0):
        raise InvalidInputError("dt must be finite and >= 0 seconds (log_time must increase).")
    f1, q1 = _axis_blocks(model, dt1, cfg)
    n, k = f1.shape[0], f1.shape[1]
    eye2 = np.eye(2)
    f = np.einsum("nij,ab->niajb", f1, eye2).reshape(n, 2 * k, 2 * k)
    q = np.einsum("nij,ab->niajb", q1, eye2).reshape(n, 2 * k, 2 * k)
    if model is not MotionModel.STATIC and model is not MotionModel.RANDOM_WALK:
        q[:, 0, 0] += cfg.q_floor * dt1
        q[:, 1, 1] += cfg.q_floor * dt1
    if scalar:
        return f[0], q[0]
    return f, q


def initial_covariance(
    model: MotionModel | str,
    sigma: npt.ArrayLike,
    *,
    config: MotionModelConfig | None = None,
) -> npt.NDArray[np.float64]:
    """Initial state covariance of tracks started from centroids of uncertainty ``sigma``.

    Parameters
    ----------
    model : MotionModel or str
        The motion model.
    sigma : (n,) array_like
        Centroid uncertainties, px, > 0: position variance ``sigma²`` per axis.
    config : MotionModelConfig, optional
        Gives ``init_velocity_sigma`` and ``init_acceleration_sigma``.

    Returns
    -------
    (n, d, d) ndarray of float64
        Diagonal covariances (positions, then velocities, then accelerations).
    """
    model = MotionModel.parse(model)
    cfg = MotionModelConfig() if config is None else config
    s = np.atleast_1d(np.asarray(sigma, dtype=np.float64))
    d = _DIM[model]
    diag = np.empty((s.shape[0], d))
    diag[:, 0] = diag[:, 1] = s**2
    if d >= 4:
        diag[:, 2:4] = cfg.init_velocity_sigma**2
    if d == 6:
        diag[:, 4:6] = cfg.init_acceleration_sigma**2
    out = np.zeros((s.shape[0], d, d))
    idx = np.arange(d)
    out[:, idx, idx] = diag
    return out
