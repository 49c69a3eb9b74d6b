"""A stage's fixed costs and records: its input's digest on a thread, a write that fails, provenance."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import pytest

from starlog.io import LogReader, LogWriter, Provenance, file_digest
from starlog.codecs import json_message_type
from starlog import topics
from starlog.io.provenance import BackgroundDigest
from starlog.stages.compensate import compensate_log
from starlog.stages.simulate import simulate_log
from starlog.stages.track import track_log
from tests.helpers import small_config


def _layer(base: Path, out: Path) -> None:
    with LogReader(base) as log:
        layer = log.layer_base()
    with LogWriter(out, layer=layer) as writer:
        channel = writer.add_channel("/extra", json_message_type("starlog.FrameInfo"))
        writer.write(channel, log_time=10**12, data=b'{"frame":0,"width":4,"height":4,"encoding":"mono8",'
                                                    b'"bit_depth":8,"source":""}')


def test_background_digest_is_the_file_sha256(sim_log: Path) -> None:
    expected = "sha256:" + hashlib.sha256(sim_log.read_bytes()).hexdigest()
    assert BackgroundDigest(sim_log).result() == expected == file_digest(sim_log)


def test_a_digest_hands_over_the_error_of_its_thread(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        BackgroundDigest(tmp_path / "missing.mcap").result()


def test_a_failed_write_back_fails_the_close_and_leaves_no_output(
        sim_log: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def fail(fd: int) -> None:
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "fsync", fail)
    with pytest.raises(OSError, match="cannot write .*out.mcap: an input/output error"):  # a FileAccessError
        _layer(sim_log, tmp_path / "out.mcap")
    assert list(tmp_path.iterdir()) == []


def test_stage_provenance_names_the_input_digest(sim_log: Path, tmp_path: Path) -> None:
    from starlog.stages.centroid import centroid_log

    out = tmp_path / "cen.mcap"
    centroid_log(sim_log, out, methods=["MOMENT"])
    with LogReader(out) as log:
        record: Provenance = log.provenance()[-1]
    assert record.input_digest == file_digest(sim_log)


def test_the_paper_protocol_never_reads_the_truth(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from starlog.stages.centroid import centroid_log

    sim, cen, trk = tmp_path / "sim.mcap", tmp_path / "cen.mcap", tmp_path / "trk.mcap"
    simulate_log(small_config(width=96, height=80, n_stars=4, n_frames=160, margin=12.0), sim)
    centroid_log(sim, cen, methods=["MOMENT"])
    track_log(cen, trk, method="MOMENT", models=["STATIC"])
    paper = compensate_log(trk, tmp_path / "paper.mcap", rates=[50], protocols="paper")

    def unread(read: Any) -> Any:
        def guarded(self: LogReader, topic: str | Iterable[str], **kwargs: Any) -> Any:
            wanted = [topic] if isinstance(topic, str) else list(topic)
            if topics.TRUTH in wanted:
                raise AssertionError("the truth was read")
            return read(self, wanted, **kwargs)
        return guarded

    for method in ("messages", "raw_messages"):  # the reader's ways to a channel's messages
        monkeypatch.setattr(LogReader, method, unread(getattr(LogReader, method)))
    assert compensate_log(trk, tmp_path / "again.mcap", rates=[50], protocols="paper").records == paper.records
    with pytest.raises(AssertionError, match="truth was read"):
        compensate_log(trk, tmp_path / "truth.mcap", rates=[50], protocols="truth")
