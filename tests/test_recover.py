"""`starlog recover`: truncated, unfinished and damaged logs give back every complete message."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from starlog.cli import cli
from starlog.errors import CorruptLogError
from starlog.io import LogReader, LogWriter, file_digest
from starlog.codecs import encode_json, json_message_type
from starlog import topics
from starlog.io.recover import recover_log
from starlog.stages import simulate_log
from tests.helpers import killed_writer_bytes, small_config


@pytest.fixture(scope="module")
def chunky_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A log with many small chunks, so truncation lands in many places."""
    path = tmp_path_factory.mktemp("rec") / "chunky.mcap"
    simulate_log(small_config(n_frames=40), path, compression="lz4")
    return path


def _rewrite_with_small_chunks(src: Path, dst: Path) -> None:
    with LogReader(src) as log, LogWriter(dst, chunk_size=8192, compression="lz4") as w:
        ids = {}
        for schema, channel, message in log.raw_messages(log.topics):
            if channel.topic not in ids:
                from starlog.codecs.schemas import MessageType

                ids[channel.topic] = w.add_channel(channel.topic, MessageType(
                    schema.name, schema.encoding, schema.data, channel.message_encoding))
            w.write(ids[channel.topic], log_time=message.log_time, data=message.data)


@pytest.mark.parametrize("fraction", [0.05, 0.2, 0.45, 0.7, 0.9, 0.999])
def test_truncated_log_recovers_complete_messages(chunky_log: Path, tmp_path: Path, fraction: float) -> None:
    small = tmp_path / "small_chunks.mcap"
    _rewrite_with_small_chunks(chunky_log, small)
    data = small.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * fraction)])
    before = file_digest(cut)
    report = recover_log(cut, tmp_path / "rec.mcap")
    assert file_digest(cut) == before
    assert not report.had_footer and report.tail_bytes_lost > 0
    with LogReader(tmp_path / "rec.mcap") as log, LogReader(small) as full:
        counts = {c.topic: c.message_count for c in log.channels()}
        assert counts == report.kept_by_topic
        original = {m.log_time: m.payload for m in full.messages(topics.TRUTH)}
        for m in log.messages(topics.TRUTH) if topics.TRUTH in log.topics else []:
            assert m.payload == original[m.log_time]  # kept messages are exact
    assert sum(counts.values()) >= 0.8 * fraction * 120 - 20  # nearly everything before the cut


def test_flipped_byte_drops_only_that_chunk(chunky_log: Path, tmp_path: Path) -> None:
    small = tmp_path / "small_chunks.mcap"
    _rewrite_with_small_chunks(chunky_log, small)
    data = bytearray(small.read_bytes())
    with LogReader(small) as log:
        second = log.files[-1].summary.chunk_indexes[1]
    data[second.chunk_start_offset + 80] ^= 0xFF
    broken = tmp_path / "flip.mcap"
    broken.write_bytes(bytes(data))
    with LogReader(broken) as log, pytest.raises(CorruptLogError, match="starlog recover"):
        for _ in log.messages(log.topics):
            pass
    report = recover_log(broken, tmp_path / "rec.mcap")
    (lost,) = report.lost_chunks
    assert lost.offset == second.chunk_start_offset
    assert (lost.message_start_time, lost.message_end_time) == (second.message_start_time, second.message_end_time)
    assert sum(lost.messages_by_topic.values()) + sum(report.kept_by_topic.values()) == 120


def test_unfinished_log_without_summary(tmp_path: Path) -> None:
    path = tmp_path / "unfinished.mcap"
    writer = LogWriter(tmp_path / "never.mcap", chunk_size=1024)
    ch = writer.add_channel("/a", json_message_type("starlog.FrameInfo"))
    for n in range(50):
        writer.write(ch, log_time=n, data=encode_json({"frame": n, "width": 1, "height": 1, "encoding": "mono8",
                                                         "bit_depth": 8, "source": ""}))
    path.write_bytes(killed_writer_bytes(writer))  # flushed, never finished
    report = recover_log(path, tmp_path / "rec.mcap")
    assert report.kept_by_topic == {"/a": 50}


def test_recover_cli_reports(chunky_log: Path, tmp_path: Path) -> None:
    data = chunky_log.read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    result = CliRunner().invoke(cli, ["recover", str(tmp_path / "cut.mcap"), "-o", str(tmp_path / "r.mcap")])
    assert result.exit_code == 0, result.output
    assert "messages kept" in result.output and "unreadable" in result.output


def test_not_an_mcap_file(tmp_path: Path) -> None:
    (tmp_path / "x.mcap").write_bytes(b"hello world, not mcap")
    with pytest.raises(CorruptLogError, match="magic"):
        recover_log(tmp_path / "x.mcap", tmp_path / "r.mcap")
