"""Temporal filtering of star centroids: motion models, a batched UKF, multi-star tracking.

numpy (+ scipy's assignment solver; filterpy as the reference filter), no I/O; the tracker's
frame is one compiled (numba) call, the numpy steps kept as its reference.

* :mod:`starlog.tracking.models` — :class:`MotionModel` (STATIC, RANDOM_WALK, BROWNIAN_MOTION,
  POLYNOMIAL_TREND, CONSTANT_VELOCITY), :class:`MotionModelConfig`, exact discretisation.
* :mod:`starlog.tracking.ukf` — :class:`BatchUKF` and the functional core (Merwe sigma points,
  unscented transform, gated update), vectorised across stars; :mod:`starlog.tracking.ukf_filterpy` — filterpy's
  per-object filter, its reference.
* :mod:`starlog.tracking.association` — :class:`StarTracker`: frame-by-frame association, track
  life cycle, per-track statistics, :meth:`StarTracker.brightest_track`.
* :mod:`starlog.tracking.frame_steps` — the tracker's numpy steps of a frame (the reference);
  :mod:`starlog.tracking.tracker_config` — :class:`TrackerConfig`.
* :mod:`starlog.tracking.frame_kernel` — the tracker's frame compiled: prediction, association, gated
  update, life cycle and output rows of every track in one call.
* :mod:`starlog.tracking.table` — :data:`TRACK_DTYPE` and :data:`TRACK_STATS_DTYPE` row layouts.
* :mod:`starlog.tracking.state` — the live tracks' arrays, held in one structure (take/concat).

Coordinates: x = column, y = row, px, (0, 0) at the centre of the top-left pixel; times are
int ns ``log_time``.
"""

from __future__ import annotations

from starlog.tracking.association import NoTrackError, StarTracker, TrackerConfig, track_centroids
from starlog.tracking.models import (
    MotionModel,
    MotionModelConfig,
    discretize,
    initial_covariance,
    state_dim,
)
from starlog.tracking.table import TRACK_DTYPE, TRACK_STATS_DTYPE, empty_tracks
from starlog.tracking.ukf import (
    DEFAULT_GATE_PROBABILITY,
    BatchUKF,
    SigmaPoints,
    UKFUpdate,
    gate_threshold,
    ukf_predict,
    ukf_update,
)
from starlog.tracking.ukf_filterpy import filterpy_step, make_filterpy_ukf

__all__ = [
    "MotionModel",
    "MotionModelConfig",
    "discretize",
    "initial_covariance",
    "state_dim",
    "BatchUKF",
    "SigmaPoints",
    "UKFUpdate",
    "DEFAULT_GATE_PROBABILITY",
    "gate_threshold",
    "ukf_predict",
    "ukf_update",
    "make_filterpy_ukf",
    "filterpy_step",
    "StarTracker",
    "TrackerConfig",
    "NoTrackError",
    "track_centroids",
    "TRACK_DTYPE",
    "TRACK_STATS_DTYPE",
    "empty_tracks",
]
