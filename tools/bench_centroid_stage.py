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

Run: python tools/bench_centroid_stage.py [--quick] [--frames 300] [--size 1024] [--methods MOMENT,GAUSSFIT]

Run time of --quick (512x512, 40 stars, 100 / 200 frames, one repeat) on a 2-core machine: about
20 s once its logs are in --dir; the first run simulates them too (about 70 s in all). No pass/fail
target: the figures are printed and the exit status is 0.
"""

from __future__ import annotations

import argparse
import itertools
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from starlog.centroid import CentroidMethod, measure_centroids
from starlog.detect import detect_stars
from starlog.io.reader import LogReader
from starlog.io.records import record_encoder
from starlog.stages._centroid_frames import reuse_frame_buffers

STARLOG = [sys.executable, "-m", "starlog"]


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
    encoder = record_encoder("starlog.Detections", "stars")  # as the stage encodes them, schema check included
    out["encode (detections)"] = per_frame_cpu(lambda d: encoder.encode({"frame": 0}, d), dets)
    return out


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
    args = ap.parse_args(argv)
    for name, full, quick in (("frames", 300, 100), ("size", 1024, 512), ("stars", 50, 40), ("repeats", 2, 1)):
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)
    folder = Path(args.dir)
    folder.mkdir(parents=True, exist_ok=True)
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
