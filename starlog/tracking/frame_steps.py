"""The tracker's numpy steps of one frame, on the live tracks' tables: the reference of its compiled call.

:class:`~starlog.tracking.association.StarTracker` runs a frame through these (``vectorised=True``), and takes a
frame over with them where the compiled call (:mod:`starlog.tracking.frame_kernel`) hands it back. The steps are
numbered as in :mod:`starlog.tracking.association`: the frame's centroids checked (:func:`frame_arrays`), step 2
(:func:`associate`), step 3 (:func:`apply_measurements`), the life-cycle counters (:func:`count_frame`) and the
output rows (:func:`track_rows`, :func:`stats_rows`). Each acts on a :class:`~starlog.tracking.state.TrackState`
in place or returns new arrays.

Coordinates: x = column, y = row, px, (0, 0) at the centre of the top-left pixel; times are int ns ``log_time``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from scipy.optimize import linear_sum_assignment

from starlog.errors import InvalidInputError
from starlog.tracking.state import FrameRows, TrackState
from starlog.tracking.table import TRACK_DTYPE, TRACK_STATS_DTYPE
from starlog.tracking.tracker_config import TrackerConfig
from starlog.tracking.ukf import ukf_update

__all__ = ["BAD_SIGMA", "NON_FINITE", "Centroids", "apply_measurements", "associate", "count_frame", "frame_arrays",
           "frame_columns", "stats_rows", "track_rows"]

Array = npt.NDArray[np.float64]
_EYE2 = np.eye(2)
_NO_PAIRS = (np.zeros(0, np.intp), np.zeros(0, np.intp))


class Centroids(NamedTuple):
    """One frame's centroids, validated; ``sigma`` already raised to the tracker's floor."""

    x: Array
    y: Array
    sigma: Array
    flux: Array
    var: Array  # sigma², the diagonal of R


def frame_columns(
    x: npt.ArrayLike, y: npt.ArrayLike, sigma: npt.ArrayLike, flux: npt.ArrayLike
) -> tuple[Array, Array, Array, Array]:
    """The centroid columns as float64 arrays of one length (values not checked)."""
    xs = np.asarray(x, dtype=np.float64)
    ys = np.asarray(y, dtype=np.float64)
    sigmas = np.asarray(sigma, dtype=np.float64)
    fluxes = np.asarray(flux, dtype=np.float64)
    if (xs.ndim != 1 or ys.shape != xs.shape or sigmas.shape != xs.shape
            or fluxes.shape != xs.shape):
        raise InvalidInputError(
            "x, y, sigma and flux must be 1-D arrays of one length (one entry per centroid), "
            f"got shapes {xs.shape}, {ys.shape}, {sigmas.shape}, {fluxes.shape}."
        )
    return xs, ys, sigmas, fluxes


NON_FINITE = "centroid x, y and flux must be finite (no NaN or inf)."
BAD_SIGMA = "centroid sigma must be finite and >= 0 px."


def frame_arrays(
    x: npt.ArrayLike, y: npt.ArrayLike, sigma: npt.ArrayLike, flux: npt.ArrayLike
) -> tuple[Array, Array, Array, Array]:
    """The centroid columns (:func:`frame_columns`), their values checked."""
    xs, ys, sigmas, fluxes = frame_columns(x, y, sigma, flux)
    if xs.size and not (
        np.isfinite(xs).all() and np.isfinite(ys).all() and np.isfinite(fluxes).all()
    ):
        raise InvalidInputError(NON_FINITE)
    if xs.size and not ((sigmas >= 0) & (sigmas < np.inf)).all():
        raise InvalidInputError(BAD_SIGMA)
    return xs, ys, sigmas, fluxes


def associate(tracks: TrackState, c: Centroids, config: TrackerConfig,
              threshold: float) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """Step 2: indices (tracks, centroids) of the admissible optimal assignment (``threshold``: the gate's NIS)."""
    if not (len(tracks) and c.x.size):
        return _NO_PAIRS
    px = tracks.x[:, 0]
    py = tracks.x[:, 1]
    nx = c.x[None, :] - px[:, None]
    ny = c.y[None, :] - py[:, None]
    a = tracks.P[:, 0, 0][:, None] + c.var[None, :]
    b = tracks.P[:, 0, 1][:, None]
    cc = tracks.P[:, 1, 1][:, None] + c.var[None, :]
    d2 = (cc * nx * nx - 2.0 * b * nx * ny + a * ny * ny) / (a * cc - b * b)
    r2 = config.association_radius**2
    if config.max_distance is None:
        ok = ((nx * nx + ny * ny) <= r2) | (d2 <= threshold)
    else:  # only near where the star was last seen, however far the prediction has coasted
        ax = c.x[None, :] - tracks.anchor[:, 0][:, None]
        ay = c.y[None, :] - tracks.anchor[:, 1][:, None]
        ok = (ax * ax + ay * ay) <= config.max_distance**2
    if not ok.any():
        return _NO_PAIRS
    big = 1e3 * (float(d2[ok].max()) + 1.0)
    cost = np.where(ok, d2, big)
    rows, cols = linear_sum_assignment(cost)
    keep = ok[rows, cols]
    return rows[keep], cols[keep]


def apply_measurements(
    tracks: TrackState, t: int, c: Centroids, ti: npt.NDArray[np.intp], mj: npt.NDArray[np.intp],
    config: TrackerConfig, threshold: float,
) -> tuple[FrameRows, npt.NDArray[np.bool_]]:
    """Step 3: gated UKF update of the associated tracks; the rows and who was associated."""
    n = len(tracks)
    rows = FrameRows.empty(n)
    associated = np.zeros(n, dtype=bool)
    if ti.size:
        cfg = config
        z = np.stack((c.x[mj], c.y[mj]), axis=1)
        R = c.var[mj][:, None, None] * _EYE2
        reset = tracks.gated_streak[ti] >= cfg.max_gated
        thr: float | Array = (
            np.where(reset, np.inf, threshold) if reset.any() else threshold
        )
        res = ukf_update(tracks.x[ti], tracks.P[ti], z, R, points=cfg.points, threshold=thr)
        tracks.x[ti] = res.x
        tracks.P[ti] = res.P
        rows.innovation[ti] = res.innovation
        rows.nis[ti] = res.nis
        rows.measured[ti] = res.applied
        associated[ti] = True
        rows.meas[ti, 0] = c.x[mj]
        rows.meas[ti, 1] = c.y[mj]
        rows.meas[ti, 2] = c.sigma[mj]
        rows.meas[ti, 3] = c.flux[mj]
        ok = ti[res.applied]
        tracks.hits[ok] += 1
        tracks.last_time[ok] = t
        tracks.anchor[ok] = tracks.x[ok, :2]
        tracks.sums[ok] += rows.meas[ok][:, [3, 0, 1]]
    rows.gated = associated & ~rows.measured
    return rows, associated


def count_frame(tracks: TrackState, rows: FrameRows, associated: npt.NDArray[np.bool_]) -> None:
    """Life-cycle counters after this frame's measurements."""
    gated = rows.gated
    measured = rows.measured
    tracks.gated[gated] += 1
    tracks.gated_streak[gated] += 1
    tracks.gated_streak[~gated] = 0
    tracks.missed[measured] = 0
    tracks.missed[~measured] += 1
    tracks.coast[associated] = 0
    tracks.coast[~associated] += 1
    tracks.age += 1


def track_rows(tracks: TrackState, rows: FrameRows, confirm_hits: int) -> npt.NDArray[np.void]:
    """One :data:`TRACK_DTYPE` row per live track."""
    out = np.empty(len(tracks), dtype=TRACK_DTYPE)
    out["track"] = tracks.ids
    out["x"] = tracks.x[:, 0]
    out["y"] = tracks.x[:, 1]
    if tracks.d >= 4:
        out["vx"] = tracks.x[:, 2]
        out["vy"] = tracks.x[:, 3]
    else:
        out["vx"] = 0.0
        out["vy"] = 0.0
    out["cov_xx"] = tracks.P[:, 0, 0]
    out["cov_xy"] = tracks.P[:, 0, 1]
    out["cov_yy"] = tracks.P[:, 1, 1]
    out["innovation_x"] = rows.innovation[:, 0]
    out["innovation_y"] = rows.innovation[:, 1]
    out["nis"] = rows.nis
    out["measured"] = rows.measured
    out["gated"] = rows.gated
    out["meas_x"] = rows.meas[:, 0]
    out["meas_y"] = rows.meas[:, 1]
    out["meas_sigma"] = rows.meas[:, 2]
    out["flux"] = rows.meas[:, 3]
    out["age"] = tracks.age
    out["missed"] = tracks.missed
    out["confirmed"] = tracks.hits >= confirm_hits
    out["hits"] = tracks.hits
    return out


def stats_rows(tracks: TrackState, confirm_hits: int, *, alive: bool) -> npt.NDArray[np.void]:
    """One :data:`TRACK_STATS_DTYPE` row per track of ``tracks``."""
    out = np.zeros(len(tracks), dtype=TRACK_STATS_DTYPE)
    out["track"] = tracks.ids
    out["alive"] = alive
    out["confirmed"] = tracks.hits >= confirm_hits
    out["hits"] = tracks.hits
    out["gated"] = tracks.gated
    out["first_log_time"] = tracks.first_time
    out["last_log_time"] = tracks.last_time
    mean = tracks.sums / np.maximum(tracks.hits, 1)[:, None]
    out["mean_flux"] = mean[:, 0]
    out["mean_x"] = mean[:, 1]
    out["mean_y"] = mean[:, 2]
    return out
