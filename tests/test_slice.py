"""--start / --end on the replay stages and ``run``: only the range is read and written, and it is recorded;
``filter`` (and the copying behind it) cuts a range of every channel into a new log."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from starlog.cli import cli
from starlog.errors import InvalidParameterError
from starlog.io import LogReader, file_digest
from starlog.io.copying import copy_log
from starlog.io.timerange import TimeRange
from starlog.pipeline import PipelineConfig, run_pipeline
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log
from starlog.stages.track import track_log
from tests.helpers import small_config

FPS = 100.0


@pytest.fixture(scope="module")
def long_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """96 frames of 256x256 at 100 Hz: several chunk groups of ~31 frames (4 MB chunks)."""
    path = tmp_path_factory.mktemp("slice") / "long.mcap"
    simulate_log(small_config(width=256, height=256, n_frames=96, fps=FPS, n_stars=4, margin=20.0), path)
    return path


def _frame_times(path: Path, topic: str = "/camera/image") -> list[int]:
    with LogReader(path) as log:
        return [m.log_time for _, _, m in log.raw_messages([topic])]


def _counts(path: Path) -> dict[str, int]:
    with LogReader(path) as log:
        return {c.topic: c.message_count for c in log.channels()}


def test_slice_copies_inner_chunks_and_reencodes_the_boundaries(long_log: Path, tmp_path: Path) -> None:
    times = _frame_times(long_log)
    with LogReader(long_log) as log:
        groups = sorted({(ci.message_start_time, ci.message_end_time) for ci in log.files[-1].summary.chunk_indexes})
    assert len(groups) >= 3, "the fixture must span several chunk groups"
    resolved = TimeRange.parse("frame:5", "frame:90").resolve(lambda n: times[n] if n < len(times) else None)
    report = copy_log(long_log, tmp_path / "s.mcap", time_range=resolved)
    assert report.chunks_copied >= 3 and report.chunks_reencoded >= 2
    assert set(_counts(tmp_path / "s.mcap").values()) == {85}
    assert _frame_times(tmp_path / "s.mcap") == times[5:90]
    source = long_log.read_bytes()
    out = (tmp_path / "s.mcap").read_bytes()
    with LogReader(tmp_path / "s.mcap") as log:
        inner = [ci for ci in log.files[-1].summary.chunk_indexes
                 if resolved.covers(ci.message_start_time, ci.message_end_time)
                 and times[5] < ci.message_start_time and ci.message_end_time < times[89]]
        assert inner
        for ci in inner:  # a chunk inside the range is the input's chunk, byte for byte
            assert out[ci.chunk_start_offset: ci.chunk_start_offset + ci.chunk_length] in source


def _layer_counts(path: Path) -> dict[str, int]:
    """Messages per channel of the layer ``path`` itself (its stage's channels)."""
    with LogReader(path, chain=False) as log:
        return {c.topic: c.message_count for c in log.channels()}


def test_centroid_with_frame_range_writes_only_that_range(long_log: Path, tmp_path: Path) -> None:
    out = tmp_path / "cen.mcap"
    summary = centroid_log(long_log, out, methods="MOMENT", start="frame:10", end="frame:60")
    assert summary.frames == 50
    counts = _layer_counts(out)
    assert set(counts.values()) == {50}, counts
    times = _frame_times(long_log)
    assert _frame_times(out) == times  # the base is whole
    assert _frame_times(out, "/stars/centroids/MOMENT") == times[10:60]
    with LogReader(out) as log:
        record = log.provenance()[-1]
    assert record.stage == "centroid"
    assert record.parameters["range"] == {"start": "frame:10", "end": "frame:60", "start_ns": times[10],
                                          "end_ns": times[60], "frame_topic": "/camera/image"}
    assert record.input_digest == file_digest(long_log)
    info = CliRunner().invoke(cli, ["info", str(out)])
    assert f"range [frame:10, frame:60): log_time {times[10]} to {times[60]} ns (end exclusive)" in info.output
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "nothing hidden left behind"


def test_seconds_are_log_time_and_the_end_is_exclusive(long_log: Path, tmp_path: Path) -> None:
    times = _frame_times(long_log)
    out = tmp_path / "cen.mcap"
    result = CliRunner().invoke(cli, ["centroid", str(long_log), "-o", str(out), "--method", "NONE", "-q",
                                      "--workers", "1", "--start", "0.25s", "--end", f"{times[50]}"])
    assert result.exit_code == 0, result.output
    assert _frame_times(out, "/stars/centroids/NONE") == [t for t in times if 250_000_000 <= t < times[50]]
    assert len(_frame_times(out, "/stars/centroids/NONE")) == 25


@pytest.mark.parametrize(("start", "end", "message"), [
    ("frame:15", "frame:5", "reversed"),
    ("1s", "1s", "empty"),
    ("50s", None, "outside"),
    ("frame:20", None, "outside the log"),
    (None, "frame:200", "outside the log"),
    ("soon", None, "expected log time"),
])
def test_bad_ranges_are_clear_errors(sim_log: Path, tmp_path: Path, start: str | None, end: str | None,
                                     message: str) -> None:
    with pytest.raises(InvalidParameterError, match=message):
        centroid_log(sim_log, tmp_path / "x.mcap", methods="NONE", start=start, end=end)
    assert not (tmp_path / "x.mcap").exists()
    args = ["centroid", str(sim_log), "-o", str(tmp_path / "x.mcap"), "-q"]
    args += ["--start", start] if start else []
    args += ["--end", end] if end else []
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 1 and message in result.output
    assert list(tmp_path.iterdir()) == []


def test_track_counts_frames_of_its_centroid_channel(sim_log: Path, tmp_path: Path) -> None:
    cen = tmp_path / "cen.mcap"
    centroid_log(sim_log, cen, methods="MOMENT")
    out = tmp_path / "trk.mcap"
    summary = track_log(cen, out, method="MOMENT", models="STATIC", start="frame:4", end="frame:16")
    assert summary.frames == 12
    assert set(_layer_counts(out).values()) == {12}
    with LogReader(out) as log:
        record = log.provenance()[-1]
    assert record.parameters["range"]["frame_topic"] == "/stars/centroids/MOMENT"
    assert record.input_digest == file_digest(cen)


def test_run_windows_its_first_stage_and_equals_the_stages_one_by_one(sim_log: Path, tmp_path: Path) -> None:
    config = PipelineConfig.from_dict({"centroid": {"methods": ["MOMENT"]},
                                       "track": {"methods": ["MOMENT"], "models": ["STATIC"]}})
    (tmp_path / "run").mkdir()
    run_pipeline(sim_log, tmp_path / "run" / "out.mcap", config, start="frame:3", end="0.15s")
    centroid_log(sim_log, tmp_path / "out.1-centroid.mcap", methods=["MOMENT"], start="frame:3", end="0.15s")
    track_log(tmp_path / "out.1-centroid.mcap", tmp_path / "out.mcap", method="MOMENT", models=["STATIC"])
    with LogReader(tmp_path / "run" / "out.mcap") as log:
        ranges = [p.parameters.get("range") for p in log.provenance()]
        assert log.channel("/track/MOMENT/STATIC").message_count == 12  # frames 3..14 at 100 Hz
        assert log.channel("/camera/image").message_count == 20
    assert ranges[0] is None and ranges[1]["start"] == "frame:3" and ranges[2] is None
    assert _messages(tmp_path / "run" / "out.mcap") == _messages(tmp_path / "out.mcap")
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["out.1-centroid.mcap", "out.mcap"]


def _messages(path: Path) -> list[tuple[str, int, bytes]]:
    with LogReader(path) as log:
        return [(c.topic, m.log_time, m.data) for _, c, m in log.raw_messages(log.topics)]


def test_run_refuses_a_compensate_rate_too_low_for_the_range_before_any_stage(long_log: Path,
                                                                             tmp_path: Path) -> None:
    stages = {"centroid": {"methods": ["MOMENT"]}, "track": {"methods": ["MOMENT"], "models": ["STATIC"]}}
    config = PipelineConfig.from_dict({**stages, "compensate": {"rates": [50, 10]}})
    with pytest.raises(InvalidParameterError, match=r"\(96 frames, 0.95 s\) is too short .*\n  10 Hz paper: 9 samples, "
                                                     r"needs 16 \(a log of at least 1.67 s: 167 frames at 100 Hz\)"):
        run_pipeline(long_log, tmp_path / "run.mcap", config)  # 96 frames at 100 Hz: 0.95 s
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no output, no sidecar left behind
    config = PipelineConfig.from_dict({**stages, "compensate": {"rates": [50]}})
    with pytest.raises(InvalidParameterError, match=r"\(26 frames, 0.25 s\) is too short .*\n  50 Hz paper: 12 samples"):
        run_pipeline(long_log, tmp_path / "run.mcap", config, start="frame:70")
