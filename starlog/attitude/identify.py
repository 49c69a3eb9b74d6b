"""Star identification and attitude of a sequence of frames: lost in space once, then tracking.

Per frame, from its centroids (x, y, flux, sigma):

* **tracking** (a previous frame was solved): the catalogue stars near the previous boresight are
  projected with the previous attitude and camera, each centroid is paired with its nearest projected
  star when they are each other's nearest and closer than ``match_radius`` px
  (:func:`~starlog.attitude.matching.match_mutual`), and the attitude is refined by Davenport's
  q-method weighting each star by its centroid's ``1 / sigma^2``
  (:func:`~starlog.attitude.qmethod.davenport_q_method`); matched and refined twice, then refitted
  without the pairs whose residual is an outlier (:func:`outlier_pairs`). Fewer than
  ``min_matches`` pairs: the frame falls back to
* **lost in space** (:func:`~starlog.attitude.lost_in_space.solve_lost_in_space`): cedar-solve's pattern
  match, the camera fitted to its matches, then re-matched to the catalogue with shrinking radii (4 px
  for the brightest stars first, so that chance coincidences in a dense field cannot pull the fit, then 2 px),
  refitting the camera (attitude, focal length, distortion) each time; the attitude is then the
  q-method's on the final matches, as in tracking. The solver's patterns (ratios of distances) do not
  change in a mirror, so a mirrored image solves as it is (every mirrored real frame of the benchmark
  does), its camera fitted with parity -1; with ``try_mirrored`` set, a frame that does not solve is tried
  again with its columns reversed. A mirrored frame says so.

A frame that cannot be solved says why (too few stars, no solution, ...); the next frame starts again
from lost in space.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from starlog.attitude.camera import Camera, fit_camera
from starlog.attitude.catalogue import Catalogue
from starlog.attitude.lost_in_space import LostInSpace, solve_lost_in_space
from starlog.attitude.matching import match_mutual
from starlog.attitude.qmethod import QMethodResult, davenport_q_method

__all__ = ["ARCSEC_PER_RAD", "AttitudeTracker", "FrameAttitude", "TrackerSettings", "identify_and_refine",
           "outlier_pairs"]

ARCSEC_PER_RAD = 180.0 * 3600.0 / math.pi
_EMPTY = np.zeros(0, np.int64)


@dataclass(frozen=True)
class FrameAttitude:
    """One frame's attitude and identified stars, or why it has none.

    ``catalogue_rows`` index the catalogue, ``centroid_rows`` the centroids given; ``cat_x``, ``cat_y``
    are the identified catalogue stars projected with the solved camera (px); residuals are measured
    minus projected. ``covariance`` (rad^2, camera frame: x, y cross-boresight, z roll) is Shuster's,
    from the centroids' sigmas.
    """

    solved: bool
    reason: str = ""
    mode: str = ""
    camera: Camera | None = None
    fit: QMethodResult | None = None
    catalogue_rows: npt.NDArray[np.int64] = field(default_factory=lambda: _EMPTY)
    centroid_rows: npt.NDArray[np.int64] = field(default_factory=lambda: _EMPTY)
    cat_x: npt.NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    cat_y: npt.NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    solver: dict[str, Any] = field(default_factory=dict)

    @property
    def n_matched(self) -> int:
        return int(self.catalogue_rows.size)

    def residuals(self, x: npt.NDArray[np.float64], y: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """(n_matched, 2) measured minus projected, px."""
        rows = self.centroid_rows
        return np.column_stack([x[rows] - self.cat_x, y[rows] - self.cat_y])

    def residual_rms(self, x: npt.NDArray[np.float64], y: npt.NDArray[np.float64]) -> float:
        """Per-axis RMS of the residuals, px (NaN unsolved)."""
        if not self.solved or self.n_matched == 0:
            return math.nan
        return float(np.sqrt(np.mean(np.square(self.residuals(x, y)))))


def _q_method(camera: Camera, vectors: npt.NDArray[np.float64], x: npt.NDArray[np.float64],
              y: npt.NDArray[np.float64], sigma: npt.NDArray[np.float64], *,
              covariance: bool = True) -> tuple[Camera, QMethodResult]:
    """The camera's attitude replaced by the q-method's for matched (sky vector, pixel, sigma px) stars."""
    fit = davenport_q_method(camera.pixel_vectors(x, y), vectors, camera.angular_sigma(sigma), covariance=covariance)
    return replace(camera, rotation=fit.attitude), fit


def identify_and_refine(camera: Camera, catalogue: Catalogue, candidates: npt.NDArray[np.int64],
                        x: npt.NDArray[np.float64], y: npt.NDArray[np.float64], sigma: npt.NDArray[np.float64], *,
                        radius: float, min_matches: int, passes: int = 2, reject: float = 4.0) -> FrameAttitude:
    """Match ``candidates`` (catalogue rows) projected with ``camera`` to the centroids within ``radius`` px and
    refine the attitude by the q-method, ``passes`` times; unsolved when fewer than ``min_matches`` match.
    Then the pairs whose residual is an outlier (:func:`outlier_pairs`, ``reject`` > 0) are left out and the
    attitude refitted."""
    vectors = catalogue.vectors[candidates]
    fit = None
    rows, cols = 2.0 * camera.cy + 1.0, 2.0 * camera.cx + 1.0
    for k in range(passes):
        px, py, front = camera.project(vectors)
        seen = np.flatnonzero(front & (px > -radius) & (px < cols + radius) & (py > -radius) & (py < rows + radius))
        cat, det = match_mutual(px[seen], py[seen], x, y, radius)
        cat = seen[cat]
        if cat.size < min_matches:
            return FrameAttitude(False, f"tracking: {cat.size} stars matched within {radius:g} px "
                                        f"(fewer than {min_matches})")
        camera, fit = _q_method(camera, vectors[cat], x[det], y[det], sigma[det], covariance=k == passes - 1)
    px, py, _ = camera.project(vectors[cat])
    if reject > 0:
        keep = ~outlier_pairs(x[det] - px, y[det] - py, sigma[det], reject)
        if not keep.all() and keep.sum() >= min_matches:
            cat, det = cat[keep], det[keep]
            camera, fit = _q_method(camera, vectors[cat], x[det], y[det], sigma[det])
            px, py, _ = camera.project(vectors[cat])
    return FrameAttitude(True, "", "tracking", camera, fit, candidates[cat], det, px, py)


def outlier_pairs(dx: npt.NDArray[np.float64], dy: npt.NDArray[np.float64], sigma: npt.NDArray[np.float64],
                  reject: float) -> npt.NDArray[np.bool_]:
    """Pairs whose normalised residual ``z = sqrt((dx^2 + dy^2) / 2) / sigma`` exceeds ``reject`` times the
    pairs' robust scale of ``z`` (its median over 0.8326, the median of ``z`` for Gaussian errors of the stated
    sigma). Relative to the pairs' own scale, so that a camera model or catalogue error common to every star
    (real sky: residuals many times the centroids' sigmas) rejects nothing, while a star whose centroid is pulled
    (an unresolved neighbour) is left out."""
    z = np.sqrt((dx * dx + dy * dy) / 2.0) / sigma
    scale = float(np.median(z)) / 0.8326
    return z > reject * max(scale, 1e-12)


def _refine_rounds(camera: Camera, vectors: npt.NDArray[np.float64], magnitude: npt.NDArray[np.float64],
                   x: npt.NDArray[np.float64], y: npt.NDArray[np.float64], flux: npt.NDArray[np.float64],
                   sigma: npt.NDArray[np.float64], *, brightest: int, fit_intrinsics: bool,
                   fit_distortion: bool, min_matches: int) -> Camera | None:
    """Re-match the field's catalogue stars to the centroids with shrinking radii, refitting each time
    (None: fewer than ``min_matches`` at some round)."""
    bright_cat = np.argsort(magnitude, kind="stable")[:brightest]
    bright_det = np.argsort(-flux, kind="stable")[:brightest]
    every = np.arange(x.size)
    for radius, cat_rows, det_rows in ((4.0, bright_cat, bright_det), (2.0, np.arange(magnitude.size), every)):
        px, py, _ = camera.project(vectors[cat_rows])
        cat, det = match_mutual(px, py, x[det_rows], y[det_rows], radius)
        if cat.size < min_matches:
            return None
        v, det = vectors[cat_rows[cat]], det_rows[det]
        if fit_intrinsics:
            camera = fit_camera(camera, v, x[det], y[det], fit_distortion=fit_distortion and cat.size >= 8)
        else:
            camera, _ = _q_method(camera, v, x[det], y[det], sigma[det])
    return camera


def _mirrored(camera: Camera) -> Camera:
    """The camera seeing the image with its columns reversed (``x -> 2 cx - x``)."""
    return replace(camera, parity=-camera.parity)


@dataclass(frozen=True)
class TrackerSettings:
    """How :class:`AttitudeTracker` identifies stars.

    ``match_radius`` (px): a centroid and a projected catalogue star pair only when nearer; ``min_matches``:
    fewer identified stars leave the frame unsolved (tracking then falls back to lost in space); ``min_stars``:
    fewer usable centroids and the frame is not tried; ``fov_deg``: the horizontal field of view given to the
    lost-in-space solver (None: searched); ``focal_px`` / ``distortion``: a known camera (its focal length in
    px and ``k``; None: fitted on each lost-in-space frame and kept while tracking); ``brightest``: centroids
    given to the solver; ``timeout_ms``: the solver's time limit per attempt; ``try_mirrored``: solve a frame
    with its columns reversed when it does not solve as it is; ``tracking``: False solves every frame lost in
    space; ``max_magnitude``: catalogue stars fainter are never identified; ``reject``: a pair whose normalised
    residual exceeds this many times the frame's robust scale is left out of the attitude (0: none;
    :func:`outlier_pairs`).
    """

    match_radius: float = 3.0
    min_matches: int = 6
    min_stars: int = 4
    fov_deg: float | None = None
    focal_px: float | None = None
    distortion: float = 0.0
    fit_distortion: bool = True
    brightest: int = 50
    timeout_ms: int = 5000
    try_mirrored: bool = False
    tracking: bool = True
    max_magnitude: float | None = None
    reject: float = 4.0


class AttitudeTracker:
    """Solves frames one after another (module docstring): lost in space, then tracking from the previous
    attitude. ``solver``: a cedar-solve ``Tetra3`` (default: :func:`~starlog.attitude.lost_in_space.load_solver`)."""

    def __init__(self, catalogue: Catalogue, shape: tuple[int, int], settings: TrackerSettings | None = None, *,
                 solver: Any = None) -> None:
        self.settings = settings or TrackerSettings()
        s = self.settings
        self.catalogue = catalogue if s.max_magnitude is None else catalogue.brighter_than(s.max_magnitude)
        self.shape = shape
        self.solver = solver
        self.camera: Camera | None = None
        self._candidates = _EMPTY
        self._candidate_centre = np.zeros(3)

    def solve(self, x: npt.NDArray[np.float64], y: npt.NDArray[np.float64], flux: npt.NDArray[np.float64],
              sigma: npt.NDArray[np.float64]) -> FrameAttitude:
        """The attitude of one frame from its usable centroids (finite, sigma > 0)."""
        s = self.settings
        if x.size < s.min_stars:
            self.camera = None
            return FrameAttitude(False, f"too few stars ({x.size} usable centroids, fewer than {s.min_stars})")
        tracked = None
        if self.camera is not None and s.tracking:
            tracked = identify_and_refine(self.camera, self.catalogue, self._field_rows(self.camera), x, y, sigma,
                                          radius=s.match_radius, min_matches=s.min_matches, reject=s.reject)
            if tracked.solved:
                self.camera = tracked.camera
                return tracked
        result = self._lost_in_space(x, y, flux, sigma)
        if not result.solved and tracked is not None:
            result = replace(result, reason=f"{tracked.reason}; {result.reason}")
        self.camera = result.camera if result.solved else None
        return result

    def _field_rows(self, camera: Camera) -> npt.NDArray[np.int64]:
        """Catalogue rows within the field's circumscribed cone (plus 1 deg), cached while the boresight stays
        within 0.5 deg of where they were selected."""
        boresight = camera.rotation[2]
        if self._candidates.size == 0 or float(boresight @ self._candidate_centre) < math.cos(math.radians(0.5)):
            rows, cols = self.shape
            radius = math.degrees(math.atan(math.hypot(rows, cols) / 2.0 / camera.focal)) + 1.0
            self._candidates = self.catalogue.cone(boresight, radius)
            self._candidate_centre = boresight.copy()
        return self._candidates

    def _solve_lis(self, x: npt.NDArray[np.float64], y: npt.NDArray[np.float64], flux: npt.NDArray[np.float64]
                   ) -> tuple[LostInSpace, bool]:
        """The solver on the frame, then (``try_mirrored``) on its mirror image; (solution, mirrored)."""
        s = self.settings
        fov = s.fov_deg
        if fov is None and s.focal_px is not None:
            fov = math.degrees(2.0 * math.atan(self.shape[1] / 2.0 / s.focal_px))
        options = {"fov_deg": fov, "brightest": s.brightest, "timeout_ms": s.timeout_ms, "solver": self.solver,
                   "fit_distortion": s.fit_distortion}
        lis = solve_lost_in_space(x, y, flux, self.shape, **options)
        if lis.camera is not None or not s.try_mirrored:
            return lis, False
        flipped = solve_lost_in_space((self.shape[1] - 1.0) - x, y, flux, self.shape, **options)
        if flipped.camera is None:
            return lis, False
        return replace(flipped, camera=_mirrored(flipped.camera)), True

    def _lost_in_space(self, x: npt.NDArray[np.float64], y: npt.NDArray[np.float64], flux: npt.NDArray[np.float64],
                       sigma: npt.NDArray[np.float64]) -> FrameAttitude:
        s = self.settings
        lis, mirrored = self._solve_lis(x, y, flux)
        if lis.camera is None:
            return FrameAttitude(False, lis.reason, solver=lis.solver)
        camera = lis.camera
        known = s.focal_px is not None
        if known:
            camera = replace(camera, focal=float(s.focal_px), k=float(s.distortion))
        self._candidates = _EMPTY
        rows = self._field_rows(camera)
        refined = _refine_rounds(camera, self.catalogue.vectors[rows], self.catalogue.magnitude[rows], x, y, flux,
                                 sigma, brightest=s.brightest, fit_intrinsics=not known,
                                 fit_distortion=s.fit_distortion, min_matches=s.min_matches)
        if refined is None:
            return FrameAttitude(False, f"lost-in-space: the solution is not confirmed by the catalogue (fewer than "
                                        f"{s.min_matches} stars re-matched)", solver=lis.solver)
        result = identify_and_refine(refined, self.catalogue, self._field_rows(refined), x, y, sigma,
                                     radius=s.match_radius, min_matches=s.min_matches, reject=s.reject)
        if not result.solved:
            return replace(result, reason=f"lost-in-space: {result.reason}", solver=lis.solver)
        note = "mirrored image (columns reversed): solved with parity -1" if mirrored or refined.parity < 0 else ""
        return replace(result, mode="lost_in_space", reason=note, solver=lis.solver)
