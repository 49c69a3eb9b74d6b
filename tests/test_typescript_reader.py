"""A second, independent reader: the TypeScript MCAP indexed reader (@mcap/core) Foxglove uses."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from starlog.io import LogWriter, encode_json, json_message_type

TS_DIR = Path(__file__).resolve().parent.parent / "tools" / "ts_reader"


@pytest.fixture(scope="module")
def node_reader() -> Path:
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip("Node.js is not installed: the TypeScript MCAP reader check needs node and npm.")
    if not (TS_DIR / "node_modules" / "@mcap" / "core").is_dir():
        subprocess.run([npm, "ci", "--no-audit", "--no-fund", "--loglevel=error"], cwd=TS_DIR, check=True,
                       capture_output=True, timeout=300)
    return TS_DIR / "check.mjs"


def _read_with_node(script: Path, log: Path) -> dict[str, object]:
    result = subprocess.run(["node", str(script), str(log)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def test_typescript_reader_reads_a_simulated_log(node_reader: Path, sim_log: Path) -> None:
    report = _read_with_node(node_reader, sim_log)
    assert report["counts"] == {"/camera/image": 20, "/camera/frame": 20, "/sim/truth": 20}
    assert report["metadata"] == ["starlog.provenance"]
    assert report["statistics"] == 60


@pytest.mark.parametrize("compression", ["lz4", "none"])
def test_typescript_reader_reads_an_appended_log(node_reader: Path, sim_log: Path, tmp_path: Path,
                                                 compression: str) -> None:
    out = tmp_path / "appended.mcap"
    with LogWriter(out, base=sim_log, compression=compression) as w:
        ch = w.add_channel("/extra", json_message_type("starlog.FrameInfo"))
        for n in range(3):
            w.write(ch, log_time=n * 10_000_000, data=encode_json(
                {"frame": n, "width": 1, "height": 1, "encoding": "mono8", "bit_depth": 8, "source": ""}))
        w.add_metadata("starlog.provenance", {"stage": "extra"})
    report = _read_with_node(node_reader, out)
    assert report["counts"] == {"/camera/image": 20, "/camera/frame": 20, "/sim/truth": 20, "/extra": 3}
    assert report["metadata"] == ["starlog.provenance", "starlog.provenance"]
