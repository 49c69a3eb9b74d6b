"""Attitude from the log: `starlog solve` on real sky against cedar-solve, on simulated sky against the truth.

Needs cedar-solve (``pip install 'starlog[solve]'``, or ``pip install --no-deps cedar-solve`` with NumPy 2)
and, for part 1, the real frames in ``../shared/data/real-sky/`` (esa/tetra3's test data).

1. **Real sky.** The frames are ingested into a log, centroided (``starlog centroid``, default methods) and
   solved (``starlog solve --centroids all``); every frame must be solved by every method, and its attitude
   must agree with cedar-solve's own solution of the same image file (``Tetra3.solve_from_image``: its own
   centroids, field of view and distortion) within 60 arcsec in boresight and 0.05 deg in roll. The solve
   summary (catalogue residuals per method, fitted camera) is printed as ``starlog solve`` prints it.
2. **Simulated sky with known attitude.** ``starlog simulate --sky-attitude`` fields (512 x 512 px, 10 deg,
   catalogue stars to magnitude 7, 5 Hz jitter of 0.5 px and a 2 mrad roll at 1 Hz), centroided (GAUSSFIT)
   and solved: the RMS attitude error divided by the q-method's 1-sigma (Shuster's covariance from the
   centroids' sigmas) must be <= 1.2, cross-boresight and in roll.
3. **Tracking speed.** One core: a field of the catalogue's 30 brightest stars in a 10 deg camera, the
   attitude turning slowly, 0.05 px of noise; frames identified from the previous attitude
   (``AttitudeTracker``: projection, matching, two q-method passes). Target >= 1000 frames/s.
4. **Lost-in-space time.** On the real frames' GAUSSFIT centroids: starlog's lost-in-space solve (the
   solver's pattern match, the camera refit against the catalogue, the q-method) against the solver
   alone, ``Tetra3.solve_from_image`` on the image file (its own centroiding and solve). Target: not
   slower. The solver's pattern match alone on the same centroids (``solve_from_centroids``) is printed
   beside it: the difference is starlog's catalogue refinement. The same centroids with their columns
   reversed (a mirrored image) must solve, say they are mirrored, and give the frame's own attitude.

Run: python tools/bench_attitude.py [--quick] [--images DIR]. The full run about 25 s on a 2-core machine,
--quick (one simulated field of 60 frames, 1000 tracked frames) about 10 s. Exit status 1 when a target is
missed.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_realsky import default_images, list_images, missing_images  # noqa: E402
from bench_targets import Targets  # noqa: E402
from starlog.attitude.camera import camera_for_image, focal_from_fov  # noqa: E402
from starlog.attitude.catalogue import load_catalogue  # noqa: E402
from starlog.attitude.identify import AttitudeTracker, TrackerSettings  # noqa: E402
from starlog.attitude.lost_in_space import load_solver  # noqa: E402
from starlog.attitude.rotation import (  # noqa: E402
    attitude_from_radec_roll, radec_roll, radec_vectors, small_rotation)
from starlog.io.reader import LogReader  # noqa: E402
from starlog.sim import Jitter, SimulationConfig  # noqa: E402
from starlog.stages import ingest_source, simulate_log  # noqa: E402
from starlog.stages.centroid import centroid_log  # noqa: E402
from starlog.stages.solve import solve_log  # noqa: E402

SKY_FIELDS = ((80.0, 20.0, 30.0), (210.0, -35.0, 120.0), (300.0, 45.0, 250.0))


def solver_missing() -> str | None:
    """Why cedar-solve cannot be loaded, or None."""
    try:
        load_solver()
    except Exception as err:  # noqa: BLE001 - any failure to load is reported as such
        return str(err)
    return None


def angle_between(ra1: float, dec1: float, ra2: float, dec2: float) -> float:
    """Angle between two sky directions, arcsec."""
    cos = float(radec_vectors(ra1, dec1) @ radec_vectors(ra2, dec2))
    return math.degrees(math.acos(max(-1.0, min(1.0, cos)))) * 3600.0


def cedar_solutions(images: list[Path]) -> tuple[list[dict[str, Any]], list[float]]:
    """cedar-solve's own solution of each image file, and its wall time per file (s)."""
    from PIL import Image

    solver = load_solver()
    solutions, seconds = [], []
    for path in images:
        with Image.open(path) as image, warnings.catch_warnings():
            # cedar-solve 0.5's centroiding imports scipy.ndimage.filters, deprecated in SciPy 1.x
            warnings.simplefilter("ignore", DeprecationWarning)
            start = time.perf_counter()
            solutions.append(solver.solve_from_image(image))
            seconds.append(time.perf_counter() - start)
    return solutions, seconds


def real_sky(folder: Path, work: Path, targets: Targets) -> Path:
    """Part 1; returns the solved log."""
    images = list_images(folder)
    print(f"1. real sky: {len(images)} frames of {folder}, `starlog solve --centroids all` against cedar-solve's "
          "solve_from_image")
    ingest_source(folder, work / "sky.mcap", fps=1.0, force=True)
    centroid_log(work / "sky.mcap", work / "sky-cen.mcap", force=True)
    summary = solve_log(work / "sky-cen.mcap", work / "sky-att.mcap", centroids="all", force=True)
    for line in summary.lines():
        print(f"   {line}")
    solutions, _ = cedar_solutions(images)
    by_name = {path.name: solution for path, solution in zip(images, solutions)}
    print(f"   {'method':<10}{'solved':>8}{'max boresight arcsec':>22}{'max |roll| deg':>16}")
    with LogReader(work / "sky-att.mcap") as log:
        sources = {m.payload["frame"]: Path(m.payload["source"]).name for m in log.messages("/camera/frame")}
        for method in summary.methods:
            records = [m.payload for m in log.messages(f"/attitude/{method}")]
            solved = [r for r in records if r["solved"]]
            seps, rolls = [], []
            for r in records:
                ref = by_name[sources[r["frame"]]]
                if r["solved"] and ref.get("RA") is not None:
                    seps.append(angle_between(r["ra_deg"], r["dec_deg"], ref["RA"], ref["Dec"]))
                    rolls.append(abs((r["roll_deg"] - ref["Roll"] + 180.0) % 360.0 - 180.0))
            sep, roll = max(seps, default=math.inf), max(rolls, default=math.inf)
            print(f"   {method:<10}{len(solved):>4}/{len(records):<3}{sep:>22.2f}{roll:>16.4f}")
            targets.check(f"real sky {method}: {len(solved)}/{len(images)} frames solved", len(solved) == len(images))
            targets.check(f"real sky {method}: boresight vs cedar-solve {sep:.2f} arcsec <= 60, roll {roll:.4f} deg "
                          "<= 0.05", sep <= 60.0 and roll <= 0.05)
    return work / "sky-att.mcap"


def simulated_sky(work: Path, fields: tuple[tuple[float, float, float], ...], frames: int, targets: Targets) -> None:
    """Part 2."""
    print(f"\n2. simulated sky: {len(fields)} field(s) x {frames} frames, 512 x 512 px, 10 deg, magnitude <= 7, "
          "jitter 5 Hz:0.5 px, roll 1 Hz:2 mrad; GAUSSFIT")
    errors, sigmas = [], []
    for k, attitude in enumerate(fields):
        config = SimulationConfig(width=512, height=512, sky_attitude=attitude, fov_deg=10.0, magnitude_limit=7.0,
                                  n_frames=frames, jitter=(Jitter(5.0, 0.5),), roll_amplitude_rad=0.002,
                                  roll_frequency_hz=1.0, seed=k)
        log = work / f"field{k}.mcap"
        simulate_log(config, log, force=True)
        centroid_log(log, work / f"field{k}-cen.mcap", methods="GAUSSFIT", force=True)
        summary = solve_log(work / f"field{k}-cen.mcap", work / f"field{k}-att.mcap", centroids="GAUSSFIT",
                            force=True)
        m = summary.methods["GAUSSFIT"]
        print(f"   field RA {attitude[0]:g} Dec {attitude[1]:g} roll {attitude[2]:g}: {m['solved']}/{m['frames']} "
              f"solved ({m['lost_in_space']} lost in space, {m['tracking']} tracked), {m['matched_per_frame']:.1f} "
              "stars/frame")
        with LogReader(work / f"field{k}-att.mcap") as reader:
            for message in reader.messages("/attitude/GAUSSFIT"):
                r = message.payload
                if r["solved"]:
                    errors.append([r["error_x_arcsec"], r["error_y_arcsec"], r["error_roll_arcsec"]])
                    sigmas.append([r["sigma_x_arcsec"], r["sigma_y_arcsec"], r["sigma_roll_arcsec"]])
    err, sig = np.array(errors), np.array(sigmas)
    cross = float(np.sqrt(np.mean((err[:, :2] / sig[:, :2]) ** 2)))
    roll = float(np.sqrt(np.mean((err[:, 2] / sig[:, 2]) ** 2)))
    rms, bound = np.sqrt(np.mean(err**2, axis=0)), np.sqrt(np.mean(sig**2, axis=0))
    print(f"   RMS error arcsec x {rms[0]:.3f}, y {rms[1]:.3f}, roll {rms[2]:.2f}; 1-sigma x {bound[0]:.3f}, "
          f"y {bound[1]:.3f}, roll {bound[2]:.2f} ({err.shape[0]} frames)")
    targets.check(f"simulated sky: cross-boresight error / q-method sigma {cross:.2f} <= 1.2", cross <= 1.2)
    targets.check(f"simulated sky: roll error / q-method sigma {roll:.2f} <= 1.2", roll <= 1.2)


def tracking_speed(frames: int, targets: Targets, stars: int = 30) -> None:
    """Part 3."""
    catalogue = load_catalogue()
    shape = (1024, 1024)
    base = attitude_from_radec_roll(80.0, 20.0, 30.0)
    camera = camera_for_image(shape, focal_from_fov(10.0, shape[1]))
    rows = catalogue.cone(base[2], 10.0)
    x, y, front = replace(camera, rotation=base).project(catalogue.vectors[rows])
    inside = front & (x > 20) & (x < shape[1] - 21) & (y > 20) & (y < shape[0] - 21)
    field = rows[inside][np.argsort(catalogue.magnitude[rows[inside]])[:stars]]
    rng = np.random.default_rng(1)
    settings = TrackerSettings(focal_px=camera.focal, distortion=0.0)
    tracker = AttitudeTracker(catalogue, shape, settings)
    inputs = []
    for n in range(frames + 1):
        attitude = small_rotation([2e-5 * n, -1e-5 * n, 3e-5 * n]) @ base
        cam = replace(camera, rotation=attitude)
        px, py, _ = cam.project(catalogue.vectors[field])
        inputs.append((px + rng.normal(0, 0.05, stars), py + rng.normal(0, 0.05, stars),
                       10.0 ** (-0.4 * catalogue.magnitude[field]), np.full(stars, 0.05)))
    first = tracker.solve(*inputs[0])
    assert first.solved, first.reason
    start = time.perf_counter()
    results = [tracker.solve(*frame) for frame in inputs[1:]]
    rate = frames / (time.perf_counter() - start)
    tracked = sum(r.solved and r.mode == "tracking" for r in results)
    print(f"\n3. tracking: {frames} frames of {stars} stars, {tracked} tracked; {rate:.0f} frames/s on one core "
          f"(load average {' '.join(f'{v:.2f}' for v in os.getloadavg())})")
    targets.check(f"tracking {rate:.0f} frames/s >= 1000 (30 stars a frame, one core)", rate >= 1000 and
                  tracked == frames, informational="wall clock on a shared machine")


def lost_in_space_time(images: list[Path], solved_log: Path, targets: Targets) -> None:
    """Part 4, and each frame's centroids with their columns reversed (a mirrored image) solved too."""
    solver = load_solver()
    catalogue = load_catalogue()
    ours, centroids_only, mirrored = [], [], []
    with LogReader(solved_log) as log:
        shape = next((int(m.payload["height"]), int(m.payload["width"])) for m in log.messages("/camera/frame"))
        attitudes = [m.payload for m in log.messages("/attitude/GAUSSFIT")]
        for message, solved in zip(log.messages("/stars/centroids/GAUSSFIT"), attitudes):
            s = [r for r in message.payload["stars"] if r["sigma"] > 0 and not r["flags"] & 4]
            x, y, flux, sigma = (np.array([r[k] for r in s]) for k in ("x", "y", "flux", "sigma"))
            tracker = AttitudeTracker(catalogue, shape, TrackerSettings(tracking=False), solver=solver)
            start = time.perf_counter()
            assert tracker.solve(x, y, flux, sigma).solved
            ours.append(time.perf_counter() - start)
            order = np.argsort(-flux)[:50]
            start = time.perf_counter()
            solver.solve_from_centroids(np.column_stack([y[order] + 0.5, x[order] + 0.5]), size=shape,
                                        distortion=0.0, match_threshold=1e-7, solve_timeout=5000)
            centroids_only.append(time.perf_counter() - start)
            flipped = AttitudeTracker(catalogue, shape, TrackerSettings(tracking=False), solver=solver).solve(
                shape[1] - 1.0 - x, y, flux, sigma)
            if flipped.solved and "mirrored" in flipped.reason:
                ra, dec, roll = radec_roll(flipped.camera.rotation)
                mirrored.append((angle_between(ra, dec, solved["ra_deg"], solved["dec_deg"]),
                                 abs((roll - solved["roll_deg"] + 180.0) % 360.0 - 180.0)))
    _, image_seconds = cedar_solutions(images)
    a, b, c = (1000 * float(np.median(v)) for v in (ours, image_seconds, centroids_only))
    print(f"\n4. lost in space, median per frame: starlog {a:.1f} ms; cedar-solve solve_from_image {b:.1f} ms; "
          f"its pattern match alone on the same centroids {c:.1f} ms (load average "
          f"{' '.join(f'{v:.2f}' for v in os.getloadavg())})")
    targets.check(f"lost in space {a:.1f} ms <= the solver alone on the image {b:.1f} ms", a <= b,
                  informational="wall clock on a shared machine")
    sep = max((m[0] for m in mirrored), default=math.inf)
    roll = max((m[1] for m in mirrored), default=math.inf)
    print(f"   mirrored (columns reversed): {len(mirrored)}/{len(attitudes)} frames solved and said mirrored; largest "
          f"difference from the frame's own attitude {sep:.2f} arcsec boresight, {roll:.4f} deg roll")
    targets.check(f"mirrored frames {len(mirrored)}/{len(attitudes)} solved and said mirrored, same attitude within "
                  f"1 arcsec ({sep:.2f}) and 0.001 deg ({roll:.4f})",
                  len(mirrored) == len(attitudes) and sep <= 1.0 and roll <= 0.001)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one simulated field of 60 frames, 1000 tracked frames")
    parser.add_argument("--images", type=Path, default=None, help="folder of real frames")
    parser.add_argument("--workdir", type=Path, help="folder for the logs (kept)")
    args = parser.parse_args(argv)
    problem = solver_missing()
    if problem:
        print(f"bench_attitude: {problem}", file=sys.stderr)
        return 2
    images = args.images or default_images()
    targets = Targets()
    with tempfile.TemporaryDirectory(prefix="attitude-") as tmp:
        work = args.workdir or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        solved = None
        if missing_images(images) is None:
            solved = real_sky(images, work, targets)
        else:
            targets.check("real sky", False, not_judged=missing_images(images) or "")
        simulated_sky(work, SKY_FIELDS[:1] if args.quick else SKY_FIELDS, 60 if args.quick else 150, targets)
        tracking_speed(1000 if args.quick else 3000, targets)
        if solved is not None:
            lost_in_space_time(list_images(images), solved, targets)
    return targets.report()


if __name__ == "__main__":
    sys.exit(main())
