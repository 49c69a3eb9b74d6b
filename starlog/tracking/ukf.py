"""Batched unscented Kalman filter for star centroids (paper §2.1; docs/PAPER.md, "Temporal filtering").

One filter step per star and frame: predict with a :mod:`~starlog.tracking.models` motion
model, then update with the centroid ``z = (x, y)`` (px) and its own uncertainty ``sigma``
(px), ``R = diag(sigma², sigma²)``. The filter is the textbook UKF with Merwe's scaled sigma
points, exactly as :class:`filterpy.kalman.UnscentedKalmanFilter` computes it (sigma points
from a Cholesky factor, the prior's sigma points recomputed after adding ``Q``, the update
``P ← P − K S Kᵀ``, here computed as ``P − Pxz Kᵀ``), but vectorised across stars: states
are ``(n, d)`` arrays and covariances ``(n, d, d)`` arrays, so one call filters every star
of a frame.

Glossary (the textbook symbols are kept inside the math): ``x`` state, ``P`` state
covariance, ``Q`` process noise, ``R`` measurement noise, ``z`` measurement, ``ν = z − ẑ``
innovation (px), ``S`` innovation covariance (px²), ``K`` gain,
``NIS = νᵀ S⁻¹ ν`` the normalised innovation squared (the squared Mahalanobis distance).

Innovation gate: a measurement whose NIS exceeds the chi-square(2 dof) quantile of
``gate_probability`` (default 0.9999, threshold ``-2 ln(1 - p) ≈ 18.42``) is a transient
outlier: it is not applied (the step is predict-only) and is reported as gated. A correct
measurement is rejected with probability ``1 - p``.

Coordinates: x = column, y = row, px, (0, 0) at the centre of the top-left pixel.

The per-object :mod:`filterpy` filter is the reference path (:mod:`starlog.tracking.ukf_filterpy`);
the batched path agrees with it to rounding error and is the one starlog uses.

References
----------
R. van der Merwe, "Sigma-Point Kalman Filters for Probabilistic Inference in Dynamic
State-Space Models", PhD thesis, OGI, 2004 (scaled sigma points).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from starlog.errors import FitError, InvalidInputError, InvalidParameterError
from starlog.tracking.models import (
    MotionModel,
    MotionModelConfig,
    discretize,
    initial_covariance,
    state_dim,
)

__all__ = [
    "DEFAULT_GATE_PROBABILITY",
    "SigmaPoints",
    "UKFUpdate",
    "BatchUKF",
    "gate_threshold",
    "sigma_points",
    "sigma_offsets",
    "unscented_transform",
    "ukf_predict",
    "ukf_update",
]

DEFAULT_GATE_PROBABILITY = 0.9999
"""Default probability of the innovation gate (chi-square, 2 dof): threshold ≈ 18.42."""

Array = npt.NDArray[np.float64]
_EYE2 = np.eye(2)


def gate_threshold(probability: float) -> float:
    """NIS threshold of the innovation gate: the chi-square(2) quantile ``-2 ln(1 - p)``.

    Parameters
    ----------
    probability : float
        Probability that a correct measurement passes, in (0, 1); ``1.0`` disables the gate
        (threshold ``inf``).

    Returns
    -------
    float
        The NIS threshold (dimensionless).
    """
    p = float(probability)
    if not (0.0 < p <= 1.0):
        raise InvalidParameterError(f"gate probability must be in (0, 1], got {probability!r}.")
    return math.inf if p == 1.0 else -2.0 * math.log1p(-p)


@dataclass(frozen=True)
class SigmaPoints:
    """Merwe's scaled sigma points (as :class:`filterpy.kalman.MerweScaledSigmaPoints`).

    Parameters
    ----------
    alpha : float
        Spread of the points, in (0, 1]. Default 1.0: the motion models are linear, so the
        unscented transform is exact for any ``alpha``, and ``alpha = 1, kappa = 0`` gives
        non-negative weights (``Wm₀ = 0``) with no cancellation between large weights of
        opposite sign (``alpha = 1e-3`` would amplify rounding by ~1e6).
    beta : float
        Prior-distribution parameter (2 is optimal for Gaussians), >= 0.
    kappa : float
        Secondary scaling; ``n + kappa`` must stay > 0 for every state size ``n``.
    """

    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0

    def __post_init__(self) -> None:
        for name in ("alpha", "beta", "kappa"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)):
                raise InvalidParameterError(f"SigmaPoints.{name} must be a number, got {value!r}.")
            if not math.isfinite(value):
                raise InvalidParameterError(f"SigmaPoints.{name} must be finite, got {value!r}.")
            object.__setattr__(self, name, float(value))
        if not (0.0 < self.alpha <= 1.0):
            raise InvalidParameterError(f"SigmaPoints.alpha must be in (0, 1], got {self.alpha}.")
        if self.beta < 0:
            raise InvalidParameterError(f"SigmaPoints.beta must be >= 0, got {self.beta}.")
        if 2 + self.kappa <= 0:
            raise InvalidParameterError(
                f"SigmaPoints.kappa must be > -2 (n + kappa > 0 for n >= 2), got {self.kappa}."
            )

    def scale(self, n: int) -> float:
        """``n + lambda`` with ``lambda = alpha² (n + kappa) - n``."""
        return self.alpha**2 * (n + self.kappa)

    @functools.lru_cache(maxsize=16)  # noqa: B019 - frozen, hashable, few instances
    def weights(self, n: int) -> tuple[Array, Array]:
        """Mean and covariance weights ``(Wm, Wc)``, each of shape (2n + 1,)."""
        c = self.scale(n)
        lam = c - n
        wm = np.full(2 * n + 1, 0.5 / c)
        wc = wm.copy()
        wm[0] = lam / c
        wc[0] = lam / c + (1.0 - self.alpha**2 + self.beta)
        wm.flags.writeable = False
        wc.flags.writeable = False
        return wm, wc


try:  # the gufunc behind np.linalg.cholesky / inv, without their per-call checks
    from numpy.linalg import _umath_linalg as _ul

    _CHOL = _ul.cholesky_lo
    _INV = _ul.inv
except (ImportError, AttributeError):  # pragma: no cover - other numpy layouts
    _CHOL = _INV = None


def _cholesky(a: Array) -> Array:
    """Batched lower Cholesky factor; repairs matrices that rounding made indefinite."""
    if _CHOL is not None:
        with np.errstate(invalid="ignore", over="ignore", divide="ignore", under="ignore"):
            low = _CHOL(a, signature="d->d")
        if np.isfinite(low).all():
            return low
    else:  # pragma: no cover
        try:
            return np.linalg.cholesky(a)
        except np.linalg.LinAlgError:
            pass
    sym = 0.5 * (a + a.swapaxes(-1, -2))
    if not np.isfinite(sym).all():
        raise FitError("the state covariance has non-finite values; the filter diverged.")
    w, v = np.linalg.eigh(sym)
    floor = np.maximum(np.abs(w).max(axis=-1, keepdims=True), 1e-300) * 1e-13
    w = np.maximum(w, floor)
    repaired = np.matmul(v * w[..., None, :], v.swapaxes(-1, -2))
    try:
        return np.linalg.cholesky(repaired)
    except np.linalg.LinAlgError as err:  # pragma: no cover - cannot happen after the floor
        raise FitError(
            "the state covariance is not positive definite and cannot be repaired."
        ) from err


def _inv2(a: Array) -> Array:
    """Batched inverse of (n, 2, 2) innovation covariances (positive definite)."""
    if _INV is not None:
        return _INV(a, signature="d->d")  # type: ignore[no-any-return]
    return np.linalg.inv(a)  # pragma: no cover


def sigma_offsets(P: Array, *, points: SigmaPoints) -> Array:
    """Offsets of the sigma points from their mean: ``χ − x``.

    Parameters
    ----------
    P : (n, d, d) ndarray
        Covariances (symmetric positive definite; rounding-level indefiniteness is repaired).
    points : SigmaPoints
        Scaling parameters.

    Returns
    -------
    (n, 2d + 1, d) ndarray
        ``0``, then ``+L[:, k]``, then ``−L[:, k]`` (k = 0 … d−1) with
        ``L Lᵀ = (d + λ) P``,
        the ordering of filterpy's ``MerweScaledSigmaPoints``.
    """
    d = P.shape[-1]
    lt = _cholesky(points.scale(d) * P).swapaxes(-1, -2)
    return np.concatenate((np.zeros_like(lt[:, :1, :]), lt, -lt), axis=1)


def sigma_points(x: Array, P: Array, *, points: SigmaPoints) -> Array:
    """Sigma points of the Gaussians ``N(x[i], P[i])``.

    Parameters
    ----------
    x : (n, d) ndarray
        Means.
    P : (n, d, d) ndarray
        Covariances (symmetric positive definite).
    points : SigmaPoints
        Scaling parameters.

    Returns
    -------
    (n, 2d + 1, d) ndarray
        ``χ₀ = x``, ``χ_k = x + L[:, k]``, ``χ_{d+k} = x − L[:, k]`` with
        ``L Lᵀ = (d + λ) P`` (see :func:`sigma_offsets`).
    """
    return x[:, None, :] + sigma_offsets(P, points=points)


def unscented_transform(
    sigmas: Array, wm: Array, wc: Array, noise_cov: Array | None = None
) -> tuple[Array, Array]:
    """Weighted mean and covariance of transformed sigma points.

    Parameters
    ----------
    sigmas : (n, s, k) ndarray
        Transformed sigma points.
    wm, wc : (s,) ndarray
        Mean and covariance weights.
    noise_cov : (k, k) or (n, k, k) ndarray, optional
        Additive noise covariance.

    Returns
    -------
    mean : (n, k) ndarray
    cov : (n, k, k) ndarray
    """
    mean = np.matmul(wm, sigmas)
    dev = sigmas - mean[:, None, :]
    cov = np.matmul(dev.swapaxes(-1, -2) * wc, dev)
    if noise_cov is not None:
        cov += noise_cov
    return mean, cov


def ukf_predict(
    x: Array,
    P: Array,
    *,
    fx: Callable[[Array], Array],
    Q: Array,
    points: SigmaPoints,
) -> tuple[Array, Array]:
    """UKF prediction (prior) for a batch of states.

    Parameters
    ----------
    x : (n, d) ndarray
        Posterior means.
    P : (n, d, d) ndarray
        Posterior covariances.
    fx : callable
        Maps sigma points of shape (n, s, d) to propagated points of the same shape.
    Q : (d, d) or (n, d, d) ndarray
        Process noise.
    points : SigmaPoints
        Sigma-point scaling.

    Returns
    -------
    x_prior : (n, d) ndarray
    P_prior : (n, d, d) ndarray
    """
    wm, wc = points.weights(x.shape[-1])
    x_prior, p_prior = unscented_transform(fx(sigma_points(x, P, points=points)), wm, wc, Q)
    p_prior += p_prior.swapaxes(-1, -2)  # exact symmetry (rounding breaks it otherwise)
    p_prior *= 0.5
    return x_prior, p_prior


@dataclass(frozen=True)
class UKFUpdate:
    """Result of :func:`ukf_update` for ``n`` stars.

    Attributes
    ----------
    x : (n, d) ndarray
        Posterior means (the prior where the measurement was gated).
    P : (n, d, d) ndarray
        Posterior covariances (the prior where gated).
    innovation : (n, 2) ndarray
        ``ν = z − ẑ``, px.
    S : (n, 2, 2) ndarray
        Innovation covariance, px².
    nis : (n,) ndarray
        ``νᵀ S⁻¹ ν``.
    applied : (n,) ndarray of bool
        The measurement was applied (``nis <= threshold``); the rest were gated.
    """

    x: Array
    P: Array
    innovation: Array
    S: Array
    nis: Array
    applied: npt.NDArray[np.bool_]


def ukf_update(
    x: Array,
    P: Array,
    z: Array,
    R: Array,
    *,
    points: SigmaPoints,
    threshold: float | Array = math.inf,
) -> UKFUpdate:
    """UKF measurement update with ``h(x) = (x[0], x[1])`` and an innovation gate.

    Parameters
    ----------
    x : (n, d) ndarray
        Prior means.
    P : (n, d, d) ndarray
        Prior covariances.
    z : (n, 2) ndarray
        Measured positions, px.
    R : (n, 2, 2) or (2, 2) ndarray
        Measurement noise covariances, px².
    points : SigmaPoints
        Sigma-point scaling.
    threshold : float or (n,) ndarray
        NIS gate (see :func:`gate_threshold`), one for all or one per star; ``inf`` applies
        every measurement.

    Returns
    -------
    UKFUpdate
    """
    d = x.shape[-1]
    wm, wc = points.weights(d)
    # χ − x: filterpy forms the same deviations by subtracting the prior mean from χ
    dx = sigma_offsets(P, points=points)
    dh = dx[:, :, :2]  # h(χ) − h(x), h(χ) = (χx, χy)
    mh = np.matmul(wm, dh)  # ẑ − h(x)
    dz = dh - mh[:, None, :]  # h(χ) − ẑ
    dzw = dz * wc[:, None]
    S = np.matmul(dzw.swapaxes(-1, -2), dz) + R
    pxz = np.matmul(dx.swapaxes(-1, -2), dzw)  # (n, d, 2)
    si = _inv2(S)
    nu = z - x[:, :2] - mh  # z − ẑ
    si_nu = np.matmul(si, nu[:, :, None])  # (n, 2, 1)
    nis = np.matmul(nu[:, None, :], si_nu)[:, 0, 0]
    applied = nis <= threshold
    K = np.matmul(pxz, si)  # (n, d, 2)
    x_post = x + np.matmul(pxz, si_nu)[:, :, 0]
    P_post = P - np.matmul(pxz, K.swapaxes(-1, -2))  # K S Kᵀ = Pxz Kᵀ
    P_post += P_post.swapaxes(-1, -2)
    P_post *= 0.5
    if not applied.all():
        rej = ~applied
        x_post[rej] = x[rej]
        P_post[rej] = P[rej]
    return UKFUpdate(x=x_post, P=P_post, innovation=nu, S=S, nis=nis, applied=applied)


def _as_float_array(name: str, value: npt.ArrayLike, shape: tuple[int, ...]) -> Array:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != shape:
        raise InvalidInputError(f"{name} must have shape {shape}, got {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        raise InvalidInputError(f"{name} must be finite (no NaN or inf).")
    return arr


class BatchUKF:
    """Unscented Kalman filters of ``n`` stars with one motion model, stepped together.

    Parameters
    ----------
    model : MotionModel or str
        Motion model (see :mod:`starlog.tracking.models`).
    x : (n, d) array_like
        Initial states, ordered (x, y, vx, vy, ax, ay) up to ``d = state_dim(model)``.
    P : (n, d, d) array_like
        Initial covariances (symmetric positive definite).
    config : MotionModelConfig, optional
        Process-noise intensities.
    points : SigmaPoints, optional
        Sigma-point scaling (default ``SigmaPoints()``).
    gate_probability : float
        Innovation gate probability (default 0.9999, see module docstring; 1.0 disables).

    Notes
    -----
    The arrays passed in are copied. :meth:`from_centroids` starts filters at measured
    positions with zero velocity and acceleration.
    """

    def __init__(
        self,
        model: MotionModel | str,
        *,
        x: npt.ArrayLike,
        P: npt.ArrayLike,
        config: MotionModelConfig | None = None,
        points: SigmaPoints | None = None,
        gate_probability: float = DEFAULT_GATE_PROBABILITY,
    ) -> None:
        self.model = MotionModel.parse(model)
        self.config = MotionModelConfig() if config is None else config
        self.points = SigmaPoints() if points is None else points
        self.threshold = gate_threshold(gate_probability)
        d = state_dim(self.model)
        xa = np.asarray(x, dtype=np.float64)
        if xa.ndim != 2 or xa.shape[1] != d:
            raise InvalidInputError(
                f"x must have shape (n, {d}) for {self.model.value}, got {xa.shape}."
            )
        n = xa.shape[0]
        self._x = _as_float_array("x", xa, (n, d)).copy()
        self._P = _as_float_array("P", P, (n, d, d)).copy()
        self._cache: dict[float, tuple[Array, Array]] = {}

    @classmethod
    def from_centroids(
        cls,
        model: MotionModel | str,
        *,
        x: npt.ArrayLike,
        y: npt.ArrayLike,
        sigma: npt.ArrayLike,
        config: MotionModelConfig | None = None,
        points: SigmaPoints | None = None,
        gate_probability: float = DEFAULT_GATE_PROBABILITY,
    ) -> BatchUKF:
        """Filters started at centroids ``(x, y)`` (px) of uncertainty ``sigma`` (px)."""
        model = MotionModel.parse(model)
        xs = np.atleast_1d(np.asarray(x, dtype=np.float64))
        n = xs.shape[0]
        ys = _as_float_array("y", np.atleast_1d(np.asarray(y, dtype=np.float64)), (n,))
        ss = _as_float_array("sigma", np.atleast_1d(np.asarray(sigma, dtype=np.float64)), (n,))
        if np.any(ss <= 0):
            raise InvalidInputError("sigma must be > 0 px.")
        state = np.zeros((n, state_dim(model)))
        state[:, 0] = xs
        state[:, 1] = ys
        cov = initial_covariance(model, ss, config=config)
        return cls(
            model, x=state, P=cov, config=config, points=points, gate_probability=gate_probability
        )

    @property
    def n(self) -> int:
        """Number of stars."""
        return int(self._x.shape[0])

    @property
    def x(self) -> Array:
        """Current states, (n, d) (a copy)."""
        return self._x.copy()

    @property
    def P(self) -> Array:
        """Current covariances, (n, d, d) (a copy)."""
        return self._P.copy()

    def _transition(self, dt: float | npt.ArrayLike) -> tuple[Array, Array]:
        """``(Fᵀ, Q)`` for ``dt``; scalar steps are memoised (frame intervals repeat)."""
        if np.ndim(dt) == 0:
            key = float(dt)  # type: ignore[arg-type]
            hit = self._cache.get(key)
            if hit is None:
                F, Q = discretize(self.model, key, config=self.config)
                if len(self._cache) >= 256:
                    self._cache.clear()
                hit = self._cache[key] = (np.ascontiguousarray(F.T), Q)
            return hit
        F, Q = discretize(self.model, dt, config=self.config)
        if F.shape[0] != self.n:
            raise InvalidInputError(f"dt must be a scalar or have shape ({self.n},).")
        return F.swapaxes(-1, -2), Q

    def predict(self, dt: float | npt.ArrayLike) -> None:
        """Advance every filter by ``dt`` seconds (scalar, or one per star), >= 0."""
        Ft, Q = self._transition(dt)
        self._x, self._P = ukf_predict(
            self._x, self._P, fx=lambda s: np.matmul(s, Ft), Q=Q, points=self.points
        )

    def update(
        self,
        z: npt.ArrayLike,
        sigma: npt.ArrayLike,
        *,
        mask: npt.ArrayLike | None = None,
    ) -> UKFUpdate:
        """Apply the measurements ``z`` (n, 2) px with uncertainties ``sigma`` (n,) px.

        Parameters
        ----------
        z : (n, 2) array_like
            Measured positions (x, y), px.
        sigma : (n,) array_like
            Per-measurement uncertainty, px, > 0; ``R = diag(sigma², sigma²)``.
        mask : (n,) array_like of bool, optional
            Which stars were measured; the others are left at their prior and report
            ``innovation = 0``, ``nis = 0``, ``applied = False``.

        Returns
        -------
        UKFUpdate
            For all ``n`` stars.
        """
        n = self.n
        za = np.asarray(z, dtype=np.float64)
        sa = np.asarray(sigma, dtype=np.float64)
        if za.shape != (n, 2) or sa.shape != (n,):
            raise InvalidInputError(
                f"z must have shape ({n}, 2) and sigma ({n},), got {za.shape} and {sa.shape}."
            )
        if not (np.isfinite(za).all() and ((sa > 0) & (sa < np.inf)).all()):
            raise InvalidInputError("z must be finite and sigma finite and > 0 px.")
        R = (sa * sa)[:, None, None] * _EYE2
        if mask is None:
            res = ukf_update(self._x, self._P, za, R, points=self.points, threshold=self.threshold)
            self._x, self._P = res.x, res.P
            return res
        m = np.asarray(mask, dtype=bool)
        if m.shape != (n,):
            raise InvalidInputError(f"mask must have shape ({n},), got {m.shape}.")
        idx = np.flatnonzero(m)
        sub = ukf_update(
            self._x[idx], self._P[idx], za[idx], R[idx], points=self.points,
            threshold=self.threshold,
        )
        innovation = np.zeros((n, 2))
        S = np.zeros((n, 2, 2))
        nis = np.zeros(n)
        applied = np.zeros(n, dtype=bool)
        self._x[idx] = sub.x
        self._P[idx] = sub.P
        innovation[idx] = sub.innovation
        S[idx] = sub.S
        nis[idx] = sub.nis
        applied[idx] = sub.applied
        return UKFUpdate(
            x=self._x.copy(), P=self._P.copy(), innovation=innovation, S=S, nis=nis,
            applied=applied,
        )

    def step(
        self,
        dt: float | npt.ArrayLike,
        z: npt.ArrayLike,
        sigma: npt.ArrayLike,
        *,
        mask: npt.ArrayLike | None = None,
    ) -> UKFUpdate:
        """:meth:`predict` by ``dt`` seconds, then :meth:`update`."""
        self.predict(dt)
        return self.update(z, sigma, mask=mask)
