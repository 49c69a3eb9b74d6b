"""Benchmark of the foundation: simulate and ingest throughput, and memory of reading logs.

Prints two tables, every ratio measured in this one run:

1. frames/s and MB/s (raw mono16 pixel bytes per second) of ``simulate`` and ``ingest`` for
   512x512 and 1024x1024 frames, beside numpy ``tofile`` of the same bytes (the disk's raw
   write speed, the ceiling for any logger);
2. peak resident memory of ``starlog info`` and of streaming a whole image channel, for a log
   and one 10x longer (it must stay flat).

Usage::

    python tools/bench_io.py            # full (a few minutes)
    python tools/bench_io.py --quick    # seconds
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

from starlog.sim import SimulationConfig, Simulator
from starlog.stages import ingest_folder, simulate_log


def _mb(frames: int, size: int) -> float:
    return frames * size * size * 2 / 1e6


def bench_throughput(size: int, frames: int, tmp: Path) -> list[tuple[str, float, float]]:
    rows = []
    config = SimulationConfig(width=size, height=size, n_stars=50, n_frames=frames, seed=1)
    sim = Simulator(config)
    images = [sim.render(n).image for n in range(frames)]

    start = time.perf_counter()
    with open(tmp / "raw.bin", "wb") as f:
        for image in images:
            image.tofile(f)
        f.flush()
        os.fsync(f.fileno())
    dt = time.perf_counter() - start
    rows.append(("numpy tofile (reference)", frames / dt, _mb(frames, size) / dt))

    for compression, workers in [("lz4", 1), ("lz4", 2), ("zstd", 2)]:
        out = tmp / f"sim_{size}_{compression}_{workers}.mcap"
        start = time.perf_counter()
        simulate_log(config, out, compression=compression, workers=workers)
        dt = time.perf_counter() - start
        rows.append((f"simulate {compression} workers={workers}", frames / dt, _mb(frames, size) / dt))

    folder = tmp / f"png{size}"
    folder.mkdir(exist_ok=True)
    for n, image in enumerate(images):
        cv2.imwrite(str(folder / f"f{n:05d}.png"), image)
    for compression, workers in [("lz4", 1), ("lz4", 2), ("zstd", 2)]:
        out = tmp / f"ingest_{size}_{compression}_{workers}.mcap"
        start = time.perf_counter()
        ingest_folder(folder, out, fps=300.0, compression=compression, workers=workers)
        dt = time.perf_counter() - start
        rows.append((f"ingest PNG {compression} workers={workers}", frames / dt, _mb(frames, size) / dt))
    return rows


_READ_ALL = """
import sys
from starlog.io import LogReader
with LogReader(sys.argv[1]) as log:
    n = sum(1 for _ in log.frames())
print(n)
"""


def _peak_rss_mib(argv: list[str]) -> float:
    """Peak RSS (MiB) of a command, from GNU time (a forked child's own ``ru_maxrss`` would count the pages
    it inherited from this benchmark process before ``exec``)."""
    result = subprocess.run(["/usr/bin/time", "-f", "STARLOG_MAXRSS_KB %M", *argv], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"{argv} failed:\n{result.stderr}")
    line = [x for x in result.stderr.splitlines() if x.startswith("STARLOG_MAXRSS_KB")][-1]
    return int(line.split()[1]) / 1024


def bench_memory(frames: int, tmp: Path) -> list[tuple[str, int, float, float]]:
    rows = []
    logs = {}
    for n in (frames, 10 * frames):
        config = SimulationConfig(width=256, height=256, n_stars=20, n_frames=n, seed=2)
        logs[n] = tmp / f"mem_{n}.mcap"
        simulate_log(config, logs[n], compression="lz4", workers=2)
    starlog = [sys.executable, "-m", "starlog"]
    for label, argv_of in [
        ("starlog info", lambda p: [*starlog, "info", str(p)]),
        ("stream /camera/image", lambda p: [sys.executable, "-c", _READ_ALL, str(p)]),
    ]:
        small, large = (_peak_rss_mib(argv_of(logs[n])) for n in (frames, 10 * frames))
        rows.append((label, frames, small, large))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small sizes, seconds")
    parser.add_argument("--memory-only", action="store_true", help="only the memory table")
    args = parser.parse_args()
    cases = [(512, 60), (1024, 20)] if args.quick else [(512, 600), (1024, 150)]
    mem_frames = 100 if args.quick else 500
    print(f"# starlog bench_io  (cores: {os.cpu_count()}, quick: {args.quick})\n")
    with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_TMP")) as d:
        tmp = Path(d)
        print(f"{'frames':>7} {'size':>9}  {'case':<28} {'frames/s':>9} {'MB/s':>8}")
        for size, frames in ([] if args.memory_only else cases):
            for name, fps, mbs in bench_throughput(size, frames, tmp):
                print(f"{frames:>7} {size:>4}x{size:<4}  {name:<28} {fps:>9.1f} {mbs:>8.1f}")
        print("\nTarget: ingest of 512x512 mono16 with lz4 >= 150 MB/s (a 300 Hz camera = 157 MB/s).\n")
        print(f"{'case':<24} {'frames':>7} {'peak MiB':>9} {'10x frames':>11} {'peak MiB':>9} {'growth':>7}")
        for name, n, small, large in bench_memory(mem_frames, tmp):
            print(f"{name:<24} {n:>7} {small:>9.1f} {10 * n:>11} {large:>9.1f} {100 * (large / small - 1):>6.1f}%")
        print("\nTarget: peak memory flat (within 10 %) from 1x to 10x the frames.")


if __name__ == "__main__":
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    main()
