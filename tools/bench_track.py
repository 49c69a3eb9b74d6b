"""Benchmark of starlog's tracking filters: filter updates per second per model.

One update = one star in one frame (predict + measurement update). Measured, per motion model:

* ``batched x20``  — :class:`starlog.track.BatchUKF` stepping 20 stars per call;
* ``single``       — the same filter with one star per call;
* ``filterpy``     — filterpy's per-object ``UnscentedKalmanFilter`` (reference, same run);
* ``tracker``      — :class:`starlog.track.StarTracker` (predict, association, gated update,
  output rows) on a synthetic 300 Hz log of 20 stars, 3248 frames (the paper's lab dataset
  size), wall time and updates/s.

PASS/FAIL compares the batched and tracker rates with the target of 6,000 updates/s.

Usage::

    python tools/bench_track.py            # full run (about a minute on a slow core)
    python tools/bench_track.py --quick    # a few seconds
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

from starlog.track import (
    BatchUKF,
    MotionModel,
    StarTracker,
    filterpy_step,
    make_filterpy_ukf,
)

TARGET = 6000.0
N_STARS = 20
PERIOD_NS = 3_333_333  # 300 Hz


def synthetic_log(n_frames: int, seed: int = 0):
    """Centroids of a static 20-star field with 20 Hz micro-vibration, 300 Hz frames."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(30, 1000, (N_STARS, 2))
    flux = rng.uniform(2e3, 1e5, N_STARS)
    sigma = 0.02 + 15.0 / np.sqrt(flux)
    t = np.arange(n_frames) * PERIOD_NS
    shake = 0.05 * np.sin(2 * np.pi * 20.0 * t * 1e-9)[:, None] * np.array([1.0, 0.6])
    frames = []
    for k in range(n_frames):
        p = pos + shake[k] + rng.normal(size=pos.shape) * sigma[:, None]
        order = rng.permutation(N_STARS)
        frames.append((int(t[k]), p[order, 0], p[order, 1], sigma[order], flux[order]))
    return frames


def bench_batched(model: MotionModel, n: int, steps: int, rng: np.random.Generator) -> float:
    x0 = rng.uniform(0, 1000, n)
    y0 = rng.uniform(0, 1000, n)
    s = np.full(n, 0.1)
    ukf = BatchUKF.from_centroids(model, x=x0, y=y0, sigma=s)
    z = np.stack([x0, y0], 1) + rng.normal(0, 0.1, (steps, n, 2))
    dt = 1 / 300
    for k in range(min(steps, 20)):  # warm-up (caches, first-call costs)
        ukf.step(dt, z[k], s)
    t0 = time.perf_counter()
    for k in range(steps):
        ukf.step(dt, z[k], s)
    return steps * n / (time.perf_counter() - t0)


def bench_filterpy(model: MotionModel, steps: int, rng: np.random.Generator) -> float:
    ref = BatchUKF.from_centroids(model, x=[500.0], y=[500.0], sigma=[0.1])
    ukf = make_filterpy_ukf(model, x=ref.x[0], P=ref.P[0])
    z = np.array([500.0, 500.0]) + rng.normal(0, 0.1, (steps, 2))
    t0 = time.perf_counter()
    for k in range(steps):
        filterpy_step(ukf, model, 1 / 300, z[k], 0.1)
    return steps / (time.perf_counter() - t0)


def bench_tracker(model: MotionModel, frames) -> tuple[float, float, int]:
    tracker = StarTracker(model=model)
    updates = 0
    t0 = time.perf_counter()
    for t, x, y, s, f in frames:
        rows = tracker.update(t, x, y, s, f)
        updates += int(rows["measured"].sum() + rows["gated"].sum())
    wall = time.perf_counter() - t0
    return wall, updates / wall, tracker.n_live


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short run (a few seconds)")
    args = ap.parse_args()
    steps = 150 if args.quick else 1000
    fp_steps = 60 if args.quick else 300
    n_frames = 300 if args.quick else 3248
    rng = np.random.default_rng(1)
    frames = synthetic_log(n_frames)

    print(f"starlog tracking benchmark ({'quick' if args.quick else 'full'} run)")
    print(f"python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}, "
          f"one core; target {TARGET:,.0f} updates/s (one star in one frame = one update)")
    print(f"filters: {steps} steps (filterpy {fp_steps}); tracker: {N_STARS} stars x "
          f"{n_frames} frames at 300 Hz, synthetic centroids")
    print()
    head = (f"{'model':<18} {'batched x20':>12} {'single':>9} {'filterpy':>9} "
            f"{'tracker wall s':>14} {'tracker upd/s':>13} {'live':>4}  result")
    print(head)
    print("-" * len(head))
    all_pass = True
    for model in MotionModel:
        batched = bench_batched(model, N_STARS, steps, rng)
        single = bench_batched(model, 1, steps, rng)
        fp = bench_filterpy(model, fp_steps, rng)
        wall, trk, live = bench_tracker(model, frames)
        ok = batched >= TARGET and trk >= TARGET
        all_pass &= ok
        print(f"{model.value:<18} {batched:>12,.0f} {single:>9,.0f} {fp:>9,.0f} "
              f"{wall:>14.2f} {trk:>13,.0f} {live:>4}  {'PASS' if ok else 'FAIL'}")
    print()
    print("columns: updates/s of BatchUKF with 20 stars per call, with 1 star per call, of "
          "filterpy's per-object UKF; StarTracker wall time for the whole log and its updates/s")
    print(f"overall: {'PASS' if all_pass else 'FAIL'} (batched and tracker >= {TARGET:,.0f}/s)")


if __name__ == "__main__":
    main()
