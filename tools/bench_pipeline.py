"""Stage-level throughput of starlog as a user runs it: the CLI on a log on disk, its output written.

For each frame size (512x512 with 40 stars and 1024x1024 with 50 stars by default) and each log
length (300 and 3000 frames at 300 Hz by default) a log is simulated once, then
``python -m starlog <stage>`` (this interpreter, a subprocess) is timed for:

* ``centroid`` with one method on one core (``--workers 1``: MOMENT, GAUSSFIT), and GAUSSFIT on all cores;
* ``track`` of the GAUSSFIT centroids with one model (STATIC, ``sigma_floor = 0.05``);
* ``compensate`` of that one track at one rate (50 Hz, paper protocol);
* ``run`` of GAUSSFIT -> STATIC -> compensate 50 Hz, paper protocol (the same options), all cores.

Printed as Markdown tables, every ratio from this one run:

1. throughput: wall seconds per log length (median of ``--repeat``); the marginal rate, i.e. the
   slope of a straight line through (frames, seconds) as frames/s, so start-up is separate; the
   start-up cost (its intercept). Each repeat runs a stage on every log length in a row and gives
   its own line; the median over the repeats is reported, so a drift of the machine's speed
   between repeats does not enter a rate; with ``--workers 1``, the marginal rate on CPU time (user + sys:
   less sensitive to other jobs on a shared machine; not shown for more workers, whose pool
   processes are children of a fork server, not of the command, and escape the count);
   peak RSS (GNU time ``%M``: the largest process of the command) on the shortest and longest log;
2. the centroid stage against SEP (``sep.Background`` + ``sep.extract`` + ``sep.flux_radius`` +
   ``sep.winpos``, one core, on the same frames held in memory: no decode, no write);
3. a breakdown per stage: the stage run in-process on one core on the shortest log under a
   wall-clock stack sampler (SIGALRM every millisecond; the time since the previous sample goes to
   the innermost starlog frame of the interrupted stack): read/decode and encode/write
   (``starlog.io``, by the reading or writing side it serves), algorithm (``starlog.detect``,
   ``.centroid``, ``.track``, ``.compensate``), stage code (``starlog.stages``, ``.pipeline``,
   ``.cli``: per-message conversion, orchestration), import, other (outside starlog);
4. checks: output SHA-256 identical for ``--workers 1`` and all cores, and on a rerun;
5. the tracker's own time, the denominator of the ``track`` target: ``StarTracker.update`` with the
   stage's options on every frame of the longest log's centroids (decoded beforehand), in this
   process, the best of two runs, timed right after each repeat of the ``track`` stage; the target
   is the median over the repeats of each repeat's ratio, so both sides of a ratio see the machine
   at the same speed. (Before, it was the sampled ``algorithm`` time of the breakdown on the
   shortest log: a few tenths of a second of samples, which moved the ratio by 20 %.)
6. the disk's estimated floor: each stage's output grows by some bytes a frame (a stage's output
   holds its input's data section, the images included, and is synced before the command returns);
   this folder's disk is timed writing ``--disk-probe-mib`` MiB and syncing them (before and after a
   size's stages; the faster of the two), and bytes a frame / that rate estimates the time a frame
   that writing the output takes here. The ``track`` and ``compensate`` targets say when their
   allowance is below it. An estimate: a disk's rate varies (a virtual disk's by 2x from one hour
   to the next), and a file system that shares blocks (Btrfs, XFS) does not write the copied data
   section at all.

Before any timed run, the centroid stage runs once on a few frames with every timed method, so the
compiled kernels' first compilation (and its disk cache) is not timed.

Usage::

    python tools/bench_pipeline.py                  # full run (tens of minutes on 2 cores)
    python tools/bench_pipeline.py --quick          # smoke run: 256x256, 120 and 480 frames
    python tools/bench_pipeline.py --sizes 512 --frames 300,1200 --repeat 2 --keep /tmp/bp --json bp.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import CodeType, FrameType
from typing import Any

import numpy as np

# the environment a user's shell would give the CLI (the SEP helper sets OMP_NUM_THREADS=1 on import)
_USER_ENV = dict(os.environ)
STARLOG = [sys.executable, "-m", "starlog"]
CAMERA_HZ = 300.0
PIPELINE_METHOD, PIPELINE_MODEL, PIPELINE_RATE, PIPELINE_PROTOCOL = "GAUSSFIT", "STATIC", 50, "paper"
TRACK_TOPIC = f"/track/{PIPELINE_METHOD}/{PIPELINE_MODEL}"
RUN_CONFIG = f"""[centroid]
methods = ["{PIPELINE_METHOD}"]
[track]
methods = ["{PIPELINE_METHOD}"]
models = "{PIPELINE_MODEL}"
[track.tracker]
sigma_floor = 0.05
[compensate]
tracks = ["{PIPELINE_METHOD}/{PIPELINE_MODEL}"]
rates = [{PIPELINE_RATE}]
protocols = "{PIPELINE_PROTOCOL}"
"""
CATEGORIES = ("read", "algorithm", "write", "stage", "import", "other")
CATEGORY_TITLES = {"read": "read/decode", "algorithm": "algorithm", "write": "encode/write",
                   "stage": "stage code", "import": "import", "other": "other"}
ALGORITHM_PACKAGES = ("starlog.detect", "starlog.centroid", "starlog.track", "starlog.compensate", "starlog.sim")
READ_WORDS = ("decompress", "decode", "unpack", "read", "parse", "load", "digest")
WRITE_WORDS = ("compress", "encode", "pack", "write", "dump", "serial")


def stars_for(size: int) -> int:
    """40 stars on 512x512 and 50 on 1024x1024; other sizes in proportion to the side."""
    return {512: 40, 1024: 50}.get(size, max(8, round(40 * size / 512)))


# ---------------------------------------------------------------- measuring a command
@dataclass
class Timing:
    """One command: wall seconds, CPU seconds (user + sys, children included), peak RSS in MiB."""

    seconds: float
    cpu_seconds: float
    peak_mib: float


def run_command(argv: Sequence[str]) -> Timing:
    """Run ``argv`` (user's environment, output discarded) and measure it; raise with its stderr on failure.

    The peak comes from GNU time, not from ``wait4`` on a child of this process where it can be
    avoided: a forked child's ``ru_maxrss`` may count pages inherited from this process.
    """
    gnu_time = shutil.which("time", path="/usr/bin:/bin")
    prefix = [gnu_time, "-f", "BENCH_PIPELINE %U %S %M"] if gnu_time else []
    with tempfile.TemporaryFile("w+") as err:
        start = time.perf_counter()
        proc = subprocess.Popen([*prefix, *argv], stdout=subprocess.DEVNULL, stderr=err, env=_USER_ENV)
        _, status, usage = os.wait4(proc.pid, 0)
        seconds = time.perf_counter() - start
        proc.returncode = os.waitstatus_to_exitcode(status)
        err.seek(0)
        text = err.read()
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed:\n{text}")
    if gnu_time:
        user, sys_, peak_kb = [x for x in text.splitlines() if x.startswith("BENCH_PIPELINE")][-1].split()[1:]
        return Timing(seconds, float(user) + float(sys_), int(peak_kb) / 1024)
    return Timing(seconds, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024)


def marginal_fit(frames: Sequence[int], seconds: Sequence[float]) -> tuple[float, float]:
    """Least-squares line ``seconds = start_up + frames / rate``; returns ``(rate, start_up)``.

    The rate is NaN when the line does not rise (noise larger than the work of the extra frames).
    """
    n = np.asarray(frames, dtype=float)
    t = np.asarray(seconds, dtype=float)
    if n.size < 2 or np.ptp(n) == 0:
        raise ValueError("the marginal rate needs at least two different log lengths")
    slope, intercept = np.polyfit(n, t, 1)
    return (1.0 / slope if slope > 0 else math.nan), float(intercept)


def sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


# ---------------------------------------------------------------- in-process breakdown
_MISSING = object()


def _frame_tag(code: CodeType, module: str) -> str | None:
    """Category of one stack frame; ``"io"`` is a log-layer frame that serves whichever side calls it."""
    if code.co_filename.startswith("<frozen importlib"):
        return "import"
    if module == "starlog.io" or module.startswith("starlog.io."):
        name = code.co_name.lower()
        if module == "starlog.io.reader" or any(w in name for w in READ_WORDS):
            return "read"
        if module == "starlog.io.writer" or any(w in name for w in WRITE_WORDS):
            return "write"
        return "io"
    if any(module == p or module.startswith(p + ".") for p in ALGORITHM_PACKAGES):
        return "algorithm"
    if module == "starlog" or module.startswith("starlog."):
        return "stage"
    return None


def classify(frame: FrameType | None, cache: dict[CodeType, Any]) -> str:
    """Category of a stack, from its innermost starlog frame.

    A log-layer helper (e.g. schema validation) takes the side of the nearest enclosing reading or
    writing frame of the log layer; any import machinery on the stack makes it ``import``.
    """
    decided: str | None = None
    pending_io = False
    while frame is not None:
        code = frame.f_code
        tag = cache.get(code, _MISSING)
        if tag is _MISSING:
            tag = cache[code] = _frame_tag(code, frame.f_globals.get("__name__") or "")
        if tag == "import":
            return "import"
        if decided is None and tag is not None:
            if tag == "io":
                pending_io = True
            elif pending_io and tag not in ("read", "write"):
                decided = "other"
            else:
                decided = tag
        frame = frame.f_back
    return decided or "other"


@dataclass
class StackSampler:
    """Wall-clock sampler of the main thread: every ``interval`` s (SIGALRM), the time since the
    previous sample goes to the category of the interrupted stack. A signal that arrives during a
    long C call is handled when the call returns, in the frame that made it, so that time goes to
    the caller."""

    interval: float = 0.001
    seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    _cache: dict[CodeType, Any] = field(default_factory=dict)
    _last: float = 0.0

    def _sample(self, signum: int, frame: FrameType | None) -> None:
        now = time.perf_counter()
        self.seconds[classify(frame, self._cache)] += now - self._last
        self._last = now

    def __enter__(self) -> StackSampler:
        self._previous = signal.signal(signal.SIGALRM, self._sample)
        self._last = time.perf_counter()
        signal.setitimer(signal.ITIMER_REAL, self.interval, self.interval)
        return self

    def __exit__(self, *exc: object) -> None:
        signal.setitimer(signal.ITIMER_REAL, 0, 0)
        signal.signal(signal.SIGALRM, self._previous)
        self.seconds["other"] += time.perf_counter() - self._last


def profile_stage(json_path: str, cli_args: list[str]) -> int:
    """Run one CLI command in this process under :class:`StackSampler`; write seconds per category."""
    import importlib
    import pkgutil

    import starlog
    from starlog.cli import cli

    # import every module first, so lazy imports inside the commands (start-up) are not sampled
    for module in pkgutil.walk_packages(starlog.__path__, "starlog."):
        if not module.name.endswith("__main__"):
            importlib.import_module(module.name)
    start = time.perf_counter()
    with StackSampler() as sampler:
        cli.main(args=cli_args, prog_name="starlog", standalone_mode=False)
    total = time.perf_counter() - start
    Path(json_path).write_text(json.dumps({"total": total, **{c: sampler.seconds.get(c, 0.0) for c in CATEGORIES}}))
    return 0


def breakdown(cli_args: list[str], json_path: Path) -> dict[str, float]:
    """Seconds per category of one stage run in-process (in a fresh interpreter, like the CLI)."""
    argv = [sys.executable, str(Path(__file__).resolve()), "--profile-stage", str(json_path), "--", *cli_args]
    run_command(argv)
    return json.loads(json_path.read_text())


# ---------------------------------------------------------------- SEP reference
def sep_reference(log: Path, max_frames: int) -> dict[str, float]:
    """SEP frames/s on one core on the first frames of ``log`` (decoded beforehand, not timed)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_centroid import sep_extract  # sets OMP_NUM_THREADS=1 in this process's environment

    from starlog.io import LogReader

    seconds = 0.0
    count = 0
    with LogReader(log) as reader:
        for index, _, image in reader.frames():
            if index >= max_frames:
                break
            start = time.perf_counter()
            sep_extract(image)
            seconds += time.perf_counter() - start
            count += 1
    return {"frames": count, "seconds": seconds, "fps": count / seconds}


# ---------------------------------------------------------------- the stages
def simulate(size: int, frames: int, path: Path, workers: int) -> None:
    """The input log (kept and reused when it exists, e.g. under ``--keep``)."""
    if path.exists():
        return
    run_command([*STARLOG, "simulate", "-o", str(path), "--size", f"{size}x{size}", "--stars", str(stars_for(size)),
                 "--fps", str(CAMERA_HZ), "--frames", str(frames), "--jitter", "25:0.05", "--seed", "1",
                 "--workers", str(workers), "-q"])


def warm_up(log: Path, folder: Path, methods: list[str]) -> None:
    """Run the centroid stage once, untimed, on the first frames with every timed method: the compiled
    kernels are compiled then and cached on disk (on a fresh clone, or after a change of the code), so a
    compilation never lands in a timed run (it added seconds to one run and moved its peak memory)."""
    out = folder / ".warm-up.mcap"
    run_command([*STARLOG, "centroid", str(log), "-o", str(out), "--method", ",".join(methods), "--end", "frame:3",
                 "--workers", "1", "-q", "--force"])
    out.unlink(missing_ok=True)


def centroid_command(log: Path, folder: Path, method: str, workers: int) -> tuple[list[str], Path]:
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / f"centroid_{method}.mcap"
    return [*STARLOG, "centroid", str(log), "-o", str(out), "--method", method, "--workers", str(workers),
            "-q", "--force"], out


def chain_commands(log: Path, folder: Path, workers: int) -> list[tuple[str, list[str], Path]]:
    """(label, CLI arguments, output) of the pipeline's stages one by one, then ``run``, in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    config = folder / "pipeline.toml"
    config.write_text(RUN_CONFIG)
    centroid, centroids = centroid_command(log, folder, PIPELINE_METHOD, workers)
    tracks, compensated, run_out = folder / "track.mcap", folder / "compensate.mcap", folder / "run.mcap"
    common = ["--workers", str(workers), "-q", "--force"]
    return [
        (f"centroid {PIPELINE_METHOD}", centroid, centroids),
        (f"track {PIPELINE_MODEL}", [*STARLOG, "track", str(centroids), "-o", str(tracks), "--centroids",
                                     PIPELINE_METHOD, "--model", PIPELINE_MODEL, "--set", "sigma_floor=0.05",
                                     *common], tracks),
        (f"compensate {PIPELINE_RATE} Hz {PIPELINE_PROTOCOL}",
         [*STARLOG, "compensate", str(tracks), "-o", str(compensated), "--track", TRACK_TOPIC, "--rate",
          str(PIPELINE_RATE), "--protocol", PIPELINE_PROTOCOL, *common], compensated),
        ("run (paper protocol)", [*STARLOG, "run", str(log), "-o", str(run_out), "--config", str(config), *common],
         run_out),
    ]


@dataclass
class StageResult:
    """One timed stage across the log lengths, run as pairs (every length once per repeat, in a row).

    ``seconds``/``cpu_seconds``: the median per length; ``paired``/``paired_cpu``: per repeat, the
    seconds of each length; peak: the largest.
    """

    label: str
    workers: int
    frames: list[int] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    cpu_seconds: list[float] = field(default_factory=list)
    peak_mib: list[float] = field(default_factory=list)
    digests: dict[int, list[str]] = field(default_factory=dict)
    paired: list[list[float]] = field(default_factory=list)
    paired_cpu: list[list[float]] = field(default_factory=list)
    output_bytes: list[int] = field(default_factory=list)

    def add_pairs(self, frames: list[int], runs: list[list[Timing]], digests: dict[int, list[str]]) -> None:
        """``runs[r][i]``: repeat ``r`` on the log of ``frames[i]`` frames."""
        self.frames = list(frames)
        self.paired = [[t.seconds for t in run] for run in runs]
        self.paired_cpu = [[t.cpu_seconds for t in run] for run in runs]
        self.seconds = [float(np.median([run[i] for run in self.paired])) for i in range(len(frames))]
        self.cpu_seconds = [float(np.median([run[i] for run in self.paired_cpu])) for i in range(len(frames))]
        self.peak_mib = [max(run[i].peak_mib for run in runs) for i in range(len(frames))]
        self.digests = digests

    def fit(self) -> dict[str, float]:
        """Median over the repeats of each repeat's own line: drift between repeats cancels within a pair."""
        fits = [marginal_fit(self.frames, run) for run in self.paired]
        cpu = [marginal_fit(self.frames, run)[0] for run in self.paired_cpu]
        return {"rate": _median([f[0] for f in fits]), "start_up": _median([f[1] for f in fits]),
                "cpu_rate": _median(cpu), "peak_growth": self.peak_mib[-1] / self.peak_mib[0] - 1.0,
                "bytes_per_frame": self.bytes_per_frame()}

    def bytes_per_frame(self) -> float:
        """How much the output grows a frame (NaN when the output sizes were not recorded)."""
        if len(self.output_bytes) != len(self.frames) or len(self.frames) < 2:
            return math.nan
        return (self.output_bytes[-1] - self.output_bytes[0]) / (self.frames[-1] - self.frames[0])


def disk_write_rate(folder: Path, mib: int, block_mib: int = 8) -> float:
    """Bytes per second this folder's disk takes, ``mib`` MiB written and synced (``fdatasync``) as a
    stage's output is. One block of random bytes written again and again: a compressing file system
    does not flatter the rate (one that deduplicates would)."""
    block = os.urandom(block_mib << 20)
    path = folder / ".bench-disk-probe"
    try:
        start = time.perf_counter()
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            for _ in range(max(1, mib // block_mib)):
                os.write(fd, block)
            getattr(os, "fdatasync", os.fsync)(fd)
        finally:
            os.close(fd)
        seconds = time.perf_counter() - start
    finally:
        path.unlink(missing_ok=True)
    return max(1, mib // block_mib) * len(block) / seconds


def write_floor(bytes_per_frame: float, disk_rate: float) -> float:
    """Seconds a frame spent writing ``bytes_per_frame`` at ``disk_rate`` bytes/s (NaN when unknown)."""
    return bytes_per_frame / disk_rate if disk_rate > 0 and math.isfinite(bytes_per_frame) else math.nan


def _seconds_per_frame(rate: float) -> float:
    """1 / rate; infinite for a rate that could not be measured (a line that did not rise: NaN or 0)."""
    return 1.0 / rate if rate > 0 else math.inf


def _median(values: list[float]) -> float:
    """Median, NaN (a repeat whose line did not rise) counted as the slowest."""
    return float(np.median([v if not math.isnan(v) else 0.0 for v in values]))


def timed(label: str, argv: list[str], out: Path) -> tuple[Timing, str]:
    timing = run_command(argv)
    print(f"  {label}: {timing.seconds:.1f} s", file=sys.stderr, flush=True)
    return timing, sha256(out)


def bench_size(size: int, lengths: list[int], root: Path, args: argparse.Namespace) -> dict[str, Any]:
    """Every table's figures for one frame size.

    Stage by stage, each repeat runs every log length in a row, so a drift of the machine's speed
    between repeats does not enter a marginal rate (the slope of one repeat's pair of lengths).
    """
    n_all = args.workers_all
    results: dict[tuple[str, int], StageResult] = {}
    logs, plans = {}, {}
    for n in lengths:
        logs[n] = root / f"sim_{size}_{n}.mcap"
        print(f"# {size}x{size}, {n} frames: simulate", file=sys.stderr, flush=True)
        simulate(size, n, logs[n], n_all)
        plan = [(f"centroid {m}", 1, *centroid_command(logs[n], root / f"{n}/workers1", m, 1))
                for m in args.methods]
        plan += [(label, n_all, argv, out) for label, argv, out in chain_commands(logs[n], root / f"{n}/all", n_all)]
        plans[n] = plan
    warm_up(logs[lengths[0]], root, args.methods)  # args.methods holds the pipeline's method too
    track_label = f"track {PIPELINE_MODEL}"
    tracker_times: list[float] = []  # the tracker alone, once after each repeat of the track stage
    disk_rates = [disk_write_rate(root, args.disk_probe_mib)]
    print(f"  disk: {disk_rates[-1] / 1e6:.0f} MB/s written and synced", file=sys.stderr, flush=True)
    for k, (label, workers, _, _) in enumerate(plans[lengths[0]]):  # stage order: a stage's input exists
        runs: list[list[Timing]] = []
        digests: dict[int, list[str]] = {n: [] for n in lengths}
        for _ in range(args.repeat):
            run = []
            for n in lengths:
                _, _, argv, out = plans[n][k]
                timing, digest = timed(f"{size} {n} {label} w{workers}", argv, out)
                run.append(timing)
                digests[n].append(digest)
            runs.append(run)
            if label == track_label:
                tracker_times.append(tracker_alone(root / f"{lengths[-1]}/all/centroid_{PIPELINE_METHOD}.mcap"))
                print(f"  tracker alone: {1e3 * tracker_times[-1]:.3f} ms a frame", file=sys.stderr, flush=True)
        results[(label, workers)] = StageResult(label, workers)
        results[(label, workers)].add_pairs(lengths, runs, digests)
        results[(label, workers)].output_bytes = [plans[n][k][3].stat().st_size for n in lengths]
    disk_rates.append(disk_write_rate(root, args.disk_probe_mib))
    print(f"  disk: {disk_rates[-1] / 1e6:.0f} MB/s written and synced", file=sys.stderr, flush=True)
    track_runs = next(r for r in results.values() if r.label == track_label).paired
    track_ratio = float(np.median([_seconds_per_frame(marginal_fit(lengths, run)[0]) / t
                                   for run, t in zip(track_runs, tracker_times, strict=True)]))
    checks: list[tuple[str, bool]] = []
    for n in lengths:
        checks.append((f"{n} frames: centroid {PIPELINE_METHOD} --workers 1 == --workers {n_all}",
                       _same(root / f"{n}/workers1/centroid_{PIPELINE_METHOD}.mcap",
                             root / f"{n}/all/centroid_{PIPELINE_METHOD}.mcap")))
        checks.append((f"{n} frames: run == centroid, track, compensate one by one",
                       _same(root / f"{n}/all/run.mcap", root / f"{n}/all/compensate.mcap")))
    checks += determinism_checks(logs[lengths[0]], lengths[0], root, results, args)
    sep = sep_reference(logs[lengths[0]], args.sep_frames)
    print(f"  SEP: {sep['fps']:.1f} frames/s", file=sys.stderr, flush=True)
    profiles = breakdowns(logs[lengths[0]], root / f"{lengths[0]}/profile", args)
    return {"size": size, "stars": stars_for(size), "lengths": lengths,
            "stages": [{**asdict(r), **r.fit()} for r in results.values()],
            "sep": sep, "breakdown": profiles, "frames_profiled": lengths[0],
            "tracker_s_per_frame": float(np.median(tracker_times)), "track_ratio": track_ratio,
            "disk_rates": disk_rates, "disk_rate": max(disk_rates),
            "checks": [{"check": text, "ok": ok} for text, ok in checks]}


def tracker_alone(centroids: Path, repeat: int = 2) -> float:
    """Seconds a frame of the tracker alone (``StarTracker.update``, the ``track`` stage's options) on every
    frame of the centroid channel of ``centroids``, decoded beforehand; the best of ``repeat`` runs."""
    from starlog.io import LogReader
    from starlog.track import MotionModel, StarTracker, TrackerConfig

    with LogReader(centroids) as log:
        frames = []
        for message in log.messages(f"/stars/centroids/{PIPELINE_METHOD}"):
            stars = message.payload["stars"]
            columns = [np.array([star[k] for star in stars], dtype=np.float64) for k in ("x", "y", "sigma", "flux")]
            frames.append((message.log_time, *columns))
    best = math.inf
    for _ in range(repeat):
        tracker = StarTracker(TrackerConfig(model=MotionModel.parse(PIPELINE_MODEL), sigma_floor=0.05))
        start = time.perf_counter()
        for log_time, x, y, sigma, flux in frames:
            tracker.update(log_time, x, y, sigma, flux)
        tracker.brightest_track()
        best = min(best, time.perf_counter() - start)
    return best / len(frames)


def _same(a: Path, b: Path) -> bool:
    return sha256(a) == sha256(b)


def determinism_checks(log: Path, n: int, root: Path, results: dict[tuple[str, int], StageResult],
                       args: argparse.Namespace) -> list[tuple[str, bool]]:
    """On the shortest log: the other stages with ``--workers 1``, and a rerun of every stage on all cores."""
    checks = []
    one = chain_commands(log, root / f"{n}/workers1", 1)
    for label, argv, out in one[1:]:  # the centroid stage on one core is already timed
        timed(f"{n} {label} w1 (check)", argv, out)
    for label, argv, out in chain_commands(log, root / f"{n}/rerun", args.workers_all):
        timed(f"{n} {label} (rerun)", argv, out)
    for (label, _, out), (_, _, rerun) in zip(chain_commands(log, root / f"{n}/all", args.workers_all),
                                              chain_commands(log, root / f"{n}/rerun", args.workers_all)):
        checks.append((f"{n} frames: {label} rerun gives the same bytes", _same(out, rerun)))
        if not label.startswith("centroid"):
            checks.append((f"{n} frames: {label} --workers 1 == --workers {args.workers_all}",
                           _same(root / f"{n}/workers1" / out.name, out)))
    for result in results.values():
        for frames, digests in result.digests.items():
            if len(digests) > 1:
                checks.append((f"{frames} frames: {result.label} w{result.workers} same bytes on all "
                               f"{len(digests)} repeats", len(set(digests)) == 1))
    return checks


def breakdowns(log: Path, folder: Path, args: argparse.Namespace) -> dict[str, dict[str, float]]:
    """Each stage in-process on one core, under the stack sampler."""
    folder.mkdir(parents=True, exist_ok=True)
    plan = [(f"centroid {m}", centroid_command(log, folder, m, 1)[0]) for m in args.methods
            if m != PIPELINE_METHOD]
    plan += [(label, argv) for label, argv, _ in chain_commands(log, folder, 1)]
    out = {}
    for label, argv in plan:
        out[label] = breakdown(argv[len(STARLOG):], folder / f"{label.split()[0]}_{len(out)}.json")
        print(f"  profile {label}: {out[label]['total']:.1f} s", file=sys.stderr, flush=True)
    return out


# ---------------------------------------------------------------- tables
def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A Markdown table with padded columns (text left, numbers right)."""
    cells = [[str(h) for h in headers]] + [[str(c) for c in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    numeric = [all(_is_number(r[i]) for r in cells[1:]) for i in range(len(headers))]

    def line(row: list[str]) -> str:
        return "| " + " | ".join(c.rjust(w) if num else c.ljust(w) for c, w, num in zip(row, widths, numeric)) + " |"

    rule = "|" + "|".join(("-" * (w + 1) + ":") if num else ("-" * (w + 2)) for w, num in zip(widths, numeric)) + "|"
    return "\n".join([line(cells[0]), rule, *(line(r) for r in cells[1:])])


def _is_number(text: str) -> bool:
    try:
        float(text.rstrip("x%").replace(",", ""))
    except ValueError:
        return text in ("", "n/a")
    return True


def _f(value: float, digits: int = 1) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value:,.{digits}f}"


def _x(ratio: float) -> str:
    return _f(ratio, 2) + ("x" if math.isfinite(ratio) else "")


def throughput_table(sizes: list[dict[str, Any]]) -> str:
    lengths = sizes[0]["lengths"]
    headers = ["size", "stage", "workers", *(f"s @{n}" for n in lengths), "frames/s marginal", "x camera",
               "start-up s", "frames/s cpu", f"peak MiB @{lengths[0]}", f"@{lengths[-1]}", "growth",
               "output KB/frame", "disk floor ms/frame"]
    rows = []
    for s in sizes:
        for r in s["stages"]:
            floor = write_floor(r.get("bytes_per_frame", math.nan), s.get("disk_rate", math.nan))
            rows.append([f"{s['size']}², {s['stars']} stars", r["label"], r["workers"], *(_f(x, 2) for x in r["seconds"]),
                         _f(r["rate"]), _x(r["rate"] / CAMERA_HZ), _f(r["start_up"], 2),
                         _f(r["cpu_rate"]) if r["workers"] == 1 else "n/a", _f(r["peak_mib"][0]), _f(r["peak_mib"][-1]),
                         _f(100 * r["peak_growth"]) + "%", _f(r.get("bytes_per_frame", math.nan) / 1e3),
                         _f(1e3 * floor, 2)])
    return markdown_table(headers, rows)


def _stage(s: dict[str, Any], label: str, workers: int | None = None) -> dict[str, Any] | None:
    found = [r for r in s["stages"] if r["label"] == label and (workers is None or r["workers"] == workers)]
    return found[0] if found else None


def sep_table(sizes: list[dict[str, Any]], workers_all: int) -> str:
    headers = ["size", "SEP frames/s (1 core, in memory)", "centroid stage", "frames/s marginal", "x SEP",
               "algorithm only frames/s", "x SEP", f"workers {workers_all} / 1"]
    rows = []
    for s in sizes:
        sep_fps = s["sep"]["fps"]
        for r in s["stages"]:
            if not r["label"].startswith("centroid"):
                continue
            prof = s["breakdown"].get(r["label"]) if r["workers"] == 1 else None
            algo = s["frames_profiled"] / prof["algorithm"] if prof and prof["algorithm"] > 0 else math.nan
            one = _stage(s, r["label"], 1)
            ratio = r["rate"] / one["rate"] if one and r["workers"] != 1 else math.nan
            rows.append([f"{s['size']}²", _f(sep_fps), f"{r['label'].split()[1]} w{r['workers']}", _f(r["rate"]),
                         _x(r["rate"] / sep_fps), _f(algo), _x(algo / sep_fps),
                         _x(ratio)])
    return markdown_table(headers, rows)


def breakdown_table(sizes: list[dict[str, Any]]) -> str:
    headers = ["size", "stage (1 core)", "frames", "in-process s", *(f"{CATEGORY_TITLES[c]} ms/frame" for c in CATEGORIES)]
    rows = []
    for s in sizes:
        n = s["frames_profiled"]
        for label, prof in s["breakdown"].items():
            total = sum(prof[c] for c in CATEGORIES) or 1.0
            rows.append([f"{s['size']}²", label, n, _f(prof["total"], 2),
                         *(f"{1e3 * prof[c] / n:.2f} ({100 * prof[c] / total:.0f}%)" for c in CATEGORIES)])
    return markdown_table(headers, rows)


def checks_table(sizes: list[dict[str, Any]]) -> str:
    rows = [[f"{s['size']}²", c["check"], "same" if c["ok"] else "DIFFERENT"] for s in sizes for c in s["checks"]]
    return markdown_table(["size", "output SHA-256", "result"], rows)


def targets(sizes: list[dict[str, Any]], workers_all: int) -> list[tuple[str, bool]]:
    """The stage-level targets, each judged on this run's figures (every size measured)."""
    out = []
    for s in sizes:
        tag = f"{s['size']}²"
        run = _stage(s, "run (paper protocol)")
        out.append((f"{tag}: run marginal {_f(run['rate'])} frames/s >= 300", run["rate"] >= 300))
        sep_fps = s["sep"]["fps"]
        for method, factor in (("MOMENT", 3.0), ("GAUSSFIT", 2.0)):
            one = _stage(s, f"centroid {method}", 1)
            if one:
                out.append((f"{tag}: centroid {method} --workers 1 {_f(one['rate'])} frames/s >= {factor} x SEP "
                            f"{_f(sep_fps)}", one["rate"] >= factor * sep_fps))
        one, all_ = _stage(s, f"centroid {PIPELINE_METHOD}", 1), _stage(s, f"centroid {PIPELINE_METHOD}", workers_all)
        out.append((f"{tag}: centroid {PIPELINE_METHOD} --workers {workers_all} / --workers 1 = "
                    f"{_f(all_['rate'] / one['rate'], 2)} >= 1.8", all_["rate"] >= 1.8 * one["rate"]))
        track = _stage(s, f"track {PIPELINE_MODEL}")
        ratio = s["track_ratio"]
        out.append((f"{tag}: track marginal time {_f(1e3 * _seconds_per_frame(track['rate']), 3)} ms / tracker's own time "
                    f"{_f(1e3 * s['tracker_s_per_frame'], 3)} ms = {_f(ratio, 2)} <= 1.5 (median of the repeats' "
                    "ratios)" + disk_note(s, track, 1.5 * s["tracker_s_per_frame"]), ratio <= 1.5))
        comp = _stage(s, f"compensate {PIPELINE_RATE} Hz {PIPELINE_PROTOCOL}")
        extra = 1200 * _seconds_per_frame(comp["rate"])
        out.append((f"{tag}: compensate of 1200 frames = {_f(extra, 2)} s + start-up {_f(comp['start_up'], 2)} s; "
                    "<= 1 s + start-up" + disk_note(s, comp, 1.0 / 1200), extra <= 1.0))
        for r in s["stages"]:
            out.append((f"{tag}: {r['label']} w{r['workers']} peak memory {_f(100 * r['peak_growth'])}% from "
                        f"{r['frames'][0]} to {r['frames'][-1]} frames, within 10 %", abs(r["peak_growth"]) <= 0.10))
        for c in s["checks"]:
            if "one by one" not in c["check"]:
                out.append((f"{tag}: {c['check']}", c["ok"]))
    return out


def disk_note(s: dict[str, Any], stage: dict[str, Any], allowed: float) -> str:
    """What writing ``stage``'s output costs a frame on this disk (estimated from this run's probe), against the
    ``allowed`` seconds a frame of its target; flagged when that alone exceeds the allowance."""
    floor = write_floor(stage.get("bytes_per_frame", math.nan), s.get("disk_rate", math.nan))
    if not math.isfinite(floor):
        return ""
    text = (f"; writing its output ({_f(stage['bytes_per_frame'] / 1e3)} KB a frame at "
            f"{_f(s['disk_rate'] / 1e6, 0)} MB/s) takes {_f(1e3 * floor, 2)} ms a frame, {_f(1e3 * allowed, 2)} allowed")
    return text + (" — BELOW THE DISK'S ESTIMATED FLOOR" if floor > allowed else "")


def print_report(sizes: list[dict[str, Any]], args: argparse.Namespace) -> None:
    load = ", ".join(f"{x:.1f}" for x in args.load_before + os.getloadavg())
    print(f"# starlog bench_pipeline (cores: {os.cpu_count()}, repeat: {args.repeat}, quick: {args.quick}; "
          f"load average 1/5/15 min before and after: {load})\n")
    print(f"Wall time of `python -m starlog <stage>` (median of {args.repeat}); frames/s marginal and start-up s: "
          "the median over the repeats of each repeat's line through (frames, seconds), the lengths run in a row; "
          "frames/s cpu the same from user + sys seconds (one worker only); camera = 300 Hz.\n")
    print("## Throughput per stage\n")
    print(throughput_table(sizes))
    print("\n## Centroid stage against SEP (same frames, same run)\n")
    print(sep_table(sizes, args.workers_all))
    print(f"\n## Breakdown per stage (in-process, one core, {sizes[0]['frames_profiled']} frames; "
          "ms/frame and share of the sampled time)\n")
    print(breakdown_table(sizes))
    print("\n## Checks\n")
    print(checks_table(sizes))
    print("\n## Targets\n")
    results = targets(sizes, args.workers_all)
    for text, ok in results:
        print(f"{'PASS' if ok else 'FAIL'}  {text}")
    print(f"\n{sum(ok for _, ok in results)}/{len(results)} targets met")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="smoke run: 256x256, 120 and 480 frames")
    ap.add_argument("--sizes", default=None, help="frame sizes (square), comma-separated [512,1024]")
    ap.add_argument("--frames", default=None, help="log lengths, comma-separated, at least two [300,3000]")
    ap.add_argument("--repeat", type=int, default=1, help="timed runs of each stage on every length in a row (median rate reported)")
    ap.add_argument("--keep", metavar="DIR", help="keep logs and outputs in DIR (simulated logs found there are reused)")
    ap.add_argument("--json", metavar="FILE", help="also write every figure as JSON to FILE")
    ap.add_argument("--methods", default="MOMENT,GAUSSFIT", help="centroid methods timed on one core")
    ap.add_argument("--sep-frames", type=int, default=300, help="frames SEP is timed on")
    ap.add_argument("--disk-probe-mib", type=int, default=1024,
                    help="MiB written and synced to time the disk (the floor of a stage writing its output)")
    ap.add_argument("--profile-stage", metavar="JSON", help=argparse.SUPPRESS)
    ap.add_argument("command", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    args.sizes = [int(x) for x in (args.sizes or ("256" if args.quick else "512,1024")).split(",")]
    args.lengths = sorted({int(x) for x in (args.frames or ("120,480" if args.quick else "300,3000")).split(",")})
    args.methods = [m.strip().upper() for m in args.methods.split(",")]
    if PIPELINE_METHOD not in args.methods:
        args.methods.append(PIPELINE_METHOD)
    args.workers_all = max(2, os.cpu_count() or 1)
    if len(args.lengths) < 2 and not args.profile_stage:
        ap.error("--frames needs at least two log lengths (the marginal rate is their difference)")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.profile_stage:
        command = args.command[1:] if args.command[:1] == ["--"] else args.command
        return profile_stage(args.profile_stage, command)
    args.load_before = os.getloadavg()  # other jobs on the machine make every wall time slower
    with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_TMP")) as tmp:
        root = Path(args.keep) if args.keep else Path(tmp)
        sizes = []
        for size in args.sizes:
            (root / str(size)).mkdir(parents=True, exist_ok=True)
            sizes.append(bench_size(size, args.lengths, root / str(size), args))
        print_report(sizes, args)
        if args.json:
            Path(args.json).write_text(json.dumps({"cores": os.cpu_count(), "args": vars(args), "sizes": sizes},
                                                  indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
