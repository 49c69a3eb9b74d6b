"""Benchmark of the `centroid` stage as a user runs it, against SEP on the same frames.

Simulates (once, cached in --dir) two logs of N and 2N frames (--size, --stars), then, in one
run and interleaved so that other load on the machine hits both alike:

- SEP: sep.Background + sep.extract + sep.winpos on the decoded frames (one core);
- the per-frame parts of the stage in this process: decode, detection, one method, message
  encoding (OpenCV on one thread, as the stage runs it);
- `starlog centroid --workers W --method M` end to end on both logs: the marginal cost of a
  frame is the difference of the two runs divided by N (start-up separate).

CPU time (user + system) is reported next to wall time: on a shared machine CPU time per frame
is the stable figure; `fps` = 1 / CPU time per frame. For W > 1 only the wall time is measured
(worker processes are not children of this one). Each figure is the minimum over --repeats.

Then tracking mode against full mode (``--mode tracking`` / ``--mode full``, GAUSSFIT, ``--acquire-every``
default) on simulated 300 Hz logs of --tracking-size px, one per motion regime: static, drifting 0.5 px a
frame (stars leave and enter the field), jitter of 2 px at 25 Hz, a roll of 0.005 rad at 2 Hz, and hot pixels
with cosmic rays (jitter 0.05 px). Each centroid is matched to the nearest true position (within 1 px); the
RMSE of each mode is taken over the (frame, star) pairs both modes measured. Targets: tracking's RMSE within
1.02x full mode's in every regime; no star that full mode measures goes unmeasured by tracking for more than
one acquisition period; a star entering the field is measured by tracking within one acquisition period of
full mode's first measurement of it.

Last, the choice of ``--acquire-every``: in this process, CPU time a frame of tracking mode (search, windows,
measurement, messages; no decode) on the first 300 frames of the --size log, for several periods, and the
searches each made; period 1 is full mode.

Run: python tools/bench_centroid_stage.py [--quick] [--frames 300] [--size 1024] [--methods MOMENT,GAUSSFIT]

Run time of --quick (512x512, 40 stars, 100 / 200 frames, one repeat; tracking regimes 256x256, 600 frames)
on a 2-core machine: about 1 minute once its logs are in --dir; the first run simulates them too. The exit
status is 1 when a tracking target is missed.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from starlog.centroiding import CentroidMethod, measure_centroids
from starlog.detect import detect_stars
from starlog.io.reader import LogReader
from starlog.io.frames import reuse_frame_buffers
from starlog.codecs.star_tables import star_codec

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_targets import Targets  # noqa: E402

STARLOG = [sys.executable, "-m", "starlog"]
CAMERA_HZ = 300
#: The tracking regimes: ``starlog simulate`` motion options of each.
TRACKING_REGIMES = {
    "static": [],
    "drift 0.5 px/frame": ["--drift", f"{0.5 * CAMERA_HZ:g},0"],
    "jitter 2 px": ["--jitter", "25:2"],
    "roll 0.005 rad": ["--roll", "2:0.005"],
    "hot pixels + cosmic rays": ["--jitter", "25:0.05", "--hot-pixels", "40", "--cosmic-rays", "2"],
}
RMSE_LIMIT = 1.02


def simulate(path: Path, frames: int, size: int, stars: int) -> None:
    if not path.exists():
        subprocess.run([*STARLOG, "simulate", "-o", str(path), "--size", f"{size}x{size}", "--stars", str(stars),
                        "--frames", str(frames), "-q"], check=True)


def cli_run(log: Path, out: Path, method: str, workers: int) -> tuple[float, float]:
    """(wall, cpu) seconds of one `starlog centroid` run."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([*STARLOG, "centroid", str(log), "-o", str(out), "--workers", str(workers), "--method", method,
                    "--force", "-q"], check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def per_frame_cpu(fn, items) -> float:
    c0 = time.process_time()
    for item in items:
        fn(item)
    return (time.process_time() - c0) / len(items)


def sep_frame(img: np.ndarray) -> None:
    import sep

    data = img.astype(np.float64)
    bkg = sep.Background(data)
    sub = data - bkg.back()
    objs = sep.extract(sub, 1.5, err=bkg.globalrms)
    sep.winpos(sub, objs["x"], objs["y"], np.full(len(objs), 1.2))


def in_process_parts(log: Path, methods: list[str], count: int) -> dict[str, float]:
    """CPU s per frame of SEP and of the stage's parts, on the first ``count`` frames."""
    c0 = time.process_time()
    with LogReader(log) as reader:
        frames = [img for _, _, img in itertools.islice(reader.frames(), count)]
    out = {"decode": (time.process_time() - c0) / len(frames), "SEP": per_frame_cpu(sep_frame, frames)}
    cv2.setNumThreads(1)  # as the stage runs them, allocator setting included
    reuse_frame_buffers()
    detect_stars(frames[0])  # compiled kernels load on first use: a process's cost, not a frame's
    out["detection"] = per_frame_cpu(detect_stars, frames)
    dets = [detect_stars(f) for f in frames]
    pairs = list(zip(frames, dets))
    for m in methods:
        def measure(p, m=m):  # type: ignore[no-untyped-def]
            return measure_centroids(p[0], p[1], method=CentroidMethod(m), gain=1.0, read_noise=3.0, psf_sigma=1.2)

        measure(pairs[0])  # its kernels loaded first, as for detection
        out[m] = per_frame_cpu(measure, pairs)
    encoder = star_codec("starlog.Detections")  # as the stage encodes them, columns checked
    out["encode (detections)"] = per_frame_cpu(lambda d: encoder.encode({"frame": 0}, d), dets)
    return out


def frame_matches(payload: dict, truth: dict, radius: float = 1.0) -> dict[int, tuple[float, float]]:
    """``{true star id: (dx, dy)}`` of the centroids of one frame matched to their nearest true star within
    ``radius`` px (a star matched twice keeps its nearer centroid)."""
    stars = truth["stars"]
    if not stars or not payload["stars"]:
        return {}
    tx = np.array([s["x"] for s in stars])
    ty = np.array([s["y"] for s in stars])
    out: dict[int, tuple[float, float]] = {}
    for c in payload["stars"]:
        d = np.hypot(tx - c["x"], ty - c["y"])
        k = int(np.argmin(d))
        if d[k] <= radius and (stars[k]["star"] not in out or d[k] < np.hypot(*out[stars[k]["star"]])):
            out[stars[k]["star"]] = (c["x"] - tx[k], c["y"] - ty[k])
    return out


def mode_matches(out: Path, sim: Path) -> list[dict[int, tuple[float, float]]]:
    """Per frame, :func:`frame_matches` of the GAUSSFIT centroids of ``out`` against the truth of ``sim``."""
    with LogReader(sim) as log:
        truths = [m.payload for m in log.messages("/sim/truth")]
    with LogReader(out) as log:
        rows = [m.payload for m in log.messages("/stars/centroids/GAUSSFIT")]
    return [frame_matches(c, t) for c, t in zip(rows, truths, strict=True)]


def longest_gap(full: list[dict], tracked: list[dict]) -> int:
    """The most consecutive frames in which one star that full mode measured went unmeasured by tracking."""
    worst, running = 0, {}
    for f, t in zip(full, tracked):
        for star in f:
            running[star] = running.get(star, 0) + 1 if star not in t else 0
            worst = max(worst, running[star])
        for star in list(running):
            if star not in f:
                running[star] = 0
    return worst


def entry_delay(full: list[dict], tracked: list[dict]) -> int:
    """The most frames by which tracking's first measurement of a star came after full mode's, over the stars
    full mode first measured after the first frame (0 when none did, or tracking measured them first)."""
    first_full: dict[int, int] = {}
    first_tracked: dict[int, int] = {}
    for k, (f, t) in enumerate(zip(full, tracked)):
        for star in f:
            first_full.setdefault(star, k)
        for star in t:
            first_tracked.setdefault(star, k)
    delays = [max(0, first_tracked.get(star, len(full)) - k) for star, k in first_full.items() if k > 0]
    return max(delays, default=0)


def paired_rmse(full: list[dict], tracked: list[dict]) -> tuple[float, float, int]:
    """RMSE of full mode and of tracking over the (frame, star) pairs both measured, and the number of pairs."""
    a, b = [], []
    for f, t in zip(full, tracked):
        for star in f.keys() & t.keys():
            a.append(f[star])
            b.append(t[star])
    if not a:
        return float("nan"), float("nan"), 0
    return float(np.sqrt(np.mean(np.square(a)) * 2)), float(np.sqrt(np.mean(np.square(b)) * 2)), len(a)


def tracking_accuracy(args: argparse.Namespace, targets: Targets) -> None:
    """Tracking against full mode on each regime (:data:`TRACKING_REGIMES`): figures printed, targets checked."""
    from starlog.centroiding.tracking import DEFAULT_ACQUIRE_EVERY

    folder = Path(args.dir)
    period = DEFAULT_ACQUIRE_EVERY
    print(f"\n# tracking vs full mode, GAUSSFIT, {args.tracking_size}x{args.tracking_size}, {args.stars} stars, "
          f"{args.tracking_frames} frames at {CAMERA_HZ} Hz, acquire every {period} frames; RMSE against the truth "
          "over the (frame, star) pairs both modes measured")
    print(f"{'regime':<26}{'pairs':>8}{'full px':>10}{'tracking px':>12}{'ratio':>7}{'searches':>10}"
          f"{'longest gap':>12}{'entry delay':>12}")
    for name, motion in TRACKING_REGIMES.items():
        sim = folder / f"track_{args.tracking_size}_{args.tracking_frames}_{name.split()[0]}.mcap"
        if not sim.exists():
            subprocess.run([*STARLOG, "simulate", "-o", str(sim), "--size", f"{args.tracking_size}x{args.tracking_size}",
                            "--stars", str(args.stars), "--fps", str(CAMERA_HZ), "--frames", str(args.tracking_frames),
                            "--seed", "2", *motion, "-q"], check=True)
        matches, searches = {}, 0
        for mode in ("full", "tracking"):
            out = folder / f"track_{mode}.mcap"
            done = subprocess.run([*STARLOG, "centroid", str(sim), "-o", str(out), "--method", "GAUSSFIT", "--mode", mode,
                                   "--workers", "1", "--force", "--json", "-q"], check=True, capture_output=True, text=True)
            matches[mode] = mode_matches(out, sim)
            searches = json.loads(done.stdout)["acquisitions"]
        full_rmse, tracked_rmse, pairs = paired_rmse(matches["full"], matches["tracking"])
        gap, delay = longest_gap(matches["full"], matches["tracking"]), entry_delay(matches["full"], matches["tracking"])
        ratio = tracked_rmse / full_rmse
        print(f"{name:<26}{pairs:>8}{full_rmse:>10.4f}{tracked_rmse:>12.4f}{ratio:>7.3f}{searches:>10}{gap:>12}"
              f"{delay:>12}")
        targets.check(f"{name}: tracking RMSE {tracked_rmse:.4f} px / full {full_rmse:.4f} px = {ratio:.3f} <= "
                      f"{RMSE_LIMIT}", ratio <= RMSE_LIMIT)
        targets.check(f"{name}: longest run of frames a star full mode measures goes unmeasured {gap} <= {period}",
                      gap <= period)
        targets.check(f"{name}: a star entering is measured {delay} frames after full mode first does <= {period}",
                      delay <= period)


def acquisition_sweep(log: Path, periods: list[int], count: int = 300) -> None:
    """CPU ms a frame of tracking mode in this process for each period of full searches (GAUSSFIT, frames
    decoded beforehand, messages encoded), best of two runs, and the searches made: what the period costs."""
    from starlog.centroiding.tracking import TrackingSettings
    from starlog.stages.centroid.frames import FrameExtractor

    with LogReader(log) as reader:
        frames = [img for _, _, img in itertools.islice(reader.frames(), count)]
    cv2.setNumThreads(1)
    reuse_frame_buffers()
    print(f"\n# --acquire-every: tracking in this process on {len(frames)} frames of {log.name} (GAUSSFIT, decoded "
          "beforehand; messages encoded), CPU ms a frame, best of 2; period 1 searches every frame")
    print(f"{'acquire every':>14}{'ms cpu/frame':>14}{'searches':>10}")
    for period in periods:
        extract = FrameExtractor(methods=(CentroidMethod.GAUSSFIT,), gain=1.0, read_noise=3.0,
                                 options={"psf_sigma": 1.2}, tracking=TrackingSettings(acquire_every=period))
        best, searches = float("inf"), 0
        for _ in range(2):
            block, searches = extract.block(), 0
            start = time.process_time()
            for k, image in enumerate(frames):
                detections, centroids, searched = block.measure(image)
                extract.encode(k, k, None, detections, centroids, searched)
                searches += searched
            best = min(best, (time.process_time() - start) / len(frames))
        print(f"{period:>14}{1e3 * best:>14.2f}{searches:>10}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n")[-1])
    ap.add_argument("--quick", action="store_true",
                    help="512x512, 40 stars, 100 / 200 frames, one repeat (about 20 s)")
    ap.add_argument("--frames", type=int, default=None, help="frames of the shorter log [300; --quick 100]")
    ap.add_argument("--size", type=int, default=None, help="frame width and height [1024; --quick 512]")
    ap.add_argument("--stars", type=int, default=None, help="stars [50; --quick 40]")
    ap.add_argument("--methods", default="MOMENT,GAUSSFIT")
    ap.add_argument("--workers", default=f"1,{os.cpu_count() or 1}")
    ap.add_argument("--repeats", type=int, default=None, help="runs of each figure, the least kept [2; --quick 1]")
    ap.add_argument("--dir", default="/tmp/starlog_bench_centroid")
    ap.add_argument("--tracking-size", type=int, default=None, help="frame side of the tracking regimes [512; --quick 256]")
    ap.add_argument("--tracking-frames", type=int, default=None, help="frames of each tracking regime [1500; --quick 600]")
    ap.add_argument("--tracking-only", action="store_true",
                    help="only tracking against full mode and the --acquire-every sweep")
    args = ap.parse_args(argv)
    for name, full, quick in (("frames", 300, 100), ("size", 1024, 512), ("stars", 50, 40), ("repeats", 2, 1),
                              ("tracking_size", 512, 256), ("tracking_frames", 1500, 600)):
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)
    folder = Path(args.dir)
    folder.mkdir(parents=True, exist_ok=True)
    targets = Targets()
    if not args.tracking_only:
        stage_speed(args, folder)
    tracking_accuracy(args, targets)
    sweep_log = folder / f"sim{args.size}_{args.stars}_{args.frames}.mcap"
    simulate(sweep_log, args.frames, args.size, args.stars)
    acquisition_sweep(sweep_log, [1, 10, 25, 50, 100, 200])
    return targets.report()


def stage_speed(args: argparse.Namespace, folder: Path) -> None:
    """The stage's parts in process and its CLI end to end, against SEP: figures printed."""
    n = args.frames
    logs = {k: folder / f"sim{args.size}_{args.stars}_{k}.mcap" for k in (n, 2 * n)}
    for k, path in logs.items():
        simulate(path, k, args.size, args.stars)
    methods = args.methods.split(",")
    parts: dict[str, list[float]] = {}
    runs: dict[tuple[str, int, int], list[tuple[float, float]]] = {}
    for _ in range(args.repeats):
        for key, value in in_process_parts(logs[n], methods, 30).items():
            parts.setdefault(key, []).append(value)
        for m in methods:
            for w in (int(x) for x in args.workers.split(",")):
                for k, path in logs.items():
                    runs.setdefault((m, w, k), []).append(cli_run(path, folder / "out.mcap", m, w))
    best = {key: min(v) for key, v in parts.items()}
    sep_cpu = best["SEP"]
    print(f"# {args.size}x{args.size}, {args.stars} stars; marginal over {n} -> {2 * n} frames; "
          f"min of {args.repeats}; SEP = Background + extract + winpos, one core")
    print(f"{'part (in process)':<34}{'ms cpu/frame':>14}{'SEP/part':>9}")
    for key, value in best.items():
        print(f"{key:<34}{1e3 * value:>14.2f}{sep_cpu / value:>9.2f}")
    print(f"\n{'starlog centroid (CLI)':<34}{'ms cpu/frame':>14}{'fps(cpu)':>10}{'x SEP':>8}{'fps(wall)':>11}")
    for m in methods:
        for w in (int(x) for x in args.workers.split(",")):
            (w1, c1), (w2, c2) = min(runs[(m, w, n)]), min(runs[(m, w, 2 * n)])
            wall_fps = n / (w2 - w1)
            if w == 1:
                cpu = (c2 - c1) / n
                label = f"{m} --workers {w}"
                print(f"{label:<34}{1e3 * cpu:>14.2f}{1 / cpu:>10.1f}{sep_cpu / cpu:>8.2f}{wall_fps:>11.1f}")
            else:
                print(f"{f'{m} --workers {w}':<34}{'':>14}{'':>10}{'':>8}{wall_fps:>11.1f}")
    print(f"\nSEP: {1 / sep_cpu:.1f} fps (cpu)")


if __name__ == "__main__":
    sys.exit(main())
