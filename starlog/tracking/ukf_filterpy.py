"""The per-object :mod:`filterpy` UKF: the reference :mod:`starlog.tracking.ukf`'s batched filter is tested against.

:func:`make_filterpy_ukf` builds a :class:`filterpy.kalman.UnscentedKalmanFilter` for one star with the same
motion model and Merwe sigma points, and :func:`filterpy_step` takes it through one predict and gated update as
:class:`~starlog.tracking.ukf.BatchUKF` does; the batched path agrees with it to rounding error. filterpy is
imported on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from starlog.tracking.models import MotionModel, MotionModelConfig, discretize, state_dim
from starlog.tracking.ukf import DEFAULT_GATE_PROBABILITY, SigmaPoints, gate_threshold

if TYPE_CHECKING:
    from filterpy.kalman import UnscentedKalmanFilter

__all__ = ["make_filterpy_ukf", "filterpy_step"]

Array = npt.NDArray[np.float64]


def _fx_linear(s: Array, dt: float, F: Array) -> Array:
    return F @ s


def _hx_position(s: Array) -> Array:
    return s[:2]


def make_filterpy_ukf(
    model: MotionModel | str,
    *,
    x: npt.ArrayLike,
    P: npt.ArrayLike,
    points: SigmaPoints | None = None,
) -> UnscentedKalmanFilter:
    """A :class:`filterpy.kalman.UnscentedKalmanFilter` for one star (reference path).

    Parameters
    ----------
    model : MotionModel or str
        Motion model.
    x : (d,) array_like
        Initial state.
    P : (d, d) array_like
        Initial covariance.
    points : SigmaPoints, optional
        Merwe scaling, passed to :class:`filterpy.kalman.MerweScaledSigmaPoints`.

    Returns
    -------
    filterpy.kalman.UnscentedKalmanFilter
        Step it with :func:`filterpy_step`, which sets ``Q``, ``R`` and ``F`` per step.
    """
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    model = MotionModel.parse(model)
    pts = SigmaPoints() if points is None else points
    d = state_dim(model)
    merwe = MerweScaledSigmaPoints(d, alpha=pts.alpha, beta=pts.beta, kappa=pts.kappa)
    ukf = UnscentedKalmanFilter(
        dim_x=d, dim_z=2, dt=1.0, hx=_hx_position, fx=_fx_linear, points=merwe
    )
    ukf.x = np.array(x, dtype=np.float64).reshape(d)
    ukf.P = np.array(P, dtype=np.float64).reshape(d, d)
    return ukf


def filterpy_step(
    ukf: Any,
    model: MotionModel | str,
    dt: float,
    z: npt.ArrayLike | None,
    sigma: float,
    *,
    config: MotionModelConfig | None = None,
    gate_probability: float = DEFAULT_GATE_PROBABILITY,
) -> tuple[float, bool]:
    """One predict + gated update of a :func:`make_filterpy_ukf` filter.

    Parameters
    ----------
    ukf : filterpy.kalman.UnscentedKalmanFilter
        The filter (modified in place).
    model : MotionModel or str
        Its motion model.
    dt : float
        Step, s.
    z : (2,) array_like or None
        Measured (x, y), px; ``None`` predicts only.
    sigma : float
        Measurement uncertainty, px.
    config : MotionModelConfig, optional
        Process-noise intensities.
    gate_probability : float
        Innovation gate probability.

    Returns
    -------
    nis : float
        ``νᵀ S⁻¹ ν`` (0 when ``z`` is None).
    applied : bool
        Whether the measurement was applied (False when gated or absent).
    """
    F, Q = discretize(model, dt, config=config)
    ukf.Q = Q
    ukf.predict(dt=dt, F=F)
    if z is None:
        return 0.0, False
    x0, p0 = ukf.x.copy(), ukf.P.copy()
    ukf.update(np.asarray(z, dtype=np.float64), R=np.eye(2) * float(sigma) ** 2)
    nis = float(ukf.y @ ukf.SI @ ukf.y)
    if nis > gate_threshold(gate_probability):
        ukf.x, ukf.P = x0, p0
        return nis, False
    return nis, True
