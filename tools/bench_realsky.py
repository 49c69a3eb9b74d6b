"""Real sky as a test: centroid accuracy of starlog and SEP against a star catalogue, on real frames.

Benchmark-only dependencies: sep, and cedar-solve (import name ``tetra3``; it ships a
Hipparcos pattern database for fields of view 10-30 deg, stars to magnitude ~8, so solving
needs no network).

Protocol, per frame:

1. The image is read as a grey array: a grey TIFF/PNG/JPEG as it is (8 or 16 bit); a colour
   one as the plain sum of its colour channels (every channel's photons count; no colour
   weighting, no tone curve undone: the camera's is unknown), a pixel saturated when any of
   its channels is at the file's maximum.
2. Centroids: starlog's detection and every method of ``starlog.centroiding.CentroidMethod``
   (``starlog.centroiding.extract_stars``, the library call of the centroid stage; read noise from
   the frame's measured background noise, the PSF width estimated from the frame). The gain of
   an unknown camera is measured, not assumed (``--gain auto``, :func:`estimate_gain`): the
   background's noise variance against its level over the frame (vignetting, sky gradient) has
   slope 1/gain whatever the pedestal and read noise; 1 e-/DN, the stage's default, when the
   levels span too little or the relation is not linear (tone-mapped JPEGs). SEP:
   ``sep.extract`` (isophotal barycentre) and ``sep.winpos`` (sig = 2/2.35 x half-flux radius)
   at detection thresholds of 1.5 and 5 times the global background RMS.
3. Plate solve once (lost in space, no field-of-view hint) from starlog's 50 brightest GAUSSFIT
   centroids. The solver's matched stars give a first camera: pinhole, principal point at the
   image centre, pointing + roll (a rotation), focal length and one radial distortion term
   ``x_d = x_u (1 + k r^2)``, r in units of the half-width (the solver fits one such term
   too); it is refined by re-matching the catalogue to the same centroids with shrinking radii
   (8, 4, 2 px; the brightest stars first), and a frame with fewer than 10 matches is left out.
4. Every catalogue star (database, magnitude <= ~8) projected into the frame at least
   ``--margin`` px inside the edges, with no other catalogue star within twice the match
   radius, is matched one-to-one to each centroider's nearest detection within
   ``--match-radius`` px.
5. The stars matched by ALL compared centroiders form the common set. The camera (rotation,
   focal length, distortion) is refitted to each centroider's positions of the common stars
   separately (least squares), and the residual RMSE (per axis, px: sqrt(mean(dx^2 + dy^2)/2))
   is that centroider's figure for the frame. Pooled: all frames' residuals together.
6. The ratio best starlog method / best SEP setting is computed on the pooled RMSEs, with a
   95 % bootstrap interval over the common stars.

Pixel phase (``--phase-correction auto``, the default): between steps 2 and 3, every centroider's
pixel-phase S-curve is calibrated on all frames' own stars (one camera, as one log; no catalogue)
with :mod:`starlog.centroiding.phase`, as ``starlog centroid --phase-correction auto`` does, and
removed: starlog's columns are the corrected positions, SEP's are shown as they are and corrected
(``+pc``). The headline ratio compares starlog corrected with SEP as users run it; a second line
with SEP corrected too.

Investigation options (none changes the figures above unless given): ``--by-mag`` (RMSE per
catalogue magnitude), ``--only NAME ...`` (compare fewer centroiders: a larger common set),
``--plate-order N`` (a polynomial field pattern fitted instead of the camera refit),
``--phase-equalise`` (each centroider also with the full empirical phase mapping; with
``--phase-correction off``), ``--phase-harmonics K`` (S-curve harmonics calibrated),
``--gain`` / ``--starlog-option KEY=VALUE`` (other settings of starlog).

Cameras and leave-one-camera-out (``--degraded``, ``--simulated``, ``--camera NAME=DIR``, ``--loco``): every
camera (a folder of frames) goes through the same protocol; ``tools/loco.py`` picks the default method on all
cameras but one and scores it on that one, and checks the method starlog trusts on each camera (the sky's
evidence, :mod:`starlog.attitude.sky_evidence`) against the benchmark's figure. To score your own cameras the
same way: ``--camera NAME=DIR`` once per camera, with ``--loco``.

Run: python tools/bench_realsky.py [--images DIR] [--json OUT] [--by-mag] [--degraded] [--simulated] [--loco]
(default images: ../shared/data/real-sky/ relative to the repository's root, read in place)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import dataclass, replace
from typing import Any
from dataclasses import field as dataclass_field
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # tools/loco.py, tools/sim_cameras.py

# the camera model, matching and plate solving live in starlog.attitude; the names below are also this
# module's (the benchmark's tests and tools/bench_attitude.py use them from here)
from starlog.attitude.camera import (  # noqa: E402, F401
    Camera, camera_for_image, camera_from_pairs, fit_camera, initial_rotation, residual_rmse)
from starlog.attitude.lost_in_space import load_solver, solve_lost_in_space  # noqa: E402
from starlog.attitude.matching import isolated, match_nearest  # noqa: E402
from starlog.attitude.rotation import radec_vectors  # noqa: E402, F401
from starlog.centroiding import CentroidFlag, CentroidMethod, estimate_psf_sigma, extract_stars  # noqa: E402
from starlog.centroiding.epsf import EPSF, epsf_from_frames  # noqa: E402
from starlog.centroiding.psf_width import window_half_size  # noqa: E402
from starlog.centroiding.phase import PhaseCalibration, estimate_phase_calibration, phase_sample_mask  # noqa: E402
from starlog.detect import detect_stars  # noqa: E402
from starlog.errors import InvalidInputError  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
REAL_SKY = Path("shared") / "data" / "real-sky"
IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".jpg", ".jpeg")
SEP_THRESHOLDS = (1.5, 5.0)
EPILOG = ("Run time on a 2-core machine: about 7 s for the 8 real-sky frames, with or without --quick. No "
          "pass/fail target: the figures are printed and the exit status is 0; 2, with one line saying how "
          "to get them, when the frames or a benchmark-only package are missing.")
MAG_BINS = (-2.0, 4.0, 5.0, 6.0, 7.0, 9.0)


# ----------------------------------------------------------------------------- images

def load_grey(path: Path) -> tuple[np.ndarray, float]:
    """A grey image (integers kept as they are, colour summed over channels) and its saturation level, DN."""
    suffix = path.suffix.lower()
    if suffix in (".tif", ".tiff"):
        import tifffile

        raw = tifffile.imread(str(path))
    else:
        import cv2

        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise ValueError(f"cannot read image {str(path)!r}.")
    return to_grey(np.asarray(raw))


def to_grey(raw: np.ndarray) -> tuple[np.ndarray, float]:
    """Grey version of a (rows, cols) or (rows, cols, channels) array, and the saturation level.

    Colour: the sum of the colour channels (alpha dropped), as float; a pixel with any channel
    at the integer maximum is set to the saturation level (channels x maximum).
    """
    if raw.ndim == 2:
        full = float(np.iinfo(raw.dtype).max) if np.issubdtype(raw.dtype, np.integer) else float("inf")
        return raw, full
    if raw.ndim != 3 or raw.shape[2] not in (3, 4):
        raise ValueError(f"expected a grey or colour image, got shape {raw.shape}.")
    colour = raw[:, :, :3]
    top = float(np.iinfo(raw.dtype).max) if np.issubdtype(raw.dtype, np.integer) else float("inf")
    grey = colour.astype(np.float64).sum(axis=2)
    saturation = 3.0 * top
    if math.isfinite(top):
        grey[(colour >= top).any(axis=2)] = saturation
    return grey, saturation


def default_images(repo: Path = REPO) -> Path:
    """``../shared/data/real-sky`` beside the repository (for a git worktree: beside its main checkout)."""
    candidates = [repo.parent / REAL_SKY]
    dot_git = repo / ".git"
    if dot_git.is_file():  # a worktree: "gitdir: <main>/.git/worktrees/<name>"
        gitdir = Path(dot_git.read_text().partition("gitdir:")[2].strip())
        candidates.append(gitdir.parent.parent.parent.parent / REAL_SKY)
    return next((c for c in candidates if c.is_dir()), candidates[0])


def list_images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def missing_images(folder: Path) -> str | None:
    """Why ``folder`` holds no frames to measure, naming how to get them; None when it has some."""
    if folder.is_dir() and list_images(folder):
        return None
    what = "is not a folder" if not folder.is_dir() else "holds no TIFF/PNG/JPEG frames"
    return (f"{folder} {what}: put the esa/tetra3 repository's test_data/*.tiff (github.com/esa/tetra3) in "
            f"../{REAL_SKY.as_posix()}/ beside the repository, or pass --images DIR")


def missing_packages() -> str | None:
    """Which benchmark-only package is not installed, and how to install it; None when both are."""
    try:
        import sep  # noqa: F401
    except ImportError:
        return "SEP is not installed: pip install -e '.[bench]'"
    try:
        load_solver()
    except ImportError:
        return ("cedar-solve (import name tetra3) is not installed: pip install --no-deps cedar-solve "
                "(or pip install -e '.[realsky]', which pins NumPy 1.26)")
    return None


def estimate_gain(image: np.ndarray, *, cell: int = 32, min_span: float = 1.2, max_error: float = 0.1) -> float | None:
    """Gain (e-/DN) from the frame's own photon transfer: background variance against level over cells.

    Each ``cell`` x ``cell`` block gives its median level and its noise variance (from the MAD of
    horizontal neighbour differences, blind to smooth gradients and to most stars). Shot noise
    makes ``variance = const + level / gain`` whatever the pedestal and read noise; the slope is
    fitted with 3-sigma clipping. None when the levels span less than ``min_span`` (max/min, 2nd to
    98th percentile: no lever arm) or the slope's relative error exceeds ``max_error``.
    """
    a = np.asarray(image, np.float64)
    rows, cols = (a.shape[0] // cell) * cell, (a.shape[1] // cell) * cell
    if rows == 0 or cols < 2 * cell:
        return None
    blocks = a[:rows, :cols].reshape(rows // cell, cell, cols // cell, cell).swapaxes(1, 2)
    blocks = blocks.reshape(-1, cell, cell)
    level = np.median(blocks.reshape(blocks.shape[0], -1), axis=1)
    diff = np.diff(blocks, axis=2).reshape(blocks.shape[0], -1)
    mad = np.median(np.abs(diff - np.median(diff, axis=1)[:, None]), axis=1)
    var = (1.4826 * mad) ** 2 / 2.0
    lo, hi = np.percentile(level, [2, 98])
    if not (lo > 0 and hi / lo >= min_span):
        return None
    keep = (level >= lo) & (level <= hi)
    for _ in range(5):
        design = np.column_stack([np.ones(keep.sum()), level[keep]])
        coef, *_ = np.linalg.lstsq(design, var[keep], rcond=None)
        resid = var - (coef[0] + coef[1] * level)
        scale = 1.4826 * np.median(np.abs(resid[keep]))
        keep = (level >= lo) & (level <= hi) & (np.abs(resid) <= 3.0 * scale)
    design = np.column_stack([np.ones(keep.sum()), level[keep]])
    coef, res, *_ = np.linalg.lstsq(design, var[keep], rcond=None)
    dof = max(int(keep.sum()) - 2, 1)
    cov = np.linalg.inv(design.T @ design) * (float(res[0]) / dof if res.size else 0.0)
    slope, err = float(coef[1]), float(np.sqrt(max(cov[1, 1], 0.0)))
    if not (slope > 0 and err / slope <= max_error):
        return None
    return 1.0 / slope


# ----------------------------------------------------------------------------- centroiders

@dataclass(frozen=True)
class Positions:
    """One centroider's stars in a frame: x, y (px, 0-based, pixel-centre origin), flux (any unit), and
    for starlog the SNR of unsaturated stars (0 for saturated ones)."""

    x: np.ndarray
    y: np.ndarray
    flux: np.ndarray
    snr: np.ndarray | None = None
    sigma: np.ndarray | None = None  # starlog: each centroid's own uncertainty, px
    calibration: np.ndarray | None = None  # starlog: the stars a phase calibration may learn from


def starlog_positions(image: np.ndarray, saturation: float, *, gain: float, read_noise: float | None,
                      options: dict) -> dict[str, Positions]:
    """starlog's detection and every CentroidMethod on one frame (failed fits left out); PSFFIT fits
    the frame's own empirical PSF, built as ``starlog centroid --psf empirical`` builds a log's."""
    methods = list(CentroidMethod)
    epsf = frame_epsf(image, saturation, gain=gain, read_noise=read_noise, options=options)
    _, centroids = extract_stars(image, methods=methods, gain=gain, read_noise=read_noise,
                                 saturation=saturation, epsf=epsf, **options)
    out = {}
    for method, c in centroids.items():
        keep = ((c["flags"] & int(CentroidFlag.FIT_FAILED)) == 0) & np.isfinite(c["x"]) & np.isfinite(c["y"])
        snr = np.where((c["flags"] & int(CentroidFlag.SATURATED)) == 0, c["snr"], 0.0)
        out[method.value] = Positions(c["x"][keep], c["y"][keep], c["flux"][keep], snr[keep], c["sigma"][keep],
                                      phase_sample_mask(c)[keep])
    return out


def frame_epsf(image: np.ndarray, saturation: float, *, gain: float, read_noise: float | None,
               options: dict) -> EPSF | None:
    """The frame's ePSF from its bright, isolated, unsaturated stars (None: no star qualifies, PSFFIT
    then fits the Gaussian)."""
    det = detect_stars(image, saturation=saturation, **options.get("detect_options", {}))
    psf = options.get("psf_sigma") or estimate_psf_sigma(image, det, gain=gain, saturation=saturation)
    try:
        return epsf_from_frames([(image, det)], psf_sigma=psf, half_size=window_half_size(psf, options.get("window")),
                                gain=gain, read_noise=read_noise, saturation=saturation)
    except InvalidInputError:
        return None


def sep_positions(image: np.ndarray, threshold: float) -> dict[str, Positions]:
    """SEP at ``threshold`` x global RMS: isophotal barycentres and ``sep.winpos`` (bench_centroid's settings)."""
    import sep

    data = np.ascontiguousarray(image, dtype=np.float64)
    bkg = sep.Background(data)
    sub = data - bkg.back()
    objs = sep.extract(sub, threshold, err=bkg.globalrms)
    tag = f"{threshold:g}s"
    if len(objs) == 0:
        empty = Positions(np.zeros(0), np.zeros(0), np.zeros(0))
        return {f"SEP iso {tag}": empty, f"SEP winpos {tag}": empty}
    radius, _ = sep.flux_radius(sub, objs["x"], objs["y"], 6.0 * objs["a"], 0.5, subpix=5)
    sig = 2.0 / 2.35 * np.where(radius > 0, radius, 1.0)
    xw, yw, _ = sep.winpos(sub, objs["x"], objs["y"], sig)
    flux = np.asarray(objs["flux"], np.float64)
    return {f"SEP iso {tag}": Positions(np.asarray(objs["x"], np.float64), np.asarray(objs["y"], np.float64), flux),
            f"SEP winpos {tag}": Positions(np.asarray(xw, np.float64), np.asarray(yw, np.float64), flux)}


# ----------------------------------------------------------------------------- camera model

def plate_basis(x: np.ndarray, y: np.ndarray, cam: Camera, order: int) -> np.ndarray:
    """Monomials u^i v^j, i + j <= order, of the offsets (u, v) from the image centre in half-widths."""
    u, v = (x - cam.cx) / cam.half_width, (y - cam.cy) / cam.half_width
    return np.column_stack([u**i * v ** (t - i) for t in range(order + 1) for i in range(t + 1)])


def without_plate_terms(res: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Residuals (n, 2) less their least-squares polynomial field pattern (each axis)."""
    if basis.shape[0] <= basis.shape[1]:
        return res
    return res - basis @ np.linalg.lstsq(basis, res, rcond=None)[0]


# ----------------------------------------------------------------------------- matching

@dataclass(frozen=True)
class FrameComparison:
    """Per centroider: RMSE on the common stars after its own refit, its residuals and matches."""

    common: np.ndarray  # indices into the field's catalogue stars
    xy: np.ndarray  # (n_common, 2) catalogue positions of the common stars under the solved camera, px
    rmse: dict[str, float]
    residuals: dict[str, np.ndarray]  # (n_common, 2)
    matched: dict[str, int]
    identified: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = dataclass_field(default_factory=dict)
    """Per centroider: the field's catalogue stars it matched (indices into the field) and its x, y of them."""


def compare_centroiders(cam: Camera, vectors: np.ndarray, positions: dict[str, Positions], *,
                        radius: float, fit_distortion: bool = True, plate_order: int = 0) -> FrameComparison:
    """Match the catalogue stars to every centroider, keep the stars all matched, refit each (steps 4-5).

    ``plate_order`` > 0 instead keeps the solved camera and fits, per centroider, a polynomial
    field pattern of that order in (x, y) to its residuals (plate constants: its linear terms
    take the place of the pointing, roll and scale refit; the rest absorbs differential
    refraction, tilt, any smooth pattern).
    """
    cat_x, cat_y, _ = cam.project(vectors)
    idx = {name: match_nearest(cat_x, cat_y, p.x, p.y, radius) for name, p in positions.items()}
    common = np.flatnonzero(np.all([i >= 0 for i in idx.values()], axis=0)) if idx else np.zeros(0, int)
    rmse, res = {}, {}
    for name, p in positions.items():
        sel = idx[name][common]
        x, y = p.x[sel], p.y[sel]
        if common.size >= 6 and plate_order == 0:
            fitted = fit_camera(cam, vectors[common], x, y, fit_distortion=fit_distortion)
        else:
            fitted = cam
        px, py, _ = fitted.project(vectors[common])
        res[name] = np.column_stack([x - px, y - py])
        if plate_order > 0:
            res[name] = without_plate_terms(res[name], plate_basis(x, y, cam, plate_order))
        rmse[name] = float(np.sqrt(np.mean(res[name] ** 2))) if common.size else float("nan")
    xy = np.column_stack([cat_x[common], cat_y[common]])
    identified = {n: (np.flatnonzero(i >= 0), positions[n].x[i[i >= 0]], positions[n].y[i[i >= 0]])
                  for n, i in idx.items()}
    return FrameComparison(common, xy, rmse, res, {n: int((i >= 0).sum()) for n, i in idx.items()}, identified)


def field_stars(cam: Camera, catalogue: np.ndarray, shape: tuple[int, int], *, margin: float,
                isolation: float) -> np.ndarray:
    """Indices of catalogue rows (columns 2:5 = unit vector) inside the frame and isolated."""
    x, y, front = cam.project(catalogue[:, 2:5])
    rows, cols = shape
    inside = front & (x >= margin) & (x <= cols - 1 - margin) & (y >= margin) & (y <= rows - 1 - margin)
    near = np.flatnonzero(front & (x > -10) & (x < cols + 10) & (y > -10) & (y < rows + 10))
    alone = isolated(x[near], y[near], isolation)
    keep = np.zeros(x.size, bool)
    keep[near[alone]] = True
    return np.flatnonzero(inside & keep)


# ----------------------------------------------------------------------------- plate solving

def solve_frame(solver, positions: Positions, shape: tuple[int, int], *, brightest: int = 50,
                timeout_ms: int = 10000) -> Camera | None:
    """Lost-in-space solve from the brightest centroids; the camera fitted to the solver's matches
    (:func:`starlog.attitude.lost_in_space.solve_lost_in_space`). The solver's own matches use a radius of 1 %
    of the image width and may hold mismatches: :func:`refine_camera` re-matches before any comparison."""
    return solve_lost_in_space(positions.x, positions.y, positions.flux, shape, brightest=brightest,
                               timeout_ms=timeout_ms, solver=solver).camera


def refine_camera(cam: Camera, vectors: np.ndarray, magnitudes: np.ndarray, positions: Positions, *,
                  brightest: int = 50) -> tuple[Camera, int]:
    """Re-match catalogue stars to the positions with shrinking radii, refitting each time; (camera, matches).

    The first, wide-radius rounds pair only the brightest catalogue stars with the brightest
    detections, so that chance coincidences in a dense field cannot pull the fit.
    """
    bright_cat = np.argsort(magnitudes)[:brightest]
    bright_det = np.argsort(-positions.flux)[:brightest]
    n = 0
    for radius, cat, det in ((8.0, bright_cat, bright_det), (4.0, bright_cat, bright_det),
                             (2.0, slice(None), slice(None)), (2.0, slice(None), slice(None))):
        v = vectors[cat]
        x, y = positions.x[det], positions.y[det]
        px, py, _ = cam.project(v)
        idx = match_nearest(px, py, x, y, radius)
        ok = idx >= 0
        n = int(ok.sum())
        if n < 6:
            return cam, n
        cam = fit_camera(cam, v[ok], x[idx[ok]], y[idx[ok]])
    return cam, n


# ----------------------------------------------------------------------------- run and report

@dataclass(frozen=True)
class FrameResult:
    name: str
    detections: dict[str, int]
    field: int
    comparison: FrameComparison | None
    magnitudes: np.ndarray  # of the common stars
    note: str = ""
    gain: float = float("nan")  # e-/DN used for starlog
    camera: Camera | None = None  # the refined camera of a solved frame


def frame_gain(image: np.ndarray, choice: str) -> float:
    """``--gain``: a number (e-/DN), or "auto": :func:`estimate_gain`, 1 e-/DN when it cannot tell."""
    if choice != "auto":
        return float(choice)
    gain = estimate_gain(image)
    return 1.0 if gain is None else gain


@dataclass(frozen=True)
class MeasuredFrame:
    name: str
    shape: tuple[int, int]
    gain: float
    positions: dict[str, Positions]


def measure_frame(path: Path, args) -> MeasuredFrame:
    """Steps 1-2 on one image file: every centroider's positions."""
    image, saturation = load_grey(path)
    gain = frame_gain(image, args.gain)
    positions = starlog_positions(image, saturation, gain=gain, read_noise=args.read_noise,
                                  options=args.starlog_options)
    for threshold in SEP_THRESHOLDS:
        positions.update(sep_positions(image, threshold))
    return MeasuredFrame(path.name, image.shape, gain, positions)


def phase_equalised(frames: list[MeasuredFrame], *, min_snr: float = 30.0) -> list[MeasuredFrame]:
    """Investigation: every centroider also with its pixel-phase bias removed by phase-histogram equalisation.

    True sub-pixel phases of stars are uniform; a centroider biased towards (or away from) pixel
    centres bunches its measured phases. The empirical distribution F of one centroider's measured
    phases (x and y pooled, bright stars, all frames) maps each of its measured phases ``p`` to
    ``F(p) - 1/2``. Bright: starlog's unsaturated stars with SNR >= ``min_snr``; for SEP, as many of
    its brightest stars per frame as GAUSSFIT has bright ones. No catalogue is used: a
    self-calibration, like the per-log PSF width.
    """
    names = [n for n in frames[0].positions if not n.endswith("+eq")]
    maps = {}
    for n in names:
        phases = []
        for f in frames:
            p = f.positions[n]
            if p.snr is not None:
                bright = p.snr >= min_snr
            else:
                count = int((f.positions[CentroidMethod.GAUSSFIT.value].snr >= min_snr).sum())
                bright = np.argsort(-p.flux)[:count]
            phases += [p.x[bright] - np.rint(p.x[bright]), p.y[bright] - np.rint(p.y[bright])]
        maps[n] = np.sort(np.concatenate(phases))

    def equalise(v: np.ndarray, table: np.ndarray) -> np.ndarray:
        return np.rint(v) + np.searchsorted(table, v - np.rint(v)) / table.size - 0.5

    out = []
    for f in frames:
        extra = {f"{n}+eq": replace(f.positions[n], x=equalise(f.positions[n].x, maps[n]),
                                    y=equalise(f.positions[n].y, maps[n])) for n in names if maps[n].size >= 50}
        out.append(replace(f, positions={**f.positions, **extra}))
    return out


def calibration_samples(frames: list[MeasuredFrame], name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, y, sigma) a centroider's phase calibration learns from, pooled over the frames.

    starlog: the stars ``starlog centroid --phase-correction auto`` uses
    (:func:`starlog.centroiding.phase.phase_sample_mask`). SEP reports no uncertainty: per frame,
    its brightest stars, as many as GAUSSFIT's usable ones there, sigma 0.
    """
    xs, ys, ss = [], [], []
    for f in frames:
        p = f.positions[name]
        if p.calibration is not None:
            pick = np.flatnonzero(p.calibration)
            sig = p.sigma[pick]
        else:
            count = int(f.positions[CentroidMethod.GAUSSFIT.value].calibration.sum())
            pick = np.argsort(-p.flux)[:count]
            sig = np.zeros(pick.size)
        xs.append(p.x[pick])
        ys.append(p.y[pick])
        ss.append(sig)
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(ss)


def phase_corrected(frames: list[MeasuredFrame], *, harmonics: int) -> tuple[list[MeasuredFrame],
                                                                          dict[str, PhaseCalibration | str]]:
    """The frames with every centroider's pixel phase calibrated on all frames' stars (one camera,
    as one log): starlog's methods replaced by their corrected positions (what ``starlog centroid
    --phase-correction auto`` writes), SEP's kept and added corrected as ``<name>+pc``. Also each
    centroider's calibration (or why it declined)."""
    calibrations: dict[str, PhaseCalibration | str] = {}
    for name in frames[0].positions:
        x, y, sig = calibration_samples(frames, name)
        try:
            calibrations[name] = estimate_phase_calibration(x, y, sig, method=name, harmonics=harmonics)
        except InvalidInputError as err:
            calibrations[name] = str(err)
    out = []
    for f in frames:
        positions = dict(f.positions)
        for name, cal in calibrations.items():
            if isinstance(cal, str):
                continue
            p = f.positions[name]
            x, y = cal.apply(p.x, p.y)
            key = f"{name}+pc" if name.startswith("SEP") else name
            positions[key] = replace(p, x=x, y=y)
        out.append(replace(f, positions=positions))
    return out, calibrations


def compare_frame(frame: MeasuredFrame, solver, args) -> FrameResult:
    """Steps 3-5 on one measured frame."""
    positions = frame.positions
    reference = positions[CentroidMethod.GAUSSFIT.value]
    if args.only:
        positions = {k: v for k, v in positions.items() if k in args.only}
    detections = {name: int(p.x.size) for name, p in positions.items()}
    cam = solve_frame(solver, reference, frame.shape)
    if cam is None:
        return FrameResult(frame.name, detections, 0, None, np.zeros(0), "not solved", frame.gain)
    catalogue = solver.star_table
    field = field_stars(cam, catalogue, frame.shape, margin=args.margin, isolation=2.0 * args.match_radius)
    cam, matched = refine_camera(cam, catalogue[field, 2:5], catalogue[field, 5], reference)
    if matched < 10:
        return FrameResult(frame.name, detections, 0, None, np.zeros(0), f"solution not confirmed ({matched} stars)",
                           frame.gain)
    field = field_stars(cam, catalogue, frame.shape, margin=args.margin, isolation=2.0 * args.match_radius)
    comparison = compare_centroiders(cam, catalogue[field, 2:5], positions, radius=args.match_radius,
                                     fit_distortion=not args.no_distortion, plate_order=args.plate_order)
    comparison = replace(comparison, identified={n: (field[rows], x, y) for n, (rows, x, y)
                                                 in comparison.identified.items()})
    return FrameResult(frame.name, detections, int(field.size), comparison, catalogue[field[comparison.common], 5],
                       gain=frame.gain, camera=cam)


def pooled_rmse(results: list[FrameResult], name: str) -> float:
    res = [r.comparison.residuals[name] for r in results if r.comparison is not None and r.comparison.common.size]
    return float(np.sqrt(np.mean(np.concatenate(res) ** 2))) if res else float("nan")


def best_ratio(pooled: dict[str, float]) -> tuple[str, str, float]:
    """(best starlog method, best SEP setting, ratio of their pooled RMSEs)."""
    ours = {k: v for k, v in pooled.items() if not k.startswith("SEP") and not k.endswith("+eq")}
    theirs = {k: v for k, v in pooled.items() if k.startswith("SEP") and not k.endswith(("+eq", "+pc"))}
    a = min(ours, key=ours.get)
    b = min(theirs, key=theirs.get)
    return a, b, ours[a] / theirs[b]


def print_table(results: list[FrameResult], names: list[str]) -> dict[str, float]:
    width = max(len(n) for n in names) + 2
    print(f"{'frame':<34}{'gain':>6}{'field':>6}{'common':>7}  " + "".join(f"{n:>{width}}" for n in names))
    for r in results:
        if r.comparison is None:
            print(f"{r.name[:33]:<34}{r.gain:>6.3f}{'':>6}{'':>7}  {r.note}")
            continue
        c = r.comparison
        print(f"{r.name[:33]:<34}{r.gain:>6.3f}{r.field:>6}{c.common.size:>7}  "
              + "".join(f"{c.rmse[n]:>{width}.4f}" for n in names))
    n_common = sum(r.comparison.common.size for r in results if r.comparison is not None)
    pooled = {n: pooled_rmse(results, n) for n in names}
    print(f"{'pooled RMSE px':<40}{'':>6}{n_common:>7}  " + "".join(f"{pooled[n]:>{width}.4f}" for n in names))
    det = {n: sum(r.detections[n] for r in results) / max(len(results), 1) for n in names}
    print(f"{'detections / frame':<40}{'':>6}{'':>7}  " + "".join(f"{det[n]:>{width}.1f}" for n in names))
    solved = [r for r in results if r.comparison is not None]
    n_field = sum(r.field for r in solved)
    matched = {n: sum(r.comparison.matched[n] for r in solved) / max(n_field, 1) for n in names}
    print(f"{'catalogue stars matched (fraction)':<40}{n_field:>6}{'':>7}  "
          + "".join(f"{matched[n]:>{width}.3f}" for n in names))
    return pooled


def bootstrap_ratio(results: list[FrameResult], best: str, best_sep: str, *, draws: int = 2000,
                    seed: int = 1) -> tuple[float, float]:
    """95 % interval of the pooled-RMSE ratio, resampling the common stars (the refits held fixed)."""
    done = [r.comparison for r in results if r.comparison is not None and r.comparison.common.size]
    if not done:
        return float("nan"), float("nan")
    a = np.concatenate([c.residuals[best] for c in done])
    b = np.concatenate([c.residuals[best_sep] for c in done])
    sa, sb = (a**2).sum(axis=1), (b**2).sum(axis=1)
    rng = np.random.default_rng(seed)
    pick = rng.integers(0, sa.size, (draws, sa.size))
    ratios = np.sqrt(sa[pick].sum(axis=1) / sb[pick].sum(axis=1))
    lo, hi = np.percentile(ratios, [2.5, 97.5])
    return float(lo), float(hi)


def print_calibrations(calibrations: dict) -> None:
    """Each centroider's S-curve as calibrated (first harmonic per axis), or why it declined."""
    print("\npixel-phase calibration (S-curve amplitude px, negative: pulled towards pixel centres; applied / "
          "estimate +- standard error, distinct stars)")
    for name, cal in calibrations.items():
        if isinstance(cal, str):
            print(f"  {name:<18} declined: {cal}")
            continue
        print(f"  {name:<18} x {cal.amplitude_x[0]:+.4f} / {cal.estimate_x[0]:+.4f} +- {cal.error_x[0]:.4f}   "
              f"y {cal.amplitude_y[0]:+.4f} / {cal.estimate_y[0]:+.4f} +- {cal.error_y[0]:.4f}   {cal.n_stars}")


def print_by_magnitude(results: list[FrameResult], names: list[str]) -> None:
    """Pooled RMSE of the common stars per catalogue-magnitude bin."""
    done = [r for r in results if r.comparison is not None and r.comparison.common.size]
    if not done:
        return
    mags = np.concatenate([r.magnitudes for r in done])
    width = max(len(n) for n in names) + 2
    print(f"\n{'magnitude':<16}{'stars':>6}  " + "".join(f"{n:>{width}}" for n in names))
    for lo, hi in zip(MAG_BINS[:-1], MAG_BINS[1:]):
        sel = (mags >= lo) & (mags < hi)
        if not sel.any():
            continue
        row = []
        for n in names:
            res = np.concatenate([r.comparison.residuals[n] for r in done])[sel]
            row.append(float(np.sqrt(np.mean(res**2))))
        print(f"{f'{lo:g} .. {hi:g}':<16}{int(sel.sum()):>6}  " + "".join(f"{v:>{width}.4f}" for v in row))


def frame_record(r: FrameResult) -> dict:
    """A frame's figures for ``--json``, with every common star: catalogue x, y, magnitude, residuals (dx, dy)."""
    c = r.comparison
    stars = [] if c is None else [
        {"x": float(c.xy[i, 0]), "y": float(c.xy[i, 1]), "mag": float(r.magnitudes[i]),
         "residual": {n: [float(v) for v in res[i]] for n, res in c.residuals.items()}}
        for i in range(c.common.size)]
    return {"name": r.name, "gain": r.gain, "field": r.field, "note": r.note, "detections": r.detections,
            "matched": c.matched if c else {}, "common": int(c.common.size) if c else 0,
            "rmse": c.rmse if c else {}, "stars": stars}


def parse_options(pairs: list[str]) -> dict:
    """KEY=VALUE pairs (VALUE as JSON, else a string) for extract_stars."""
    out = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=EPILOG)
    ap.add_argument("--images", type=Path, default=None, help="folder of TIFF/PNG/JPEG frames")
    ap.add_argument("--quick", action="store_true",
                    help="the same run (it takes about 7 s): the pixel-phase calibration is learnt from the "
                         "frames' own stars, so a subset of the frames would change the figures (a calibration from fewer "
                         "distinct stars)")
    ap.add_argument("--gain", default="auto",
                    help="camera gain e-/DN, or 'auto' (default): from each frame's background photon transfer, "
                         "1 when that cannot tell")
    ap.add_argument("--read-noise", type=float, default=None, help="read noise e- (default: from the frame)")
    ap.add_argument("--match-radius", type=float, default=2.0, help="catalogue match radius, px")
    ap.add_argument("--margin", type=float, default=8.0, help="catalogue stars kept this far inside the edges, px")
    ap.add_argument("--no-distortion", action="store_true", help="refit without the radial distortion term")
    ap.add_argument("--starlog-option", action="append", default=[], metavar="KEY=VALUE",
                    help="extra keyword option of starlog.centroiding.extract_stars (JSON value), repeatable")
    ap.add_argument("--plate-order", type=int, default=0,
                    help="fit a polynomial field pattern of this order instead of the camera refit (investigation)")
    ap.add_argument("--phase-correction", choices=("auto", "off"), default="auto",
                    help="auto (default): every centroider's pixel phase calibrated on the frames' own stars "
                         "(starlog.centroiding.phase, as starlog centroid --phase-correction auto); starlog's columns "
                         "corrected, SEP's shown as they are and corrected (+pc)")
    ap.add_argument("--phase-harmonics", type=int, default=1,
                    help="harmonics of the S-curve per axis the calibration estimates (default 1)")
    ap.add_argument("--phase-equalise", action="store_true",
                    help="also every centroider with its pixel-phase bias self-calibrated (investigation)")
    ap.add_argument("--only", nargs="+", default=None, metavar="NAME",
                    help="compare only these centroiders (names as in the table's header)")
    ap.add_argument("--by-mag", action="store_true", help="also print the RMSE per catalogue magnitude")
    ap.add_argument("--json", type=Path, default=None, help="write the figures to this JSON file")
    ap.add_argument("--degraded", action="store_true",
                    help="also run on degraded copies of the frames, built in a temporary folder: 8-bit, JPEG at "
                         "qualities 95/85/70, colour JPEG, Bayer-demosaiced colour, 2x2 binned, defocused (Gaussian "
                         "blur of 1 px); about 2 minutes for the eight on a 2-core machine")
    ap.add_argument("--simulated", action="store_true",
                    help="also run on the simulator's cameras (tools/sim_cameras.py: the catalogue's sky rendered with "
                         "other PSFs and sensors, in a temporary folder); about 4 minutes for the eight")
    ap.add_argument("--camera", action="append", default=[], metavar="NAME=DIR",
                    help="another camera: a folder of its frames, scored like the others (repeatable)")
    ap.add_argument("--loco", action="store_true",
                    help="leave-one-camera-out over every camera of the run (tools/loco.py): per camera, the default "
                         "method picked on the others and its held-out ratio, and the method starlog trusts on the "
                         "camera's own frames, checked against the benchmark's figure")
    ap.add_argument("--loco-with", action="append", default=[], type=Path, metavar="RUN.json",
                    help="with --loco: the cameras of an earlier run (its --json) as another setting to pick from")
    args = ap.parse_args(argv)
    args.starlog_options = parse_options(args.starlog_option)
    args.images = args.images or default_images()
    return args


@dataclass
class BenchRun:
    """One run of the protocol on a folder of frames: per-frame results, pooled RMSEs, the headline ratio."""

    results: list[FrameResult]
    names: list[str]
    pooled: dict[str, float]
    best: str
    best_sep: str
    ratio: float
    calibrations: dict


def run_folder(folder: Path, solver, args) -> BenchRun:
    """Steps 1-6 on every frame of ``folder`` (with the pixel-phase calibration as ``args`` say)."""
    frames = [measure_frame(p, args) for p in list_images(folder)]
    calibrations: dict = {}
    if args.phase_correction == "auto":
        frames, calibrations = phase_corrected(frames, harmonics=args.phase_harmonics)
    if args.phase_equalise:
        frames = phase_equalised(frames)
    results = [compare_frame(f, solver, args) for f in frames]
    names = list(results[0].detections)
    pooled = {n: pooled_rmse(results, n) for n in names}
    best, best_sep, ratio = best_ratio(pooled)
    return BenchRun(results, names, pooled, best, best_sep, ratio, calibrations)


def print_run(run: BenchRun, args) -> None:
    """The tables and headline lines of one run."""
    print(f"# {len(run.results)} frames from {args.images}; gain {args.gain} e-/DN, read noise "
          f"{args.read_noise if args.read_noise is not None else 'from the frame'}; match radius "
          f"{args.match_radius} px, margin {args.margin} px, distortion {'off' if args.no_distortion else 'k r^2'}, "
          f"plate terms of order {args.plate_order}; "
          f"starlog options {args.starlog_options or 'defaults'}")
    print("# RMSE px per axis on the stars matched by every centroider, camera refitted per centroider")
    pooled = print_table(run.results, run.names)
    best, best_sep = run.best, run.best_sep
    lo, hi = bootstrap_ratio(run.results, best, best_sep)
    print(f"\nbest starlog {best} {pooled[best]:.4f} px / best SEP {best_sep} {pooled[best_sep]:.4f} px = "
          f"{run.ratio:.3f} (95 % bootstrap over stars {lo:.3f} .. {hi:.3f})")
    corrected = {k[:-3]: v for k, v in pooled.items() if k.endswith("+pc")}
    if corrected:
        pc_sep = min(corrected, key=corrected.get)
        print(f"the same, SEP phase-corrected too: best starlog {best} {pooled[best]:.4f} px / best SEP {pc_sep}+pc "
              f"{corrected[pc_sep]:.4f} px = {pooled[best] / corrected[pc_sep]:.3f}")
    if run.calibrations:
        print_calibrations(run.calibrations)
    equalised = {k[:-3]: v for k, v in pooled.items() if k.endswith("+eq")}
    if equalised:
        eq, eq_sep, eq_ratio = best_ratio(equalised)
        print(f"investigation, both phase-equalised: best starlog {eq}+eq {equalised[eq]:.4f} px / best SEP "
              f"{eq_sep}+eq {equalised[eq_sep]:.4f} px = {eq_ratio:.3f}; against SEP as it is: "
              f"{equalised[eq] / pooled[best_sep]:.3f}")
    if args.by_mag:
        print_by_magnitude(run.results, run.names)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    problem = missing_images(args.images) or missing_packages()
    if problem:
        print(f"bench_realsky: {problem}", file=sys.stderr)
        return 2
    solver = load_solver()
    t0 = time.perf_counter()
    run = run_folder(args.images, solver, args)
    print_run(run, args)
    cameras = []
    if args.loco or args.simulated or args.camera:
        cameras = score_cameras(args, solver, run)
    elif args.degraded:
        print_degraded(args, solver, run)
    print(f"# {time.perf_counter() - t0:.1f} s; load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    if args.json:
        lo, hi = bootstrap_ratio(run.results, run.best, run.best_sep)
        payload = {"frames": [frame_record(r) for r in run.results], "pooled": run.pooled, "best_starlog": run.best,
                   "best_sep": run.best_sep, "ratio": run.ratio, "ratio_95": [lo, hi],
                   "phase_calibrations": {k: v if isinstance(v, str) else v.to_dict()
                                          for k, v in run.calibrations.items()},
                   "cameras": [c.to_dict() for c in cameras]}
        args.json.write_text(json.dumps(payload, indent=2))
    return 0


# ----------------------------------------------------------------------------- cameras, leave-one-camera-out

def camera_folders(args) -> list[tuple[str, Any]]:
    """Every camera of the run after the real frames, as (name, writer of its frames into a folder): the
    degraded copies (``--degraded``), the simulator's cameras (``--simulated``), the folders of ``--camera``."""
    import shutil

    import sim_cameras

    out: list[tuple[str, Any]] = []
    if args.degraded:
        out += [(kind, lambda folder, k=kind: write_degraded(args.images, k, folder)) for kind in DEGRADED]
    if args.simulated:
        out += [(name, lambda folder, n=name: sim_cameras.write_camera(n, folder, write_degraded))
                for name in sim_cameras.SIM_CAMERAS]
    for spec in args.camera:
        name, _, folder = spec.partition("=")
        out.append((name, lambda dest, src=Path(folder): [shutil.copy2(p, dest) for p in list_images(src)]))
    return out


def score_cameras(args, solver, original: BenchRun) -> list:
    """Every camera of the run scored (``loco.score_camera``), one line each; with ``--loco`` the held-out table."""
    import tempfile

    import loco

    catalogue = solver.star_table
    setting = args.json.stem if args.json else "this run"
    name = args.images.name or "frames"
    scores = [loco.score_camera(name, setting, original, catalogue)]
    print("\ncameras (pooled RMSE / best SEP on each camera's common stars; the method starlog trusts there)")
    print_camera_line(scores[0])
    for camera, write in camera_folders(args):
        with tempfile.TemporaryDirectory(prefix="realsky-") as tmp:
            write(Path(tmp))
            run = run_folder(Path(tmp), solver, args)
        scores.append(loco.score_camera(camera, setting, run, catalogue))
        print_camera_line(scores[-1])
        sys.stdout.flush()
    if args.loco:
        loco.print_loco(scores + loco.load_scores(args.loco_with), setting)
    return scores


def print_camera_line(score) -> None:
    ratios = "  ".join(f"{m} {v:.3f}" for m, v in score.ratios.items())
    print(f"{score.camera:<26}{score.common:>6}  trusted {score.trusted} ({'ok' if score.trusted_ok else 'NOT the best'}"
          f")  {ratios}  [{score.best_sep}]")


# ----------------------------------------------------------------------------- degraded copies

DEGRADED = ("8-bit", "jpeg-95", "jpeg-85", "jpeg-70", "colour-jpeg-90", "bayer-demosaiced", "binned-2x2",
            "defocused-1.0")
"""``--degraded``: the frames as a cheaper camera or pipeline would give them: 8 bits (the top 8 of the 16),
JPEG of that 8-bit frame at three qualities, a colour JPEG (the 8-bit frame in three channels of unequal
response, quality 90, chroma subsampled 4:2:0 as cameras write them), a colour sensor's frame (the 16-bit frame
through an RGGB Bayer mosaic of unequal channel responses, demosaiced by OpenCV, 16-bit colour), 2 x 2 binned
(the mean of each block, 16 bits) and defocused (a Gaussian blur of sigma 1 px, 16 bits). Colour frames are
read as the sum of their channels (step 1)."""

CHANNEL_RESPONSE = (0.6, 1.0, 0.8)
"""Relative response of the blue, green and red channels of the colour copies."""


def write_degraded(images: Path, kind: str, folder: Path) -> None:
    """The frames of ``images`` degraded as ``kind`` (:data:`DEGRADED`) into ``folder`` (PNG, JPEG or TIFF)."""
    import cv2
    import tifffile

    for path in list_images(images):
        image, _ = load_grey(path)
        image = np.asarray(image)
        stem = folder / path.stem
        if kind == "8-bit" or kind.startswith("jpeg"):
            eight = (image.astype(np.uint32) * 255 // int(np.iinfo(image.dtype).max)).astype(np.uint8)
            if kind == "8-bit":
                cv2.imwrite(str(stem) + ".png", eight)
            else:
                cv2.imwrite(str(stem) + ".jpg", eight, [cv2.IMWRITE_JPEG_QUALITY, int(kind.split("-")[1])])
        elif kind == "colour-jpeg-90":
            eight = image.astype(np.float64) * 255 / float(np.iinfo(image.dtype).max)
            colour = np.stack([np.rint(eight * r) for r in CHANNEL_RESPONSE], axis=-1).astype(np.uint8)
            cv2.imwrite(str(stem) + ".jpg", colour, [cv2.IMWRITE_JPEG_QUALITY, 90])
        elif kind == "bayer-demosaiced":
            tifffile.imwrite(str(stem) + ".tiff", demosaiced(image))
        elif kind == "binned-2x2":
            rows, cols = image.shape[0] // 2 * 2, image.shape[1] // 2 * 2
            blocks = image[:rows, :cols].astype(np.float64).reshape(rows // 2, 2, cols // 2, 2)
            tifffile.imwrite(str(stem) + ".tiff", np.rint(blocks.mean(axis=(1, 3))).astype(image.dtype))
        else:
            blurred = cv2.GaussianBlur(image.astype(np.float64), (0, 0), float(kind.split("-")[1]))
            tifffile.imwrite(str(stem) + ".tiff", np.rint(blurred).astype(image.dtype))


def demosaiced(image: np.ndarray) -> np.ndarray:
    """``image`` as a colour sensor would give it: each pixel keeps the channel of an RGGB Bayer mosaic,
    scaled by that channel's :data:`CHANNEL_RESPONSE`, and OpenCV interpolates the other two (BGR, the
    image's dtype)."""
    import cv2

    blue, green, red = CHANNEL_RESPONSE
    rows, cols = np.indices(image.shape)
    response = np.where((rows % 2 == 0) & (cols % 2 == 0), red,
                        np.where((rows % 2 == 1) & (cols % 2 == 1), blue, green))
    mosaic = np.rint(image.astype(np.float64) * response).astype(image.dtype)
    return cv2.cvtColor(mosaic, cv2.COLOR_BayerBG2BGR)


def print_degraded(args, solver, original: BenchRun) -> None:
    """``--degraded``: the protocol on each degraded copy of the frames (built in a temporary folder, removed
    after), one line each: best starlog against best SEP, and each starlog method's pooled RMSE."""
    import tempfile

    ours = [n for n in original.names if not n.startswith("SEP")]
    print(f"\ndegraded copies (pooled RMSE px on each copy's common stars)\n{'copy':<16}{'common':>7}  "
          + "".join(f"{n:>16}" for n in ours) + f"{'best SEP':>24}  ratio")
    for kind in DEGRADED:
        with tempfile.TemporaryDirectory(prefix="realsky-") as tmp:
            write_degraded(args.images, kind, Path(tmp))
            run = run_folder(Path(tmp), solver, args)
        common = sum(r.comparison.common.size for r in run.results if r.comparison is not None)
        print(f"{kind:<16}{common:>7}  " + "".join(f"{run.pooled[n]:>16.4f}" for n in ours)
              + f"{run.best_sep:>18} {run.pooled[run.best_sep]:.4f}  {run.ratio:.3f} ({run.best})")


if __name__ == "__main__":
    sys.exit(main())
