"""Row layouts of the tracker's results (structured numpy dtypes).

Coordinates: x = column, y = row, pixels, 0-based, (0, 0) at the centre of the top-left
pixel. No field is ever NaN: quantities that do not exist in a row are 0 and a flag says so.

``TRACK_DTYPE`` — one row per live track per frame (:meth:`StarTracker.update`), rows sorted
by ``track``:

================  =======  ====  ==========================================================
field             type     unit  meaning
================  =======  ====  ==========================================================
``track``         int32    —     track id: 0, 1, 2 … in order of birth, never reused
``x``             float64  px    filtered column: posterior if ``measured``, else the
                                 prediction (prior) for this frame's ``log_time``
``y``             float64  px    filtered row (as ``x``)
``vx``            float64  px/s  filtered column velocity; 0 for STATIC and RANDOM_WALK
``vy``            float64  px/s  filtered row velocity; 0 for STATIC and RANDOM_WALK
``cov_xx``        float64  px²   variance of ``x`` (state covariance P[0, 0])
``cov_xy``        float64  px²   covariance of ``x`` and ``y`` (P[0, 1])
``cov_yy``        float64  px²   variance of ``y`` (P[1, 1])
``innovation_x``  float64  px    ``meas_x`` minus the predicted ``x`` (0 if no measurement was
                                 associated, or at the track's birth)
``innovation_y``  float64  px    as ``innovation_x`` for ``y``
``nis``           float64  —     normalised innovation squared ``νᵀ S⁻¹ ν`` (squared
                                 Mahalanobis distance) of the associated measurement; 0 if none
``measured``      bool     —     a measurement was applied this frame (or started the track);
                                 its ``nis`` exceeds the gate only when applied after
                                 ``max_gated`` consecutive gated frames
``gated``         bool     —     a measurement was associated but rejected by the innovation
                                 gate (``nis`` above the threshold); the row is a prediction
``meas_x``        float64  px    the associated centroid's ``x`` (0 if none)
``meas_y``        float64  px    the associated centroid's ``y`` (0 if none)
``meas_sigma``    float64  px    the associated centroid's uncertainty as used in ``R``
                                 (after the tracker's ``sigma_floor``; 0 if none)
``flux``          float64  —     the associated centroid's flux, its own unit (0 if none)
``age``           int32    frames  frames since the track's birth (0 in its first frame)
``missed``        int32    frames  consecutive frames up to this one without an applied
                                 measurement (0 when ``measured``)
``confirmed``     bool     —     the track has had ``confirm_hits`` applied measurements
``hits``          int32    —     applied measurements so far, birth included
================  =======  ====  ==========================================================

``TRACK_STATS_DTYPE`` — one row per track ever started (:meth:`StarTracker.track_stats`):

===================  =======  ====  =======================================================
field                type     unit  meaning
===================  =======  ====  =======================================================
``track``            int32    —     track id
``alive``            bool     —     still tracked (not lost)
``confirmed``        bool     —     reached ``confirm_hits`` applied measurements
``hits``             int32    —     applied measurements, birth included
``gated``            int32    —     measurements rejected by the innovation gate
``first_log_time``   int64    ns    ``log_time`` of the track's birth
``last_log_time``    int64    ns    ``log_time`` of its last applied measurement
``mean_flux``        float64  —     mean flux of the applied measurements (centroid unit)
``mean_x``           float64  px    mean measured ``x`` of the applied measurements
``mean_y``           float64  px    mean measured ``y`` of the applied measurements
===================  =======  ====  =======================================================
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["TRACK_DTYPE", "TRACK_STATS_DTYPE", "empty_tracks"]

TRACK_DTYPE = np.dtype(
    [
        ("track", np.int32),
        ("x", np.float64),
        ("y", np.float64),
        ("vx", np.float64),
        ("vy", np.float64),
        ("cov_xx", np.float64),
        ("cov_xy", np.float64),
        ("cov_yy", np.float64),
        ("innovation_x", np.float64),
        ("innovation_y", np.float64),
        ("nis", np.float64),
        ("measured", np.bool_),
        ("gated", np.bool_),
        ("meas_x", np.float64),
        ("meas_y", np.float64),
        ("meas_sigma", np.float64),
        ("flux", np.float64),
        ("age", np.int32),
        ("missed", np.int32),
        ("confirmed", np.bool_),
        ("hits", np.int32),
    ]
)
"""Per-frame track rows; see the module docstring for every field."""

TRACK_STATS_DTYPE = np.dtype(
    [
        ("track", np.int32),
        ("alive", np.bool_),
        ("confirmed", np.bool_),
        ("hits", np.int32),
        ("gated", np.int32),
        ("first_log_time", np.int64),
        ("last_log_time", np.int64),
        ("mean_flux", np.float64),
        ("mean_x", np.float64),
        ("mean_y", np.float64),
    ]
)
"""Per-track summary rows; see the module docstring for every field."""


def empty_tracks(n: int = 0) -> npt.NDArray[np.void]:
    """A zero-filled ``TRACK_DTYPE`` array of ``n`` rows."""
    return np.zeros(n, dtype=TRACK_DTYPE)
