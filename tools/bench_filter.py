"""Benchmark of ``starlog filter``: copying kept chunks against a plain disk copy of the same bytes.

Generates a simulated log of 400 1024x1024 mono16 frames (~310 MB of image chunks; ``--quick``:
80 frames of 512x512, ~16 MB) in a temporary folder, then times, in this one run and on the same warm page
cache:

* ``shutil.copyfile`` of the log (the kernel's copy; no fsync), and the same followed by
  ``fsync`` (what ``filter`` does before renaming its output into place);
* ``filter --topic '/camera/*'`` (every image chunk kept whole, ``/sim/truth`` dropped);
* ``filter --start/--end`` on chunk boundaries (every chunk in the range copied whole);
* ``filter --start/--end`` off the boundaries (the two boundary chunk groups re-encoded);
* for the topic filter, its two parts alone: the chunk copy, and the input's SHA-256 that its
  provenance record holds (computed on a thread meanwhile; MB/s of the log read).

Each row is the best of ``--repeat`` runs; MB/s counts the bytes written. The target: ``filter``
copies kept chunks at >= 50 % of the disk copy's speed.

A second table times what a user runs: ``starlog filter LOG -o OUT --topic '/camera/*'`` as a
process (interpreter start-up included) against ``cp`` + ``sync`` of the same file, on the log
and on one twice as long, so that the marginal speed (the extra bytes over the extra
seconds) and the start-up (the intercept) are separate.

Usage::

    python tools/bench_filter.py            # ~300 MB log
    python tools/bench_filter.py --quick    # ~16 MB log

Run time of --quick on a 2-core machine: about 10 s. The targets are
informational (a miss does not fail the run; exit status 0): ``filter`` hashes its input on a
thread while it copies, so it needs a free core, which other jobs on a shared machine decide.
--quick does not judge them: its copies take hundredths of a second, mostly fixed costs.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_targets import Targets  # noqa: E402
from starlog.io import LogReader, file_digest  # noqa: E402
from starlog.io.copying import TopicSelection, copy_log  # noqa: E402
from starlog.sim import SimulationConfig  # noqa: E402
from starlog.stages import simulate_log  # noqa: E402
from starlog.excerpt import filter_log  # noqa: E402

FREE_CORE = ("filter hashes its input on a thread while it copies: it needs a free core, which other jobs on a "
             "shared 2-core machine decide")
QUICK_SMALL = "--quick: a 16 MB log is copied in hundredths of a second, mostly fixed costs; judged in the full run"


def _best(action: Callable[[], Path], repeat: int) -> tuple[float, int]:
    """Fastest wall time of ``action`` and the size of what it wrote."""
    times = []
    size = 0
    for _ in range(repeat):
        start = time.perf_counter()
        written = action()
        times.append(time.perf_counter() - start)
        size = written.stat().st_size
        written.unlink()
    return min(times), size


def _copy(src: Path, dst: Path, *, sync: bool) -> Callable[[], Path]:
    def run() -> Path:
        shutil.copyfile(src, dst)
        if sync:
            with open(dst, "rb+") as f:
                os.fsync(f.fileno())
        return dst

    return run


def _filter(src: Path, dst: Path, **options: object) -> Callable[[], Path]:
    def run() -> Path:
        filter_log(src, dst, force=True, **options)  # type: ignore[arg-type]
        return dst

    return run


def _slice(src: Path, dst: Path) -> Callable[[], Path]:
    """The topic filter's copy without its provenance record (no digest of the input)."""

    def run() -> Path:
        copy_log(src, dst, topics=TopicSelection(("/camera/*",)), force=True)
        return dst

    return run


def _digest(src: Path, dst: Path) -> Callable[[], Path]:
    """The input's SHA-256 alone (``filter`` hashes it on a thread while it copies); writes nothing."""

    def run() -> Path:
        file_digest(src)
        dst.write_bytes(b"")
        return dst

    return run


def _ranges(log: Path) -> tuple[tuple[int, int], tuple[int, int]]:
    """A range on image-chunk boundaries (the 2nd image chunk's start to the last one's) and one off them.

    On the boundaries every image chunk in the range is copied whole (the small frame-info and
    truth chunks that straddle a boundary are re-encoded); off them, two image chunks are too.
    """
    with LogReader(log) as f:
        summary = f.files[0].summary  # a recording: one file
        image = next(c.id for c in summary.channels.values() if c.topic == "/camera/image")
        starts = sorted(ci.message_start_time for ci in summary.chunk_indexes if image in ci.message_index_offsets)
        first, last = f.time_range()
    step = (last - first) // 50
    return (starts[1], starts[-1]), (starts[1] + step, starts[-1] - step)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__.split("\n\n")[-1])
    parser.add_argument("--quick", action="store_true", help="512x512 frames, a ~16 MB log (about 10 s)")
    parser.add_argument("--repeat", type=int, default=3, help="runs per row (the best is kept)")
    parser.add_argument("--dir", type=Path, help="folder for the logs [default: a temporary folder]")
    args = parser.parse_args()
    size, frames = (512, 80) if args.quick else (1024, 400)
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        folder = Path(tmp)
        log = folder / "sim.mcap"
        simulate_log(SimulationConfig(width=size, height=size, n_stars=50, n_frames=frames, seed=1), log,
                     workers=os.cpu_count() or 1)
        log.read_bytes()  # the same warm page cache for every row
        aligned, unaligned = _ranges(log)
        out = folder / "out.mcap"
        rows = [
            ("shutil.copyfile", _copy(log, out, sync=False)),
            ("shutil.copyfile + fsync", _copy(log, out, sync=True)),
            ("filter --topic '/camera/*'", _filter(log, out, topics=["/camera/*"])),
            ("filter --start/--end on chunk boundaries", _filter(log, out, start=aligned[0], end=aligned[1])),
            ("filter --start/--end off chunk boundaries", _filter(log, out, start=unaligned[0], end=unaligned[1])),
            ("  of which: chunk copy alone (copy_log)", _slice(log, out)),
            ("  of which: input SHA-256 for the provenance", _digest(log, out)),
        ]
        results = [(name, *_best(action, args.repeat)) for name, action in rows]
        long_log = folder / "sim4.mcap"
        simulate_log(SimulationConfig(width=size, height=size, n_stars=50, n_frames=2 * frames, seed=1), long_log,
                     workers=os.cpu_count() or 1)
        long_log.read_bytes()
        targets = Targets()
        not_judged = QUICK_SMALL if args.quick else ""
        report_in_process(results, frames, size, args.repeat, targets, not_judged)
        cli_table(log, long_log, out, args.repeat, targets, not_judged)
    return targets.report()


def report_in_process(results: list[tuple[str, float, int]], frames: int, size: int, repeat: int,
                      targets: Targets, not_judged: str) -> None:
    """The in-process table: each operation's MB/s against copyfile and copyfile + fsync."""
    copy_speed = results[0][2] / results[0][1]
    synced_speed = results[1][2] / results[1][1]
    print(f"log: {frames} frames {size}x{size} mono16, {log_size(results):.0f} MB; best of {repeat}; "
          f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"| {'operation':<46} | {'MB written':>10} | {'s':>6} | {'MB/s':>7} | {'vs copyfile':>11} | "
          f"{'vs copy+fsync':>13} |")
    print(f"|{'-' * 48}|{'-' * 12}|{'-' * 8}|{'-' * 9}|{'-' * 13}|{'-' * 15}|")
    for name, seconds, written in results:
        written = written or results[0][2]  # the digest writes nothing: count the log it reads
        speed = written / seconds
        print(f"| {name:<46} | {written / 1e6:>10.1f} | {seconds:>6.3f} | {speed / 1e6:>7.0f} | "
              f"{100 * speed / copy_speed:>10.0f}% | {100 * speed / synced_speed:>12.0f}% |")
        if name.startswith("filter"):
            targets.check(f"{name}: {100 * speed / synced_speed:.0f} % of copyfile + fsync's speed >= 50 %",
                          speed >= 0.5 * synced_speed, not_judged=not_judged, informational=FREE_CORE)


def _cli_filter(src: Path, dst: Path) -> Callable[[], Path]:
    def run() -> Path:
        subprocess.run([sys.executable, "-m", "starlog", "filter", str(src), "-o", str(dst), "--topic", "/camera/*",
                        "--force", "-q"], check=True, stdout=subprocess.DEVNULL)
        return dst

    return run


def _cli_copy(src: Path, dst: Path) -> Callable[[], Path]:
    def run() -> Path:
        subprocess.run(["cp", str(src), str(dst)], check=True)
        subprocess.run(["sync", str(dst)], check=True)
        return dst

    return run


def cli_table(short: Path, long: Path, out: Path, repeat: int, targets: Targets, not_judged: str) -> None:
    """CLI filter against cp + sync on two log lengths: marginal MB/s and start-up."""
    rows = {}
    for name, make in (("starlog filter (CLI)", _cli_filter), ("cp + sync", _cli_copy)):
        (t1, b1), (t2, b2) = _best(make(short, out), repeat), _best(make(long, out), repeat)
        marginal = (b2 - b1) / (t2 - t1)
        rows[name] = (t1, t2, b1, b2, marginal, t1 - b1 / marginal)
    print(f"\n| {'command':<22} | {'s short':>7} | {'s long':>7} | {'MB short':>8} | {'MB long':>8} | "
          f"{'marginal MB/s':>13} | {'start-up s':>10} | {'marginal vs cp+sync':>19} | {'long, total vs cp+sync':>22} |")
    print(f"|{'-' * 24}|{'-' * 9}|{'-' * 9}|{'-' * 10}|{'-' * 10}|{'-' * 15}|{'-' * 12}|{'-' * 21}|{'-' * 24}|")
    base = rows["cp + sync"]
    for name, (t1, t2, b1, b2, marginal, startup) in rows.items():
        print(f"| {name:<22} | {t1:>7.3f} | {t2:>7.3f} | {b1 / 1e6:>8.1f} | {b2 / 1e6:>8.1f} | {marginal / 1e6:>13.0f} | "
              f"{startup:>10.2f} | {100 * marginal / base[4]:>18.0f}% | {100 * base[1] / t2:>21.0f}% |")
    marginal, base_marginal = rows["starlog filter (CLI)"][4], base[4]
    targets.check(f"starlog filter (CLI): marginal speed {100 * marginal / base_marginal:.0f} % of cp + sync's >= 50 %",
                  marginal >= 0.5 * base_marginal, not_judged=not_judged, informational=FREE_CORE)


def log_size(results: list[tuple[str, float, int]]) -> float:
    return results[0][2] / 1e6


if __name__ == "__main__":
    sys.exit(main())
