"""Single-frame star detection: background, matched-filter threshold, components, screening.

Coordinates: x = column, y = row, 0-based, (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

from starlog.detect._flags import StarFlag as DetectionFlag
from starlog.detect.background import Background, estimate_background
from starlog.detect.detection import DETECTION_DTYPE, DetectionWarning, detect_stars, empty_detections

__all__ = [
    "DETECTION_DTYPE",
    "Background",
    "DetectionFlag",
    "DetectionWarning",
    "detect_stars",
    "empty_detections",
    "estimate_background",
]
