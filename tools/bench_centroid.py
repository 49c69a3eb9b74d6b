"""Benchmark of starlog's detection and centroid methods against the truth, the Cramer-Rao
bound, SEP and photutils (benchmark-only dependencies: sep, photutils).

Simulated frames (starlog.sim): isolated stars on a sky of 20 e-/px, read noise 3 e-, gain 1,
bias 100 DN, 16-bit ADC; three flux regimes x three PSF sigmas. The star field of a regime is
fixed and re-exposed ``--reps`` times (fresh noise), so each star has a per-star RMSE over
noise realisations, compared to its own Cramer-Rao bound (at its pixel phase, known flux, sky
and PSF; ``starlog.centroiding.centroid_crb``).

Columns: compl = matched stars / true stars (match radius 3 px; stars are >= 30 px apart); false = unmatched
detections per frame; rmse = per-axis RMS error of matched stars about the truth, px;
bias = mean (x, y) error, px; rmse/crb = median over stars of per-star RMSE / bound;
sig/rmse = median over stars of (reported sigma, RMS over realisations) / per-star RMSE;
fps = frames per second on one core (detection + PSF estimate + that method; SEP: background +
extract + flux_radius + winpos; photutils: starlog's detection + centroid_2dg), from the median
frame time over the realisations; fps* = the same with the PSF sigma known (no estimate). The
speed targets are judged on fps*, because that is how `starlog centroid` runs: it estimates the
PSF width once per log and passes it to every frame (fps shows the cost of re-estimating it).

PSFFIT fits the empirical PSF (ePSF) of each regime, built as ``starlog centroid`` builds it
(``starlog.centroiding.epsf.epsf_from_frames``) from ``--epsf-frames`` further exposures of the same
field (not used for the errors; its time is not in fps). The non-Gaussian section renders the
stars with a pixel-integrated Moffat (beta 2.5) or Airy PSF of the same FWHM as the Gaussian of
sigma 1.2 px (starlog.sim.profiles) and compares to that PSF's own bound
(``starlog.centroiding.crb.centroid_crb_psf``); its column sys = RMS error of the method on the
noise-free frame (the systematic, pixel-phase part a wrong PSF model leaves), px.


Artefact run (200 hot pixels + 40 cosmic-ray tracks per 1024x1024 frame, as many per pixel in a
smaller one; ``add_artifacts``): every realisation is exposed twice from one noise seed, clean and
with artefacts, and every method runs with its robust windows (the default) and without
(``robust=False``) on both: RMSE clean vs with artefacts, false detections per frame, RMSE against
SEP on the same frames (and on the stars both matched), and the cost of the masking on the clean
frames (CPU time with and without, the least of 20 calls each on every clean frame).

Dense artefact run (512x512 frames, hot pixels on 3e-4 of the pixels and 20 cosmic-ray tracks a
frame; PSF sigma 1.2 and 2.0): false detections a frame once the detections only an artefact made
are left out (flag ARTEFACT, ``starlog.centroiding.artefact_detections``), and before; RMSE against the
clean frames and SEP; true stars left out as artefacts. Every table takes starlog's detections as
the centroid stage keeps them.

One module of over 500 lines: its sections share the simulated fields, the matching to the truth,
SEP's extraction and the judging of the targets.

Run: python tools/bench_centroid.py [--quick] [--reps N] [--no-photutils] [--artifacts-only] [--no-nongaussian]
"""



from __future__ import annotations

import argparse
import math
import os
import sys
import time
import warnings
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_targets import Targets  # noqa: E402
from starlog.centroiding import (  # noqa: E402
    CentroidFlag,
    CentroidMethod,
    artefact_detections,
    centroid_crb,
    estimate_psf_sigma,
    extract_stars,
    measure_centroids,
)
from starlog.centroiding.crb import centroid_crb_psf  # noqa: E402
from starlog.centroiding.epsf import epsf_from_frames  # noqa: E402
from starlog.centroiding.extract import artefact_candidates  # noqa: E402
from starlog.centroiding.psf_width import window_half_size  # noqa: E402
from starlog.detect import detect_stars  # noqa: E402
from starlog.sim.camera import CameraModel  # noqa: E402
from starlog.sim.profiles import AIRY_FWHM_PER_LAMBDA_D, AiryPSF, MoffatPSF, render_profile_stars  # noqa: E402
from starlog.sim.psf import render_stars  # noqa: E402

SKY, RN, GAIN, BIAS = 20.0, 3.0, 1.0, 100.0
HOT_PIXELS, CR_TRACKS = 200, 40  # per 1024x1024 frame; a smaller frame gets as many per pixel
REGIMES = {"bright": (2e4, 1e5), "medium": (2e3, 8e3), "faint": (250.0, 800.0)}
SIGMAS = (0.7, 1.2, 2.0)
METHODS = [m for m in CentroidMethod]
MATCH = 3.0
QUICK_SIZE, FULL_SIZE = 512, 1024
EPILOG = """\
run time on a 2-core machine: --quick (512x512 frames, 50 stars, 4 realisations) about 25 s; the full
run (1024x1024, 12 realisations) about 5 minutes.
exit status: 1 when a target is missed, 0 when all are met. The masking-cost targets are informational
(a miss prints as MISS and does not fail the run): other jobs on a shared machine move them by more than
their margin. --quick judges the accuracy, completeness and artefact-vs-clean targets; the speed,
false-detection and artefact-vs-SEP targets are set for the full run and print as n/a, with the reason
on one line. The dense artefact run's frames are 512x512 in both runs: --quick judges its false detections
(4 frames) but not its RMSE against SEP.
"""
# Targets whose miss is printed but does not fail the run, and why.
INFORMATIONAL = {
    "reference": "WINPOS is SExtractor's windowed position, the estimator SEP users know, kept beside starlog's "
                 "methods: its Gaussian window has the PSF's width, which is not the optimal weight of a photon-limited "
                 "star, so it is not a default and its bound is not a target",
    "method_sep": "RMSE with artefacts against SEP's where the method's RMSE on the clean frames is already above "
                  "SEP's with artefacts (GRADIENT, faint s=2.0): the method's own accuracy on faint wide PSFs, which "
                  "no handling of artefacts can bring under SEP; its artefact-vs-clean target is judged",
    "cost": "masking cost: a CPU-time ratio of calls of 1-9 ms, which other jobs on a shared machine move by more "
            "than its margin (MOMENT, faint s=2.0: 10 % idle, 22 % at load average 1.7)",
}


def _against_sep(clean: float, sep_art: float) -> str:
    """The kind of a method's "RMSE with artefacts <= SEP's" target: judged ("art_sep") when the method's
    RMSE on the clean frames is within SEP's with artefacts, informational otherwise ("method_sep")."""
    return "art_sep" if clean <= sep_art else "method_sep"


# Targets set for the full run that the quick run's 512x512 frames and 4 realisations cannot judge, and why.
NOT_AT_QUICK_SIZE = {
    "speed": "--quick: speed against SEP is set on 1024x1024 frames; on 512x512 SEP's per-pixel time is a "
             "quarter, the methods' time per call (about 1.5 ms) is not",
    "false": "--quick: at most 2 false detections per 1024x1024 frame; 4 frames of 512x512 are one such "
             "frame's worth, too few detections to tell a rate of 1 from 3",
    "art_sep": "--quick: RMSE with artefacts against SEP's; 4 realisations cannot order two RMSEs a few % apart "
               "(faint s=2.0: 0.5 % apart in the full run)",
}



def star_field(rng: np.random.Generator, shape: tuple[int, int], n: int, margin: int = 20, sep: float = 30.0):
    xs: list[float] = []
    ys: list[float] = []
    while len(xs) < n:
        x = rng.uniform(margin, shape[1] - 1 - margin)
        y = rng.uniform(margin, shape[0] - 1 - margin)
        if all((x - a) ** 2 + (y - b) ** 2 > sep * sep for a, b in zip(xs, ys)):
            xs.append(x)
            ys.append(y)
    return np.array(xs), np.array(ys)


def artifact_counts(size: int) -> tuple[int, int]:
    """Hot pixels and cosmic-ray tracks in a ``size`` x ``size`` frame: the full run's density."""
    area = (size / 1024) ** 2
    return round(HOT_PIXELS * area), round(CR_TRACKS * area)


def add_artifacts(expected: np.ndarray, rng: np.random.Generator, n_hot: int, n_cr: int) -> np.ndarray:
    img = expected.copy()
    rows, cols = img.shape
    hy, hx = rng.integers(0, rows, n_hot), rng.integers(0, cols, n_hot)
    img[hy, hx] += rng.uniform(300, 5000, n_hot)
    layer = np.zeros_like(img, dtype=np.float32)
    for _ in range(n_cr):
        x0, y0 = rng.uniform(5, cols - 5), rng.uniform(5, rows - 5)
        length, ang = rng.uniform(0, 10), rng.uniform(0, np.pi)
        x1, y1 = x0 + length * np.cos(ang), y0 + length * np.sin(ang)
        val = float(rng.uniform(500, 5000))
        p0 = (int(round(x0 * 16)), int(round(y0 * 16)))
        p1 = (int(round(x1 * 16)), int(round(y1 * 16)))
        cv2.line(layer, p0, p1, val, thickness=1, lineType=cv2.LINE_AA, shift=4)
    return img + layer


def match(det_x, det_y, tx, ty):
    """Greedy one-to-one nearest matching; returns index of detection per truth (-1 = none)."""
    out = np.full(tx.size, -1)
    if det_x.size == 0:
        return out
    d = np.hypot(det_x[None, :] - tx[:, None], det_y[None, :] - ty[:, None])
    used = np.zeros(det_x.size, bool)
    for i in np.argsort(d.min(axis=1)):
        j = np.argmin(np.where(used, np.inf, d[i]))
        if d[i, j] <= MATCH:
            out[i] = j
            used[j] = True
    return out


def real_detections(img: np.ndarray, psf: float):
    """starlog's detections of a frame as the centroid stage keeps them (those only an artefact made
    left out), all of them, and the PSF sigma estimated from them (``psf`` when none)."""
    every, _ = extract_stars(img, methods=[METHODS[0]], gain=GAIN)
    psf_est = estimate_psf_sigma(img, every, gain=GAIN) if every.size else psf
    return every[(every["flags"] & CentroidFlag.ARTEFACT) == 0], every, psf_est


def sep_extract(img: np.ndarray):
    import sep

    data = img.astype(np.float64)
    bkg = sep.Background(data)
    sub = data - bkg.back()
    objs = sep.extract(sub, 1.5, err=bkg.globalrms)
    if len(objs) == 0:
        return np.zeros(0), np.zeros(0)
    r, _ = sep.flux_radius(sub, objs["x"], objs["y"], 6.0 * objs["a"], 0.5, subpix=5)
    sig = 2.0 / 2.35 * np.where(r > 0, r, 1.0)
    xw, yw, _ = sep.winpos(sub, objs["x"], objs["y"], sig)
    return xw, yw


def photutils_2dg(img: np.ndarray, xs: np.ndarray, ys: np.ndarray, bkg: np.ndarray, psf: float):
    from photutils.centroids import centroid_2dg

    h = max(3, int(np.ceil(3 * psf)))
    out = np.full((xs.size, 2), np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for k, (x, y) in enumerate(zip(xs, ys)):
            xi, yi = int(round(x)), int(round(y))
            cut = img[yi - h : yi + h + 1, xi - h : xi + h + 1].astype(np.float64) - bkg[k]
            cx, cy = centroid_2dg(cut)
            out[k] = (xi - h + cx, yi - h + cy)
    return out


def _truth_and_bound(flux_range, psf, args, rng, profile=None):
    """A fixed star field of the regime, its expected image and each star's Cramer-Rao bound
    (``profile``: a Moffat or Airy PSF instead of the Gaussian of sigma ``psf``)."""
    shape = (args.size, args.size)
    tx, ty = star_field(rng, shape, args.nstars)
    tf = rng.uniform(*flux_range, tx.size)
    px, py = tx - np.rint(tx), ty - np.rint(ty)
    if profile is not None:
        expected = SKY + render_profile_stars(shape, tx, ty, tf, profile)
        crb_x = np.array([centroid_crb_psf(flux=f, pixel_psf=profile.pixel_values, sky=SKY, read_noise=RN,
                                           x_phase=a, y_phase=b) for f, a, b in zip(tf, px, py)])
        crb_y = np.array([centroid_crb_psf(flux=f, pixel_psf=profile.pixel_values, sky=SKY, read_noise=RN,
                                           x_phase=b, y_phase=a) for f, a, b in zip(tf, px, py)])
        return tx, ty, expected, np.sqrt(0.5 * (crb_x**2 + crb_y**2))
    expected = SKY + render_stars(shape, tx, ty, tf, psf)
    crb_x = centroid_crb(flux=tf, psf_sigma=psf, sky=SKY, read_noise=RN, x_phase=px, y_phase=py)
    crb_y = centroid_crb(flux=tf, psf_sigma=psf, sky=SKY, read_noise=RN, x_phase=py, y_phase=px)
    return tx, ty, expected, np.sqrt(0.5 * (crb_x**2 + crb_y**2))


def build_regime_epsf(make_expected, cam, rng, frames):
    """The regime's ePSF from ``frames`` extra exposures, as ``starlog centroid`` builds a log's."""
    images = [cam.expose(make_expected(), rng) for _ in range(frames)]
    dets = [detect_stars(img) for img in images]
    psf = float(np.median([estimate_psf_sigma(i, d, gain=GAIN) for i, d in zip(images, dets) if d.size]))
    return epsf_from_frames(zip(images, dets), psf_sigma=psf, half_size=window_half_size(psf, None), gain=GAIN)


def _record(err, r, key, idx, x, y, tx, ty):
    """Errors of the positions (x, y) matched to the truth by ``idx`` (-1: unmatched)."""
    ok = idx >= 0
    err[key][r, ok, 0] = x[idx[ok]] - tx[ok]
    err[key][r, ok, 1] = y[idx[ok]] - ty[ok]


def _measure_frame(img, r, psf, tx, ty, args, acc):
    """Detection, PSF estimate, every method, SEP (and photutils) on one realisation."""
    t_start = time.perf_counter()
    det = detect_stars(img)
    t1 = time.perf_counter()
    psf_est = estimate_psf_sigma(img, det, gain=GAIN) if det.size else psf
    acc["t_psf"].append(time.perf_counter() - t1)
    tables = {}
    for m in METHODS:
        t0 = time.perf_counter()
        tables[m] = measure_centroids(img, det, method=m, gain=GAIN, psf_sigma=psf_est,
                                      epsf=acc["epsf"] if m is CentroidMethod.PSFFIT else None)
        acc["tm"][m.value].append(time.perf_counter() - t0)
    t0 = time.perf_counter()  # the centroid stage's drop of detections only an artefact made
    kept = ~artefact_detections(img, det, psf_sigma=psf_est, gain=GAIN, candidates=artefact_candidates(det, tables.values()))
    acc["t_det"].append(t1 - t_start + time.perf_counter() - t0)
    det = det[kept]
    idx = match(det["x"], det["y"], tx, ty)
    acc["found"][r] = (idx >= 0).sum()
    acc["false"][r] = det.size - (idx >= 0).sum()
    ok = idx >= 0
    for m, c in tables.items():
        c = c[kept]
        _record(acc["err"], r, m.value, idx, c["x"], c["y"], tx, ty)
        acc["sig"][m.value][r, ok] = c["sigma"][idx[ok]]
    t0 = time.perf_counter()
    sx, sy = sep_extract(img)
    acc["tm"]["SEP winpos"].append(time.perf_counter() - t0)
    sidx = match(sx, sy, tx, ty)
    acc["sep_found"][r] = (sidx >= 0).sum()
    acc["sep_false"][r] = sx.size - (sidx >= 0).sum()
    _record(acc["err"], r, "SEP winpos", sidx, sx, sy, tx, ty)
    if args.photutils and r < args.photutils_reps:
        sel = np.flatnonzero(idx >= 0)[: args.photutils_stars]
        t0 = time.perf_counter()
        pc = photutils_2dg(img, det["x"][idx[sel]], det["y"][idx[sel]], det["background"][idx[sel]], psf)
        acc["tm"]["photutils 2dg"].append((time.perf_counter() - t0) * (det.size / max(sel.size, 1)))
        acc["err"]["photutils 2dg"][r, sel, 0] = pc[:, 0] - tx[sel]
        acc["err"]["photutils 2dg"][r, sel, 1] = pc[:, 1] - ty[sel]


def noise_free_errors(expected, tx, ty, epsf, methods=("PSFFIT", "GAUSSFIT", "MOMENT")):
    """Per-axis RMS error of each method on the noise-free frame (its systematic error), px; the
    weights of the fits take the read noise as the pixels' noise."""
    img = expected + BIAS
    det = detect_stars(img)
    psf = estimate_psf_sigma(img, det, gain=GAIN)
    idx = match(det["x"], det["y"], tx, ty)
    ok = idx >= 0
    out = {}
    for k in methods:
        c = measure_centroids(img, det, method=k, gain=GAIN, read_noise=RN, psf_sigma=psf,
                              epsf=epsf if k == "PSFFIT" else None)
        e = np.concatenate([c["x"][idx[ok]] - tx[ok], c["y"][idx[ok]] - ty[ok]])
        out[k] = float(np.sqrt(np.mean(e**2)))
    return out


def _summary_row(k, acc, crb, n_true, reps, args):
    """(method, compl, false, rmse, bias, rmse/crb, sig/rmse, fps, fps*) of one method over the realisations."""
    nreps = reps if k != "photutils 2dg" else min(reps, args.photutils_reps)
    e = acc["err"][k][:nreps]
    sig = acc["sig"]
    per_star_n = np.isfinite(e[:, :, 0]).sum(axis=0)
    use = per_star_n >= max(2, nreps // 2)
    sq = 0.5 * (e[:, :, 0] ** 2 + e[:, :, 1] ** 2)
    rmse = float(np.sqrt(np.nanmean(sq))) if np.isfinite(sq).any() else np.nan
    bias = (float(np.nanmean(e[:, :, 0])), float(np.nanmean(e[:, :, 1]))) if np.isfinite(sq).any() else (np.nan, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        star_rmse = np.sqrt(np.nanmean(sq, axis=0))
        ratio = float(np.nanmedian((star_rmse / crb)[use])) if use.any() else np.nan
        if k in sig and np.isfinite(sig[k]).any():
            star_sig = np.sqrt(np.nanmean(sig[k] ** 2, axis=0))
            sr = float(np.nanmedian((star_sig / star_rmse)[use])) if use.any() else np.nan
        else:
            sr = np.nan
    # frame times: the median over realisations (robust to other load on the machine)
    td, tp = float(np.median(acc["t_det"])), float(np.median(acc["t_psf"]))
    if k == "SEP winpos":
        fps = fps_known = 1.0 / float(np.median(acc["tm"][k]))
        compl, fal = acc["sep_found"].sum() / (n_true * reps), acc["sep_false"].mean()
    else:
        tk = float(np.median(acc["tm"][k]))
        fps = 1.0 / (td + tp + tk)
        fps_known = 1.0 / (td + tk)
        compl, fal = acc["found"].sum() / (n_true * reps), acc["false"].mean()
    return (k, compl, fal, rmse, bias, ratio, sr, fps, fps_known)


def run_regime(name, flux_range, psf, args, rng, artifacts=False, profile=None):
    tx, ty, expected, crb = _truth_and_bound(flux_range, psf, args, rng, profile)
    cam = CameraModel(read_noise=RN, gain=GAIN, bias=BIAS, adc_bits=16)
    art = (lambda: add_artifacts(expected, rng, *artifact_counts(args.size))) if artifacts else (lambda: expected)
    reps = args.reps
    keys = [m.value for m in METHODS] + ["SEP winpos"] + (["photutils 2dg"] if args.photutils else [])
    acc = {
        "err": {k: np.full((reps, tx.size, 2), np.nan) for k in keys},
        "sig": {k: np.full((reps, tx.size), np.nan) for k in keys},
        "tm": {k: [] for k in keys},
        "t_det": [], "t_psf": [],
        "found": np.zeros(reps), "false": np.zeros(reps), "sep_found": np.zeros(reps), "sep_false": np.zeros(reps),
    }
    acc["epsf"] = build_regime_epsf(art, cam, rng, args.epsf_frames)
    for r in range(reps):
        _measure_frame(cam.expose(art(), rng), r, psf, tx, ty, args, acc)
    rows = [_summary_row(k, acc, crb, tx.size, reps, args) for k in keys]
    return rows, float(np.median(crb)), noise_free_errors(expected, tx, ty, acc["epsf"]) if profile is not None else {}


def _nongaussian_section(args, rng, targets):
    """Moffat and Airy stars: PSFFIT (ePSF) against that PSF's bound; GAUSSFIT's rmse and systematic error."""
    fwhm = 2.0 * np.sqrt(2.0 * np.log(2.0)) * 1.2
    profiles = {"moffat b=2.5": MoffatPSF(fwhm=fwhm, beta=2.5), "airy": AiryPSF(lambda_d=fwhm / AIRY_FWHM_PER_LAMBDA_D)}
    print(f"\n# non-Gaussian PSFs of FWHM {fwhm:.3f} px (the Gaussian of sigma 1.2): rmse/crb against that PSF's "
          "bound; sys = RMS error on the noise-free frame, px")
    print(f"{'regime':<22}{'method':<16}{'compl':>7}{'rmse px':>10}{'bias x,y px':>20}{'sys px':>10}{'rmse/crb':>10}"
          f"{'sig/rmse':>9}")
    for name, profile in profiles.items():
        for reg in ("bright", "medium"):
            rows, crb_med, sys_err = run_regime(reg, REGIMES[reg], 1.2, args, rng, profile=profile)
            tag = f"{name} {reg}"
            print(f"{tag:<22}{'(median CRB)':<16}{'':>7}{crb_med:>10.4f}")
            byk = {r[0]: r for r in rows}
            for k in ("PSFFIT", "GAUSSFIT", "MOMENT", "SEP winpos"):
                _, compl, fal, rmse, bias, ratio, sr, fps, fk = byk[k]
                sys_k = sys_err.get(k, np.nan)
                print(f"{'':<22}{k:<16}{compl:>7.3f}{rmse:>10.4f}{bias[0]:>10.4f}{bias[1]:>10.4f}{sys_k:>10.4f}"
                      f"{ratio:>10.3f}{sr:>9.2f}")
            r = byk["PSFFIT"]
            targets.append((f"{tag}: PSFFIT rmse/crb {r[5]:.3f} <= 1.10 (GAUSSFIT {byk['GAUSSFIT'][5]:.3f}, "
                            f"its systematic error {sys_err['GAUSSFIT']:.4f} px)", bool(r[5] <= 1.10), "acc"))
            sys.stdout.flush()


ARTIFACT_REGIMES = (("medium", 1.2), ("faint", 2.0), ("bright", 0.7))


def _rmse(err: np.ndarray) -> float:
    sq = 0.5 * (err[..., 0] ** 2 + err[..., 1] ** 2)
    return float(np.sqrt(np.nanmean(sq))) if np.isfinite(sq).any() else float("nan")


COST_CALLS = 20  # calls timed per method, masked and plain, on each clean frame


def masking_times(img, det, method, psf_est, *, first: bool) -> dict[bool, float]:
    """Least CPU seconds of ``COST_CALLS`` calls of a method with masking (True) and without (False), the
    two interleaved (``first``: the one that starts): CPU time, so that other jobs on the machine add
    no waiting, and the least of several calls, so that what they do to the caches counts least."""
    best = {True: math.inf, False: math.inf}
    for call in range(COST_CALLS):
        for robust in (first, not first) if call % 2 == 0 else (not first, first):
            start = time.process_time()
            measure_centroids(img, det, method=method, gain=GAIN, psf_sigma=psf_est, robust=robust)
            best[robust] = min(best[robust], time.process_time() - start)
    return best


def run_artifact_regime(flux_range, psf, args, rng, counts=None, timed=True):
    """Paired frames of one field: each realisation exposed clean and with artefacts from the same noise
    seed. Every method with and without masking on both, SEP on both; method times on the clean frames
    (``timed``). ``counts``: hot pixels and cosmic-ray tracks per frame (default: ``artifact_counts``).
    starlog's detections are those the centroid stage keeps; ``false`` counts also those it leaves out
    as artefacts (``who`` = "all") and the true stars among them (``who`` = "lost")."""
    tx, ty, expected, _ = _truth_and_bound(flux_range, psf, args, rng)
    counts = counts or artifact_counts(args.size)
    cam = CameraModel(read_noise=RN, gain=GAIN, bias=BIAS, adc_bits=16)
    reps = args.reps
    keys = [(m.value, robust) for m in METHODS for robust in (True, False)] + [("SEP winpos", None)]
    err = {(kind, k): np.full((reps, tx.size, 2), np.nan) for kind in ("clean", "art") for k in keys}
    times = {k: [] for k in keys}
    false = {(kind, who): np.zeros(reps) for kind in ("clean", "art") for who in ("starlog", "all", "lost", "SEP")}
    for r in range(reps):
        seed = int(rng.integers(2**63))
        frames = {"clean": cam.expose(expected, np.random.default_rng(seed)),
                  "art": cam.expose(add_artifacts(expected, rng, *counts), np.random.default_rng(seed))}
        for kind, img in frames.items():
            det, every, psf_est = real_detections(img, psf)
            idx = match(det["x"], det["y"], tx, ty)
            false[kind, "starlog"][r] = det.size - (idx >= 0).sum()
            all_idx = match(every["x"], every["y"], tx, ty)
            false[kind, "all"][r] = every.size - (all_idx >= 0).sum()
            false[kind, "lost"][r] = (all_idx >= 0).sum() - (idx >= 0).sum()
            for m in METHODS:
                for robust in (True, False):
                    c = measure_centroids(img, det, method=m, gain=GAIN, psf_sigma=psf_est, robust=robust)
                    _record(err, r, (kind, (m.value, robust)), idx, c["x"], c["y"], tx, ty)
                if kind == "clean" and timed:
                    for robust, seconds in masking_times(img, det, m, psf_est, first=bool(r % 2)).items():
                        times[m.value, robust].append(seconds)
            sx, sy = sep_extract(img)
            sidx = match(sx, sy, tx, ty)
            false[kind, "SEP"][r] = sx.size - (sidx >= 0).sum()
            _record(err, r, (kind, ("SEP winpos", None)), sidx, sx, sy, tx, ty)
    rows = []
    sep_art = err["art", ("SEP winpos", None)]
    for k in keys:
        who = "SEP" if k[0] == "SEP winpos" else "starlog"
        t = float(np.median(times[k])) if times[k] else float("nan")
        both = np.isfinite(err["art", k][..., 0]) & np.isfinite(sep_art[..., 0])  # stars SEP matched too
        common = (_rmse(err["art", k][both]), _rmse(sep_art[both]))
        rows.append((k, _rmse(err["clean", k]), _rmse(err["art", k]), false["clean", who].mean(),
                     false["art", who].mean(), t, common))
    rows.append((("starlog", "artefacts"), *(false[kind, who].mean() for kind in ("clean", "art")
                                              for who in ("all", "lost"))))
    return rows


def artifact_section(args, rng):
    """The artefact run: RMSE clean vs with artefacts, false detections, the cost of masking on clean frames."""
    hot, tracks = artifact_counts(args.size)
    print(f"\n# with {hot} hot pixels (300-5000 e-) and {tracks} cosmic-ray tracks (0-10 px, 500-5000 e-/px) per frame;")
    print("# each realisation exposed twice from one noise seed (clean / with artefacts). masked: robust windows")
    print(f"# (default); plain: robust=False. ms: CPU time per clean frame (measure_centroids, PSF known; the least of "
          f"{COST_CALLS} calls, median over realisations).")
    print("# common / SEP common: RMSE with artefacts on the stars both starlog and SEP matched (SEP drops faint ones).")
    print(f"{'regime':<14}{'method':<16}{'clean rmse':>11}{'art rmse':>10}{'art/clean':>10}{'plain art':>10}"
          f"{'common':>8}{'SEP com':>8}{'false/fr':>9}{'ms masked':>10}{'ms plain':>9}{'cost':>7}")
    targets: list[tuple[str, bool, str]] = []
    for reg, psf in ARTIFACT_REGIMES:
        rows = {k: row for k, *row in run_artifact_regime(REGIMES[reg], psf, args, rng)}
        tag = f"{reg} s={psf}"
        sep_clean, sep_art, _, sep_false, _, _ = rows["SEP winpos", None]
        print(f"{tag:<14}{'SEP winpos':<16}{sep_clean:>11.4f}{sep_art:>10.4f}{sep_art / sep_clean:>10.3f}{'':>10}"
              f"{'':>8}{'':>8}{sep_false:>9.2f}")
        for m in METHODS:
            clean, art, _, fal, t_mask, (common, sep_common) = rows[m.value, True]
            _, plain_art, _, _, t_plain, _ = rows[m.value, False]
            cost = t_mask / t_plain - 1.0
            print(f"{'':<14}{m.value:<16}{clean:>11.4f}{art:>10.4f}{art / clean:>10.3f}{plain_art:>10.4f}"
                  f"{common:>8.4f}{sep_common:>8.4f}{fal:>9.2f}{1e3 * t_mask:>10.2f}{1e3 * t_plain:>9.2f}"
                  f"{100 * cost:>6.0f}%")
            targets.append((f"artifacts {tag}: {m.value} rmse {art:.4f} <= 1.15 x clean {clean:.4f}",
                            bool(art <= 1.15 * clean), "art"))
            targets.append((f"artifacts {tag}: {m.value} rmse {art:.4f} <= SEP {sep_art:.4f} "
                            f"(common stars: {common:.4f} vs SEP {sep_common:.4f})", bool(art <= sep_art),
                            _against_sep(clean, sep_art)))
            targets.append((f"{tag}: {m.value} masking cost on clean frames {100 * cost:.0f}% <= 15%",
                            bool(cost <= 0.15), "cost"))
        fal = rows[METHODS[0].value, True][3]
        before = rows["starlog", "artefacts"][2]
        per_full_frame = fal / (args.size / 1024) ** 2
        targets.append((f"artifacts {tag}: false detections per 1024x1024 frame {per_full_frame:.2f} <= 2 "
                        f"({fal:.2f} per {args.size}x{args.size} frame, {before:.2f} before those only an artefact "
                        f"made are left out; SEP {sep_false:.2f})", bool(per_full_frame <= 2.0), "false"))
        sys.stdout.flush()
    return targets


DENSE_SIZE, DENSE_HOT_FRACTION, DENSE_TRACKS = 512, 3e-4, 20  # per frame
DENSE_REGIMES = (("medium", 1.2), ("faint", 2.0))


def dense_artifact_section(args, rng):
    """Dense artefacts on 512x512 frames (hot pixels on 3e-4 of the pixels, 20 cosmic-ray tracks a frame):
    false detections with and without those only an artefact made, RMSE against clean and SEP, and the
    true stars left out as artefacts (none may be, on clean frames)."""
    dense = argparse.Namespace(**{**vars(args), "size": DENSE_SIZE})
    counts = (round(DENSE_HOT_FRACTION * DENSE_SIZE**2), DENSE_TRACKS)
    print(f"\n# dense artefacts: {DENSE_SIZE}x{DENSE_SIZE} frames, {counts[0]} hot pixels ({DENSE_HOT_FRACTION:g} of "
          f"the pixels) and {counts[1]} cosmic-ray tracks per frame, {args.reps} paired realisations; false/fr: "
          "detections the centroid stage keeps that match no star; all/fr: every detection that matches none (before "
          "those only an artefact made are left out); lost: true stars left out as artefacts, per frame")
    print(f"{'regime':<20}{'method':<16}{'clean rmse':>11}{'art rmse':>10}{'art/clean':>10}{'SEP art':>9}"
          f"{'false/fr':>9}{'all/fr':>8}{'SEP/fr':>8}{'lost cl':>8}{'lost art':>9}")
    targets: list[tuple[str, bool, str]] = []
    for reg, psf in DENSE_REGIMES:
        rows = {k: row for k, *row in run_artifact_regime(REGIMES[reg], psf, dense, rng, counts=counts, timed=False)}
        tag = f"dense {reg} s={psf}"
        _, sep_art, _, sep_false, _, _ = rows["SEP winpos", None]
        all_clean, lost_clean, all_art, lost_art = rows["starlog", "artefacts"]
        fal = rows[METHODS[0].value, True][3]
        for m in METHODS:
            clean, art, _, _, _, _ = rows[m.value, True]
            print(f"{tag if m is METHODS[0] else '':<20}{m.value:<16}{clean:>11.4f}{art:>10.4f}{art / clean:>10.3f}"
                  f"{sep_art:>9.4f}{fal:>9.2f}{all_art:>8.2f}{sep_false:>8.2f}{lost_clean:>8.2f}{lost_art:>9.2f}")
            targets.append((f"{tag}: {m.value} rmse {art:.4f} <= 1.15 x clean {clean:.4f}", bool(art <= 1.15 * clean),
                            "art"))
            targets.append((f"{tag}: {m.value} rmse {art:.4f} <= SEP {sep_art:.4f}", bool(art <= sep_art),
                            _against_sep(clean, sep_art)))
        targets.append((f"{tag}: false detections per frame {fal:.2f} <= 1 ({all_art:.2f} before those only an "
                        f"artefact made are left out; SEP {sep_false:.2f})", bool(fal <= 1.0), "dense_false"))
        targets.append((f"{tag}: true stars left out as artefacts on clean frames {lost_clean:.2f} per frame = 0 "
                        f"(false detections there {all_clean:.2f})", bool(lost_clean == 0), "compl"))
        sys.stdout.flush()
    return targets


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=EPILOG,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="512x512 frames, 4 realisations (about 25 s)")
    ap.add_argument("--reps", type=int, default=None, help="noise realisations per regime")
    ap.add_argument("--no-photutils", dest="photutils", action="store_false")
    ap.add_argument("--seed", type=int, default=12345)
    ap.add_argument("--regimes", default="bright,medium,faint")
    ap.add_argument("--sigmas", default=",".join(str(s) for s in SIGMAS))
    ap.add_argument("--no-artifacts", dest="artifacts", action="store_false")
    ap.add_argument("--no-nongaussian", dest="nongaussian", action="store_false",
                    help="skip the Moffat / Airy section")
    ap.add_argument("--epsf-frames", type=int, default=None, help="exposures the ePSF of a regime is built from")
    ap.add_argument("--artifacts-only", action="store_true", help="only the artefact run (and masking cost)")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    args.size = QUICK_SIZE if args.quick else FULL_SIZE
    args.nstars = 50  # the ePSF learns the PSF from this many pixel phases: fewer leave PSFFIT a systematic error
    args.reps = args.reps or (4 if args.quick else 12)
    args.epsf_frames = args.epsf_frames or (8 if args.quick else 12)
    args.photutils_reps = 2 if args.quick else 3
    args.photutils_stars = 10 if args.quick else 20
    rng = np.random.default_rng(args.seed)
    print(f"# frames {args.size}x{args.size}, {args.nstars} stars, {args.reps} noise realisations per regime; "
          f"sky {SKY} e-/px, read noise {RN} e-, gain {GAIN}, bias {BIAS} DN; cv2 threads = 1")
    print("# SEP: sep.Background(); sep.extract(data - back, 1.5, err=globalrms) (defaults: minarea 5, 3x3 "
          "conv filter); sep.winpos(sig = 2/2.35 * flux_radius(0.5)).  photutils: centroid_2dg on "
          f"starlog's cutouts ({args.photutils_stars} stars x {args.photutils_reps} realisations; fps scaled).")
    targets: list[tuple[str, bool, str]] = []
    hdr = f"{'regime':<14}{'method':<16}{'compl':>7}{'false':>7}{'rmse px':>10}{'bias x,y px':>20}{'rmse/crb':>10}{'sig/rmse':>9}{'fps':>8}{'fps*':>8}"
    print(hdr)
    for reg in [] if args.artifacts_only else args.regimes.split(","):
        for psf in (float(s) for s in args.sigmas.split(",")):
            rows, crb_med, _ = run_regime(reg, REGIMES[reg], psf, args, rng)
            tag = f"{reg} s={psf}"
            print(f"{tag:<14}{'(median CRB)':<16}{'':>7}{'':>7}{crb_med:>10.4f}")
            byk = {r[0]: r for r in rows}
            for k, compl, fal, rmse, bias, ratio, sr, fps, fk in rows:
                print(f"{'':<14}{k:<16}{compl:>7.3f}{fal:>7.2f}{rmse:>10.4f}{bias[0]:>10.4f}{bias[1]:>10.4f}{ratio:>10.3f}{sr:>9.2f}{fps:>8.1f}{fk:>8.1f}")
            for m in METHODS:
                lim = {CentroidMethod.GAUSSFIT: 1.10, CentroidMethod.PSFFIT: 1.05}.get(m, 1.25)
                r = byk[m.value]
                targets.append((f"{tag}: {m.value} rmse/crb {r[5]:.3f} <= {lim}", bool(r[5] <= lim),
                                "reference" if m is CentroidMethod.WINPOS else "acc"))
            targets.append((f"{tag}: completeness {byk['MOMENT'][1]:.3f} >= SEP {byk['SEP winpos'][1]:.3f}",
                            bool(byk["MOMENT"][1] >= byk["SEP winpos"][1]), "compl"))
            sep_fps = byk["SEP winpos"][7]
            for m, fac in ((CentroidMethod.MOMENT, 2.0), (CentroidMethod.GRADIENT, 2.0), (CentroidMethod.GAUSSFIT, 1.0)):
                targets.append((f"{tag}: {m.value} fps* {byk[m.value][8]:.1f} >= {fac} x SEP {sep_fps:.1f}",
                                bool(byk[m.value][8] >= fac * sep_fps), "speed"))
            sys.stdout.flush()
    if args.artifacts:
        targets += artifact_section(args, rng)
        targets += dense_artifact_section(args, rng)
    if args.nongaussian:
        _nongaussian_section(args, rng, targets)
    return report_targets(targets, quick=args.quick)


def report_targets(targets: list[tuple[str, bool, str]], *, quick: bool) -> int:
    """Print each target's verdict (at --quick, n/a for the kinds it cannot judge); 1 if a target failed."""
    judged = Targets()
    for text, ok, kind in targets:
        judged.check(text, ok, not_judged=NOT_AT_QUICK_SIZE.get(kind, "") if quick else "",
                     informational=INFORMATIONAL.get(kind, ""))
    return judged.report()


if __name__ == "__main__":
    sys.exit(main())
