"""Attitude from matched vector pairs: Davenport's q-method, and Shuster's covariance of the result.

Wahba's problem: find the rotation ``A`` minimising ``L(A) = 1/2 sum_i w_i |b_i - A r_i|^2`` for
observed unit vectors ``b_i`` (camera frame) and reference unit vectors ``r_i`` (sky frame).
Davenport's q-method (Keat 1977, "Analysis of least-squares attitude determination routine DOAOP";
Markley & Crassidis 2014, *Fundamentals of Spacecraft Attitude Determination and Control*, §5.5)
writes the gain ``tr(A B^T)``, ``B = sum_i w_i b_i r_i^T``, as the quadratic form ``q^T K q`` of the
attitude quaternion, with

    K = [[S - sigma I, z], [z^T, sigma]],  S = B + B^T,  sigma = tr B,
    z = (B23 - B32, B31 - B13, B12 - B21),

so the optimal quaternion is the eigenvector of ``K`` with the largest eigenvalue. It is exact for
noise-free vectors and needs no starting guess.

With the QUEST measurement model (Shuster & Oh 1981: each ``b_i`` is the true vector plus
isotropic noise of ``sigma_i`` rad perpendicular to it) and weights ``w_i = 1 / sigma_i^2``, the
covariance of the small rotation error ``dtheta`` (camera frame, ``A_true = R(dtheta) A``) is
Shuster's

    P = [ sum_i sigma_i^-2 (I - b_i b_i^T) ]^-1,

the inverse Fisher information, attained by the q-method to first order. Its x and y diagonal
terms are the cross-boresight variances, z the roll's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from starlog.attitude.rotation import quaternion_from_matrix

__all__ = ["QMethodResult", "davenport_q_method", "shuster_covariance"]


@dataclass(frozen=True)
class QMethodResult:
    """The optimal attitude (matrix and quaternion, :mod:`starlog.attitude.rotation`'s convention), its
    covariance (rad^2, camera frame) and Wahba's loss at the optimum."""

    attitude: npt.NDArray[np.float64]
    quaternion: npt.NDArray[np.float64]
    covariance: npt.NDArray[np.float64]
    loss: float


def _shuster_matrix(q: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Shuster's attitude matrix of a quaternion (vector first): ``(q4^2 - |q|^2) I + 2 q q^T - 2 q4 [q x]``."""
    v, s = q[:3], q[3]
    cross = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return (s * s - v @ v) * np.eye(3) + 2.0 * np.outer(v, v) - 2.0 * s * cross


def davenport_q_method(observed: npt.NDArray[np.float64], reference: npt.NDArray[np.float64],
                       sigma: npt.NDArray[np.float64], *, covariance: bool = True) -> QMethodResult:
    """The rotation taking ``reference`` (n, 3) onto ``observed`` (n, 3), unit vectors, weighted by
    ``1 / sigma**2`` (``sigma``: each observation's 1-sigma error, rad); Davenport's q-method.

    Needs at least two non-parallel pairs. The covariance is :func:`shuster_covariance` of the observed
    vectors (NaN with ``covariance=False``, for an intermediate fit).
    """
    b = np.asarray(observed, np.float64)
    r = np.asarray(reference, np.float64)
    w = 1.0 / np.square(np.asarray(sigma, np.float64))
    big_b = (b * w[:, None]).T @ r
    s_mat = big_b + big_b.T
    trace = np.trace(big_b)
    z = np.array([big_b[1, 2] - big_b[2, 1], big_b[2, 0] - big_b[0, 2], big_b[0, 1] - big_b[1, 0]])
    k = np.empty((4, 4))
    k[:3, :3] = s_mat - trace * np.eye(3)
    k[:3, 3] = z
    k[3, :3] = z
    k[3, 3] = trace
    values, vectors = np.linalg.eigh(k)
    attitude = _shuster_matrix(vectors[:, -1])
    loss = float(w.sum() - values[-1])
    if not covariance:
        return QMethodResult(attitude, np.full(4, np.nan), np.full((3, 3), np.nan), max(loss, 0.0))
    return QMethodResult(attitude, quaternion_from_matrix(attitude), shuster_covariance(b, sigma), max(loss, 0.0))


def shuster_covariance(observed: npt.NDArray[np.float64], sigma: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """``[sum_i sigma_i^-2 (I - b_i b_i^T)]^-1``, rad^2 (camera frame); infinite when the pairs cannot fix the
    attitude (fewer than two non-parallel vectors)."""
    b = np.asarray(observed, np.float64)
    w = 1.0 / np.square(np.asarray(sigma, np.float64))
    info = w.sum() * np.eye(3) - (b * w[:, None]).T @ b
    try:
        return np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return np.full((3, 3), np.inf)
