"""The pieces of ``starlog live`` that read a source: following a growing MCAP file, cutting blocks as chunks
arrive, the complete copy of the part read, writing a log at its camera's rate, the latency histogram.

Known answers: the follower of a file grown in arbitrary pieces gives what a reader of the finished file gives;
the cutter gives the centroid stage's blocks; the snapshot reads as the chunks it copied.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from starlog.io import LogReader, LogWriter
from starlog.codecs import json_message_type
from starlog.io.mcap_file import McapFile
from starlog.io.verify import verify_log
from starlog.live.follow import DamagedChunk, FollowedChunk, FollowedMessage, McapFollower
from starlog.live.pace import write_at_camera_rate
from starlog.live.snapshot import snapshot_log
from starlog.live.sources import BlockCutter
from starlog.live.status import LatencyHistogram
from starlog.stages import simulate_log
from starlog.replay.blocks import channel_blocks
from tests.helpers import small_config


def _log(path: Path, frames: int = 12, *, per_frame: bool = True) -> Path:
    """A log of two JSON channels, one chunk group per frame (``per_frame``) or a few big chunks."""
    with LogWriter(path, force=True, chunk_size=1 << 20) as out:
        a = out.add_channel("/a", json_message_type("starlog.FrameInfo"))
        b = out.add_channel("/b", json_message_type("starlog.FrameInfo"))
        out.add_metadata("note", {"k": "v"})
        for n in range(frames):
            info = b'{"frame":%d,"width":4,"height":4,"encoding":"mono8","bit_depth":8,"source":""}' % n
            out.write(a, log_time=1000 + n, data=info)
            out.write(b, log_time=1000 + n, data=info)
            if per_frame:
                out.flush()
    return path


def _messages(path: Path) -> list[tuple[str, int, bytes]]:
    with LogReader(path) as log:
        return sorted((c.topic, m.log_time, bytes(m.data)) for _, c, m in log.raw_messages(log.topics))


def _followed(events: list[object]) -> list[tuple[str, int, bytes]]:
    out = []
    for event in events:
        messages = event.messages if isinstance(event, FollowedChunk) else [event] if isinstance(
            event, FollowedMessage) else []
        out += [(m.channel.topic, m.message.log_time, bytes(m.message.data)) for m in messages]
    return out


@pytest.fixture(scope="module")
def whole(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _log(tmp_path_factory.mktemp("follow") / "whole.mcap")


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cuts=st.lists(st.floats(0, 1), max_size=30))
def test_a_file_grown_in_any_pieces_is_followed_to_what_its_reader_reads(whole: Path, tmp_path: Path,
                                                                        cuts: list[float]) -> None:
    data = whole.read_bytes()
    growing = tmp_path / f"growing-{len(cuts)}.mcap"
    growing.write_bytes(b"")
    events: list[object] = []
    with McapFollower(growing) as follower, open(growing, "ab") as writer:
        for end in [*sorted(int(c * len(data)) for c in cuts), len(data)]:
            writer.write(data[writer.tell():end])
            writer.flush()
            events += follower.poll(max_events=1000)
            assert follower.position <= end  # nothing handed over before its last byte is there
        events += follower.poll(max_events=1000)
        assert follower.finished
    assert sorted(_followed(events)) == _messages(whole)


def test_a_chunk_cut_off_is_held_back_until_its_last_byte(whole: Path, tmp_path: Path) -> None:
    data = whole.read_bytes()
    with McapFile(whole) as file:
        ci = sorted(file.summary.chunk_indexes, key=lambda c: c.chunk_start_offset)[3]
    growing = tmp_path / "cut.mcap"
    growing.write_bytes(data[: ci.chunk_start_offset + ci.chunk_length - 1])
    with McapFollower(growing) as follower:
        before = _followed(follower.poll(max_events=1000))
        assert follower.position == ci.chunk_start_offset and follower.pending() == ci.chunk_length - 1
        with open(growing, "ab") as f:
            f.write(data[ci.chunk_start_offset + ci.chunk_length - 1:])
        after = _followed(follower.poll(max_events=1000))
    assert len(before) == 3 and len(after) == 1 + (len(_messages(whole)) - 4)


def test_a_damaged_chunk_is_reported_and_the_chunks_after_it_are_read(whole: Path, tmp_path: Path) -> None:
    data = bytearray(whole.read_bytes())
    with McapFile(whole) as file:
        ci = sorted(file.summary.chunk_indexes, key=lambda c: c.chunk_start_offset)[5]
    data[ci.chunk_start_offset + ci.chunk_length - 3] ^= 0xFF  # inside its compressed data
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    with McapFollower(damaged) as follower:
        events = follower.poll(max_events=10_000)
    bad = [e for e in events if isinstance(e, DamagedChunk)]
    assert [(b.offset, b.start) for b in bad] == [(ci.chunk_start_offset, ci.message_start_time)]
    assert len(_followed(events)) == len(_messages(whole)) - 1 and follower.finished


class _Chunks:
    """What :func:`channel_blocks` reads of a log: each chunk's time range and count of the channel's messages."""

    def __init__(self, counts: list[int]) -> None:
        self.counts = counts

    def chunk_message_counts(self, topic: str) -> list[tuple[int, int, int]]:
        out, t = [], 0
        for n in self.counts:
            out.append((t, t + n - 1, n))
            t += n
        return out


@given(counts=st.lists(st.integers(1, 40), min_size=1, max_size=60), per_block=st.integers(1, 50))
def test_the_cutter_cuts_the_blocks_the_centroid_stage_cuts(counts: list[int], per_block: int) -> None:
    blocks = channel_blocks(_Chunks(counts), "/x", per_block, at_most=True)  # type: ignore[arg-type]
    assert blocks is not None
    cutter = BlockCutter(per_block)
    starts, first = [], 0
    for n in counts:
        if cutter.chunk(n, first, first + n - 1):
            starts.append(first)
        first += n
    assert starts == [first_message for _, _, first_message in blocks]


def test_the_snapshot_of_a_prefix_holds_its_chunks_as_they_were(tmp_path: Path) -> None:
    log = tmp_path / "sim.mcap"
    simulate_log(small_config(n_frames=30), log, chunk_per_frame=True)
    with McapFile(log) as file:
        chunks = sorted(file.summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    end = chunks[12].chunk_start_offset  # after the 4 first frames' chunks (image, frame info, truth each)
    with open(log, "rb") as source:
        snapshot = snapshot_log(source, end, tmp_path / "snap.mcap")
    assert verify_log(snapshot).ok
    with LogReader(snapshot) as copy, LogReader(log) as original:
        assert copy.chunk_message_counts("/camera/image") == original.chunk_message_counts("/camera/image")[:4]
        kept = [(m.log_time, bytes(m.data)) for _, _, m in copy.raw_messages(["/camera/image"])]
        assert kept == [(m.log_time, bytes(m.data)) for _, _, m in original.raw_messages(["/camera/image"])][:4]
        assert [p.stage for p in copy.provenance()] == []  # written at the end of the original, after the cut


def test_a_log_is_written_again_no_faster_than_its_camera(tmp_path: Path) -> None:
    log = tmp_path / "sim.mcap"
    config = small_config(n_frames=20, fps=200.0)
    simulate_log(config, log, chunk_per_frame=True)
    flushed: list[tuple[int, int]] = []
    begin = time.monotonic_ns()
    assert write_at_camera_rate(log, tmp_path / "paced.mcap", on_frame=lambda t, at: flushed.append((t, at))) == 20
    first = flushed[0][0]
    assert all(at - begin >= t - first for t, at in flushed)  # frame n not before n / fps after the first
    assert _messages(tmp_path / "paced.mcap") == _messages(log)
    with LogReader(tmp_path / "paced.mcap") as paced:
        assert [p.stage for p in paced.provenance()] == ["simulate"]


def test_latency_quantiles_are_those_of_the_latencies_within_one_percent() -> None:
    values = np.random.default_rng(5).lognormal(1.0, 1.0, 20_000)
    histogram = LatencyHistogram()
    for v in values:
        histogram.add(float(v))
    for q in (0.5, 0.9, 0.99):
        assert histogram.quantile(q) == pytest.approx(np.quantile(values, q), rel=0.012)
    assert histogram.largest == values.max() and histogram.count == values.size
