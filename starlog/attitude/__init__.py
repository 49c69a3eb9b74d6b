"""Attitude from centroids: star identification against a catalogue and the attitude with its covariance.

Plain functions on numpy arrays, no log: :mod:`~starlog.attitude.rotation` (frames, quaternions,
RA/Dec/roll), :mod:`~starlog.attitude.camera` (the gnomonic camera with one distortion term and its
fit), :mod:`~starlog.attitude.qmethod` (Davenport's q-method, Shuster's covariance),
:mod:`~starlog.attitude.matching` (catalogue-to-centroid pairing), :mod:`~starlog.attitude.catalogue`
(cedar-solve's star table), :mod:`~starlog.attitude.lost_in_space` (cedar-solve's plate solve) and
:mod:`~starlog.attitude.identify` (lost in space, then tracking). The log stage is
:mod:`starlog.stages.solve`.
"""

from __future__ import annotations

from starlog.attitude.camera import Camera, camera_for_image, camera_from_pairs, fit_camera
from starlog.attitude.catalogue import Catalogue, load_catalogue
from starlog.attitude.identify import AttitudeTracker, FrameAttitude, TrackerSettings
from starlog.attitude.qmethod import QMethodResult, davenport_q_method, shuster_covariance
from starlog.attitude.rotation import attitude_error, attitude_from_radec_roll, radec_roll, radec_vectors

__all__ = ["AttitudeTracker", "Camera", "Catalogue", "FrameAttitude", "QMethodResult", "TrackerSettings",
           "attitude_error", "attitude_from_radec_roll", "camera_for_image", "camera_from_pairs",
           "davenport_q_method", "fit_camera", "load_catalogue", "radec_roll", "radec_vectors", "shuster_covariance"]
