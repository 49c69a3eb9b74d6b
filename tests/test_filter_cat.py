"""``starlog filter`` and ``starlog cat`` on native and foreign logs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from starlog.cli import cli
from starlog.errors import InvalidParameterError
from starlog.io import LogReader, file_digest
from starlog.io.verify import verify_log
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log
from starlog.excerpt import cat_messages, filter_log
from tests.foreign_logs import write_plain, write_ros2
from tests.helpers import small_config


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A simulated log (several chunk groups), its centroids, a ROS 2 bag and an unindexed plain log of it."""
    d = tmp_path_factory.mktemp("filter")
    sim = d / "sim.mcap"
    simulate_log(small_config(width=256, height=256, n_frames=70, n_stars=4, margin=20.0), sim)
    cen = d / "cen.mcap"
    centroid_log(small_config_log(d), cen, methods="MOMENT")
    return {"sim": sim, "cen": cen,
            "ros2": write_ros2(sim, d / "ros2.mcap", chunk_size=256 * 1024),
            "plain": write_plain(sim, d / "plain.mcap", message_indexes=False, summary=False, chunk_size=200_000),
            "loose": write_plain(sim, d / "loose.mcap", use_chunking=False)}


def small_config_log(folder: Path) -> Path:
    path = folder / "small.mcap"
    simulate_log(small_config(), path)
    return path


def _counts(path: Path) -> dict[str, int]:
    with LogReader(path) as log:
        return {c.topic: c.message_count for c in log.channels()}


def _chunks(path: Path) -> list[bytes]:
    data = path.read_bytes()
    with LogReader(path) as log:
        return [data[ci.chunk_start_offset: ci.chunk_start_offset + ci.chunk_length]
                for ci in log.files[-1].summary.chunk_indexes]


def test_topic_filter_copies_every_kept_chunk_byte_for_byte(logs: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "images.mcap"
    report = filter_log(logs["sim"], out, topics=["/camera/*"])
    assert _counts(out) == {"/camera/image": 70, "/camera/frame": 70}
    assert report.chunks_reencoded == 0 and report.chunks_copied >= 4
    assert set(_chunks(out)) <= set(_chunks(logs["sim"]))  # never re-compressed
    assert verify_log(out).ok
    with LogReader(out) as log:
        records = log.provenance()
        assert [r.stage for r in records] == ["simulate", "filter"]  # metadata kept, own record added
        assert records[1].parameters == {"topics": ["/camera/*"], "exclude_topics": [], "range": None}
        assert records[1].input_digest == file_digest(logs["sim"])
        assert sum(1 for _ in log.frames()) == 70


def test_exclude_and_time_range_and_byte_identical_rerun(logs: dict[str, Path], tmp_path: Path) -> None:
    for name in ("a.mcap", "b.mcap"):
        filter_log(logs["sim"], tmp_path / name, exclude_topics=["/sim/*"], start="frame:7", end="0.5s")
    assert (tmp_path / "a.mcap").read_bytes() == (tmp_path / "b.mcap").read_bytes()
    assert _counts(tmp_path / "a.mcap") == {"/camera/image": 43, "/camera/frame": 43}  # frames 7..49 at 100 Hz
    assert verify_log(tmp_path / "a.mcap").ok


def test_filter_keeps_the_stage_channels_asked_for(logs: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "cen.mcap"
    result = CliRunner().invoke(cli, ["filter", str(logs["cen"]), "-o", str(out), "--topic", "/stars/*",
                                      "--exclude-topic", "/stars/annotations", "--json", "-q"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)["messages"] == {"/stars/detections": 20, "/stars/centroids/MOMENT": 20}
    with LogReader(out) as log:
        assert [r.stage for r in log.provenance()] == ["simulate", "centroid", "filter"]


@pytest.mark.parametrize("kind", ["ros2", "plain", "loose"])
def test_filter_foreign_and_unindexed_logs(kind: str, logs: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / f"{kind}.mcap"
    filter_log(logs[kind], out, start="frame:5", end="frame:25")
    counts = _counts(out)
    assert set(counts.values()) == {20}, counts
    report = verify_log(out)
    assert report.ok and not [p for p in report.problems if p.severity != "error" and "index" in p.kind], \
        report.verdict()
    with LogReader(out) as log:
        assert log.fully_indexed
        assert sum(1 for _ in log.frames(log.channels()[0].topic if kind == "ros2" else "/camera/image")) == 20
    if kind == "ros2":
        assert b"ros2" in out.read_bytes()[:64]  # the header keeps the bag's profile


def test_filter_errors(logs: dict[str, Path], tmp_path: Path) -> None:
    with pytest.raises(InvalidParameterError, match="matches no channel"):
        filter_log(logs["sim"], tmp_path / "x.mcap", topics=["/nope"])
    with pytest.raises(InvalidParameterError, match="outside the selected channels"):
        filter_log(logs["sim"], tmp_path / "x.mcap", start="100s")
    with pytest.raises(InvalidParameterError, match="reversed"):
        filter_log(logs["sim"], tmp_path / "x.mcap", start="0.5s", end="0.2s")
    assert not (tmp_path / "x.mcap").exists()


def test_command_errors_are_one_line(logs: dict[str, Path], tmp_path: Path) -> None:
    """A missing output folder, a start past the end, a file of another format: a clear line, no traceback."""
    not_mcap = tmp_path / "notes.txt"
    not_mcap.write_text("not a log\n")
    cases = [
        (["filter", str(logs["sim"]), "-o", str(tmp_path / "missing" / "x.mcap")], "the folder"),
        (["centroid", str(logs["sim"]), "-o", str(tmp_path / "missing" / "x.mcap"), "--start", "frame:2"],
         "does not exist"),
        (["filter", str(logs["sim"]), "-o", str(tmp_path / "x.mcap"), "--start", "100s"], "100000000000 ns on"),
        (["info", str(not_mcap)], "is not an MCAP file"),
    ]
    for args, message in cases:
        result = CliRunner().invoke(cli, args)
        assert result.exit_code == 1 and message in result.output, (args, result.output)
        assert "Traceback" not in result.output and "starlog recover" not in result.output
        assert result.exception is None or isinstance(result.exception, SystemExit)
    assert not list(tmp_path.glob("**/*.partial")) and not (tmp_path / "missing").exists()


def test_cat_streams_json_lines(logs: dict[str, Path]) -> None:
    result = CliRunner().invoke(cli, ["cat", str(logs["sim"]), "--topic", "/camera/image", "--topic", "/sim/truth",
                                      "--start", "frame:2", "--limit", "3"])
    assert result.exit_code == 0, result.output
    lines = [json.loads(line) for line in result.output.splitlines()]
    assert [line["topic"] for line in lines] == ["/camera/image", "/sim/truth", "/camera/image"]
    assert set(lines[0]) == {"topic", "log_time", "publish_time", "sequence", "message"}
    assert lines[0]["sequence"] == 2 and lines[0]["log_time"] == 20_000_000
    image = lines[0]["message"]
    assert image["width"] == 256 and image["height"] == 256 and image["encoding"] == "mono16"
    assert image["bytes"] == 256 * 256 * 2 and image["sha256"].startswith("sha256:")
    assert lines[1]["message"]["frame"] == 2 and len(lines[1]["message"]["stars"]) == 4


def test_cat_ros2_images_and_decoded_messages(logs: dict[str, Path]) -> None:
    lines = list(cat_messages(logs["ros2"], limit=2))
    assert lines[0]["message"]["encoding"] == "mono16" and lines[0]["message"]["width"] == 256
    with LogReader(logs["sim"]) as log:
        native = next(iter(cat_messages(logs["sim"], topics=["/camera/image"], limit=1)))
        assert log.channel("/camera/image").message_count == 70
    assert lines[0]["message"]["sha256"] == native["message"]["sha256"]  # same pixels, whoever wrote them


def test_cat_into_head_and_jq_exits_cleanly(tmp_path: Path) -> None:
    from mcap.writer import Writer

    path = tmp_path / "many.mcap"
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start()
        channel = writer.register_channel("/counter", "json", writer.register_schema("", "", b""))
        for n in range(30000):
            writer.add_message(channel, log_time=n, publish_time=n, data=json.dumps({"n": n}).encode())
        writer.finish()
    starlog = [sys.executable, "-m", "starlog"]
    done = subprocess.run(f"{' '.join(starlog)} cat {path} | head -n 2", shell=True, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    assert [json.loads(line)["message"] for line in done.stdout.splitlines()] == [{"n": 0}, {"n": 1}]
    with subprocess.Popen([*starlog, "cat", str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE) as process:
        assert process.stdout is not None and process.stderr is not None
        process.stdout.readline()
        process.stdout.close()  # the reader goes away while cat still writes
        assert process.wait(timeout=120) == 0
        assert b"Traceback" not in process.stderr.read()
    jq = subprocess.run(f"{' '.join(starlog)} cat {path} --start 100 --end 103 | jq -c .message.n", shell=True,
                        capture_output=True, text=True, timeout=120)
    if jq.returncode == 127:
        pytest.skip("jq is not installed")
    assert jq.stdout.split() == ["100", "101", "102"]


def test_info_shows_list_and_map_parameters(logs: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "kept.mcap"
    filter_log(logs["cen"], out, exclude_topics=["/camera/*"])
    result = CliRunner().invoke(cli, ["info", str(out)])
    assert result.exit_code == 0, result.output
    assert 'methods=["' in result.output  # the centroid stage's list parameter
    assert 'exclude_topics=["/camera/*"]' in result.output and "filter (starlog" in result.output
    assert "-> no new channel" in result.output


def test_cat_prints_bytes_and_non_finite_numbers_as_strict_json(tmp_path: Path) -> None:
    """The library gives plain values (bytes, NaN as they are); the command prints them as strict JSON."""
    import base64
    import hashlib
    import math

    from foxglove_schemas_protobuf.RawAudio_pb2 import RawAudio
    from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
    from mcap_protobuf.writer import Writer

    short, long = bytes(range(256)) * 4, bytes(range(256)) * 4 + b"!"  # 1024 bytes, inline; 1025, summarised
    path = tmp_path / "proto.mcap"
    with open(path, "wb") as f, Writer(f) as writer:
        writer.write_message("/audio", RawAudio(data=short, format="pcm-s16"), log_time=0, publish_time=0)
        writer.write_message("/audio", RawAudio(data=long, format="pcm-s16"), log_time=1, publish_time=1)
        writer.write_message("/vector", Vector3(x=float("nan"), y=float("-inf"), z=2.5), log_time=2, publish_time=2)
    plain = [line["message"] for line in cat_messages(path)]
    assert plain[0]["data"] == short and plain[1]["data"] == long
    assert math.isnan(plain[2]["x"]) and plain[2]["y"] == -math.inf
    result = CliRunner().invoke(cli, ["cat", str(path)])
    assert result.exit_code == 0, result.output

    def refuse(name: str) -> None:
        raise AssertionError(f"{name} is not JSON")

    printed = [json.loads(line, parse_constant=refuse)["message"] for line in result.output.splitlines()]
    assert base64.b64decode(printed[0]["data"]) == short
    assert printed[1]["data"] == {"bytes": 1025, "sha256": "sha256:" + hashlib.sha256(long).hexdigest()}
    assert printed[2] == {"x": None, "y": None, "z": 2.5}


_PLAIN = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text() | st.binary(max_size=1100),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=5), inner, max_size=4),
    max_leaves=20)


@settings(max_examples=200, deadline=None)
@given(_PLAIN)
def test_a_cat_line_is_strict_json_of_the_plain_values(value: Any) -> None:
    """Every plain value prints as one line of strict JSON: finite numbers, text and structure as they are,
    bytes as base64 (up to 1 KiB) or their size and SHA-256, non-finite numbers as null."""
    import base64
    import hashlib
    import math

    from starlog.cli.describe import json_line

    line = json_line(value)
    assert "\n" not in line

    def refuse(name: str) -> None:
        raise AssertionError(f"{name} is not JSON")

    def same(printed: Any, original: Any) -> bool:
        if isinstance(original, bytes):
            if len(original) <= 1024:
                return base64.b64decode(printed) == original
            return printed == {"bytes": len(original), "sha256": "sha256:" + hashlib.sha256(original).hexdigest()}
        if isinstance(original, float) and not math.isfinite(original):
            return printed is None
        if isinstance(original, dict):
            return printed.keys() == original.keys() and all(same(printed[k], v) for k, v in original.items())
        if isinstance(original, list):
            return len(printed) == len(original) and all(same(p, o) for p, o in zip(printed, original))
        return printed == original and type(printed) is type(original)

    assert same(json.loads(line, parse_constant=refuse), value)


def test_the_facts_of_an_open_log_are_those_of_its_path(logs: dict[str, Path]) -> None:
    from starlog.facts import log_facts

    with LogReader(logs["cen"]) as log:
        facts = log_facts(log)
        assert log.message_count() == facts["message_count"]  # still open
    assert facts == log_facts(logs["cen"]) and facts["path"] == str(logs["cen"])
    assert [c["topic"] for c in facts["channels"]][:3] == ["/camera/image", "/camera/frame", "/sim/truth"]
