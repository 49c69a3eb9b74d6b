"""Platform motion of a whole log, jointly with every star's static position and centroid noise.

The stars' static (focal-plane) positions are not known without a catalogue, so they are
estimated with the motion, by alternation:

1. fit each frame's motion to the current static positions (:mod:`starlog.platform_motion.fit`),
   leaving out, one at a time, stars more than ``k_sigma`` of their noise off the fit (flagged);
2. estimate each star's centroid noise from its residuals (corrected for the fit's leverage),
   which weights the next fit: the tracker's ``meas_sigma`` is floored, the residuals are not;
3. set each static position to the mean of the star's motion-removed positions;
4. fix the gauge: a constant motion of every frame cannot be told from a moved star field, so
   the static field is moved by the mean fitted motion, which makes the mean motion zero.

until the static positions move less than ``tol`` px.  The fitted motion is then the platform
(attitude) motion about its mean, and each star's residual is its centroid error alone.

Observations are flat arrays (one entry per star per frame): frame index, star index, measured
x, y and sigma, px (x = column, y = row).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from starlog.errors import InvalidInputError, InvalidParameterError
from starlog.platform_motion.fit import (
    MotionParameters,
    PlatformModel,
    apply_motion,
    frame_sums,
    information_matrix,
    leave_one_out_sums,
    observation_sums,
    remove_motion,
    solve_motion,
)

__all__ = ["Observations", "PlatformEstimate", "estimate_platform", "leave_one_out_reference", "star_reference"]

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: The smallest centroid noise a star is given, px (keeps the weights of noise-free stars finite).
NOISE_FLOOR_PX = 1e-9


@dataclass(frozen=True)
class Observations:
    """Measured star positions, one entry per (frame, star): indices into ``n_frames`` and ``n_stars``."""

    frame: I64
    star: I64
    xy: F64
    sigma: F64
    n_frames: int
    n_stars: int

    @classmethod
    def build(cls, frame: npt.ArrayLike, star: npt.ArrayLike, x: npt.ArrayLike, y: npt.ArrayLike,
              sigma: npt.ArrayLike, *, n_frames: int | None = None) -> Observations:
        """Validated observations; ``star`` ids may be any integers (mapped to 0..n_stars-1 in sorted order)."""
        f = np.asarray(frame, dtype=np.int64)
        ids = np.asarray(star, dtype=np.int64)
        xy = np.stack([np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)], axis=1)
        sig = np.asarray(sigma, dtype=np.float64)
        if not (f.shape == ids.shape == sig.shape == xy.shape[:1]) or f.ndim != 1:
            raise InvalidInputError("frame, star, x, y and sigma must be 1-D arrays of one length.")
        if not (np.isfinite(xy).all() and np.isfinite(sig).all()) or (sig <= 0).any() or (f < 0).any():
            raise InvalidInputError("positions must be finite, sigma > 0 and frame indices >= 0.")
        _, slot = np.unique(ids, return_inverse=True)
        frames = int(f.max()) + 1 if f.size else 0
        return cls(f, slot.astype(np.int64), xy, sig, max(frames, n_frames or 0),
                   int(slot.max()) + 1 if slot.size else 0)


@dataclass(frozen=True)
class PlatformEstimate:
    """The joint estimate: per-frame motion, per-star static position and noise, per-observation flags.

    Attributes
    ----------
    model : PlatformModel
    centre : (2,) ndarray
        The image centre the roll and scale are about, px.
    motion : MotionParameters
        Per frame (``n_frames`` rows); NaN where fewer than ``min_stars`` stars were usable.
    covariance : (n_frames, p, p) ndarray
        Covariance of (dx, dy[, roll[, scale]]) from the fit (px², rad²); NaN without a fit.
    n_used : (n_frames,) ndarray of int
        Stars used in each frame's fit.
    residual_rms : (n_frames,) ndarray
        Radial RMS (eq. 15 form) of the used stars' residuals, px; NaN without a fit.
    static : (n_stars, 2) ndarray
        Static position of each star, px.
    star_noise : (n_stars,) ndarray
        Each star's centroid noise (1 sigma per axis) estimated from its residuals, px.
    star_eligible : (n_stars,) ndarray of bool
        Stars seen in at least ``min_star_frames`` frames (the others take no part in the fit).
    used, outlier : (K,) ndarray of bool
        Observation used in its frame's fit / left out as more than ``k_sigma`` off it.
    residual : (K, 2) ndarray
        Measured minus fitted position (NaN in frames without a fit), px.
    iterations : int
    converged : bool
    """

    model: PlatformModel
    centre: F64
    motion: MotionParameters
    covariance: F64
    n_used: I64
    residual_rms: F64
    static: F64
    star_noise: F64
    star_eligible: npt.NDArray[np.bool_]
    used: npt.NDArray[np.bool_]
    outlier: npt.NDArray[np.bool_]
    residual: F64
    iterations: int
    converged: bool

    @property
    def valid(self) -> npt.NDArray[np.bool_]:
        """Frames with a fitted motion."""
        return np.isfinite(self.motion.dx)


@dataclass(frozen=True)
class _FrameFit:
    motion: MotionParameters
    covariance: F64
    used: npt.NDArray[np.bool_]
    residual: F64
    leverage: F64


def _fit_frames(obs: Observations, s: F64, m: F64, noise: F64, eligible: npt.NDArray[np.bool_],
                model: PlatformModel, *, k_sigma: float, min_stars: int, max_rejections: int) -> _FrameFit:
    """Every frame's motion, leaving out the worst star of a frame while it is > k_sigma off the fit."""
    used = eligible.copy()
    sigma = noise[obs.star]
    w_all = 1.0 / sigma**2
    for attempt in range(max_rejections + 1):
        w = np.where(used, w_all, 0.0)
        sums = frame_sums(obs.frame, s, m, w, obs.n_frames)
        motion = solve_motion(sums, model, min_stars=min_stars)
        at = motion.take(obs.frame)
        residual = m - apply_motion(at, s)
        cov = _inverse(information_matrix(sums, motion, model))
        leverage = _leverage(cov[obs.frame], at, s, w_all, model)
        if attempt == max_rejections:
            break
        spread = sigma * np.sqrt(np.clip(1.0 - np.where(used, leverage, 0.0), 1e-6, None))
        z = np.hypot(residual[:, 0], residual[:, 1]) / spread
        z = np.where(used & np.isfinite(z), z, -np.inf)
        worst = np.full(obs.n_frames, -np.inf)
        np.maximum.at(worst, obs.frame, z)
        drop = (z > k_sigma) & (z == worst[obs.frame])
        if not drop.any():
            break
        used &= ~drop
    return _FrameFit(motion, cov, used & np.isfinite(at.dx), residual, leverage)


def _inverse(info: F64) -> F64:
    """Batched inverse; singular or non-finite matrices give NaN."""
    out = np.full_like(info, np.nan)
    ok = np.isfinite(info).all(axis=(1, 2))
    if ok.any():
        det_ok = np.abs(np.linalg.det(info[ok])) > 0
        idx = np.flatnonzero(ok)[det_ok]
        out[idx] = np.linalg.inv(info[idx])
    return out


def _leverage(cov: F64, at: MotionParameters, s: F64, w: F64, model: PlatformModel) -> F64:
    """Per-axis leverage ``w trace(J C Jᵀ) / 2`` of each observation in its frame's fit."""
    n_par = model.n_parameters
    jac = np.zeros((s.shape[0], 2, n_par))
    jac[:, 0, 0] = jac[:, 1, 1] = 1.0
    if n_par > 2:
        a = apply_motion(MotionParameters(at.dx * 0, at.dy * 0, at.roll, at.scale), s)
        jac[:, 0, 2], jac[:, 1, 2] = -a[:, 1], a[:, 0]
        if n_par == 4:
            jac[:, :, 3] = a / at.scale[:, None]
    trace = np.einsum("kip,kpq,kiq->k", jac, cov, jac)
    return w * trace / 2.0


def _star_noise(obs: Observations, fit: _FrameFit, fallback: F64) -> F64:
    """Each star's noise from its used residuals: ``Σ|r|² / Σ 2(1 - h)`` (leverage ``h``)."""
    r2 = np.where(fit.used, np.einsum("ij,ij->i", fit.residual, fit.residual), 0.0)
    ok = fit.used & np.isfinite(fit.leverage)
    r2 = np.where(ok, r2, 0.0)
    dof = np.where(ok, 2.0 * np.clip(1.0 - fit.leverage, 1e-6, None), 0.0)
    num = np.bincount(obs.star, weights=r2, minlength=obs.n_stars)
    den = np.bincount(obs.star, weights=dof, minlength=obs.n_stars)
    with np.errstate(invalid="ignore", divide="ignore"):
        noise = np.sqrt(num / den)
    return np.maximum(np.where(den > 1.0, noise, fallback), NOISE_FLOOR_PX)


def _static_update(obs: Observations, fit: _FrameFit, m: F64, previous: F64,
                   bystander: npt.NDArray[np.bool_] | None = None) -> F64:
    """Mean motion-removed position of each star over its used observations (centred px).

    ``bystander`` marks observations of stars kept out of every fit (too short a track): their
    static position is the mean over every frame with a motion.
    """
    sel = fit.used
    if bystander is not None:
        sel = sel | (bystander & np.isfinite(fit.motion.dx)[obs.frame])
    back = remove_motion(fit.motion.take(obs.frame[sel]), m[sel])
    count = np.bincount(obs.star[sel], minlength=obs.n_stars).astype(np.float64)
    out = previous.copy()
    seen = count > 0
    for axis in (0, 1):
        total = np.bincount(obs.star[sel], weights=back[:, axis], minlength=obs.n_stars)
        out[seen, axis] = total[seen] / count[seen]
    return out


def _gauge(static: F64, motion: MotionParameters) -> F64:
    """The static field moved by the mean fitted motion (so that the motion averages to zero)."""
    ok = np.isfinite(motion.dx)
    if not ok.any():
        return static
    mean = MotionParameters(*(np.full(static.shape[0], float(np.mean(v[ok])))
                              for v in (motion.dx, motion.dy, motion.roll, motion.scale)))
    return apply_motion(mean, static)


def estimate_platform(
    obs: Observations,
    *,
    centre: tuple[float, float],
    model: PlatformModel | str = PlatformModel.RIGID,
    k_sigma: float = 5.0,
    min_stars: int = 3,
    min_star_frames: int = 10,
    max_iterations: int = 50,
    tol: float = 1e-7,
    max_rejections: int = 10,
) -> PlatformEstimate:
    """Jointly estimate per-frame platform motion and per-star static positions (module docstring).

    Parameters
    ----------
    obs : Observations
        Measured positions and their sigma (px); sigma only starts the noise estimate.
    centre : (x, y)
        Image centre, px (``((width - 1) / 2, (height - 1) / 2)``).
    model : PlatformModel or str
        ``translation``, ``rigid`` (default) or ``similarity``.
    k_sigma : float
        A star whose residual exceeds ``k_sigma`` times its noise is left out of that frame.
    min_stars : int
        Frames with fewer usable stars get no motion.
    min_star_frames : int
        Stars seen in fewer frames take no part in the fit (their static position is too uncertain).
    """
    model = PlatformModel(model)
    if not k_sigma > 0 or min_stars < model.min_stars or max_iterations < 1:
        raise InvalidParameterError(
            f"need k_sigma > 0, min_stars >= {model.min_stars} for {model.value} and max_iterations >= 1.")
    c = np.asarray(centre, dtype=np.float64)
    m = obs.xy - c
    counts = np.bincount(obs.star, minlength=obs.n_stars)
    star_ok = counts >= min_star_frames
    eligible = star_ok[obs.star]
    noise = np.maximum(_per_star_median(obs), NOISE_FLOOR_PX)
    static = _static_update(obs, _identity_fit(obs), m, np.zeros((obs.n_stars, 2)))
    converged = False
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        fit = _fit_frames(obs, static[obs.star], m, noise, eligible, model, k_sigma=k_sigma, min_stars=min_stars,
                          max_rejections=max_rejections)
        noise = _star_noise(obs, fit, noise)
        new = _gauge(_static_update(obs, fit, m, static, ~eligible), fit.motion)
        step = float(np.max(np.abs(new - static))) if new.size else 0.0
        static = new
        if step < tol:
            converged = True
            break
    fit = _fit_frames(obs, static[obs.star], m, noise, eligible, model, k_sigma=k_sigma, min_stars=min_stars,
                      max_rejections=max_rejections)
    return _estimate(obs, fit, static + c, c, noise, star_ok, model, iterations, converged)


def _identity_fit(obs: Observations) -> _FrameFit:
    """A 'fit' of no motion, every observation used (to start the static positions from plain means)."""
    k = obs.frame.size
    zero = np.zeros(obs.n_frames)
    return _FrameFit(MotionParameters(zero, zero, zero, zero + 1.0), np.zeros((0, 0, 0)), np.ones(k, dtype=bool),
                     np.zeros((k, 2)), np.zeros(k))


def _per_star_median(obs: Observations) -> F64:
    order = np.argsort(obs.star, kind="stable")
    bounds = np.searchsorted(obs.star[order], np.arange(obs.n_stars + 1))
    return np.array([np.median(obs.sigma[order][a:b]) if b > a else 1.0 for a, b in zip(bounds[:-1], bounds[1:])])


def _estimate(obs: Observations, fit: _FrameFit, static: F64, c: F64, noise: F64, star_ok: npt.NDArray[np.bool_],
              model: PlatformModel, iterations: int, converged: bool) -> PlatformEstimate:
    n_used = np.bincount(obs.frame[fit.used], minlength=obs.n_frames).astype(np.int64)
    r2 = np.bincount(obs.frame[fit.used], weights=np.einsum("ij,ij->i", fit.residual, fit.residual)[fit.used],
                     minlength=obs.n_frames)
    valid = np.isfinite(fit.motion.dx)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.where(valid & (n_used > 0), np.sqrt(r2 / n_used), np.nan)
    residual = np.where(valid[obs.frame][:, None], fit.residual, np.nan)
    eligible = star_ok[obs.star]
    outlier = eligible & valid[obs.frame] & ~fit.used
    return PlatformEstimate(model=model, centre=c, motion=fit.motion, covariance=fit.covariance, n_used=n_used,
                            residual_rms=rms, static=static, star_noise=noise, star_eligible=star_ok,
                            used=fit.used, outlier=outlier, residual=residual, iterations=iterations,
                            converged=converged)


def leave_one_out_reference(obs: Observations, est: PlatformEstimate) -> tuple[F64, F64]:
    """Each observation's expected position from the *other* stars: static + their fitted motion.

    The motion of each observation's frame is refitted without it (the frame's used stars, minus
    this one; outliers stay out), and applied to the star's static position.  The centroid errors
    of different stars are independent, so ``measured - reference`` is this star's centroid error
    plus the (smaller) error of the reference, whose variance is returned too.

    Returns
    -------
    reference : (K, 2) ndarray
        px; NaN where the other stars cannot determine the motion.
    variance : (K,) ndarray
        Predicted variance of the reference, radial (sum over both axes), px².
    """
    c = est.centre
    s = est.static[obs.star] - c
    m = obs.xy - c
    w_all = 1.0 / est.star_noise[obs.star] ** 2
    w = np.where(est.used, w_all, 0.0)
    frames = frame_sums(obs.frame, s, m, w, obs.n_frames)
    loo = leave_one_out_sums(frames, obs.frame, observation_sums(s, m, w))
    motion = solve_motion(loo, est.model, min_stars=est.model.min_stars)
    reference = apply_motion(motion, s) + c
    cov = _inverse(information_matrix(loo, motion, est.model))
    variance = 2.0 * _leverage(cov, motion, s, np.ones_like(w_all), est.model)
    return reference, variance


def star_reference(obs: Observations, est: PlatformEstimate, star: int,
                   frames: I64) -> tuple[F64, F64]:
    """Star ``star``'s expected position at frame indices ``frames`` from the other stars, and its variance.

    Where the star was measured this is :func:`leave_one_out_reference`; where it was not, the
    frame's fit (which it had no part in).  NaN where the other stars give no motion.
    """
    reference = np.full((frames.size, 2), np.nan)
    variance = np.full(frames.size, np.nan)
    mine = np.flatnonzero(obs.star == star)
    at = {int(f): i for i, f in zip(mine, obs.frame[mine])}
    measured = np.array([f in at for f in frames.tolist()], dtype=bool)
    if measured.any():
        ref, var = leave_one_out_reference(obs, est)
        rows = np.array([at[int(f)] for f in frames[measured]], dtype=np.int64)
        reference[measured], variance[measured] = ref[rows], var[rows]
    other = frames[~measured]
    if other.size:
        s = np.broadcast_to(est.static[star] - est.centre, (other.size, 2))
        motion = est.motion.take(other)
        reference[~measured] = apply_motion(motion, s) + est.centre
        ones = np.ones(other.size)
        variance[~measured] = 2.0 * _leverage(est.covariance[other], motion, s, ones, est.model)
    return reference, variance
