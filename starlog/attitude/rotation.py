"""Attitude parametrisations: unit vectors of (RA, Dec), rotation matrices, quaternions, RA/Dec/roll.

Frames. The *sky* frame is the catalogue's (ICRS, J2000 equinox): x towards RA 0 on the equator,
z towards the north celestial pole. The *camera* frame has x along the image columns (right),
y along the rows (down) and z along the boresight, out of the camera (right-handed). An attitude
is the rotation matrix ``A`` taking sky vectors to camera vectors, ``v_cam = A @ v_sky``; its
quaternion is ``(x, y, z, w)``, scalar last, with ``A`` the matrix of that rotation as
``scipy.spatial.transform.Rotation.from_quat(q).as_matrix()`` gives it.

RA/Dec are the boresight's; roll is the angle of celestial north from the image's "up" (towards
row 0), counter-clockwise on the displayed image (towards the left): the convention tetra3 and
cedar-solve report, so the two can be compared directly.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

__all__ = ["attitude_from_radec_roll", "quaternion_from_matrix", "matrix_from_quaternion", "radec_roll",
           "radec_vectors", "attitude_error", "small_rotation"]


def radec_vectors(ra_deg: npt.ArrayLike, dec_deg: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Unit vectors (n, 3) in the sky frame of right ascensions and declinations, degrees."""
    ra, dec = np.radians(np.asarray(ra_deg, np.float64)), np.radians(np.asarray(dec_deg, np.float64))
    return np.stack([np.cos(ra) * np.cos(dec), np.sin(ra) * np.cos(dec), np.sin(dec)], axis=-1)


def attitude_from_radec_roll(ra_deg: float, dec_deg: float, roll_deg: float) -> npt.NDArray[np.float64]:
    """The attitude matrix of a boresight at (RA, Dec) with the given roll (module docstring's convention).

    With east ``e`` and north ``n`` the local directions at the boresight ``b``, the camera's x axis is
    ``-cos(roll) e - sin(roll) n`` and its y axis ``sin(roll) e - cos(roll) n``: at roll 0 north is up
    and east is left, as the sky looks from inside the sphere.
    """
    ra, dec, roll = math.radians(ra_deg), math.radians(dec_deg), math.radians(roll_deg)
    b = np.array([math.cos(ra) * math.cos(dec), math.sin(ra) * math.cos(dec), math.sin(dec)])
    e = np.array([-math.sin(ra), math.cos(ra), 0.0])
    n = np.array([-math.sin(dec) * math.cos(ra), -math.sin(dec) * math.sin(ra), math.cos(dec)])
    x_axis = -math.cos(roll) * e - math.sin(roll) * n
    y_axis = math.sin(roll) * e - math.cos(roll) * n
    return np.vstack([x_axis, y_axis, b])


def radec_roll(attitude: npt.NDArray[np.float64]) -> tuple[float, float, float]:
    """(RA, Dec, roll) in degrees of an attitude matrix; RA and roll within [0, 360)."""
    b = attitude[2]
    ra = math.degrees(math.atan2(b[1], b[0])) % 360.0
    dec = math.degrees(math.asin(max(-1.0, min(1.0, float(b[2])))))
    north = attitude[:, 2]  # the celestial pole in the camera frame
    roll = math.degrees(math.atan2(-north[0], -north[1])) % 360.0
    return ra, dec, roll


def matrix_from_quaternion(q: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Rotation matrix of a quaternion ``(x, y, z, w)`` (normalised here)."""
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def quaternion_from_matrix(matrix: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Quaternion ``(x, y, z, w)`` of a rotation matrix, with ``w >= 0`` (Shepperd's method)."""
    m = np.asarray(matrix, np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    candidates = np.array([trace, m[0, 0], m[1, 1], m[2, 2]])
    k = int(np.argmax(candidates))
    if k == 0:
        w = math.sqrt(1.0 + trace) / 2.0
        q = np.array([(m[2, 1] - m[1, 2]) / (4 * w), (m[0, 2] - m[2, 0]) / (4 * w), (m[1, 0] - m[0, 1]) / (4 * w), w])
    else:
        i, j, l = k - 1, k % 3, (k + 1) % 3
        v = np.zeros(3)
        v[i] = math.sqrt(max(1.0 + m[i, i] - m[j, j] - m[l, l], 0.0)) / 2.0
        v[j] = (m[j, i] + m[i, j]) / (4 * v[i])
        v[l] = (m[l, i] + m[i, l]) / (4 * v[i])
        q = np.array([*v, (m[l, j] - m[j, l]) / (4 * v[i])])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def small_rotation(angles: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """The rotation matrix of a rotation vector (rad): Rodrigues' formula."""
    v = np.asarray(angles, np.float64)
    theta = float(np.linalg.norm(v))
    if theta < 1e-15:
        return np.eye(3)
    k = v / theta
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * cross + (1.0 - math.cos(theta)) * cross @ cross


def attitude_error(estimate: npt.NDArray[np.float64], truth: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The rotation vector (rad, camera frame) taking the true attitude to the estimate: x, y cross-boresight
    (about the column and row axes), z the roll about the boresight. ``estimate = R(error) @ truth``."""
    delta = estimate @ truth.T
    angle = math.acos(max(-1.0, min(1.0, (np.trace(delta) - 1.0) / 2.0)))
    axis = np.array([delta[2, 1] - delta[1, 2], delta[0, 2] - delta[2, 0], delta[1, 0] - delta[0, 1]])
    s = math.sin(angle)
    if s < 1e-12:
        return axis / 2.0
    return axis * angle / (2.0 * s)
