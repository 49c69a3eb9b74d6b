"""One frame's platform motion: weighted least squares of measured star positions onto static ones.

Every star of a frame sees the same platform motion, and the centroid errors of different stars
are independent.  With ``c`` the image centre, ``s`` a star's static (focal-plane) position and
``m`` its measured position, the motion is the 2-D map

    m = c + k R(roll) (s - c) + (dx, dy)

``translation`` fits (dx, dy) (roll = 0, k = 1), ``rigid`` adds the roll (rad, counter-clockwise
in (x, y) = (column, row) coordinates, i.e. clockwise on screen), ``similarity`` the scale ``k``
too.  Each star is weighted by ``1 / sigma**2``; the fit is closed-form (weighted Procrustes), so
a known motion of noise-free stars is recovered to rounding error.

The fit needs only a few weighted moment sums per frame (:class:`MomentSums`), so it runs on any
number of frames at once with ``np.bincount``, and leaving one star out of a frame's fit is a
subtraction of that star's moments (:func:`leave_one_out_sums`).

Positions in pixels, ``x`` = column, ``y`` = row, (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = [
    "MotionParameters",
    "MomentSums",
    "PlatformModel",
    "apply_motion",
    "frame_sums",
    "information_matrix",
    "leave_one_out_sums",
    "observation_sums",
    "remove_motion",
    "solve_motion",
]

F64 = npt.NDArray[np.float64]


class PlatformModel(enum.StrEnum):
    """The 2-D motion fitted per frame (about the image centre)."""

    TRANSLATION = "translation"
    RIGID = "rigid"
    SIMILARITY = "similarity"

    @property
    def n_parameters(self) -> int:
        """Free parameters: 2 (dx, dy), 3 (+ roll) or 4 (+ scale)."""
        return {"translation": 2, "rigid": 3, "similarity": 4}[self.value]

    @property
    def min_stars(self) -> int:
        """Fewest stars that determine the motion: 1 for a translation, 2 otherwise."""
        return 1 if self is PlatformModel.TRANSLATION else 2


@dataclass(frozen=True)
class MomentSums:
    """Weighted moments of a set of stars (one set per row), relative to the image centre.

    With weights ``w``, centred static positions ``s`` and centred measured positions ``m``:
    ``W = Σw``, ``S = Σw s``, ``M = Σw m``, ``Q = Σw |s|²``, ``C = Σw s·m``, ``X = Σw s×m``
    (``s×m = s_x m_y - s_y m_x``), ``n`` = number of stars with ``w > 0``.
    """

    W: F64
    S: F64
    M: F64
    Q: F64
    C: F64
    X: F64
    n: npt.NDArray[np.int64]

    def __sub__(self, other: MomentSums) -> MomentSums:
        return MomentSums(self.W - other.W, self.S - other.S, self.M - other.M, self.Q - other.Q,
                          self.C - other.C, self.X - other.X, self.n - other.n)

    def take(self, index: npt.NDArray[np.int64]) -> MomentSums:
        """The rows ``index`` (e.g. each observation's frame)."""
        return MomentSums(self.W[index], self.S[index], self.M[index], self.Q[index], self.C[index],
                          self.X[index], self.n[index])


def observation_sums(s: F64, m: F64, w: F64) -> MomentSums:
    """The moments of single observations: (K, 2) centred static ``s`` and measured ``m``, weights (K,)."""
    return MomentSums(
        W=w.copy(), S=s * w[:, None], M=m * w[:, None], Q=w * np.einsum("ij,ij->i", s, s),
        C=w * np.einsum("ij,ij->i", s, m), X=w * (s[:, 0] * m[:, 1] - s[:, 1] * m[:, 0]),
        n=(w > 0).astype(np.int64),
    )


def frame_sums(frame: npt.NDArray[np.int64], s: F64, m: F64, w: F64, n_frames: int) -> MomentSums:
    """Per-frame moments of observations (frame index (K,), centred positions (K, 2), weights (K,))."""
    one = observation_sums(s, m, w)

    def total(values: F64) -> F64:
        return np.bincount(frame, weights=values, minlength=n_frames)

    return MomentSums(
        W=total(one.W), S=np.stack([total(one.S[:, 0]), total(one.S[:, 1])], axis=1),
        M=np.stack([total(one.M[:, 0]), total(one.M[:, 1])], axis=1), Q=total(one.Q), C=total(one.C),
        X=total(one.X), n=np.bincount(frame, weights=one.n, minlength=n_frames).astype(np.int64),
    )


def leave_one_out_sums(frames: MomentSums, frame: npt.NDArray[np.int64], one: MomentSums) -> MomentSums:
    """For each observation, the moments of its frame without it (``one``: :func:`observation_sums`)."""
    return frames.take(frame) - one


@dataclass(frozen=True)
class MotionParameters:
    """Fitted motion per row: ``dx``, ``dy`` (px), ``roll`` (rad), ``scale`` (1); NaN where undetermined."""

    dx: F64
    dy: F64
    roll: F64
    scale: F64

    def matrix(self) -> tuple[F64, F64, F64, F64]:
        """``k R(roll)`` as its entries (a11, a12, a21, a22), each (rows,)."""
        c, s = self.scale * np.cos(self.roll), self.scale * np.sin(self.roll)
        return c, -s, s, c

    def take(self, index: npt.NDArray[np.int64]) -> MotionParameters:
        return MotionParameters(self.dx[index], self.dy[index], self.roll[index], self.scale[index])


def solve_motion(sums: MomentSums, model: PlatformModel, *, min_stars: int) -> MotionParameters:
    """Weighted least-squares motion of each row of ``sums`` (closed form; rows with fewer than
    ``min_stars`` stars, or degenerate geometry, give NaN)."""
    W = np.where(sums.n >= max(min_stars, model.min_stars), sums.W, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        sb = sums.S / W[:, None]
        mb = sums.M / W[:, None]
        roll = np.zeros_like(W)
        scale = np.ones_like(W)
        if model is not PlatformModel.TRANSLATION:
            cc = sums.C - W * np.einsum("ij,ij->i", sb, mb)
            ss = sums.X - W * (sb[:, 0] * mb[:, 1] - sb[:, 1] * mb[:, 0])
            roll = np.arctan2(ss, cc)
            if model is PlatformModel.SIMILARITY:
                qq = sums.Q - W * np.einsum("ij,ij->i", sb, sb)
                scale = np.hypot(cc, ss) / qq
        c, s = scale * np.cos(roll), scale * np.sin(roll)
        dx = mb[:, 0] - (c * sb[:, 0] - s * sb[:, 1])
        dy = mb[:, 1] - (s * sb[:, 0] + c * sb[:, 1])
    bad = ~np.isfinite(dx) | ~np.isfinite(dy) | ~np.isfinite(roll) | ~np.isfinite(scale)
    nan = np.where(bad, np.nan, 0.0)
    return MotionParameters(dx + nan, dy + nan, roll + nan, scale + nan)


def apply_motion(p: MotionParameters, s: F64) -> F64:
    """Centred static positions (K, 2) moved by per-row motion ``p``: ``k R s + d`` (centred)."""
    a11, a12, a21, a22 = p.matrix()
    return np.stack([a11 * s[:, 0] + a12 * s[:, 1] + p.dx, a21 * s[:, 0] + a22 * s[:, 1] + p.dy], axis=1)


def remove_motion(p: MotionParameters, m: F64) -> F64:
    """Centred measured positions (K, 2) with motion ``p`` undone: ``R^-1 (m - d) / k``."""
    u = m - np.stack([p.dx, p.dy], axis=1)
    c, s = np.cos(p.roll) / p.scale, np.sin(p.roll) / p.scale
    return np.stack([c * u[:, 0] + s * u[:, 1], -s * u[:, 0] + c * u[:, 1]], axis=1)


def information_matrix(sums: MomentSums, p: MotionParameters, model: PlatformModel) -> F64:
    """Fisher information ``Σ w Jᵀ J`` (rows, n_par, n_par) of the parameters (dx, dy[, roll[, scale]]).

    The Jacobian of a star's predicted position is ``[[1, 0, -a_y, b_x], [0, 1, a_x, b_y]]`` with
    ``a = k R s`` and ``b = R s``, so the matrix needs only the moments ``W``, ``S`` and ``Q``.
    """
    n_par = model.n_parameters
    rows = sums.W.shape[0]
    info = np.zeros((rows, n_par, n_par))
    info[:, 0, 0] = info[:, 1, 1] = sums.W
    if n_par == 2:
        return info
    a11, a12, a21, a22 = p.matrix()
    ax = a11 * sums.S[:, 0] + a12 * sums.S[:, 1]
    ay = a21 * sums.S[:, 0] + a22 * sums.S[:, 1]
    info[:, 0, 2] = info[:, 2, 0] = -ay
    info[:, 1, 2] = info[:, 2, 1] = ax
    info[:, 2, 2] = p.scale**2 * sums.Q
    if n_par == 4:
        info[:, 0, 3] = info[:, 3, 0] = ax / p.scale
        info[:, 1, 3] = info[:, 3, 1] = ay / p.scale
        info[:, 3, 3] = sums.Q
    return info
