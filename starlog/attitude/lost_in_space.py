"""Lost-in-space plate solving of one frame's centroids with cedar-solve (the maintained fork of ESA's tetra3).

The solver matches 4-star patterns of the brightest centroids against its shipped pattern database
(fields of view 10-30 deg) and needs no field-of-view estimate (it then searches the database's
whole range). Its matched stars give a first camera (:func:`starlog.attitude.camera.camera_from_pairs`:
attitude, focal length, one radial distortion term, both parities tried); the caller refines it by
re-matching the catalogue (:mod:`starlog.attitude.identify`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.attitude.camera import Camera, camera_from_pairs, focal_from_fov
from starlog.attitude.catalogue import MISSING_SOLVER, solver_data_file
from starlog.attitude.rotation import radec_vectors
from starlog.errors import InvalidParameterError

__all__ = ["LostInSpace", "load_solver", "solve_lost_in_space"]


@cache
def load_solver() -> Any:
    """cedar-solve's ``Tetra3`` with its shipped database (no download), loaded once per process; its console
    logging silenced. :class:`InvalidParameterError` naming the ``solve`` extra when it is not installed."""
    solver_data_file()
    import numpy

    if not hasattr(numpy, "math"):  # cedar-solve 0.5 calls np.math.factorial, gone in NumPy 2
        numpy.math = math  # type: ignore[attr-defined]
    logger = logging.getLogger("tetra3.Tetra3")
    if not logger.hasHandlers():
        logger.addHandler(logging.NullHandler())
    logger.setLevel(logging.WARNING)
    try:
        import tetra3
    except ImportError as err:
        raise InvalidParameterError(f"{MISSING_SOLVER} ({err})") from err
    return tetra3.Tetra3()


@dataclass(frozen=True)
class LostInSpace:
    """A lost-in-space solution: the camera fitted to the solver's matches, and the solver's own figures
    (``ra``, ``dec``, ``roll``, ``fov`` deg, ``distortion``, ``matches``, ``t_solve`` ms); or why there is none."""

    camera: Camera | None
    solver: dict[str, Any]
    reason: str = ""


def _solver_call(solver: Any, yx: npt.NDArray[np.float64], shape: tuple[int, int], fov_deg: float | None,
                 distortion: Any, timeout_ms: int) -> dict[str, Any] | None:
    """One ``solve_from_centroids`` call; None when it raises the IndexError cedar-solve 0.5 raises when a
    candidate pattern leaves no catalogue star in the field."""
    try:
        return dict(solver.solve_from_centroids(yx, size=shape, fov_estimate=fov_deg, distortion=distortion,
                                                return_matches=True, match_threshold=1e-7, solve_timeout=timeout_ms))
    except IndexError:
        return None


def solve_lost_in_space(x: npt.NDArray[np.float64], y: npt.NDArray[np.float64], flux: npt.NDArray[np.float64],
                        shape: tuple[int, int], *, fov_deg: float | None = None, brightest: int = 50,
                        timeout_ms: int = 5000, solver: Any = None, fit_distortion: bool = True) -> LostInSpace:
    """Plate solve from the ``brightest`` centroids (x = column, y = row, pixel-centre origin) of an image of
    ``shape = (rows, cols)``; ``fov_deg``: the horizontal field of view when known (None: searched).

    Solved without distortion first (fast; the solver's distortion estimate from its coarse matches can be
    off), then with a searched distortion range when that fails.
    """
    solver = solver if solver is not None else load_solver()
    order = np.argsort(-flux, kind="stable")[:brightest]
    # the solver's pixel convention puts (0.5, 0.5) at the top-left pixel's centre, (y, x) order
    yx = np.column_stack([y[order] + 0.5, x[order] + 0.5])
    sol: dict[str, Any] | None = None
    for distortion in (0.0, (-0.2, 0.1)):
        sol = _solver_call(solver, yx, shape, fov_deg, distortion, timeout_ms)
        if sol is not None and sol.get("RA") is not None:
            break
    if sol is None or sol.get("RA") is None:
        status = {2: "no match", 3: "timeout", 4: "cancelled", 5: "too few stars"}.get(
            int(sol.get("status", 2)) if sol else 2, "no match")
        return LostInSpace(None, {}, f"lost-in-space: no solution ({status})")
    stars = np.asarray(sol["matched_stars"], np.float64)
    yx_m = np.asarray(sol["matched_centroids"], np.float64)
    figures = {"ra": float(sol["RA"]), "dec": float(sol["Dec"]), "roll": float(sol["Roll"]), "fov": float(sol["FOV"]),
               "distortion": float(sol["distortion"] or 0.0), "matches": int(sol["Matches"]),
               "t_solve": float(sol["T_solve"])}
    focal = focal_from_fov(figures["fov"], shape[1])
    camera = camera_from_pairs(shape, focal, radec_vectors(stars[:, 0], stars[:, 1]), yx_m[:, 1] - 0.5,
                               yx_m[:, 0] - 0.5, fit_distortion=fit_distortion)
    return LostInSpace(camera, figures)
