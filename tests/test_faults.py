"""Faults on the way out: every command that writes, on an OS error (a file-size limit, a full or read-only
file system, permission denied, an I/O error, a folder removed meanwhile), prints one line on stderr naming
the file, what happened and what to do, exits with status 1 and leaves no partial or temporary file; its
inputs are never touched. An input removed or truncated while a stage reads it is one line too. Two commands
writing one path at once: the first to finish wins, the other says so.

Real faults where the test can make them: RLIMIT_FSIZE in the command's process (any file system), and a
small or read-only tmpfs in a mount namespace of the command's own (``unshare``; skipped, saying why, where
none can be made). Injected ``OSError``s at each write site of the writer and of ``atomic_output``.
"""

from __future__ import annotations

import errno
import hashlib
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from starlog.cli import cli
from starlog.errors import FileAccessError, OutputChangedError
from starlog.io import LogReader
from starlog.io.output_files import atomic_output
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log
from starlog.stages.compensate import compensate_log
from starlog.stages.track import track_log
from tests.helpers import small_config

PY = [sys.executable, "-m", "starlog"]
PIPELINE = '[centroid]\nmethods = ["MOMENT"]\n[track]\nmethods = ["MOMENT"]\nmodels = ["STATIC"]\n'

#: Every command that writes a file: its arguments ({i}: the inputs' folder, {o}: the output folder).
COMMANDS = {
    "simulate": ["simulate", "-o", "{o}/s.mcap", "--frames", "60", "--size", "48x48", "--stars", "3", "-q"],
    "ingest": ["ingest", "{i}/frames", "-o", "{o}/i.mcap", "--fps", "50", "-q"],
    "centroid": ["centroid", "{i}/sim.mcap", "-o", "{o}/c.mcap", "--method", "MOMENT", "-q"],
    "track": ["track", "{i}/cen.mcap", "-o", "{o}/t.mcap", "--centroids", "MOMENT", "--model", "STATIC", "-q"],
    "motion": ["motion", "{i}/trk.mcap", "-o", "{o}/m.mcap", "--track", "/track/MOMENT/STATIC", "-q"],
    "compensate": ["compensate", "{i}/trk.mcap", "-o", "{o}/k.mcap", "--rate", "50", "--protocol", "paper", "-q"],
    "run": ["run", "{i}/sim.mcap", "-o", "{o}/r.mcap", "--config", "{i}/pipeline.toml", "-q"],
    "run --flatten": ["run", "{i}/sim.mcap", "-o", "{o}/r.mcap", "--config", "{i}/pipeline.toml", "--flatten", "-q"],
    "filter": ["filter", "{i}/cmp.mcap", "-o", "{o}/f.mcap", "--topic", "/camera/*"],
    "flatten": ["flatten", "{i}/cmp.mcap", "-o", "{o}/f.mcap"],
    "recover": ["recover", "{i}/sim.mcap", "-o", "{o}/v.mcap"],
    "export": ["export", "{i}/cmp.mcap", "-o", "{o}/tables"],
    "report": ["report", "{i}/cmp.mcap", "-o", "{o}/r.html"],
    "experiment": ["experiment", "-o", "{o}/results", "--quick", "--regime", "paper", "--workers", "1", "-q"],
    "cat": ["cat", "{i}/sim.mcap", "--topic", "/sim/truth"],
    "solve": ["solve", "{i}/sky-cen.mcap", "-o", "{o}/a.mcap", "--centroids", "all", "-q"],
}


def digest(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated log and its chain (centroid, track, compensate), a folder of frames and a pipeline config."""
    import cv2
    import matplotlib.font_manager  # noqa: F401 - its font cache is built here, not in a command under a limit

    d = tmp_path_factory.mktemp("faults")
    (d / "frames").mkdir()
    rng = np.random.default_rng(1)
    for n in range(12):
        cv2.imwrite(str(d / "frames" / f"f{n}.png"), rng.integers(0, 4000, (32, 32), dtype=np.uint16))
    simulate_log(small_config(n_frames=100), d / "sim.mcap")
    centroid_log(d / "sim.mcap", d / "cen.mcap", methods="MOMENT")  # numba's kernels compiled and cached here
    track_log(d / "cen.mcap", d / "trk.mcap", method="MOMENT", models="STATIC")
    compensate_log(d / "trk.mcap", d / "cmp.mcap", rates=[50], protocols="paper")
    (d / "pipeline.toml").write_text(PIPELINE, encoding="utf-8")
    return d


def args_of(command: str, inputs: Path, out: Path) -> list[str]:
    return [a.format(i=inputs, o=out) for a in COMMANDS[command]]


def assert_one_line(stderr: str, *needles: str) -> str:
    """stderr is one line, click's ``Error: ...``, holding each of ``needles``; no traceback."""
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), stderr
    assert "Traceback" not in stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def leftovers(out: Path, keep: tuple[str, ...] = ()) -> list[str]:
    """Files (hidden ones included) under ``out``, but ``keep``."""
    return sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file() and p.name not in keep)


# ---------------------------------------------------------------- a file-size limit (EFBIG), every command
def _limited(limit: int):  # noqa: ANN202 - a preexec_fn
    def apply() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
    return apply


def _sky_log(inputs: Path) -> None:
    """A small sky field and its centroids, for solve (which needs cedar-solve's catalogue)."""
    pytest.importorskip("tetra3")
    from starlog.sim import SimulationConfig

    if not (inputs / "sky-cen.mcap").exists():
        simulate_log(SimulationConfig(width=256, height=256, sky_attitude=(120.0, -30.0, 40.0), fov_deg=10.0,
                                      magnitude_limit=7.0, n_frames=4, seed=2), inputs / "sky.mcap")
        centroid_log(inputs / "sky.mcap", inputs / "sky-cen.mcap", methods="MOMENT")


@pytest.mark.parametrize("command", list(COMMANDS))
def test_every_command_over_a_file_size_limit_says_so_in_one_line(command: str, inputs: Path, tmp_path: Path) -> None:
    if command == "solve":
        _sky_log(inputs)
    before = digest(inputs)
    out = tmp_path / "out"
    out.mkdir()
    with open(out / "stdout.txt", "wb") as stdout:  # cat's output: its standard output is a file here
        done = subprocess.run(PY + args_of(command, inputs, out), stdout=stdout, stderr=subprocess.PIPE, text=True,
                              preexec_fn=_limited(1024), timeout=300, check=False)
    assert done.returncode == 1, done.stderr
    named = "standard output" if command == "cat" else str(out)
    assert_one_line(done.stderr, "cannot write", named, "size limit")
    assert leftovers(out, keep=("stdout.txt",)) == []
    assert digest(inputs) == before, "a command changed its input"


# ---------------------------------------------------------------- a full or read-only file system
def _private_mounts() -> str | None:
    """Why a test cannot mount a tmpfs in a mount namespace of its own (None: it can)."""
    if shutil.which("unshare") is None:
        return "unshare (util-linux) is not installed"
    user = [] if os.geteuid() == 0 else ["--map-root-user"]
    probe = subprocess.run(["unshare", "--mount", *user, "sh", "-c", "mount -t tmpfs -o size=4k tmpfs /mnt"],
                           capture_output=True, text=True, timeout=30, check=False)
    return None if probe.returncode == 0 else f"no mount namespace can be made here: {probe.stderr.strip()}"


def on_small_file_system(args: list[str], out: Path, options: str) -> tuple[int, str, list[str]]:
    """Run ``starlog ARGS`` with a tmpfs mounted (``options``) on ``out`` in a mount namespace of its own: its exit
    status, its stderr, and every file left on that file system (which vanishes with the namespace)."""
    user = [] if os.geteuid() == 0 else ["--map-root-user"]
    report = out.parent / "report"
    script = ('mount -t tmpfs -o "$1" tmpfs "$2" || exit 97; out=$2; report=$3; shift 3; '
              '"$@" 2> "$report.err"; echo $? > "$report.rc"; (cd "$out" && find . -type f) > "$report.files"')
    subprocess.run(["unshare", "--mount", *user, "bash", "-c", script, "-", options, str(out), str(report),
                    *PY, *args], timeout=300, check=True)
    files = [f.removeprefix("./") for f in Path(f"{report}.files").read_text().split()]
    return int(Path(f"{report}.rc").read_text()), Path(f"{report}.err").read_text(), files


@pytest.fixture(scope="module")
def private_mounts() -> None:
    why = _private_mounts()
    if why is not None:
        pytest.skip(f"a full or read-only file system needs a tmpfs of the test's own: {why}")


@pytest.mark.parametrize("command", ["simulate", "centroid", "run --flatten", "flatten", "export", "report"])
def test_a_full_file_system_is_one_line_and_leaves_nothing(command: str, inputs: Path, tmp_path: Path,
                                                           private_mounts: None) -> None:
    out = tmp_path / "out"
    out.mkdir()
    before = digest(inputs)
    code, stderr, files = on_small_file_system(args_of(command, inputs, out), out, "size=4k")
    assert code == 1, stderr
    assert_one_line(stderr, "cannot write", str(out), "no space left on the device")
    assert files == [] and digest(inputs) == before


@pytest.mark.parametrize("command", ["simulate", "track", "run", "export", "report", "experiment"])
def test_a_read_only_file_system_is_one_line(command: str, inputs: Path, tmp_path: Path,
                                             private_mounts: None) -> None:
    out = tmp_path / "out"
    out.mkdir()
    code, stderr, files = on_small_file_system(args_of(command, inputs, out), out, "ro")
    assert code == 1, stderr
    assert_one_line(stderr, "cannot write", str(out), "read-only")
    assert files == []


# ---------------------------------------------------------------- injected errors at each write site
def _raising(code: int, after: int = 0):  # noqa: ANN202
    """A wrapper that makes a function raise ``OSError(code)`` from its ``after+1``-th call on."""
    def wrap(original):  # noqa: ANN001, ANN202
        calls = {"n": 0}

        def raise_after(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            calls["n"] += 1
            if calls["n"] > after:
                raise OSError(code, os.strerror(code))
            return original(*args, **kwargs)
        return raise_after
    return wrap


class _FailingFile:
    """The writer's output file, whose writes (or flush) fail with ``code`` after ``after`` that pass."""

    def __init__(self, file, method: str, code: int, after: int) -> None:  # noqa: ANN001
        self._file, self._method, self._code, self._left = file, method, code, after

    def __getattr__(self, name: str):  # noqa: ANN204
        attribute = getattr(self._file, name)
        if name != self._method:
            return attribute

        def failing(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            self._left -= 1
            if self._left < 0:
                raise OSError(self._code, os.strerror(self._code))
            return attribute(*args, **kwargs)
        return failing


def _failing_writes(method: str, code: int, after: int):  # noqa: ANN202
    """``os.fdopen`` (as the log writer opens its file) giving a file whose ``method`` fails."""
    def wrap(fdopen):  # noqa: ANN001, ANN202
        return lambda *args, **kwargs: _FailingFile(fdopen(*args, **kwargs), method, code, after)
    return wrap


#: Each write site: the patches (target, wrapper) per kind of output, and the words of its line.
SITES = {
    "create": ({"*": [("tempfile.mkstemp", _raising(errno.EACCES))]}, "permission denied"),
    "write": ({"mcap": [("starlog.io.writer.os.fdopen", _failing_writes("write", errno.ENOSPC, 1))],
               "report": [("pathlib.Path.write_text", _raising(errno.ENOSPC))],
               "export": [("pyarrow.parquet.ParquetWriter.write_table", _raising(errno.ENOSPC))]}, "no space left"),
    "flush": ({"mcap": [("starlog.io.writer.os.fdopen", _failing_writes("flush", errno.EDQUOT, 0))],
               "report": [("pathlib.Path.write_text", _raising(errno.EDQUOT))],
               "export": [("pyarrow.parquet.ParquetWriter.close", _raising(errno.EDQUOT))]}, "quota"),
    "fsync": ({"*": [("os.fsync", _raising(errno.EIO))]}, "input/output error"),
    "link": ({"*": [("os.link", _raising(errno.ENOENT))]}, "removed meanwhile"),
    "rename": ({"*": [("os.link", _raising(errno.EPERM)), ("os.replace", _raising(errno.ENOENT))]},
               "removed meanwhile"),
}
KIND = {"centroid": "mcap", "flatten": "mcap", "report": "report", "export": "export"}


def _patch(monkeypatch: pytest.MonkeyPatch, target: str, wrap) -> None:  # noqa: ANN001
    import importlib

    module_name, _, attribute = target.rpartition(".")
    try:
        owner: object = importlib.import_module(module_name)
    except ImportError:
        module_name, _, class_name = module_name.rpartition(".")
        owner = getattr(importlib.import_module(module_name), class_name)
    monkeypatch.setattr(owner, attribute, wrap(getattr(owner, attribute)))


@pytest.mark.parametrize("site", list(SITES))
@pytest.mark.parametrize("command", list(KIND))
def test_an_os_error_at_each_write_site_is_one_line(command: str, site: str, inputs: Path, tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    patches, words = SITES[site]
    out = tmp_path / "out"
    out.mkdir()
    before = digest(inputs)
    for target, wrap in patches.get(KIND[command], patches.get("*", [])):
        _patch(monkeypatch, target, wrap)
    result = CliRunner().invoke(cli, args_of(command, inputs, out))
    monkeypatch.undo()
    assert result.exit_code == 1, result.output
    assert_one_line(result.stderr, "cannot write", str(out), words)
    assert leftovers(out) == [] and digest(inputs) == before


def test_a_failed_export_removes_the_tables_it_wrote_and_its_folder(inputs: Path, tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    _patch(monkeypatch, "pyarrow.parquet.ParquetWriter.write_table", _raising(errno.ENOSPC, after=2))
    result = CliRunner().invoke(cli, ["export", str(inputs / "cmp.mcap"), "-o", str(tmp_path / "new" / "tables")])
    assert result.exit_code == 1
    assert_one_line(result.stderr, "no space left")
    assert not (tmp_path / "new" / "tables").exists()  # two tables were written, then removed with the folder
    kept = tmp_path / "mine"
    kept.mkdir()
    (kept / "notes.txt").write_text("the user's", encoding="utf-8")
    result = CliRunner().invoke(cli, ["export", str(inputs / "cmp.mcap"), "-o", str(kept)])
    assert result.exit_code == 1 and leftovers(kept) == ["notes.txt"]


# ---------------------------------------------------------------- while it runs: folders and inputs that go
def _when_writing(args: list[str], folder: Path, then) -> subprocess.CompletedProcess[str]:  # noqa: ANN001
    """Run ``starlog ARGS``; once its temporary output appears in ``folder``, call ``then()``."""
    proc = subprocess.Popen(PY + args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while proc.poll() is None and time.monotonic() < deadline and not list(folder.glob(".*.partial")):
        time.sleep(0.005)
    then()
    _, stderr = proc.communicate(timeout=300)
    return subprocess.CompletedProcess(args, proc.returncode, "", stderr)


def test_an_output_folder_removed_while_a_stage_writes_is_one_line(inputs: Path, tmp_path: Path) -> None:
    out = tmp_path / "gone"
    out.mkdir()
    done = _when_writing(["simulate", "-o", str(out / "s.mcap"), "--frames", "400", "--size", "64x64", "-q"], out,
                         lambda: shutil.rmtree(out))
    assert done.returncode == 1, done.stderr
    assert_one_line(done.stderr, f"cannot write {out / 's.mcap'}", "removed meanwhile")
    assert not out.exists()


@pytest.mark.parametrize("how", ["removed", "truncated"])
def test_an_input_removed_or_truncated_while_a_stage_reads_it_is_one_line(how: str, inputs: Path,
                                                                          tmp_path: Path) -> None:
    source = tmp_path / "in.mcap"
    simulate_log(small_config(n_frames=600, width=96, height=96), source)
    out = tmp_path / "out"
    out.mkdir()

    def fault() -> None:
        if how == "removed":
            source.unlink()
        else:
            os.truncate(source, source.stat().st_size // 3)

    done = _when_writing(["centroid", str(source), "-o", str(out / "c.mcap"), "--method", "MOMENT", "--workers", "2",
                          "-q"], out, fault)
    assert "Traceback" not in done.stderr
    if done.returncode == 0:  # read through before the fault: a complete layer (its base is gone or cut since)
        with LogReader(out / "c.mcap", chain=False) as log:
            assert log.topics
    else:
        assert done.returncode == 1
        assert_one_line(done.stderr, str(source))
    assert leftovers(out, keep=("c.mcap",)) == []


# ---------------------------------------------------------------- two commands writing one path
def test_two_writers_of_one_path_the_first_to_finish_wins(tmp_path: Path) -> None:
    target = tmp_path / "same.txt"
    for force in (False, True):
        with pytest.raises(OutputChangedError, match="written by another command"):
            with atomic_output(target, force=force) as first:
                first.write_text(f"first {force}", encoding="utf-8")
                with atomic_output(target, force=force) as second:  # opened later, done first
                    second.write_text(f"second {force}", encoding="utf-8")
        assert target.read_text(encoding="utf-8") == f"second {force}"
        assert leftovers(tmp_path) == ["same.txt"]
        target.unlink()


@pytest.mark.parametrize("force", [False, True])
def test_two_commands_writing_one_output_at_once(force: bool, tmp_path: Path) -> None:
    out = tmp_path / "same.mcap"
    args = PY + ["simulate", "-o", str(out), "--frames", "150", "--size", "64x64", "-q", *(["--force"] * force)]
    procs = [subprocess.Popen(args + ["--seed", str(seed)], stderr=subprocess.PIPE, text=True) for seed in (1, 2)]
    results = [(p.returncode, err) for p in procs for _, err in [p.communicate(timeout=120)]]
    codes = sorted(code for code, _ in results)
    assert codes[0] == 0 and all("Traceback" not in err for _, err in results)
    if codes[1] == 1:  # the loser's line: written meanwhile, or (it started late) exists already
        line = assert_one_line(next(err for code, err in results if code == 1), str(out))
        assert "written by another command" in line or "exists already" in line
    else:  # with --force, one started after the other had finished: it replaced it, as asked
        assert force
    with LogReader(out) as log:
        assert sum(1 for _ in log.raw_messages(log.topics)) > 0
    assert leftovers(tmp_path) == ["same.mcap"]


def test_a_file_access_error_crosses_processes_whole() -> None:
    import pickle

    err = FileAccessError("/data/out.mcap", "write", errno.ENOSPC, "No space left on device")
    again = pickle.loads(pickle.dumps(err))
    assert str(again) == str(err) and again.errno == errno.ENOSPC and isinstance(again, OSError)


def test_run_never_writes_a_layer_over_a_file_of_its_own_chain(inputs: Path, tmp_path: Path) -> None:
    """``run`` on the output of an earlier run, into the same name: its first layer's name is a file of its input's
    chain. Refused in one line, every file of the chain as it was."""
    shutil.copy(inputs / "sim.mcap", tmp_path / "sim.mcap")
    args = ["run", str(tmp_path / "sim.mcap"), "-o", str(tmp_path / "r.mcap"), "--config", str(inputs / "pipeline.toml"),
            "-q"]
    assert CliRunner().invoke(cli, args).exit_code == 0
    before = digest(tmp_path)
    again = ["run", str(tmp_path / "r.mcap"), *args[2:], "--force"]
    result = CliRunner().invoke(cli, again)
    assert result.exit_code == 1
    assert_one_line(result.stderr, str(tmp_path / "r.1-centroid.mcap"), "is one of the files it is written from")
    assert digest(tmp_path) == before
