"""A stage killed (SIGKILL) at random moments never changes its input, never leaves a
half-written file under the output name, and a rerun gives the bytes of an uninterrupted run.

Also: every command gives identical bytes for identical inputs (reproducibility).
"""

from __future__ import annotations

import hashlib
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from starlog.errors import StarlogError
from starlog.io import LogReader
from starlog.io.recover import recover_log

PY = [sys.executable, "-m", "starlog"]
SIM = ["--size", "32x32", "--stars", "3", "--seed", "1", "-q"]


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run(args: list[str], cwd: Path) -> float:
    t0 = time.perf_counter()
    subprocess.run(PY + args, cwd=cwd, check=True, capture_output=True, timeout=120)
    return time.perf_counter() - t0


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
    for delay in rng.uniform(0.3, 1.05, KILLS_PER_STAGE) * duration:
        proc = subprocess.Popen(PY + args, cwd=workdir, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(delay)
        proc.send_signal(signal.SIGKILL)
        code = proc.wait(timeout=60)
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


def test_every_command_is_reproducible(workdir: Path, tmp_path: Path) -> None:
    """Identical inputs and parameters give identical bytes (no wall-clock time, host or random order)."""
    commands = [
        ["simulate", "-o", "{d}/sim.mcap", "--frames", "80", "--fps", "100", *SIM],
        ["ingest", str(workdir / "frames"), "-o", "{d}/ing.mcap", "--fps", "50", "-q"],
        ["centroid", "{d}/sim.mcap", "-o", "{d}/cen.mcap", "--method", "MOMENT,GAUSSFIT", "-q"],
        ["track", "{d}/cen.mcap", "-o", "{d}/trk.mcap", "--centroids", "MOMENT", "--model", "STATIC", "-q"],
        ["compensate", "{d}/trk.mcap", "-o", "{d}/cmp.mcap", "--rate", "50", "--protocol", "paper", "-q"],
        ["export", "{d}/cmp.mcap", "-o", "{d}/tables"],
    ]
    digests = []
    for name in ("a", "b"):
        d = tmp_path / name
        d.mkdir()
        for command in commands:
            run([a.replace("{d}", str(d)) for a in command], tmp_path)
        data = (d / "sim.mcap").read_bytes()
        (d / "cut.mcap").write_bytes(data[: len(data) * 2 // 3])
        run(["recover", str(d / "cut.mcap"), "-o", str(d / "rec.mcap")], tmp_path)
        files = sorted(p for p in d.rglob("*") if p.is_file())
        digests.append({p.relative_to(d).as_posix(): sha(p) for p in files})
    assert digests[0] == digests[1]
    assert {"sim.mcap", "ing.mcap", "cen.mcap", "trk.mcap", "cmp.mcap", "rec.mcap"} <= set(digests[0])
    assert any(k.startswith("tables/") for k in digests[0])
    assert pq.read_table(tmp_path / "a" / "tables" / "frames.parquet").num_rows == 80
