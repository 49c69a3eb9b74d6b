"""A stage's fixed costs: the kernel copy of its input, the digest on a thread, the early write-back."""

from __future__ import annotations

import hashlib
import os
import threading
from pathlib import Path

import pytest

from starlog.errors import InvalidParameterError, OutputExistsError, TruncatedLogError
from starlog.io import LogReader, LogWriter, Provenance, encode_json, file_digest, json_message_type
from starlog.io.bytecopy import copy_range, copy_range_at
from starlog.io.layout import locate_data_end
from starlog.io.provenance import BackgroundDigest
from starlog.io.stack import StackedLog
from starlog.stages import compensate as compensate_stage
from starlog.stages.compensate import compensate_log
from starlog.stages.simulate import simulate_log
from starlog.stages.track import track_log
from tests.conftest import small_config


def _extend(base: Path, out: Path) -> None:
    with LogWriter(out, base=base) as writer:
        channel = writer.add_channel("/extra", json_message_type("starlog.FrameInfo"))
        writer.write(channel, log_time=10**12, data=b'{"frame":0,"width":4,"height":4,"encoding":"mono8",'
                                                    b'"bit_depth":8,"source":""}')


@pytest.fixture()
def refuse_kernel_copy(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object, **kwargs: object) -> int:
        raise OSError(18, "Invalid cross-device link")

    monkeypatch.setattr(os, "copy_file_range", refuse)


def test_copy_range_copies_a_range_after_what_is_there(tmp_path: Path) -> None:
    src = tmp_path / "src.bin"
    src.write_bytes(bytes(range(256)) * 1000)
    with open(src, "rb") as s, open(tmp_path / "dst.bin", "w+b") as d:
        d.write(b"head")
        assert copy_range(s, d, 1000, 50_000) == 50_000
        d.write(b"tail")  # the buffered file continues after the copied bytes
    assert (tmp_path / "dst.bin").read_bytes() == b"head" + src.read_bytes()[1000:51_000] + b"tail"


@pytest.mark.usefixtures("refuse_kernel_copy")
def test_copy_range_falls_back_to_plain_reads_and_stops_at_the_source_end(tmp_path: Path) -> None:
    src = tmp_path / "src.bin"
    src.write_bytes(os.urandom(9 * 1024 * 1024))
    with open(src, "rb") as s, open(tmp_path / "dst.bin", "w+b") as d:
        d.write(b"x")
        assert copy_range(s, d, 5, 10 * 1024 * 1024) == 9 * 1024 * 1024 - 5
        d.write(b"y")
    assert (tmp_path / "dst.bin").read_bytes() == b"x" + src.read_bytes()[5:] + b"y"


def test_an_extended_log_is_the_same_with_or_without_the_kernel_copy(
        sim_log: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _extend(sim_log, tmp_path / "kernel.mcap")
    monkeypatch.setattr(os, "copy_file_range", lambda *a, **k: (_ for _ in ()).throw(OSError(38, "ENOSYS")))
    _extend(sim_log, tmp_path / "plain.mcap")
    assert (tmp_path / "kernel.mcap").read_bytes() == (tmp_path / "plain.mcap").read_bytes()
    with open(sim_log, "rb") as f:
        data_end = locate_data_end(sim_log, f)
    assert (tmp_path / "kernel.mcap").read_bytes()[:data_end] == sim_log.read_bytes()[:data_end]


def test_a_base_cut_short_while_copied_is_refused(sim_log: Path, tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("starlog.io.bytecopy.copy_range_at", lambda *args, **kwargs: args[3] - 1)
    with pytest.raises(TruncatedLogError), LogWriter(tmp_path / "out.mcap", base=sim_log):
        pass  # the copy runs on a thread: its shortfall is raised when the log is closed
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("kernel", [True, False])
def test_a_positional_copy_leaves_both_positions_and_the_rest_of_the_file(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, kernel: bool) -> None:
    if not kernel:
        monkeypatch.setattr(os, "copy_file_range", lambda *a, **k: (_ for _ in ()).throw(OSError(18, "EXDEV")))
    src = tmp_path / "src.bin"
    src.write_bytes(os.urandom(5 * 1024 * 1024 + 17))
    with open(src, "rb") as s, open(tmp_path / "dst.bin", "w+b") as d:
        s.seek(3)
        d.seek(2_000_000)
        d.write(b"after")  # written at the end first, as a stage writes its records during the copy
        d.flush()
        assert copy_range_at(s.fileno(), d.fileno(), 100, 2_000_000, 0) == 2_000_000
        assert s.tell() == 3 and d.tell() == 2_000_005
    assert (tmp_path / "dst.bin").read_bytes() == src.read_bytes()[100:2_000_100] + b"after"


def test_a_stopped_copy_ends_at_once(tmp_path: Path) -> None:
    src = tmp_path / "src.bin"
    src.write_bytes(b"x" * 1000)
    stop = threading.Event()
    stop.set()
    with open(src, "rb") as s, open(tmp_path / "dst.bin", "w+b") as d:
        assert copy_range_at(s.fileno(), d.fileno(), 0, 1000, 0, stop=stop) == 0


def test_an_aborted_extension_leaves_nothing(sim_log: Path, tmp_path: Path) -> None:
    writer = LogWriter(tmp_path / "out.mcap", base=sim_log)
    writer.abort()  # stops the copy thread and removes the partial file
    assert list(tmp_path.iterdir()) == []


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

    monkeypatch.setattr(os, "fdatasync", fail)
    with pytest.raises(OSError, match="Input/output"):
        _extend(sim_log, tmp_path / "out.mcap")
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

    def unread(*args: object, **kwargs: object) -> None:
        raise AssertionError("the truth was read")

    monkeypatch.setattr(compensate_stage, "_star_truth", unread)
    monkeypatch.setattr(compensate_stage, "_nearest_star", unread)
    assert compensate_log(trk, tmp_path / "again.mcap", rates=[50], protocols="paper").records == paper.records
    with pytest.raises(AssertionError, match="truth was read"):
        compensate_log(trk, tmp_path / "truth.mcap", rates=[50], protocols="truth")


def _held_copy(monkeypatch: pytest.MonkeyPatch) -> threading.Event:
    """Make the background copy thread wait for the returned event before it copies."""
    from starlog.io import bytecopy

    go, real = threading.Event(), bytecopy.copy_range_at

    def held(*args: object, **kwargs: object) -> int:
        go.wait(10)
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(bytecopy, "copy_range_at", held)
    return go


def test_the_copy_writes_through_descriptors_of_its_own(sim_log: Path, tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    go = _held_copy(monkeypatch)
    writer = LogWriter(tmp_path / "out.mcap", base=sim_log)
    writer._file.close()  # as if the writer were dropped and collected: its descriptor number is free again
    victim = tmp_path / "victim.txt"
    with open(victim, "w+b") as f:
        f.write(b"precious")
        f.flush()
        go.set()
        writer._writeback.wait()  # type: ignore[union-attr]  # the whole copy, not stopped
    assert victim.read_bytes() == b"precious"
    (writer._tmp_path).unlink()


def test_an_extended_log_repeats_its_bases_chunk_indexes_then_adds_its_own(sim_log: Path, tmp_path: Path) -> None:
    """The base's chunk indexes are kept as the bytes of their records (compact), and come back as
    the same indexes in the output's summary, before the new chunks'."""
    out = tmp_path / "out.mcap"
    with LogWriter(out, base=sim_log, chunk_size=1024) as writer:
        channel = writer.add_channel("/extra", json_message_type("starlog.Centroids"))
        for t in range(3):
            writer.write(channel, log_time=t, data=b'{"frame":0,"method":"GAUSSFIT","stars":[]}')
    with open(sim_log, "rb") as f:
        data_end = locate_data_end(sim_log, f)
    assert all(ci.chunk_start_offset >= data_end for ci in writer._chunk_indexes)  # only its own chunks held
    with LogReader(sim_log) as base, LogReader(out) as log:
        inherited = base.summary.chunk_indexes
        assert log.summary.chunk_indexes[:len(inherited)] == list(inherited)
        assert len(log.summary.chunk_indexes) > len(inherited)
        assert [m.log_time for m in log.messages("/extra")] == [0, 1, 2]
        assert sum(1 for _ in log.frames()) == sum(1 for _ in base.frames())


def _stack_with_a_sidecar(sim_log: Path, folder: Path) -> tuple[StackedLog, StackedLog]:
    """The stack of ``sim_log`` alone, and with one sidecar that adds a channel."""
    stack = StackedLog.of(sim_log)
    with LogWriter(folder / "side", base=stack) as w:
        ch = w.add_channel("/demo", json_message_type("starlog.FrameInfo"))
        w.write(ch, log_time=5, data=encode_json({"frame": 5, "width": 32, "height": 32, "encoding": "mono16",
                                                  "bit_depth": 16, "source": ""}))
    return stack, stack.extend(folder / "side")


def test_an_output_begun_before_the_sidecars_is_the_stack_written_at_the_end(sim_log: Path, tmp_path: Path) -> None:
    """``run`` begins its output (the base's data copied on a thread) before the stages write their sidecars."""
    stack = StackedLog.of(sim_log)
    pending = stack.begin_output(tmp_path / "begun.mcap")
    _, stacked = _stack_with_a_sidecar(sim_log, tmp_path)
    assert pending.finish(stacked) == tmp_path / "begun.mcap"
    with stacked.open() as f:
        assert (tmp_path / "begun.mcap").read_bytes() == f.read()
    assert file_digest(tmp_path / "begun.mcap") == file_digest(stacked)
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.endswith(".partial")) == []
    pending.discard()  # nothing to do once finished
    assert (tmp_path / "begun.mcap").exists()


def test_a_begun_output_is_the_same_when_its_records_are_written_before_the_base_copy(
        sim_log: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The copy thread held until ``finish`` has written the sidecar's records and the summary after it."""
    go = _held_copy(monkeypatch)
    pending = StackedLog.of(sim_log).begin_output(tmp_path / "begun.mcap")
    _, stacked = _stack_with_a_sidecar(sim_log, tmp_path)
    release = threading.Timer(0.3, go.set)
    release.start()
    pending.finish(stacked)
    release.join()
    with stacked.open() as f:
        assert (tmp_path / "begun.mcap").read_bytes() == f.read()


def test_a_begun_output_refuses_another_base_and_a_second_finish(sim_log: Path, tmp_path: Path) -> None:
    other = tmp_path / "other.mcap"
    simulate_log(small_config(seed=7), other)
    pending = StackedLog.of(sim_log).begin_output(tmp_path / "out.mcap")
    with pytest.raises(InvalidParameterError, match="another base"):
        pending.finish(StackedLog.of(other))
    assert not (tmp_path / "out.mcap").exists()
    pending.finish(StackedLog.of(sim_log))  # the stack it was begun for still finishes it
    assert (tmp_path / "out.mcap").read_bytes() == sim_log.read_bytes()
    with pytest.raises(InvalidParameterError, match="already finished or discarded"):
        pending.finish(StackedLog.of(sim_log))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.mcap", "out.mcap"]


def test_a_discarded_output_stops_its_copy_and_leaves_nothing(sim_log: Path, tmp_path: Path) -> None:
    pending = StackedLog.of(sim_log).begin_output(tmp_path / "out.mcap")
    pending.discard()
    pending.discard()
    assert list(tmp_path.iterdir()) == []


def test_a_begun_output_whose_write_back_fails_is_not_renamed(sim_log: Path, tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    def fail(fd: int) -> None:
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "fdatasync", fail)
    pending = StackedLog.of(sim_log).begin_output(tmp_path / "out.mcap")
    with pytest.raises(OSError, match="Input/output"):
        pending.finish(StackedLog.of(sim_log))
    assert list(tmp_path.iterdir()) == []


def test_an_existing_output_is_refused_before_any_copy(sim_log: Path, tmp_path: Path) -> None:
    (tmp_path / "out.mcap").write_bytes(b"keep")
    with pytest.raises(OutputExistsError):
        StackedLog.of(sim_log).begin_output(tmp_path / "out.mcap")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mcap"]
    assert (tmp_path / "out.mcap").read_bytes() == b"keep"
