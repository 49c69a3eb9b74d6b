"""Platform motion from all stars: per-frame rigid fits, static positions, and each star's own error.

Every star in a frame sees the same platform (attitude) motion, while the centroid errors of
different stars are independent.  A per-frame weighted fit of all tracked stars onto their
static positions therefore separates the two: the fitted motion is the platform motion,
averaged over the stars, and each star's residual is its centroid error alone — the way the
noise-equivalent angle of a star tracker is measured on a test bench.  Plain numpy functions:

* :mod:`~starlog.platform_motion.fit` — the 2-D motion models and the closed-form weighted fit of a frame;
* :mod:`~starlog.platform_motion.estimate` — the joint estimate over a log (static positions, star noise,
  outlier flags) and the leave-one-out reference of each observation.

Positions in pixels, ``x`` = column, ``y`` = row, (0, 0) at the centre of the top-left pixel;
roll in radians about the image centre.
"""

from __future__ import annotations

from starlog.platform_motion.estimate import (
    NOISE_FLOOR_PX,
    Observations,
    PlatformEstimate,
    estimate_platform,
    leave_one_out_reference,
    star_reference,
)
from starlog.platform_motion.fit import (
    MomentSums,
    MotionParameters,
    PlatformModel,
    apply_motion,
    frame_sums,
    remove_motion,
    solve_motion,
)

__all__ = [
    "NOISE_FLOOR_PX",
    "MomentSums",
    "MotionParameters",
    "Observations",
    "PlatformEstimate",
    "PlatformModel",
    "apply_motion",
    "estimate_platform",
    "frame_sums",
    "leave_one_out_reference",
    "remove_motion",
    "solve_motion",
    "star_reference",
]
