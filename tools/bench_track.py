"""Benchmark of starlog's tracking: filter updates per second per model, and the ``track`` stage.

One update = one star in one frame (predict + measurement update). Measured, per motion model:

* ``batched x20``  — :class:`starlog.tracking.BatchUKF` stepping 20 stars per call;
* ``single``       — the same filter with one star per call;
* ``filterpy``     — filterpy's per-object ``UnscentedKalmanFilter`` (reference, same run);
* ``tracker``      — :class:`starlog.tracking.StarTracker` (predict, association, gated update,
  output rows; each frame one compiled call) on a synthetic 300 Hz log of 20 stars, 3248 frames
  (the paper's lab dataset size), wall time and updates/s;
* ``numpy``        — the same tracker as numpy steps (``StarTracker(vectorised=True)``, the
  compiled call's reference), updates/s, and the compiled tracker's speed-up over it.

PASS/FAIL compares the batched and tracker rates with the target of 6,000 updates/s.

``--stage`` benchmarks the ``track`` stage as a user runs it instead: ``starlog track LOG
--model STATIC`` (one model, the CLI in a new process, input log on disk, output written) on a
centroid log and on one 10x longer, against the tracker alone on the same centroids. CPU
seconds (the machine may be shared), split into interpreter start-up, the SHA-256 of the input
that the output layer's base record holds (proportional to the input's size, images included;
hashed on a thread beside the tracking) and the rest; peak resident memory of each run (must stay flat in the log's length).
By default the logs are synthetic centroid channels (40 stars, 300 Hz, no images); ``--log``
times a real one (e.g. a simulated 512x512 log centroided with GAUSSFIT).

Usage::

    python tools/bench_track.py            # full run
    python tools/bench_track.py --quick    # shorter filters and log
    python tools/bench_track.py --stage [--log cen.mcap --method GAUSSFIT]

Run times on a 2-core machine: the full run about a minute, --quick about 2 s, --stage --quick
about 35 s. Exit status 1 when a target is missed (6,000 updates/s per model; with --stage, peak
memory flat within 10 %), 0 when all are met.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_targets import Targets  # noqa: E402
from starlog.io import LogReader, LogWriter, file_digest  # noqa: E402
from starlog.codecs import protobuf_message_type
from starlog import topics
from starlog.codecs.star_tables import star_codec  # noqa: E402
from starlog.tracking import (  # noqa: E402
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


def bench_tracker(model: MotionModel, frames, *, vectorised: bool = False) -> tuple[float, float, int]:
    tracker = StarTracker(model=model, vectorised=vectorised)
    updates = 0
    t0 = time.perf_counter()
    for t, x, y, s, f in frames:
        rows = tracker.update(t, x, y, s, f)
        updates += int(rows["measured"].sum() + rows["gated"].sum())
    wall = time.perf_counter() - t0
    return wall, updates / wall, tracker.n_live


STAGE_STARS = 40
# The child's peak is its VmHWM: getrusage's ru_maxrss of a process started by fork/vfork + exec also
# counts the parent's resident set at the fork (Linux carries the old address space's high-water mark).
_STAGE_CHILD = """
import json, sys, time
from starlog.stages.track import track_log
t0 = time.process_time()
track_log(sys.argv[1], sys.argv[2], method=sys.argv[3], models="STATIC", force=True)
with open("/proc/self/status") as status:
    peak_kb = next(int(line.split()[1]) for line in status if line.startswith("VmHWM:"))
print(json.dumps({"cpu": time.process_time() - t0, "peak_mb": peak_kb / 1024}))
"""


def write_centroid_log(path: Path, n_frames: int, method: str = "GAUSSFIT", seed: int = 0) -> None:
    """A log with only a centroid channel: 40 jittering stars at 300 Hz (no images)."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(20, 490, (STAGE_STARS, 2))
    flux = rng.uniform(5e3, 5e4, STAGE_STARS)
    sigma = 0.01 + 3.0 / np.sqrt(flux)
    with LogWriter(path, force=True) as log:
        channel = log.add_channel(topics.centroid_topic(method), protobuf_message_type("starlog.Centroids"))
        codec = star_codec("starlog.Centroids")  # as the centroid stage writes them
        for k in range(n_frames):
            t = k * PERIOD_NS
            shake = 0.05 * np.sin(2 * np.pi * 25.0 * t * 1e-9)
            p = pos + shake + rng.normal(size=pos.shape) * sigma[:, None]
            stars = [{"star": i, "x": float(p[i, 0]), "y": float(p[i, 1]), "flux": float(flux[i]),
                      "snr": 100.0, "sigma": float(sigma[i]), "peak": 1000.0, "background": 100.0,
                      "psf_sigma": 1.2, "flags": 0, "n_masked": 0} for i in range(STAGE_STARS)]
            log.write(channel, log_time=t, data=codec.encode_dict({"frame": k, "method": method, "stars": stars}))


def _cpu_of(command: list[str]) -> tuple[float, str]:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    out = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, out


def bench_stage(log: Path, method: str, tmp: Path) -> dict[str, float]:
    """CPU seconds of ``starlog track`` (CLI) and its parts, and of the tracker alone, on ``log``."""
    with LogReader(log) as reader:
        frames = [(m.log_time, *(np.array([s[k] for s in m.payload["stars"]], dtype=np.float64)
                                 for k in ("x", "y", "sigma", "flux")))
                  for m in reader.messages(topics.centroid_topic(method))]
    tracker_cpu = []
    for _ in range(3):
        tracker = StarTracker(model=MotionModel.STATIC)
        t0 = time.process_time()
        for frame in frames:
            tracker.update(*frame)
        tracker_cpu.append(time.process_time() - t0)
    n_frames = len(frames)
    del frames
    out = tmp / "track_out.mcap"
    python = sys.executable
    cli = [python, "-m", "starlog", "track", str(log), "-o", str(out), "--centroids", method,
           "--model", "STATIC", "-q", "--force", "--workers", "1"]
    total = min(_cpu_of(cli)[0] for _ in range(3))
    start = min(_cpu_of([python, "-c", "import starlog.cli, starlog.stages.track"])[0] for _ in range(3))
    child = [json.loads(_cpu_of([python, "-c", _STAGE_CHILD, str(log), str(out), method])[1])
             for _ in range(3)]
    t0 = time.process_time()
    file_digest(log)
    with open(log, "rb") as f:
        while f.read(1 << 20):
            pass
    digest = time.process_time() - t0  # the base record's SHA-256 of the input, hashed on a thread by the stage
    return {"frames": n_frames, "tracker": min(tracker_cpu),
            "cli": total, "start": start, "stage": min(c["cpu"] for c in child), "digest": digest,
            "peak_mb": max(c["peak_mb"] for c in child)}


def stage_main(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory() as name:
        tmp = Path(name)
        if args.log:
            logs = [Path(args.log)]
        else:
            n = 300 if args.quick else 1200
            logs = [tmp / f"cen_{k}.mcap" for k in (n, 10 * n)]
            for path, k in zip(logs, (n, 10 * n), strict=True):
                write_centroid_log(path, k, args.method)
        print("starlog track stage benchmark: `starlog track LOG --model STATIC --workers 1` vs the "
              "tracker alone on the same centroids (CPU s, best of 3)")
        print(f"python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}")
        print()
        head = (f"{'log':<22} {'frames':>7} {'tracker':>8} {'CLI total':>9} {'start-up':>8} "
                f"{'stage':>7} {'digest':>7} {'total/trk':>9} {'stage/trk':>9} {'peak MB':>8}")
        print(head)
        print("-" * len(head))
        peaks = []
        for log in logs:
            r = bench_stage(log, args.method, tmp)
            peaks.append(r["peak_mb"])
            print(f"{log.name[:22]:<22} {r['frames']:>7} {r['tracker']:>8.3f} {r['cli']:>9.3f} {r['start']:>8.3f} "
                  f"{r['stage']:>7.3f} {r['digest']:>7.3f} {r['cli'] / r['tracker']:>9.2f} "
                  f"{(r['stage'] - r['digest']) / r['tracker']:>9.2f} {r['peak_mb']:>8.0f}")
        print()
        print("columns: tracker = StarTracker.update over every frame in this process; CLI total = the "
              "command in a new process; start-up = importing the CLI and the stage; stage = track_log in "
              "a new process; digest = SHA-256 of the input (the base record's, hashed on a thread); "
              "stage/trk = (stage - digest) / tracker; peak MB = peak RSS of the stage process")
        targets = Targets()
        if len(peaks) == 2:
            growth = peaks[1] / peaks[0] - 1
            targets.check(f"peak memory 1x -> 10x frames: {100 * growth:+.1f} % <= 10 %", growth <= 0.10)
        return targets.report()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__.split("\n\n")[-1])
    ap.add_argument("--quick", action="store_true", help="short run (about 2 s; with --stage about 35 s)")
    ap.add_argument("--stage", action="store_true", help="benchmark the track stage instead (see above)")
    ap.add_argument("--log", help="with --stage: a centroid log to time (default: synthetic, 1x and 10x)")
    ap.add_argument("--method", default="GAUSSFIT", help="with --stage: centroid method of the log")
    args = ap.parse_args()
    if args.stage:
        return stage_main(args)
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
            f"{'tracker wall s':>14} {'tracker upd/s':>13} {'numpy upd/s':>11} {'x numpy':>7} {'live':>4}  result")
    print(head)
    print("-" * len(head))
    targets = Targets()
    for model in MotionModel:
        batched = bench_batched(model, N_STARS, steps, rng)
        single = bench_batched(model, 1, steps, rng)
        fp = bench_filterpy(model, fp_steps, rng)
        bench_tracker(model, frames[:20])  # the compiled call's first use (compiled or loaded from the cache)
        wall, trk, live = bench_tracker(model, frames)
        _, ref, _ = bench_tracker(model, frames, vectorised=True)
        ok = batched >= TARGET and trk >= TARGET
        print(f"{model.value:<18} {batched:>12,.0f} {single:>9,.0f} {fp:>9,.0f} "
              f"{wall:>14.2f} {trk:>13,.0f} {ref:>11,.0f} {trk / ref:>7.1f} {live:>4}  {'PASS' if ok else 'FAIL'}")
        targets.check(f"{model.value}: batched {batched:,.0f} updates/s >= {TARGET:,.0f}", batched >= TARGET)
        targets.check(f"{model.value}: tracker {trk:,.0f} updates/s >= {TARGET:,.0f}", trk >= TARGET)
    print()
    print("columns: updates/s of BatchUKF with 20 stars per call, with 1 star per call, of "
          "filterpy's per-object UKF; StarTracker wall time for the whole log and its updates/s; the same "
          "as numpy steps (StarTracker(vectorised=True)) and the compiled tracker's speed-up over them")
    return targets.report()


if __name__ == "__main__":
    sys.exit(main())
