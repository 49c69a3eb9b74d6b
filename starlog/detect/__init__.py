"""Single-frame star detection: background, matched-filter threshold, components, screening.

Coordinates: x = column, y = row, 0-based, (0, 0) at the centre of the top-left pixel.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from starlog.detect.flags import StarFlag as DetectionFlag
    from starlog.detect.background import Background, estimate_background
    from starlog.detect.detection import DETECTION_DTYPE, DetectionWarning, detect_stars, empty_detections

#: Each public name, the module that defines it and its name there, imported on first use: a module that needs
#: only the flags (a star table's reader) does not load detection and SciPy with them.
_DEFINED_IN = {
    "DETECTION_DTYPE": ("detection", "DETECTION_DTYPE"),
    "Background": ("background", "Background"),
    "DetectionFlag": ("flags", "StarFlag"),
    "DetectionWarning": ("detection", "DetectionWarning"),
    "detect_stars": ("detection", "detect_stars"),
    "empty_detections": ("detection", "empty_detections"),
    "estimate_background": ("background", "estimate_background"),
}

__all__ = [
    "DETECTION_DTYPE",
    "Background",
    "DetectionFlag",
    "DetectionWarning",
    "detect_stars",
    "empty_detections",
    "estimate_background",
]


def __getattr__(name: str) -> Any:
    if name not in _DEFINED_IN:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module, attribute = _DEFINED_IN[name]
    value = getattr(importlib.import_module(f"{__name__}.{module}"), attribute)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_DEFINED_IN})
