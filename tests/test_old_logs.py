"""Logs whose star tables are JSON (as earlier versions wrote them) work everywhere: every reading command gives
what it gives for the protobuf log, every stage reads a JSON base, and layers of either kind sit on bases of either
kind."""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from starlog.cli import cli
from starlog.io import LogReader
from starlog.codecs.star_tables import STAR_TABLES
from starlog.sim import Jitter
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log
from starlog.stages.compensate import compensate_log
from starlog.stages.motion import motion_log
from starlog.stages.track import track_log
from tests.helpers import small_config
from tests.json_logs import write_json_log

TRACK = "/track/GAUSSFIT/STATIC"


def _invoke(*args: str) -> str:
    result = CliRunner().invoke(cli, list(args), catch_exceptions=False)
    assert result.exit_code == 0, result.output
    return result.output


def _cat(log: Path, *options: str) -> dict[str, list[str]]:
    """``starlog cat`` of a log: each channel's lines, in order (messages of one time on different channels come
    in file order, which a copy into one file may change)."""
    lines: dict[str, list[str]] = {}
    for line in _invoke("cat", str(log), *options, "-q").splitlines():
        lines.setdefault(json.loads(line)["topic"], []).append(line)
    return lines


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """simulate → centroid → track → motion → compensate (protobuf star tables), and JSON copies: the whole
    chain in one file (``old``), the centroids on their own (``old_cen``), the track layer alone on the protobuf
    centroid layer (``old_trk``)."""
    d = tmp_path_factory.mktemp("old")
    logs = {name: d / f"{name}.mcap" for name in ("sim", "cen", "trk", "mot", "comp")}
    simulate_log(small_config(width=96, height=80, n_stars=4, n_frames=120, margin=12.0,
                              jitter=(Jitter(frequency_hz=9.0, amplitude_px=0.05),)), logs["sim"])
    centroid_log(logs["sim"], logs["cen"], methods="GAUSSFIT,NONE", mode="full")
    track_log(logs["cen"], logs["trk"], method="GAUSSFIT", models="STATIC", tracker={"sigma_floor": 0.05})
    motion_log(logs["trk"], logs["mot"], model="translation")
    compensate_log(logs["mot"], logs["comp"], rates=[50], track="all", protocols="paper,truth")
    logs["old"] = write_json_log(logs["comp"], d / "old.mcap")
    logs["old_cen"] = write_json_log(logs["cen"], d / "old-cen.mcap")
    logs["old_trk"] = write_json_log(logs["trk"], d / "old-trk.mcap", base=logs["cen"])
    return logs


def test_the_old_log_holds_every_star_table_as_json(logs: dict[str, Path]) -> None:
    with LogReader(logs["old"]) as old, LogReader(logs["comp"]) as new:
        encodings = {c.topic: (c.schema_name, c.message_encoding) for c in old.channels()}
        assert {c.topic: c.message_count for c in old.channels()} == {c.topic: c.message_count for c in new.channels()}
    tables = {topic for topic, (schema, _) in encodings.items() if schema in STAR_TABLES}
    assert len(tables) == 6 and all(encodings[t][1] == "json" for t in tables)


def test_cat_prints_the_same_json_for_either_encoding(logs: dict[str, Path]) -> None:
    assert _cat(logs["old"]) == _cat(logs["comp"])


def test_export_writes_the_same_tables(logs: dict[str, Path], tmp_path: Path) -> None:
    old = json.loads(_invoke("export", str(logs["old"]), "-o", str(tmp_path / "old"), "--topic", TRACK, "--json",
                             "-q"))
    new = json.loads(_invoke("export", str(logs["comp"]), "-o", str(tmp_path / "new"), "--topic", TRACK, "--json",
                             "-q"))
    assert old["tables"] == new["tables"]
    assert {"detections", "centroids", "tracks", "motion", "residuals", "compensation",
            "track.GAUSSFIT.STATIC"} <= set(new["tables"])
    for path in sorted((tmp_path / "new").glob("*.parquet")):
        assert pq.read_table(tmp_path / "old" / path.name).equals(pq.read_table(path)), path.name


@pytest.mark.parametrize("log", ["old", "old_trk"])
def test_info_verify_and_report_read_json_star_tables(logs: dict[str, Path], log: str, tmp_path: Path) -> None:
    info = json.loads(_invoke("info", str(logs[log]), "--json"))
    assert any(ch["schema"] == "starlog.Tracks" and ch["message_encoding"] == "json" for ch in info["channels"])
    assert json.loads(_invoke("verify", str(logs[log]), "--json"))["ok"] is True
    _invoke("report", str(logs[log]), "-o", str(tmp_path / "r.html"), "-q")
    assert "starlog.Tracks" in (tmp_path / "r.html").read_text() or TRACK in (tmp_path / "r.html").read_text()


def test_filter_and_flatten_copy_json_star_tables(logs: dict[str, Path], tmp_path: Path) -> None:
    _invoke("filter", str(logs["old"]), "-o", str(tmp_path / "f.mcap"), "--topic", "/stars/*", "--start", "frame:10",
            "--end", "frame:20", "-q")
    assert _cat(tmp_path / "f.mcap") == _cat(logs["comp"], "--topic", "/stars/*", "--start", "frame:10",
                                             "--end", "frame:20")
    _invoke("flatten", str(logs["old_trk"]), "-o", str(tmp_path / "flat.mcap"), "-q")
    assert _cat(tmp_path / "flat.mcap") == _cat(logs["trk"])


def test_stages_on_a_json_base_write_what_they_write_on_a_protobuf_one(logs: dict[str, Path], tmp_path: Path) -> None:
    """A protobuf track layer on JSON centroids, then motion on it: the same messages as on the protobuf chain."""
    track_log(logs["old_cen"], tmp_path / "trk.mcap", method="GAUSSFIT", models="STATIC",
              tracker={"sigma_floor": 0.05})
    motion_log(tmp_path / "trk.mcap", tmp_path / "mot.mcap", model="translation")
    for topic in (TRACK, "/platform/*", "/stars/residuals/*"):
        assert _cat(tmp_path / "mot.mcap", "--topic", topic) == _cat(logs["mot"], "--topic", topic)


def test_compensate_and_motion_read_a_json_track_layer_on_a_protobuf_base(logs: dict[str, Path],
                                                                           tmp_path: Path) -> None:
    motion_log(logs["old_trk"], tmp_path / "mot.mcap", model="translation")
    compensate_log(tmp_path / "mot.mcap", tmp_path / "comp.mcap", rates=[50], track="all", protocols="paper,truth")
    assert _cat(tmp_path / "comp.mcap", "--topic", "/compensated/*") == _cat(logs["comp"], "--topic",
                                                                              "/compensated/*")
