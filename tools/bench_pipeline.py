"""Stage-level throughput of starlog as a user runs it: the CLI on a log on disk, its output written.

For each frame size (512x512 with 40 stars and 1024x1024 with 50 stars by default) and each log
length (300 and 3000 frames at 300 Hz by default) a log is simulated once, then
``python -m starlog <stage>`` (this interpreter, a subprocess) is timed for:

* ``centroid`` with one method on one core (``--workers 1``: MOMENT, GAUSSFIT), and GAUSSFIT on all cores, in the
  stage's default mode (``auto``: tracking on these image sequences); GAUSSFIT in full mode (``--mode full``) on
  one core beside it; and ``decode only``, every frame of the log read and decoded in a fresh interpreter and
  nothing else: the floor of a stage that must look at every frame;
* ``track`` of the GAUSSFIT centroids with one model (STATIC, ``sigma_floor = 0.05``), on the centroid layer;
* ``motion`` (the platform motion) of that track, on the track layer;
* ``compensate`` of that track at one rate (50 Hz, paper protocol), on the track layer;
* ``run`` of GAUSSFIT -> STATIC -> compensate 50 Hz, paper protocol (the same options), all cores:
  one layer per stage; and ``run --flatten``, the same written as one self-contained file;
* ``user pipeline``: what a user writes instead of starlog (``tools/user_pipeline.py``: the ``mcap`` reader, SEP's
  extraction and windowed positions, a filterpy UKF per star), one core, on the same log;
* with ``--baseline REF``: ``run`` of the code at the git ref REF (its files from ``git archive``, run on this
  interpreter) on logs its own ``simulate`` writes, and today's ``run`` on those logs (zstd, as simulate wrote
  them before it wrote lz4): the speed-up of a change, both sides in this one run.

Each stage writes a layer: only what it adds, on the log it read. The outputs of the stages run one
by one are named as ``run``'s layers (``run.1-centroid.mcap``, ``run.2-track-GAUSSFIT.mcap``,
``run.mcap``: :func:`starlog.pipeline.layer_paths`); ``run`` writes its own in a sibling folder at the
same depth, so each of its layers must be the very bytes of the stage run alone.

Printed as Markdown tables, every ratio from this one run:

1. throughput: wall seconds per log length (median of ``--repeat``); the marginal rate, i.e. the
   slope of a straight line through (frames, seconds) as frames/s, so start-up is separate; the
   start-up cost (its intercept). Each repeat runs a stage on every log length in a row and gives
   its own line; the median over the repeats is reported, so a drift of the machine's speed
   between repeats does not enter a rate; with ``--workers 1``, the marginal rate on CPU time (user + sys:
   less sensitive to other jobs on a shared machine; not shown for more workers, whose pool
   processes are children of a fork server, not of the command, and escape the count);
   peak RSS (GNU time ``%M``: the largest process of the command) on the shortest and longest log;
   the output's size: KB a frame (its growth from the shortest to the longest log), MB and percent
   of the simulated input log on the longest log (``run``: its layers together); and what the copy
   of ``run --flatten`` costs: its marginal ms a frame minus ``run``'s, and the ratio of their rates;
2. the centroid stage against SEP (``sep.Background`` + ``sep.extract`` + ``sep.flux_radius`` +
   ``sep.winpos``, one core, on the same frames held in memory: no decode, no write);
3. a breakdown per stage: the stage run in-process on one core on the shortest log under a
   wall-clock stack sampler (SIGALRM every millisecond; the time since the previous sample goes to
   the innermost starlog frame of the interrupted stack): read/decode and encode/write
   (``starlog.io`` and ``starlog.codecs``, by the reading or writing side they serve), algorithm (``starlog.detect``,
   ``.centroid``, ``.track``, ``.motion``, ``.compensate``), stage code (``starlog.stages``,
   ``.pipeline``, ``.cli``: per-message conversion, orchestration), import, other (outside starlog);
4. checks: output SHA-256 identical for ``--workers 1`` and all cores, and on a rerun; each of
   ``run``'s layers identical to the stage run alone; a chain of five layers with no topic twice;
5. the tracker's own time beside the ``track`` stage's (whose target is its marginal time a frame at
   1024²): ``StarTracker.update`` with the stage's options on every frame of the longest log's
   centroids (decoded beforehand), in this process, the best of two runs, timed right after each
   repeat of the ``track`` stage; the ratio shown is the median over the repeats of each repeat's
   ratio, so both sides of a ratio see the machine at the same speed;
6. the cost of opening a chain, on the longest log: five layers, each on the one before (centroid
   GAUSSFIT, track STATIC, motion, compensate, track CONSTANT_VELOCITY); ``python -m starlog info``
   of the fifth layer and of the simulated base, run alternately in pairs (the target: the median
   of the pairs' differences), and ``LogReader`` open + close in this process, best of 20 each (the
   reading code alone, beside it).

Before any timed run, the centroid stage runs once on a few frames with every timed method, so the
compiled kernels' first compilation (and its disk cache) is not timed. The command exits with 1
when a target is not met, after a line naming those targets.

Usage::

    python tools/bench_pipeline.py                  # full run (tens of minutes on 2 cores)
    python tools/bench_pipeline.py --quick          # smoke run: 256x256, 120 and 480 frames
    python tools/bench_pipeline.py --sizes 512 --frames 300,1200 --repeat 2 --keep /tmp/bp --json bp.json
    python tools/bench_pipeline.py --baseline d99c6e0   # also against run of the code at that commit
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
RUN_STAGES = ["centroid", f"track {PIPELINE_METHOD}", "compensate"]  # the names run gives its stages' layers
RUN_LABEL, FLATTEN_LABEL = f"run ({PIPELINE_PROTOCOL} protocol)", f"run --flatten ({PIPELINE_PROTOCOL} protocol)"
TRACK_LABEL, MOTION_LABEL = f"track {PIPELINE_MODEL}", "motion"
COMPENSATE_LABEL = f"compensate {PIPELINE_RATE} Hz {PIPELINE_PROTOCOL}"
CHAIN_MODEL = "CONSTANT_VELOCITY"  # the fifth layer's track model (a topic of its own in the chain)
INFO_PAIRS, OPEN_REPEAT = 9, 20
# the largest output a stage may write, as a share of the simulated input log (by the label's first word)
OUTPUT_SHARE_LIMITS = {"centroid": 0.10, "track": 0.05, "motion": 0.05, "compensate": 0.05}
CHAIN_OPEN_LIMIT_S = 0.050
#: The frame size at which the centroid stage's speed against SEP is a target (smaller frames cost starlog
#: a larger share of per-call work than SEP).
SEP_TARGET_SIZE = 1024
#: ``run``'s marginal frames/s target per frame size (both cores).
RUN_TARGETS = {512: 1200.0, 1024: 600.0}
#: ``run`` at least this many times the pipeline a user writes instead (tools/user_pipeline.py, one core).
USER_PIPELINE_FACTOR = 15.0
#: ``run`` at least this many times ``run`` of the code at ``--baseline`` (each on the logs its own simulate writes).
BASELINE_FACTOR = 2.0
#: ``track``'s marginal time a frame at most this, at the frame size this is set for (50 stars).
TRACK_LIMIT_S, TRACK_LIMIT_SIZE = 0.15e-3, 1024
#: The centroid stage (default mode, one core) may take at most this many times the decode-only floor a frame, at
#: the frame size this is set for (on smaller frames the stars' own work, not the frame's pixels, dominates).
DECODE_FLOOR_FACTOR, DECODE_FLOOR_SIZE = 1.5, 1024
USER_LABEL = "user pipeline (mcap + SEP + filterpy UKF)"
ZSTD_RUN_LABEL = f"{RUN_LABEL} on a zstd log"
DECODE_LABEL, FULL_MODE_LABEL = "decode only", f"centroid {PIPELINE_METHOD} --mode full"
#: Why the motion stage's memory is not a target: its estimate is joint over the whole log.
MOTION_MEMORY = "the motion estimate is joint over the log and holds every measurement, by design"
CATEGORIES = ("read", "algorithm", "write", "stage", "import", "other")
CATEGORY_TITLES = {"read": "read/decode", "algorithm": "algorithm", "write": "encode/write",
                   "stage": "stage code", "import": "import", "other": "other"}
ALGORITHM_PACKAGES = ("starlog.detect", "starlog.centroiding", "starlog.tracking", "starlog.platform_motion", "starlog.compensation",
                      "starlog.sim")
#: The log layer: the MCAP container and the payload codecs.
LOG_PACKAGES = ("starlog.io", "starlog.codecs")
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


def run_command(argv: Sequence[str], env: dict[str, str] | None = None) -> Timing:
    """Run ``argv`` (user's environment, output discarded) and measure it; raise with its stderr on failure.

    The peak comes from GNU time, not from ``wait4`` on a child of this process where it can be
    avoided: a forked child's ``ru_maxrss`` may count pages inherited from this process.
    """
    gnu_time = shutil.which("time", path="/usr/bin:/bin")
    prefix = [gnu_time, "-f", "BENCH_PIPELINE %U %S %M"] if gnu_time else []
    with tempfile.TemporaryFile("w+") as err:
        start = time.perf_counter()
        proc = subprocess.Popen([*prefix, *argv], stdout=subprocess.DEVNULL, stderr=err, env={**_USER_ENV, **(env or {})})
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
    if any(module == p or module.startswith(p + ".") for p in LOG_PACKAGES):
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
def simulate(size: int, frames: int, path: Path, workers: int, env: dict[str, str] | None = None) -> None:
    """The input log (kept and reused when it exists, e.g. under ``--keep``), in the simulator's default
    compression (``env``: of the ``--baseline`` code)."""
    if path.exists():
        return
    run_command([*STARLOG, "simulate", "-o", str(path), "--size", f"{size}x{size}", "--stars", str(stars_for(size)),
                 "--fps", str(CAMERA_HZ), "--frames", str(frames), "--jitter", "25:0.05", "--seed", "1",
                 "--workers", str(workers), "-q"], env)


def decode_only(log: str) -> int:
    """Read and decode every frame of ``log``'s image channel, nothing else (the ``decode only`` row)."""
    from starlog.io import LogReader

    with LogReader(log) as reader:
        for _ in reader.frame_records("/camera/image"):
            pass
    return 0


def decode_command(log: Path) -> Command:
    return Command(DECODE_LABEL, [sys.executable, str(Path(__file__).resolve()), "--decode-only", str(log)], [])


def full_mode_command(log: Path, folder: Path) -> Command:
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / f"centroid_{PIPELINE_METHOD}_full.mcap"
    return Command(FULL_MODE_LABEL, [*STARLOG, "centroid", str(log), "-o", str(out), "--method", PIPELINE_METHOD,
                                     "--mode", "full", "--workers", "1", "-q", "--force"], [out])


def warm_up(log: Path, folder: Path, methods: list[str], env: dict[str, str] | None = None) -> None:
    """Run the centroid stage once, untimed, on the first frames with every timed method: the compiled
    kernels are compiled then and cached on disk (on a fresh clone, or after a change of the code), so a
    compilation never lands in a timed run (it added seconds to one run and moved its peak memory)."""
    out = folder / ".warm-up.mcap"
    run_command([*STARLOG, "centroid", str(log), "-o", str(out), "--method", ",".join(methods), "--end", "frame:3",
                 "--workers", "1", "-q", "--force"], env)
    out.unlink(missing_ok=True)


@dataclass
class Command:
    """One stage's CLI arguments and the files it writes (``run``: one layer per stage, the last one last)."""

    label: str
    argv: list[str]
    outputs: list[Path]
    env: dict[str, str] | None = None
    """Variables added to the user's environment (the ``--baseline`` code's ``PYTHONPATH``)."""


def pipeline_layers(folder: Path) -> list[Path]:
    """The layers ``run -o folder/run.mcap`` writes; the stages run one by one write files of the same names."""
    from starlog.pipeline import layer_paths

    return layer_paths(folder / "run.mcap", RUN_STAGES)


def sibling(folder: Path, suffix: str) -> Path:
    """A folder beside ``folder`` (the same depth: a layer names its base by a relative path)."""
    return folder.with_name(f"{folder.name}-{suffix}")


def centroid_command(log: Path, folder: Path, method: str, workers: int) -> Command:
    folder.mkdir(parents=True, exist_ok=True)
    out = pipeline_layers(folder)[0] if method == PIPELINE_METHOD else folder / f"centroid_{method}.mcap"
    return Command(f"centroid {method}", [*STARLOG, "centroid", str(log), "-o", str(out), "--method", method,
                                          "--workers", str(workers), "-q", "--force"], [out])


def track_arguments(model: str) -> list[str]:
    return ["--centroids", PIPELINE_METHOD, "--model", model, "--set", "sigma_floor=0.05"]


def compensate_arguments() -> list[str]:
    return ["--track", TRACK_TOPIC, "--rate", str(PIPELINE_RATE), "--protocol", PIPELINE_PROTOCOL]


def run_pipeline_command(log: Path, folder: Path, workers: int, *, flatten: bool) -> Command:
    """``run`` of the benchmark's config into ``folder``: its layers, or with ``flatten`` one file."""
    folder.mkdir(parents=True, exist_ok=True)
    config = folder / "pipeline.toml"
    config.write_text(RUN_CONFIG)
    out = folder / "run.mcap"
    argv = [*STARLOG, "run", str(log), "-o", str(out), "--config", str(config), "--workers", str(workers), "-q",
            "--force", *(["--flatten"] if flatten else [])]
    return Command(FLATTEN_LABEL if flatten else RUN_LABEL, argv, [out] if flatten else pipeline_layers(folder))


def pipeline_commands(log: Path, folder: Path, workers: int) -> list[Command]:
    """The pipeline's stages one by one in ``folder`` (outputs named as ``run``'s layers; motion and compensate
    both on the track layer), then ``run`` and ``run --flatten``, each in a sibling folder."""
    centroids, tracks, compensated = pipeline_layers(folder)
    motion = folder / "motion.mcap"
    common = ["--workers", str(workers), "-q", "--force"]
    return [
        centroid_command(log, folder, PIPELINE_METHOD, workers),
        Command(TRACK_LABEL, [*STARLOG, "track", str(centroids), "-o", str(tracks), *track_arguments(PIPELINE_MODEL),
                              *common], [tracks]),
        Command(MOTION_LABEL, [*STARLOG, "motion", str(tracks), "-o", str(motion), "--track", TRACK_TOPIC, *common],
                [motion]),
        Command(COMPENSATE_LABEL, [*STARLOG, "compensate", str(tracks), "-o", str(compensated),
                                   *compensate_arguments(), *common], [compensated]),
        run_pipeline_command(log, sibling(folder, "run"), workers, flatten=False),
        run_pipeline_command(log, sibling(folder, "flat"), workers, flatten=True),
    ]


# ---------------------------------------------------------------- what run is compared with
def user_pipeline_command(log: Path, folder: Path) -> Command:
    """The pipeline a user writes instead (``tools/user_pipeline.py``: mcap + SEP + a filterpy UKF per star)."""
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / "user_pipeline.npz"
    return Command(USER_LABEL, [sys.executable, str(Path(__file__).resolve().parent / "user_pipeline.py"), str(log),
                                str(out)], [out])


def baseline_source(ref: str, folder: Path) -> dict[str, str]:
    """The repository's files at the git ``ref`` (``git archive``) in ``folder``; the environment that runs that code
    on this interpreter (its ``PYTHONPATH``)."""
    if not (folder / "starlog").is_dir():
        repo = Path(__file__).resolve().parent.parent
        archive = subprocess.run(["git", "-C", str(repo), "archive", ref], check=True, capture_output=True).stdout
        folder.mkdir(parents=True, exist_ok=True)
        subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)
    return {"PYTHONPATH": str(folder)}


def baseline_label(ref: str) -> str:
    return f"{RUN_LABEL}, code at {ref}"


def baseline_commands(log: Path, folder: Path, workers: int, ref: str, env: dict[str, str]) -> list[Command]:
    """``run`` of the code at ``ref`` on the log its own simulate wrote (zstd), and today's ``run`` on that log."""
    before = run_pipeline_command(log, folder / "baseline-run", workers, flatten=False)
    today = run_pipeline_command(log, folder / "zstd-run", workers, flatten=False)
    return [Command(baseline_label(ref), before.argv, before.outputs, env),
            Command(ZSTD_RUN_LABEL, today.argv, today.outputs)]


@dataclass
class StageResult:
    """One timed stage across the log lengths, run as pairs (every length once per repeat, in a row).

    ``seconds``/``cpu_seconds``: the median per length; ``paired``/``paired_cpu``: per repeat, the
    seconds of each length; peak: the largest; ``output_bytes``: the size of what it wrote, per length.
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


def _seconds_per_frame(rate: float) -> float:
    """1 / rate; infinite for a rate that could not be measured (a line that did not rise: NaN or 0)."""
    return 1.0 / rate if rate > 0 else math.inf


def _median(values: list[float]) -> float:
    """Median, NaN (a repeat whose line did not rise) counted as the slowest."""
    return float(np.median([v if not math.isnan(v) else 0.0 for v in values]))


def outputs_digest(paths: Sequence[Path]) -> str:
    """SHA-256 of one file; of several, the SHA-256 of their digests in order; of none, an empty string."""
    digests = [sha256(p) for p in paths]
    if not digests:
        return ""
    return digests[0] if len(digests) == 1 else hashlib.sha256(" ".join(digests).encode()).hexdigest()


def timed(label: str, command: Command) -> tuple[Timing, str]:
    timing = run_command(command.argv, command.env)
    print(f"  {label}: {timing.seconds:.1f} s", file=sys.stderr, flush=True)
    return timing, outputs_digest(command.outputs)


def stage_plans(logs: dict[int, Path], root: Path, args: argparse.Namespace,
                baseline_logs: dict[int, Path] | None = None) -> dict[int, list[tuple[int, Command]]]:
    """Per log length, the timed stages as (workers, command), in an order where a stage's input exists."""
    plans = {}
    for n, log in logs.items():
        plan = [(1, decode_command(log)), (1, full_mode_command(log, root / f"{n}/full"))]
        plan += [(1, centroid_command(log, root / f"{n}/workers1", m, 1)) for m in args.methods]
        plan += [(args.workers_all, c) for c in pipeline_commands(log, root / f"{n}/all", args.workers_all)]
        if not args.no_user_pipeline:
            plan.append((1, user_pipeline_command(log, root / f"{n}/user")))
        if baseline_logs:
            plan += [(args.workers_all, c) for c in baseline_commands(baseline_logs[n], root / f"{n}/baseline",
                                                                       args.workers_all, args.baseline,
                                                                       args.baseline_env)]
        plans[n] = plan
    return plans


def time_stages(size: int, plans: dict[int, list[tuple[int, Command]]], root: Path,
                args: argparse.Namespace) -> tuple[list[StageResult], list[float]]:
    """Every stage on every log length in a row, ``--repeat`` times; the tracker alone after each ``track``."""
    lengths = sorted(plans)
    results, tracker_times = [], []
    centroids = pipeline_layers(root / f"{lengths[-1]}/all")[0]
    for k, (workers, first) in enumerate(plans[lengths[0]]):
        runs: list[list[Timing]] = []
        digests: dict[int, list[str]] = {n: [] for n in lengths}
        for _ in range(args.repeat):
            runs.append([])
            for n in lengths:
                timing, digest = timed(f"{size} {n} {first.label} w{workers}", plans[n][k][1])
                runs[-1].append(timing)
                digests[n].append(digest)
            if first.label == TRACK_LABEL:
                tracker_times.append(tracker_alone(centroids))
                print(f"  tracker alone: {1e3 * tracker_times[-1]:.3f} ms a frame", file=sys.stderr, flush=True)
        result = StageResult(first.label, workers)
        result.add_pairs(lengths, runs, digests)
        result.output_bytes = [sum(p.stat().st_size for p in plans[n][k][1].outputs) for n in lengths]
        results.append(result)
    return results, tracker_times


def bench_size(size: int, lengths: list[int], root: Path, args: argparse.Namespace) -> dict[str, Any]:
    """Every table's figures for one frame size.

    Stage by stage, each repeat runs every log length in a row, so a drift of the machine's speed
    between repeats does not enter a marginal rate (the slope of one repeat's pair of lengths).
    """
    logs = {n: root / f"sim_{size}_{n}.mcap" for n in lengths}
    baseline_logs = {n: root / f"sim_{size}_{n}_baseline.mcap" for n in lengths} if args.baseline else None
    for n, log in logs.items():
        print(f"# {size}x{size}, {n} frames: simulate", file=sys.stderr, flush=True)
        simulate(size, n, log, args.workers_all)
        if baseline_logs:
            simulate(size, n, baseline_logs[n], args.workers_all, args.baseline_env)
    plans = stage_plans(logs, root, args, baseline_logs)
    warm_up(logs[lengths[0]], root, args.methods)  # args.methods holds the pipeline's method too
    if baseline_logs:
        warm_up(baseline_logs[lengths[0]], root, [PIPELINE_METHOD], args.baseline_env)
    results, tracker_times = time_stages(size, plans, root, args)
    track_runs = next(r for r in results if r.label == TRACK_LABEL).paired
    track_ratio = float(np.median([_seconds_per_frame(marginal_fit(lengths, run)[0]) / t
                                   for run, t in zip(track_runs, tracker_times, strict=True)]))
    chain, chain_check = chain_open_cost(logs[lengths[-1]], root / f"{lengths[-1]}/all", root / f"{lengths[-1]}/chain")
    checks = [*pipeline_checks(lengths, root, args.workers_all), chain_check]
    checks += determinism_checks(logs[lengths[0]], lengths[0], root, results, args)
    sep = sep_reference(logs[lengths[0]], args.sep_frames)
    print(f"  SEP: {sep['fps']:.1f} frames/s", file=sys.stderr, flush=True)
    profiles = breakdowns(logs[lengths[0]], root / f"{lengths[0]}/profile", args)
    return {"size": size, "stars": stars_for(size), "lengths": lengths,
            "input_bytes": [logs[n].stat().st_size for n in lengths],
            "stages": [{**asdict(r), **r.fit()} for r in results],
            "sep": sep, "breakdown": profiles, "frames_profiled": lengths[0],
            "tracker_s_per_frame": float(np.median(tracker_times)), "track_ratio": track_ratio, "chain": chain,
            "checks": [{"check": text, "ok": ok} for text, ok in checks]}


def tracker_alone(centroids: Path, repeat: int = 2) -> float:
    """Seconds a frame of the tracker alone (``StarTracker.update``, the ``track`` stage's options) on every
    frame of the centroid channel of ``centroids``, decoded beforehand; the best of ``repeat`` runs."""
    from starlog.io import LogReader
    from starlog.tracking import MotionModel, StarTracker, TrackerConfig

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


# ---------------------------------------------------------------- opening a chain
def five_layer_chain(stage_folder: Path, folder: Path) -> list[Path]:
    """Five layers, each on the one before: the centroid, track and motion outputs of the stages in
    ``stage_folder``, then, written in ``folder``, compensate on the motion layer and a track of another
    model on the compensate layer."""
    folder.mkdir(parents=True, exist_ok=True)
    centroids, tracks, _ = pipeline_layers(stage_folder)
    motion = stage_folder / "motion.mcap"
    compensated, tracks_again = folder / "chain.4-compensate.mcap", folder / f"chain.5-track-{CHAIN_MODEL}.mcap"
    run_command([*STARLOG, "compensate", str(motion), "-o", str(compensated), *compensate_arguments(), "-q",
                 "--force"])
    run_command([*STARLOG, "track", str(compensated), "-o", str(tracks_again), *track_arguments(CHAIN_MODEL), "-q",
                 "--force"])
    return [centroids, tracks, motion, compensated, tracks_again]


def topics_per_file(layer: Path) -> list[list[str]]:
    """The topics of each file of the chain ``layer`` ends, the base first."""
    from starlog.io import LogReader

    with LogReader(layer) as log:
        return [[c.topic for c in file.summary.channels.values()] for file in log.files]


def repeated_topics(files: Sequence[Sequence[str]]) -> list[str]:
    """Topics held by more than one file of a chain (none in a valid chain), sorted."""
    seen: defaultdict[str, int] = defaultdict(int)
    for topics in files:
        for topic in set(topics):
            seen[topic] += 1
    return sorted(t for t, count in seen.items() if count > 1)


def info_seconds(base: Path, layer: Path, pairs: int) -> list[tuple[float, float]]:
    """``starlog info`` wall seconds of (base, layer), run alternately ``pairs`` times after one untimed pair."""
    out = []
    for k in range(pairs + 1):
        pair = (run_command([*STARLOG, "info", str(base)]).seconds, run_command([*STARLOG, "info", str(layer)]).seconds)
        if k:
            out.append(pair)
    return out


def reader_open_seconds(base: Path, layer: Path, repeat: int) -> tuple[float, float]:
    """Best ``LogReader`` open + close seconds of (base, layer) in this process, alternated ``repeat`` times."""
    from starlog.io import LogReader

    best = [math.inf, math.inf]
    for _ in range(repeat):
        for i, path in enumerate((base, layer)):
            start = time.perf_counter()
            LogReader(path).close()
            best[i] = min(best[i], time.perf_counter() - start)
    return best[0], best[1]


def open_cost(base: Path, layer: Path) -> dict[str, Any]:
    """Opening ``layer`` (and its chain) against opening ``base``: by the CLI and in this process."""
    pairs = info_seconds(base, layer, INFO_PAIRS)
    open_base, open_layer = reader_open_seconds(base, layer, OPEN_REPEAT)
    return {"info_pairs": pairs, "info_base_s": float(np.median([a for a, _ in pairs])),
            "info_layer_s": float(np.median([b for _, b in pairs])),
            "info_extra_s": float(np.median([b - a for a, b in pairs])), "open_base_s": open_base,
            "open_layer_s": open_layer}


def chain_topics_check(layers: list[Path]) -> tuple[str, bool]:
    """The last layer reads as one log of the base and every layer, no topic in two of its files."""
    files = topics_per_file(layers[-1])
    repeated = repeated_topics(files)
    text = (f"chain of {len(layers)} layers ({len(files)} files read as one log): no topic in two files"
            + (f" (repeated: {', '.join(repeated)})" if repeated else ""))
    return text, len(files) == len(layers) + 1 and not repeated


def chain_open_cost(log: Path, stage_folder: Path, folder: Path) -> tuple[dict[str, Any], tuple[str, bool]]:
    """How much longer opening the fifth layer of a chain on ``log`` takes than opening ``log``; and the check
    of the chain's topics."""
    layers = five_layer_chain(stage_folder, folder)
    check = chain_topics_check(layers)
    figures = {"layers": [str(p) for p in layers], "files": len(layers) + 1, **open_cost(log, layers[-1])}
    print(f"  chain of {len(layers)} layers: info +{1e3 * figures['info_extra_s']:.1f} ms, "
          f"LogReader +{1e3 * (figures['open_layer_s'] - figures['open_base_s']):.1f} ms", file=sys.stderr, flush=True)
    return figures, check


# ---------------------------------------------------------------- checks
def _same(a: Path, b: Path) -> bool:
    return sha256(a) == sha256(b)


def pipeline_checks(lengths: list[int], root: Path, workers_all: int) -> list[tuple[str, bool]]:
    """Per log length: the centroid stage on one core and on all; each of ``run``'s layers against the stage alone."""
    checks = []
    for n in lengths:
        one, alone, run = (pipeline_layers(root / f"{n}/{f}") for f in ("workers1", "all", "all-run"))
        checks.append((f"{n} frames: centroid {PIPELINE_METHOD} --workers 1 == --workers {workers_all}",
                       _same(one[0], alone[0])))
        for label, mine, theirs in zip(("centroid", "track", "compensate"), run, alone, strict=True):
            checks.append((f"{n} frames: run's layer {mine.name} == {label} run alone (stages one by one)",
                           _same(mine, theirs)))
    return checks


def determinism_checks(log: Path, n: int, root: Path, results: list[StageResult],
                       args: argparse.Namespace) -> list[tuple[str, bool]]:
    """On the shortest log: the other stages with ``--workers 1``, and a rerun of every stage on all cores."""
    checks = []
    one = pipeline_commands(log, root / f"{n}/workers1", 1)
    rerun = pipeline_commands(log, root / f"{n}/rerun", args.workers_all)
    for command in one[1:]:  # the centroid stage on one core is already timed
        timed(f"{n} {command.label} w1 (check)", command)
    for command in rerun:
        timed(f"{n} {command.label} (rerun)", command)
    for first, again, single in zip(pipeline_commands(log, root / f"{n}/all", args.workers_all), rerun, one):
        checks.append((f"{n} frames: {first.label} rerun gives the same bytes",
                       all(map(_same, first.outputs, again.outputs))))
        if not first.label.startswith("centroid"):
            checks.append((f"{n} frames: {first.label} --workers 1 == --workers {args.workers_all}",
                           all(map(_same, single.outputs, first.outputs))))
    for result in results:
        for frames, digests in result.digests.items():
            if len(digests) > 1 and digests[0]:  # a command that writes nothing has no bytes to compare
                checks.append((f"{frames} frames: {result.label} w{result.workers} same bytes on all "
                               f"{len(digests)} repeats", len(set(digests)) == 1))
    return checks


def breakdowns(log: Path, folder: Path, args: argparse.Namespace) -> dict[str, dict[str, float]]:
    """Each stage in-process on one core, under the stack sampler."""
    plan = [centroid_command(log, folder, m, 1) for m in args.methods if m != PIPELINE_METHOD]
    plan += pipeline_commands(log, folder, 1)
    out = {}
    for command in plan:
        json_path = folder / f"{command.label.split()[0]}_{len(out)}.json"
        out[command.label] = breakdown(command.argv[len(STARLOG):], json_path)
        print(f"  profile {command.label}: {out[command.label]['total']:.1f} s", file=sys.stderr, flush=True)
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


def output_share(s: dict[str, Any], stage: dict[str, Any]) -> float:
    """The stage's output on the longest log as a share of the simulated input log of that length."""
    return stage["output_bytes"][-1] / s["input_bytes"][-1]


def throughput_table(sizes: list[dict[str, Any]]) -> str:
    lengths = sizes[0]["lengths"]
    headers = ["size", "stage", "workers", *(f"s @{n}" for n in lengths), "frames/s marginal", "x camera",
               "start-up s", "frames/s cpu", f"peak MiB @{lengths[0]}", f"@{lengths[-1]}", "growth",
               "output KB/frame", f"output MB @{lengths[-1]}", "output % of input"]
    rows = []
    for s in sizes:
        for r in s["stages"]:
            rows.append([f"{s['size']}², {s['stars']} stars", r["label"], r["workers"], *(_f(x, 2) for x in r["seconds"]),
                         _f(r["rate"]), _x(r["rate"] / CAMERA_HZ), _f(r["start_up"], 2),
                         _f(r["cpu_rate"]) if r["workers"] == 1 else "n/a", _f(r["peak_mib"][0]), _f(r["peak_mib"][-1]),
                         _f(100 * r["peak_growth"]) + "%", _f(r["bytes_per_frame"] / 1e3),
                         _f(r["output_bytes"][-1] / 1e6, 2), _f(100 * output_share(s, r), 2) + "%"])
    return markdown_table(headers, rows)


def flatten_cost(run: dict[str, Any], flat: dict[str, Any]) -> tuple[float, float]:
    """Marginal seconds a frame ``run --flatten`` takes more than ``run``, and the ratio of their rates."""
    extra = _seconds_per_frame(flat["rate"]) - _seconds_per_frame(run["rate"])
    return extra, (flat["rate"] / run["rate"] if run["rate"] > 0 else math.nan)


def flatten_lines(sizes: list[dict[str, Any]]) -> list[str]:
    out = []
    for s in sizes:
        run, flat = _stage(s, RUN_LABEL), _stage(s, FLATTEN_LABEL)
        extra, ratio = flatten_cost(run, flat)
        out.append(f"{s['size']}²: the copy costs {_f(1e3 * extra, 3)} ms a frame (marginal ms a frame of `run --flatten` "
                   f"{_f(1e3 * _seconds_per_frame(flat['rate']), 3)} minus `run` "
                   f"{_f(1e3 * _seconds_per_frame(run['rate']), 3)}); frames/s of run --flatten / run = {_x(ratio)}")
    return out


def chain_table(sizes: list[dict[str, Any]]) -> str:
    headers = ["size", "frames", "files", "`info` base ms", "`info` layer 5 ms", "median difference ms",
               "LogReader base ms", "LogReader layer 5 ms", "difference ms"]
    rows = []
    for s in sizes:
        c = s["chain"]
        rows.append([f"{s['size']}²", s["lengths"][-1], c["files"], _f(1e3 * c["info_base_s"]),
                     _f(1e3 * c["info_layer_s"]), _f(1e3 * c["info_extra_s"]), _f(1e3 * c["open_base_s"], 2),
                     _f(1e3 * c["open_layer_s"], 2), _f(1e3 * (c["open_layer_s"] - c["open_base_s"]), 2)])
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
            rows.append([f"{s['size']}²", _f(sep_fps), f"{r['label'].removeprefix('centroid ')} w{r['workers']}",
                         _f(r["rate"]),
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
    rows = [[f"{s['size']}²", c["check"], "ok" if c["ok"] else "FAILED"] for s in sizes for c in s["checks"]]
    return markdown_table(["size", "check (SHA-256 of the outputs; topics of the chain)", "result"], rows)


def targets(sizes: list[dict[str, Any]], workers_all: int) -> list[tuple[str, bool | None]]:
    """The stage-level targets, each judged on this run's figures (every size measured)."""
    out = []
    for s in sizes:
        out += speed_targets(s, workers_all)
        out += comparison_targets(s)
        out += output_size_targets(s)
        out.append(chain_open_target(s))
        tag = f"{s['size']}²"
        for r in s["stages"]:
            flat = abs(r["peak_growth"]) <= 0.10
            text = (f"{tag}: {r['label']} w{r['workers']} peak memory {_f(100 * r['peak_growth'])}% from "
                    f"{r['frames'][0]} to {r['frames'][-1]} frames, within 10 %")
            if r["label"] == MOTION_LABEL:  # informational: see MOTION_MEMORY
                out.append((f"{text} (informational: {MOTION_MEMORY})", None if not flat else True))
            else:
                out.append((text, flat))
        out += [(f"{tag}: {c['check']}", c["ok"]) for c in s["checks"]]
    return out


def speed_targets(s: dict[str, Any], workers_all: int) -> list[tuple[str, bool | None]]:
    tag = f"{s['size']}²"
    run = _stage(s, RUN_LABEL)
    goal = RUN_TARGETS.get(s["size"])
    text = f"{tag}: run marginal {_f(run['rate'])} frames/s >= {_f(goal or min(RUN_TARGETS.values()), 0)}"
    out = [(text if goal else f"{text} (n/a: set for {', '.join(f'{k}²' for k in RUN_TARGETS)} frames)",
            run["rate"] >= goal if goal else None)]
    out += decode_floor_targets(s)
    sep_fps = s["sep"]["fps"]
    for method, factor in (("MOMENT", 3.0), ("GAUSSFIT", 2.0)):
        one = _stage(s, f"centroid {method}", 1)
        if one:
            text = f"{tag}: centroid {method} --workers 1 {_f(one['rate'])} frames/s >= {factor} x SEP {_f(sep_fps)}"
            judged = s["size"] == SEP_TARGET_SIZE
            out.append((text if judged else f"{text} (n/a: set for {SEP_TARGET_SIZE}² frames)",
                        one["rate"] >= factor * sep_fps if judged else None))
    one, all_ = _stage(s, f"centroid {PIPELINE_METHOD}", 1), _stage(s, f"centroid {PIPELINE_METHOD}", workers_all)
    out.append((f"{tag}: centroid {PIPELINE_METHOD} --workers {workers_all} / --workers 1 = "
                f"{_f(all_['rate'] / one['rate'], 2)} >= 1.8", all_["rate"] >= 1.8 * one["rate"]))
    track = _stage(s, TRACK_LABEL)
    seconds = _seconds_per_frame(track["rate"])
    text = f"{tag}: track marginal {_f(1e3 * seconds, 3)} ms a frame <= {_f(1e3 * TRACK_LIMIT_S, 2)} ms"
    judged = s["size"] == TRACK_LIMIT_SIZE
    out.append((text if judged else f"{text} (n/a: set for {TRACK_LIMIT_SIZE}² frames, 50 stars)",
                seconds <= TRACK_LIMIT_S if judged else None))
    out.append((f"{tag}: track marginal time / tracker's own time {_f(1e3 * s['tracker_s_per_frame'], 3)} ms = "
                f"{_f(s['track_ratio'], 2)} (median of the repeats' ratios; informational: what the stage's reading "
                "and writing add to the tracker)", None))
    comp = _stage(s, COMPENSATE_LABEL)
    extra = 1200 * _seconds_per_frame(comp["rate"])
    out.append((f"{tag}: compensate of 1200 frames = {_f(extra, 2)} s + start-up {_f(comp['start_up'], 2)} s; "
                "<= 1 s + start-up", extra <= 1.0))
    return out


def comparison_targets(s: dict[str, Any]) -> list[tuple[str, bool | None]]:
    """``run`` against the pipeline a user writes instead and against the code at ``--baseline``, rates of this run."""
    tag, run = f"{s['size']}²", _stage(s, RUN_LABEL)
    out: list[tuple[str, bool | None]] = []
    user = _stage(s, USER_LABEL)
    if user is not None:
        ratio = run["rate"] / user["rate"] if user["rate"] > 0 else math.nan
        out.append((f"{tag}: run {_f(run['rate'])} frames/s = {_x(ratio)} the {USER_LABEL} {_f(user['rate'])} "
                    f"frames/s (one core) >= {USER_PIPELINE_FACTOR:g}x", ratio >= USER_PIPELINE_FACTOR))
    before = next((r for r in s["stages"] if r["label"].startswith(f"{RUN_LABEL}, code at ")), None)
    if before is None:
        out.append((f"{tag}: run against the code before a change (n/a: no --baseline REF given)", None))
        return out
    ratio = run["rate"] / before["rate"] if before["rate"] > 0 else math.nan
    out.append((f"{tag}: run {_f(run['rate'])} frames/s = {_x(ratio)} {before['label'].removeprefix(RUN_LABEL + ', ')}"
                f" {_f(before['rate'])} frames/s, each on its own simulate's log, >= {BASELINE_FACTOR:g}x",
                ratio >= BASELINE_FACTOR))
    zstd = _stage(s, ZSTD_RUN_LABEL)
    if zstd is not None:
        out.append((f"{tag}: run on that code's zstd log {_f(zstd['rate'])} frames/s = "
                    f"{_x(zstd['rate'] / before['rate'] if before['rate'] > 0 else math.nan)} it (informational: the "
                    "same log for both)", None))
    return out


def decode_floor_targets(s: dict[str, Any]) -> list[tuple[str, bool | None]]:
    """The centroid stage (default mode, one core) within :data:`DECODE_FLOOR_FACTOR` times the decode-only floor a
    frame; full mode's ratio beside it (informational)."""
    tag, floor = f"{s['size']}²", _stage(s, DECODE_LABEL)
    stage, full = _stage(s, f"centroid {PIPELINE_METHOD}", 1), _stage(s, FULL_MODE_LABEL)
    if floor is None or stage is None:
        return []
    per_frame = _seconds_per_frame(floor["rate"])
    ratio = _seconds_per_frame(stage["rate"]) / per_frame
    text = (f"{tag}: centroid {PIPELINE_METHOD} --workers 1 (default mode) {_f(1e3 * _seconds_per_frame(stage['rate']), 2)}"
            f" ms a frame = {_x(ratio)} the decode-only floor {_f(1e3 * per_frame, 2)} ms <= {DECODE_FLOOR_FACTOR:g}x")
    judged = s["size"] == DECODE_FLOOR_SIZE
    out: list[tuple[str, bool | None]] = [
        (text if judged else f"{text} (n/a: set for {DECODE_FLOOR_SIZE}² frames; on smaller ones the stars' own work "
                             "dominates)", ratio <= DECODE_FLOOR_FACTOR if judged else None)]
    if full is not None:
        full_ratio = _seconds_per_frame(full["rate"]) / per_frame
        out.append((f"{tag}: centroid {PIPELINE_METHOD} --mode full --workers 1 = {_x(full_ratio)} the decode-only "
                    f"floor; the default mode is {_x(stage['rate'] / full['rate'] if full['rate'] > 0 else math.nan)} "
                    "as fast "
                    "(informational: what tracking saves)", None))
    return out


def share_limit(label: str) -> float | None:
    """The largest output share of the input a stage may write (None: no target, e.g. ``run``)."""
    return OUTPUT_SHARE_LIMITS.get(label.split()[0])


def output_size_targets(s: dict[str, Any]) -> list[tuple[str, bool]]:
    """Each stage's output (a layer) against its share of the input log, on the longest log."""
    out = []
    for r in s["stages"]:
        limit = share_limit(r["label"])
        if limit is not None:
            share = output_share(s, r)
            out.append((f"{s['size']}²: {r['label']} w{r['workers']} output {_f(r['output_bytes'][-1] / 1e6, 2)} MB = "
                        f"{_f(100 * share, 2)}% of the input log ({_f(s['input_bytes'][-1] / 1e6, 1)} MB, "
                        f"{s['lengths'][-1]} frames) <= {100 * limit:.0f} %", share <= limit))
    return out


def chain_open_target(s: dict[str, Any]) -> tuple[str, bool]:
    c = s["chain"]
    return (f"{s['size']}²: opening a chain of five layers costs {_f(1e3 * c['info_extra_s'])} ms more than its base "
            f"(`starlog info`, median of {len(c['info_pairs'])} alternating pairs) <= {1e3 * CHAIN_OPEN_LIMIT_S:.0f} ms "
            f"(LogReader open + close alone: {_f(1e3 * (c['open_layer_s'] - c['open_base_s']), 2)} ms more)",
            c["info_extra_s"] <= CHAIN_OPEN_LIMIT_S)


def verdict(ok: bool | None) -> str:
    """PASS, FAIL, or INFO for a target that is informational or not judged at this size (its text says why)."""
    return "INFO" if ok is None else "PASS" if ok else "FAIL"


def print_report(sizes: list[dict[str, Any]], args: argparse.Namespace) -> list[tuple[str, bool | None]]:
    """The tables and the targets (returned)."""
    load = ", ".join(f"{x:.1f}" for x in args.load_before + os.getloadavg())
    print(f"# starlog bench_pipeline (cores: {os.cpu_count()}, repeat: {args.repeat}, quick: {args.quick}; "
          f"load average 1/5/15 min before and after: {load})\n")
    print(f"Wall time of `python -m starlog <stage>` (median of {args.repeat}); frames/s marginal and start-up s: "
          "the median over the repeats of each repeat's line through (frames, seconds), the lengths run in a row; "
          "frames/s cpu the same from user + sys seconds (one worker only); camera = 300 Hz. Output: the layer a "
          "stage writes (run: its layers together; run --flatten: one self-contained file), against the simulated "
          "input log on the longest log.\n")
    print("## Throughput per stage\n")
    print(throughput_table(sizes))
    print("\n" + "\n".join(flatten_lines(sizes)))
    print("\n## Centroid stage against SEP (same frames, same run)\n")
    print(sep_table(sizes, args.workers_all))
    print(f"\n## Breakdown per stage (in-process, one core, {sizes[0]['frames_profiled']} frames; "
          "ms/frame and share of the sampled time)\n")
    print(breakdown_table(sizes))
    print(f"\n## Opening a chain of five layers (`starlog info`: median of {INFO_PAIRS} alternating pairs; "
          f"LogReader open + close in this process: best of {OPEN_REPEAT})\n")
    print(chain_table(sizes))
    print("\n## Checks\n")
    print(checks_table(sizes))
    print("\n## Targets\n")
    results = targets(sizes, args.workers_all)
    for text, ok in results:
        print(f"{verdict(ok)}  {text}")
    judged = [ok for _, ok in results if ok is not None]
    print(f"\n{sum(judged)}/{len(judged)} targets met ({len(results) - len(judged)} informational or not judged)")
    return results


def failed_summary(results: list[tuple[str, bool | None]]) -> str | None:
    """One line naming the judged targets not met (None when all are)."""
    judged = [(text, ok) for text, ok in results if ok is not None]
    failed = [text for text, ok in judged if not ok]
    return f"FAILED {len(failed)}/{len(judged)} targets: " + " | ".join(failed) if failed else None


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
    ap.add_argument("--baseline", metavar="REF", help="also time run of the code at this git ref (e.g. the commit before "
                                                      "a change) on the logs its own simulate writes: the target is a "
                                                      f"speed-up of at least {BASELINE_FACTOR:g}x")
    ap.add_argument("--no-user-pipeline", action="store_true",
                    help="leave out the user pipeline row (mcap + SEP + filterpy: slow on long logs)")
    ap.add_argument("--profile-stage", metavar="JSON", help=argparse.SUPPRESS)
    ap.add_argument("--decode-only", metavar="LOG", help=argparse.SUPPRESS)
    ap.add_argument("command", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    args.sizes = [int(x) for x in (args.sizes or ("256" if args.quick else "512,1024")).split(",")]
    args.lengths = sorted({int(x) for x in (args.frames or ("120,480" if args.quick else "300,3000")).split(",")})
    args.methods = [m.strip().upper() for m in args.methods.split(",")]
    if PIPELINE_METHOD not in args.methods:
        args.methods.append(PIPELINE_METHOD)
    args.workers_all = max(2, os.cpu_count() or 1)
    if len(args.lengths) < 2 and not (args.profile_stage or args.decode_only):
        ap.error("--frames needs at least two log lengths (the marginal rate is their difference)")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.decode_only:
        return decode_only(args.decode_only)
    if args.profile_stage:
        command = args.command[1:] if args.command[:1] == ["--"] else args.command
        return profile_stage(args.profile_stage, command)
    args.load_before = os.getloadavg()  # other jobs on the machine make every wall time slower
    with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_TMP")) as tmp:
        root = Path(args.keep) if args.keep else Path(tmp)
        args.baseline_env = baseline_source(args.baseline, root / f"baseline-{args.baseline}") if args.baseline else None
        sizes = []
        for size in args.sizes:
            (root / str(size)).mkdir(parents=True, exist_ok=True)
            sizes.append(bench_size(size, args.lengths, root / str(size), args))
        results = print_report(sizes, args)
        if args.json:
            Path(args.json).write_text(json.dumps({"cores": os.cpu_count(), "args": vars(args), "sizes": sizes},
                                                  indent=1, default=str))
    summary = failed_summary(results)
    if summary:
        print(summary)
    return 1 if summary else 0


if __name__ == "__main__":
    sys.exit(main())
