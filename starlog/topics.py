"""Channel names (topics) of a starlog log, and the names of the metadata records its stages write. Stable:
scripts outside starlog rely on them.

========================================  ===========================  ======================
topic                                     schema                       written by
========================================  ===========================  ======================
``/camera/image``                         foxglove.RawImage            simulate, ingest
``/camera/frame``                         starlog.FrameInfo            simulate, ingest
``/sim/truth``                            starlog.SimTruth             simulate
``/stars/detections``                     starlog.Detections           centroid
``/stars/annotations``                    foxglove.ImageAnnotations    centroid
``/stars/centroids/<METHOD>``             starlog.Centroids            centroid
``/track/<METHOD>/<MODEL>``               starlog.Tracks               track
``/platform/<METHOD>/<MODEL>``            starlog.PlatformMotion       motion
``/stars/residuals/<METHOD>/<MODEL>``     starlog.StarResiduals        motion
``/compensated/<METHOD>/<MODEL>/<R>Hz``   starlog.CompensatedSample    compensate
``/compensated/<METHOD>/<MODEL>/decisions``  starlog.CompensationRecord  compensate
``/compensated/<METHOD>/<MODEL>/stars/<R>Hz``  starlog.CompensatedStars  compensate --stars all
``/compensated/<METHOD>/<MODEL>/stars/decisions``  starlog.CompensationRecord  compensate --stars all
``/attitude/<METHOD>``                    starlog.Attitude             solve
``/stars/identified/<METHOD>``            starlog.IdentifiedStars      solve
``/stars/identified/<METHOD>/annotations``  foxglove.ImageAnnotations  solve
========================================  ===========================  ======================
"""

from __future__ import annotations

__all__ = [
    "IMAGE",
    "FRAME_INFO",
    "TRUTH",
    "DETECTIONS",
    "ANNOTATIONS",
    "centroid_topic",
    "track_topic",
    "platform_topic",
    "residuals_topic",
    "compensated_topic",
    "decisions_topic",
    "compensated_stars_topic",
    "stars_decisions_topic",
    "attitude_topic",
    "identified_topic",
    "identified_annotations_topic",
    "EPSF_METADATA",
    "PHASE_METADATA",
    "EVIDENCE_METADATA",
    "SOLVE_METADATA",
]

IMAGE = "/camera/image"
FRAME_INFO = "/camera/frame"
TRUTH = "/sim/truth"
DETECTIONS = "/stars/detections"
ANNOTATIONS = "/stars/annotations"

#: Name of the metadata record holding a log's empirical PSF (``starlog centroid --psf empirical``):
#: the string map of :meth:`starlog.centroiding.epsf.EPSF.to_metadata`.
EPSF_METADATA = "starlog.epsf"

#: Name of the metadata record holding a log's pixel-phase calibrations (``starlog centroid
#: --phase-correction``): source, and the calibrations as a JSON list (:mod:`starlog.centroiding.phase`).
PHASE_METADATA = "starlog.phase_correction"

#: Name of the metadata record holding the evidence on which centroid method to trust, and the method
#: recommended (:mod:`starlog.centroiding.evidence`): ``methods`` (JSON), ``recommended``, ``reason``.
EVIDENCE_METADATA = "starlog.centroid_evidence"

#: Name of the metadata record of a ``starlog solve`` run: ``methods`` (JSON), per centroid method the frames
#: solved, the catalogue residuals, the fitted camera and, on simulated sky, the attitude error.
SOLVE_METADATA = "starlog.solve"


def centroid_topic(method: str) -> str:
    """``/stars/centroids/<METHOD>``."""
    return f"/stars/centroids/{method}"


def track_topic(method: str, model: str) -> str:
    """``/track/<METHOD>/<MODEL>``."""
    return f"/track/{method}/{model}"


def platform_topic(method: str, model: str) -> str:
    """``/platform/<METHOD>/<MODEL>``: the platform motion fitted to the stars of ``/track/<METHOD>/<MODEL>``."""
    return f"/platform/{method}/{model}"


def residuals_topic(method: str, model: str) -> str:
    """``/stars/residuals/<METHOD>/<MODEL>``: each star's motion-removed residual."""
    return f"/stars/residuals/{method}/{model}"


def compensated_topic(method: str, model: str, rate_hz: float, protocol: str) -> str:
    """``/compensated/<METHOD>/<MODEL>/<RATE>Hz/<protocol>``."""
    return f"/compensated/{method}/{model}/{rate_hz:g}Hz/{protocol}"


def compensated_stars_topic(method: str, model: str, rate_hz: float, protocol: str) -> str:
    """``/compensated/<METHOD>/<MODEL>/stars/<RATE>Hz/<protocol>``: every compensated star, per frame."""
    return f"/compensated/{method}/{model}/stars/{rate_hz:g}Hz/{protocol}"


def stars_decisions_topic(method: str, model: str) -> str:
    """``/compensated/<METHOD>/<MODEL>/stars/decisions``: one decision record per star, rate and protocol."""
    return f"/compensated/{method}/{model}/stars/decisions"


def decisions_topic(method: str, model: str) -> str:
    """``/compensated/<METHOD>/<MODEL>/decisions``: one decision record per (rate, protocol)."""
    return f"/compensated/{method}/{model}/decisions"


def attitude_topic(method: str) -> str:
    """``/attitude/<METHOD>``: the attitude solved from ``/stars/centroids/<METHOD>``."""
    return f"/attitude/{method}"


def identified_topic(method: str) -> str:
    """``/stars/identified/<METHOD>``: the catalogue stars identified among ``/stars/centroids/<METHOD>``."""
    return f"/stars/identified/{method}"


def identified_annotations_topic(method: str) -> str:
    """``/stars/identified/<METHOD>/annotations``: circles and catalogue labels of the identified stars."""
    return f"/stars/identified/{method}/annotations"
