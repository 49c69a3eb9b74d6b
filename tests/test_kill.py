"""A stage killed (SIGKILL) at random moments never changes its input, never leaves a
half-written file under the output name, and a rerun gives the bytes of an uninterrupted run.

Nothing is left behind: after SIGKILL or SIGTERM of a stage, every process it started (fork server,
workers, resource tracker) is gone within 2 s; SIGTERM also removes the partial output. Ctrl-C at 50
random moments of simulate, centroid and run with two workers (to the command, or to its process group as
a terminal sends it): every process gone within 5 s each time, nothing partial, no traceback.

Also: every command gives identical bytes for identical inputs (reproducibility).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

import starlog
from starlog.errors import StarlogError
from starlog.io import LogReader
from starlog.io.recover import recover_log

PY = [sys.executable, "-m", "starlog"]
SIM = ["--size", "32x32", "--stars", "3", "--seed", "1", "-q"]


LEFTOVER_GRACE_S = 2.0


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run(args: list[str], cwd: Path) -> float:
    t0 = time.perf_counter()
    subprocess.run(PY + args, cwd=cwd, check=True, capture_output=True, timeout=120)
    return time.perf_counter() - t0


def start(args: list[str], cwd: Path, marker: str, *, new_session: bool = False,
          stderr: int = subprocess.DEVNULL) -> subprocess.Popen[bytes]:
    """Start a starlog command; every process it starts inherits ``marker`` in its environment.

    The command starts with SIGINT's default action, as from a terminal: a test suite started in
    the background by a non-interactive shell inherits SIGINT ignored, and so would the command.
    With ``new_session`` it leads a process group of its own (a terminal's Ctrl-C goes to a group).
    """
    env = {**os.environ, "STARLOG_TEST_PROCESS_MARKER": marker}
    return subprocess.Popen(PY + args, cwd=cwd, stdout=subprocess.DEVNULL, stderr=stderr, env=env,
                            preexec_fn=_default_sigint, start_new_session=new_session)


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def marked_processes(marker: str) -> list[int]:
    """Live (not zombie) processes whose environment carries ``marker``, wherever they were re-parented."""
    needle = f"STARLOG_TEST_PROCESS_MARKER={marker}".encode()
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            environ = Path(f"/proc/{entry}/environ").read_bytes()
            state = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:  # gone meanwhile, or not ours to read
            continue
        if needle in environ.split(b"\0") and state != "Z":
            found.append(int(entry))
    return found


def descendants(pid: int) -> set[int]:
    """Every process below ``pid`` (children of any of its threads, recursively)."""
    found: set[int] = set()
    todo = [pid]
    while todo:
        for task in Path(f"/proc/{todo.pop()}/task").glob("*"):
            try:
                children = {int(c) for c in (task / "children").read_text().split()}
            except OSError:
                continue
            todo.extend(children - found)
            found |= children
    return found


def assert_nothing_left(marker: str, tracked: set[int], *, grace: float = LEFTOVER_GRACE_S) -> None:
    """Within ``grace`` seconds, no process started by the killed command is alive (found by marker or by pid)."""
    deadline = time.monotonic() + grace
    while True:
        alive = set(marked_processes(marker)) | {p for p in tracked if _alive(p)}
        if not alive or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    assert not alive, f"processes left behind {grace} s after the kill: {_describe(alive)}"


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _describe(pids: set[int]) -> list[str]:
    out = []
    for pid in sorted(pids):
        try:
            out.append(f"{pid}: {Path(f'/proc/{pid}/cmdline').read_bytes().replace(bytes(1), b' ')[:120]!r}")
        except OSError:
            out.append(f"{pid}: (gone)")
    return out


needs_proc = pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="process tracking reads /proc (Linux)")


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An image folder, a simulated log and its centroid log (the stages' inputs)."""
    import cv2

    d = tmp_path_factory.mktemp("kill")
    rng = np.random.default_rng(5)
    (d / "frames").mkdir()
    for n in range(120):
        cv2.imwrite(str(d / "frames" / f"f{n}.png"), rng.integers(0, 4000, (32, 32), dtype=np.uint16))
    run(["simulate", "-o", "in.mcap", "--frames", "200", *SIM], d)
    run(["centroid", "in.mcap", "-o", "cen.mcap", "--method", "MOMENT", "-q"], d)
    return d


STAGES = {
    "simulate": (None, ["simulate", "-o", "OUT", "--frames", "200", *SIM]),
    "ingest": ("frames", ["ingest", "frames", "-o", "OUT", "--fps", "100", "-q"]),
    "centroid": ("in.mcap", ["centroid", "in.mcap", "-o", "OUT", "--method", "MOMENT,BICUBIC", "-q"]),
    "track": ("cen.mcap", ["track", "cen.mcap", "-o", "OUT", "--centroids", "MOMENT", "--model", "STATIC", "-q"]),
}
KILLS_PER_STAGE = 4


def _input_digest(workdir: Path, name: str | None) -> str:
    if name is None:
        return ""
    path = workdir / name
    if path.is_dir():
        return "".join(sha(p) for p in sorted(path.iterdir()))
    return sha(path)


@needs_proc
@pytest.mark.parametrize("stage", list(STAGES))
def test_killed_stage(workdir: Path, stage: str, tmp_path: Path) -> None:
    source, template = STAGES[stage]
    out_name = f"{stage}_out.mcap"
    args = [a if a != "OUT" else out_name for a in template]
    before = _input_digest(workdir, source)
    duration = run([*args[:1], *args[1:], "--force"], workdir)
    reference = sha(workdir / out_name)
    (workdir / out_name).unlink()
    rng = np.random.default_rng(list(STAGES).index(stage))
    phases: dict[str, int] = {}
    for n, delay in enumerate(rng.uniform(0.3, 1.05, KILLS_PER_STAGE) * duration):
        marker = f"{stage}-{n}-{os.getpid()}"
        proc = start(args, workdir, marker)
        time.sleep(delay)
        tracked = descendants(proc.pid)
        proc.send_signal(signal.SIGKILL)
        code = proc.wait(timeout=60)
        assert_nothing_left(marker, tracked)
        assert _input_digest(workdir, source) == before, "a killed stage changed its input"
        partials = sorted(workdir.glob(f".{out_name}.*.partial"))
        assert code in (0, -signal.SIGKILL)
        if (workdir / out_name).exists():  # renamed into place before the kill: complete and exact
            phase = "finished" if code == 0 else "killed after the rename"
            assert sha(workdir / out_name) == reference, "a file under the output name is not the complete output"
            (workdir / out_name).unlink()
        else:
            assert code == -signal.SIGKILL
            phase = "killed while writing" if partials else "killed before the output was opened"
        phases[phase] = phases.get(phase, 0) + 1
        for partial in partials:  # an incomplete output is something recover handles
            try:
                recover_log(partial, tmp_path / "rec.mcap", force=True)
            except StarlogError as err:
                assert partial.stat().st_size < 64, err  # only an empty or header-only file cannot be recovered
            else:
                with LogReader(tmp_path / "rec.mcap") as log:
                    for _ in log.raw_messages(log.topics):
                        pass
            partial.unlink()
    run(args, workdir)  # rerun after the kills
    assert sha(workdir / out_name) == reference
    (workdir / out_name).unlink()
    print(f"\n{stage}: {KILLS_PER_STAGE} kills over {duration:.2f} s runs, phases {phases}")


POOL_STAGES = {
    "centroid": ["centroid", "big.mcap", "-o", "OUT", "--method", "MOMENT,GAUSSFIT", "--workers", "2", "-q"],
    "simulate": ["simulate", "-o", "OUT", "--frames", "4000", "--size", "96x96", "--stars", "20", "--workers", "2",
                 "-q"],
}


@needs_proc
@pytest.mark.parametrize("how", ["SIGKILL", "SIGTERM"])  # Ctrl-C: test_ctrl_c_at_random_moments_...
@pytest.mark.parametrize("stage", list(POOL_STAGES))
def test_stopped_stage_leaves_no_process_and_no_partial_output(workdir: Path, stage: str, how: str) -> None:
    """Stopped while its worker pool runs, a stage's fork server and workers exit within 2 s."""
    if not (workdir / "big.mcap").exists():
        run(["simulate", "-o", "big.mcap", "--frames", "1500", "--size", "96x96", "--stars", "20", "-q"], workdir)
    out_name = f"{stage}_{how}.mcap"
    args = [a if a != "OUT" else out_name for a in POOL_STAGES[stage]]
    marker = f"pool-{stage}-{how}-{os.getpid()}"
    proc = start(args, workdir, marker)
    deadline = time.monotonic() + 60
    while len(descendants(proc.pid)) < 3 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)  # until the fork server and both workers run
    time.sleep(0.3)
    tracked = descendants(proc.pid)
    assert proc.poll() is None and len(tracked) >= 3, "the stage ended before its worker pool could be stopped"
    proc.send_signal(getattr(signal, how))
    code = proc.wait(timeout=30)
    assert_nothing_left(marker, tracked)
    partials = sorted(workdir.glob(f".{out_name}.*.partial"))
    if how == "SIGKILL":
        assert code == -signal.SIGKILL
        for partial in partials:
            partial.unlink()
    else:  # the stage unwinds: partial output removed, then it ends of the signal (its exit status says so)
        assert code == -getattr(signal, how)
        assert not partials, "a stopped stage left its partial output"
    assert not (workdir / out_name).exists()


STRESS_CONFIG = ('[centroid]\nmethods = ["MOMENT"]\n[track]\nmethods = ["MOMENT"]\nmodels = ["STATIC"]\n'
                 '[compensate]\nrates = [50]\nprotocols = "paper"\n')
#: Commands with two workers, stopped by Ctrl-C at random moments, and how many times each (50 in all).
STRESS = {
    "simulate": (24, ["simulate", "-o", "OUT", "--frames", "300", "--size", "48x48", "--stars", "4", "--workers", "2",
                      "-q"]),
    "centroid": (16, ["centroid", "in.mcap", "-o", "OUT", "--method", "MOMENT", "--workers", "2", "-q"]),
    "run": (10, ["run", "in.mcap", "-o", "OUT", "--config", "stress.toml", "--workers", "2", "-q"]),
}
STRESS_GRACE_S = 5.0


def _interrupt(proc: subprocess.Popen[bytes], group: bool) -> None:
    """Ctrl-C: to the command alone, or (as a terminal sends it) to its whole process group."""
    if group:
        os.killpg(proc.pid, signal.SIGINT)
    else:
        proc.send_signal(signal.SIGINT)


PACKAGE = Path(starlog.__file__).resolve().parent


def _before_starlog(stderr: bytes) -> bool:
    """A Ctrl-C while the interpreter itself was starting (its site module, runpy loading the package on its way
    to ``starlog.__main__``): it says so itself, in a traceback whose only frame of starlog's, if any, is the
    package's ``__init__`` being loaded (constants only: no starlog code had run yet)."""
    text = stderr.decode(errors="replace")
    ours = {name for name in re.findall(r'File "([^"]+)"', text) if name.startswith(str(PACKAGE))}
    return text.rstrip().endswith("KeyboardInterrupt") and ours <= {str(PACKAGE / "__init__.py")}


def _outputs_of(folder: Path, stem: str) -> list[Path]:
    """Every file or folder of ``folder`` a run writing ``STEM.mcap`` may leave (hidden temporaries included)."""
    return sorted(p for p in folder.iterdir() if p.name.startswith((f"{stem}.", f".{stem}.")))


@needs_proc
@pytest.mark.parametrize("command", list(STRESS))
def test_ctrl_c_at_random_moments_leaves_no_process_and_nothing_partial(workdir: Path, command: str,
                                                                         tmp_path: Path) -> None:
    """Ctrl-C at random moments (starting, starting its pool, working, writing, finishing) of a command with two
    workers: every process it started is gone within 5 s, no partial or temporary file is left (an output
    present is complete), and stderr holds at most click's one line ``Aborted!`` (no traceback, no warning
    of multiprocessing's)."""
    kills, template = STRESS[command]
    folder = tmp_path
    shutil.copy(workdir / "in.mcap", folder / "in.mcap")
    (folder / "stress.toml").write_text(STRESS_CONFIG, encoding="utf-8")
    run([a if a != "OUT" else "warm-up.mcap" for a in template], folder)  # the first run may compile numba's
    duration = run([a if a != "OUT" else "reference.mcap" for a in template], folder)  # kernels: drawn over a warm one
    rng = np.random.default_rng(7 + list(STRESS).index(command))
    outcomes: dict[str, int] = {}
    for n, delay in enumerate(rng.uniform(0.0, 1.0, kills) * duration):
        stem = f"out{n}"
        marker = f"stress-{command}-{n}-{os.getpid()}"
        proc = start([a if a != "OUT" else f"{stem}.mcap" for a in template], folder, marker, new_session=True,
                     stderr=subprocess.PIPE)
        time.sleep(delay)
        tracked = descendants(proc.pid)
        _interrupt(proc, group=bool(n % 2))
        try:
            _, stderr = proc.communicate(timeout=STRESS_GRACE_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            pytest.fail(f"{command} still ran {STRESS_GRACE_S} s after Ctrl-C at {delay:.2f} s")
        assert_nothing_left(marker, tracked, grace=STRESS_GRACE_S)
        if _before_starlog(stderr):  # the interpreter was still starting: it says so itself, and exits 1
            outcomes["stopped before starlog ran"] = outcomes.get("stopped before starlog ran", 0) + 1
            continue
        assert proc.returncode in (0, -signal.SIGINT), stderr
        assert {line for line in stderr.decode().splitlines() if line.strip()} <= {"Aborted!"}, stderr.decode()
        left = _outputs_of(folder, stem)
        assert all(not p.name.startswith(".") for p in left), f"temporary files left: {left}"
        if left:  # it had finished (or run had written its last layer) before the Ctrl-C: complete outputs
            assert (folder / f"{stem}.mcap").exists(), f"layers of an unfinished run left: {left}"
            with LogReader(folder / f"{stem}.mcap") as log:
                for _ in log.raw_messages(log.topics):
                    pass
        outcome = "finished" if proc.returncode == 0 else "stopped with output" if left else "stopped"
        outcomes[outcome] = outcomes.get(outcome, 0) + 1
        for path in left:
            path.unlink()
    print(f"\n{command}: {kills} Ctrl-C over {duration:.2f} s runs: {outcomes}")


CALLBACK_FROM_C = """
import ctypes, os, signal, sys, time
from starlog import cli

cli._handle_stops()


@ctypes.CFUNCTYPE(None)
def called_back():
    os.kill(os.getpid(), signal.SIGINT)
    sum(range(100_000))  # Python runs the Ctrl-C handler here, inside the callback


try:
    called_back()
    for _ in range(500):  # 5 s for the Ctrl-C to come again; Python handles it between two sleeps
        time.sleep(0.01)
except KeyboardInterrupt:
    print("stopped")
else:
    print("lost")
"""


def test_a_ctrl_c_landing_in_a_callback_from_c_still_stops_the_command_quietly() -> None:
    """numba's compiler calls back into Python (its cache); an exception raised there is only reported by Python,
    so a Ctrl-C landing there would print a traceback and be lost. The command delivers it again once the
    callback has returned: it stops, with nothing on stderr."""
    done = subprocess.run([sys.executable, "-c", CALLBACK_FROM_C], capture_output=True, timeout=60,
                          preexec_fn=_default_sigint)
    assert done.stdout.decode().strip() == "stopped"
    assert done.stderr == b""


FINALIZER_AFTER_A_STOP = """
import os, signal, sys
from starlog import cli

cli._handle_stops()


class HalfMade:
    def __del__(self):
        self.handle.close()  # never set: the stop came before it was


HalfMade()  # Python reports the finalizer's error: no stop yet, so it prints
sys.stderr.write("--\\n")
sys.stderr.flush()
try:
    os.kill(os.getpid(), signal.SIGINT)
    sum(range(100_000))
except KeyboardInterrupt:
    HalfMade()  # the stop left it half made: not reported
    print("stopped")
"""


def test_a_finalizer_failing_after_a_ctrl_c_prints_nothing() -> None:
    """A Ctrl-C landing in numba's compiler leaves llvmlite objects half made, whose finalizers then fail: once
    the command is stopping, Python's reports of those are left out (before a stop, they print as usual)."""
    done = subprocess.run([sys.executable, "-c", FINALIZER_AFTER_A_STOP], capture_output=True, timeout=60,
                          preexec_fn=_default_sigint)
    assert done.stdout.decode().strip() == "stopped"
    before, after = done.stderr.decode().split("--\n")
    assert "AttributeError" in before and after == ""


CTRL_C_AS_A_CLASS_IS_MADE = """
import os, signal
from starlog import cli


class Field:
    def __set_name__(self, owner, name):
        os.kill(os.getpid(), signal.SIGINT)
        sum(range(100_000))  # Python runs the Ctrl-C handler here: 3.11 raises it as a RuntimeError


def command(**click_arguments):
    class Record:
        value = Field()
    print("lost")


cli.cli = command
cli.main()
"""


def test_a_ctrl_c_landing_while_a_module_defines_a_class_still_stops_the_command_quietly() -> None:
    """Python wraps an exception raised while a class is created in a ``RuntimeError``: a Ctrl-C landing while a
    module defines its classes (numba's, imported on first use) ends the command of SIGINT with click's one line,
    not that error's traceback."""
    done = subprocess.run([sys.executable, "-c", CTRL_C_AS_A_CLASS_IS_MADE], capture_output=True, timeout=60,
                          preexec_fn=_default_sigint)
    assert done.returncode == -signal.SIGINT, done.stderr
    assert done.stdout == b""
    assert done.stderr.decode().strip() == "Aborted!"


#: Commands run in turn in one interpreter, each as ``starlog`` runs it (status 0, or the interpreter exits with its
#: status).
COMMANDS_IN_TURN = """
import json, sys
from starlog.cli import cli

for args in json.loads(sys.argv[1]):
    try:
        cli.main(args, prog_name="starlog")
    except SystemExit as ended:
        if ended.code:
            raise
"""


def test_every_command_is_reproducible(workdir: Path, tmp_path: Path) -> None:
    """Identical inputs and parameters give identical bytes (no wall-clock time, host or random order)."""
    commands = [
        ["simulate", "-o", "{d}/sim.mcap", "--frames", "80", "--fps", "100", *SIM],
        ["ingest", str(workdir / "frames"), "-o", "{d}/ing.mcap", "--fps", "50", "-q"],
        ["centroid", "{d}/sim.mcap", "-o", "{d}/cen.mcap", "--method", "MOMENT,GAUSSFIT", "-q"],
        ["track", "{d}/cen.mcap", "-o", "{d}/trk.mcap", "--centroids", "MOMENT", "--model", "STATIC", "-q"],
        ["compensate", "{d}/trk.mcap", "-o", "{d}/cmp.mcap", "--rate", "50", "--protocol", "paper", "-q"],
        ["export", "{d}/cmp.mcap", "-o", "{d}/tables"],
        ["recover", "{d}/cut.mcap", "-o", "{d}/rec.mcap"],
    ]
    data = (workdir / "in.mcap").read_bytes()
    runs = []
    for name in ("a", "b"):  # two interpreters at once, each with its own hash seed, each running every command
        d = tmp_path / name
        d.mkdir()
        (d / "cut.mcap").write_bytes(data[: len(data) * 2 // 3])  # a log cut off, for recover
        chain = [[a.replace("{d}", str(d)) for a in command] for command in commands]
        runs.append(subprocess.Popen([sys.executable, "-c", COMMANDS_IN_TURN, json.dumps(chain)], cwd=tmp_path,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE))
    for proc in runs:
        _, stderr = proc.communicate(timeout=300)
        assert proc.returncode == 0, stderr.decode()
    digests = [{p.relative_to(d).as_posix(): sha(p) for p in sorted(d.rglob("*")) if p.is_file()}
               for d in (tmp_path / "a", tmp_path / "b")]
    assert digests[0] == digests[1]
    assert {"sim.mcap", "ing.mcap", "cen.mcap", "trk.mcap", "cmp.mcap", "rec.mcap"} <= set(digests[0])
    assert any(k.startswith("tables/") for k in digests[0])
    assert pq.read_table(tmp_path / "a" / "tables" / "frames.parquet").num_rows == 80
