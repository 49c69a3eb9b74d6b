"""MCAP files whose summary does not repeat their schemas and channels, and every other layout the ``mcap``
writer's options make: every command reads every message, and ``verify`` says what the readers do.

The files are written by the ``mcap`` library's own writer over its options (chunked or not, each
compression, each index type, summary offsets, statistics, repeated schemas and channels,
attachments and metadata), with JSON, protobuf and schemaless messages and a ``foxglove.RawImage``
channel; what was written is the known answer. The ``mcap`` library's reader is the oracle for
``verify``'s note on readers that need the copies in the summary.
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.records import Channel
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, IndexType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from starlog.cli import cli
from starlog.errors import CorruptLogError
from starlog.parquet.tables import export_log
from starlog.io import LogReader, LogWriter
from starlog.codecs import encode_json, json_message_type
from starlog.io.summary_section import read_file_summary
from starlog.io.copying import flatten_log
from starlog.codecs.images import choose_image_topic
from starlog.io.verify import verify_log
from starlog.replay.blocks import channel_blocks

JSON, PROTO, RAW, IMAGE = "/numbers", "/vectors", "/raw", "/cam"
TOPICS = (JSON, PROTO, RAW, IMAGE)
#: The index types the writer takes (NONE: none; the others combine).
INDEX_FLAGS = (IndexType.ATTACHMENT, IndexType.CHUNK, IndexType.MESSAGE, IndexType.METADATA)


@dataclass
class Written:
    """What a test log holds: each topic's ``(log_time, value)`` in order, metadata and attachments."""

    messages: dict[str, list[tuple[int, Any]]] = field(default_factory=lambda: {t: [] for t in TOPICS})
    metadata: list[tuple[str, dict[str, str]]] = field(default_factory=list)

    def topics(self) -> set[str]:
        return {t for t, items in self.messages.items() if items}


def _image(n: int) -> np.ndarray:
    return (np.arange(6 * 8, dtype=np.uint16).reshape(6, 8) * 97 + n * 1009) % 4096


def _payload(topic: str, n: int) -> tuple[bytes, Any]:
    """The bytes written for the n-th message of ``topic`` and the value a reader must give back."""
    if topic == JSON:
        return encode_json({"n": n, "half": n / 2}), {"n": n, "half": n / 2}
    if topic == PROTO:
        return Vector3(x=n, y=-n, z=0.5).SerializeToString(), (float(n), float(-n), 0.5)
    if topic == RAW:
        return bytes(range(n % 7, n % 7 + 5)), bytes(range(n % 7, n % 7 + 5))
    image = _image(n)
    message = RawImage(frame_id="cam", width=8, height=6, encoding="mono16", step=16, data=image.tobytes())
    return message.SerializeToString(), image


class _Channels:
    """Registers each schema and channel with the writer, up front or just before its first message."""

    def __init__(self, writer: Writer) -> None:
        self.writer, self.ids = writer, {}

    def id(self, topic: str) -> int:
        if topic not in self.ids:
            w = self.writer
            if topic == JSON:
                schema = w.register_schema("numbers", "jsonschema", b'{"type": "object"}')
                self.ids[topic] = w.register_channel(topic, "json", schema)
            elif topic == RAW:
                self.ids[topic] = w.register_channel(topic, "x-raw-bytes", 0)
            else:
                kind = Vector3 if topic == PROTO else RawImage
                schema = w.register_schema(kind.DESCRIPTOR.full_name, "protobuf",
                                           build_file_descriptor_set(kind).SerializeToString())
                self.ids[topic] = w.register_channel(topic, "protobuf", schema)
        return self.ids[topic]


def write_log(path: Path, options: dict[str, Any], schedule: list[int], *, upfront: bool, metadata: bool,
              attachment: bool) -> Written:
    """A log of the ``mcap`` writer with ``options``: message k on ``TOPICS[schedule[k]]`` at log_time
    ``(k + 1) ms``; the channels registered up front or as their first message comes."""
    written = Written()
    with open(path, "wb") as f:
        writer = Writer(f, **options)
        writer.start(profile="", library="any-layout-test")
        channels = _Channels(writer)
        for topic in TOPICS if upfront else ():
            channels.id(topic)
        for k, pick in enumerate(schedule):
            topic, t = TOPICS[pick], (k + 1) * 1_000_000
            data, value = _payload(topic, len(written.messages[topic]))
            writer.add_message(channels.id(topic), log_time=t, publish_time=t, data=data, sequence=k)
            written.messages[topic].append((t, value))
            if metadata and k == len(schedule) // 2:
                writer.add_metadata("calibration", {"k": str(k)})
                written.metadata.append(("calibration", {"k": str(k)}))
            if attachment and k == 0:
                writer.add_attachment(create_time=0, log_time=t, name="notes.txt", media_type="text/plain",
                                      data=b"seen")
        writer.finish()
    return written


writer_options = st.fixed_dictionaries({
    "use_chunking": st.booleans(),
    "compression": st.sampled_from([CompressionType.NONE, CompressionType.LZ4, CompressionType.ZSTD]),
    "index_types": st.sets(st.sampled_from(INDEX_FLAGS)).map(
        lambda flags: IndexType.NONE if not flags else _combined(flags)),
    "use_summary_offsets": st.booleans(),
    "use_statistics": st.booleans(),
    "repeat_schemas": st.booleans(),
    "repeat_channels": st.booleans(),
    "chunk_size": st.sampled_from([1, 200, 1 << 20]),
})


def _combined(flags: set[IndexType]) -> IndexType:
    out = IndexType(0)
    for flag in flags:
        out |= flag
    return out


@contextmanager
def _folder() -> Iterator[Path]:
    with tempfile.TemporaryDirectory() as d:
        yield Path(d)


def _same(topic: str, got: Any, want: Any) -> bool:
    if topic == IMAGE:
        return bool(np.array_equal(got, want))
    if topic == PROTO:
        return (got.x, got.y, got.z) == want
    return bool(got == want)


def _check_log_reader(path: Path, written: Written) -> None:
    with LogReader(path) as log:
        assert written.topics() <= set(log.topics)
        counts = {c.topic: c.message_count for c in log.channels()}
        for topic in written.topics():
            assert counts[topic] == len(written.messages[topic])
            got = [(m.log_time, m.payload) for m in log.messages(topic)]
            assert [t for t, _ in got] == [t for t, _ in written.messages[topic]]
            assert all(_same(topic, a, b) for (_, a), (_, b) in zip(got, written.messages[topic], strict=True))
        assert [m for m in log.metadata() if m[0] != "starlog.provenance"] == written.metadata  # filter adds its own


def _check_cat(path: Path, written: Written) -> None:
    result = CliRunner().invoke(cli, ["cat", str(path), "-q"])
    assert result.exit_code == 0, result.output
    lines = [json.loads(line) for line in result.stdout.splitlines()]
    want = sorted((t, topic) for topic, items in written.messages.items() for t, _ in items)
    assert [(line["log_time"], line["topic"]) for line in lines] == want
    for line in lines:
        message = line["message"]
        if line["topic"] == JSON:
            assert message == dict(written.messages[JSON])[line["log_time"]]
        elif line["topic"] == PROTO:
            assert (message["x"], message["y"], message["z"]) == dict(written.messages[PROTO])[line["log_time"]]
        elif line["topic"] == RAW:
            assert message == {"schema": "", "encoding": "x-raw-bytes", "bytes": 5}
        else:
            assert (message["width"], message["height"], message["encoding"]) == (8, 6, "mono16")


def _check_export(path: Path, written: Written, out: Path) -> None:
    flat = [t for t in (JSON, PROTO) if written.messages[t]]
    if not flat and not written.messages[IMAGE]:
        return  # schemaless messages only: nothing export writes tables of
    result = export_log(path, out, topics=flat)
    for topic in flat:
        table = pq.read_table(out / f"{topic.strip('/')}.parquet")
        assert table.column("log_time").to_pylist() == [t for t, _ in written.messages[topic]]
    if written.messages[JSON]:
        assert pq.read_table(out / "numbers.parquet").column("n").to_pylist() == list(
            range(len(written.messages[JSON])))
    frames = [t for t, _ in written.messages[IMAGE]]
    assert result.get("frames", 0) == len(frames)
    if frames:
        assert pq.read_table(out / "frames.parquet").column("log_time").to_pylist() == frames


def _check_image_reading(path: Path, written: Written) -> None:
    """The centroid stage's reading: the image channel it chooses, its frames, and its blocks of whole chunks."""
    if not written.messages[IMAGE]:
        return
    with LogReader(path) as log:
        topic, _ = choose_image_topic(log.path, log.channels(), None)
        assert topic == IMAGE
        frames = [(t, image) for _, t, image in log.frames(topic)]
        blocks = channel_blocks(log, topic, 2) if log.fully_indexed else None
        if blocks is not None:
            by_block = [(t, image) for start, end, first in blocks
                        for _, t, image in log.frames(topic, start=start, end=end, first_index=first)]
            assert [t for t, _ in by_block] == [t for t, _ in frames]
    assert [t for t, _ in frames] == [t for t, _ in written.messages[IMAGE]]
    assert all(np.array_equal(a, b) for (_, a), (_, b) in zip(frames, written.messages[IMAGE], strict=True))


def _mcap_library_reads(path: Path) -> bool:
    with open(path, "rb") as f:
        try:
            for _ in make_reader(f).iter_messages():
                pass
        except KeyError:  # a channel or schema its summary does not hold
            return False
    return True


@settings(max_examples=200, deadline=None)
@given(writer_options, st.lists(st.integers(0, len(TOPICS) - 1), min_size=1, max_size=24), st.booleans(),
       st.booleans(), st.booleans())
def test_every_layout_the_mcap_writer_makes_reads_in_full_and_verify_agrees(
        options: dict[str, Any], schedule: list[int], upfront: bool, metadata: bool, attachment: bool) -> None:
    with _folder() as d:
        path = d / "any.mcap"
        written = write_log(path, options, schedule, upfront=upfront, metadata=metadata, attachment=attachment)
        report = verify_log(path)
        assert report.ok, report.lines()
        _check_log_reader(path, written)
        _check_cat(path, written)
        _check_export(path, written, d / "export")
        _check_image_reading(path, written)
        note = [p for p in report.problems if p.kind == "definitions_not_in_summary"]
        lacking = (not options["repeat_channels"] and written.topics()) or \
            (not options["repeat_schemas"] and written.topics() - {RAW})
        assert len(note) == int(bool(lacking) and _has_summary(path))
        assert bool(note and "mcap library" in note[0].detail) == (not _mcap_library_reads(path))
        breaks = _breaks_summary_rules(path)
        assert report.status == ("nonconformant" if breaks else "valid") and report.exit_status == (3 if breaks else 0)
        assert bool(note and note[0].severity == "warning") == breaks


def _breaks_summary_rules(path: Path) -> bool:
    """Whether the file breaks the MCAP specification's rules on the summary's copies, as the ``mcap`` library
    reads the file: a channel the chunk indexes name without its channel or schema record in the summary, or
    per-channel statistics without every channel record of the file in the summary."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
        if summary is None:
            return False
        f.seek(0)
        channels = {r.id: r for r in StreamReader(f).records if isinstance(r, Channel)}
    indexed = {cid for ci in summary.chunk_indexes for cid in ci.message_index_offsets}
    if any(cid not in summary.channels or (channels[cid].schema_id and channels[cid].schema_id not in summary.schemas)
           for cid in indexed):
        return True
    stats = summary.statistics
    return bool(stats and stats.channel_message_counts) and not channels.keys() <= summary.channels.keys()


def _has_summary(path: Path) -> bool:
    with open(path, "rb") as f:
        return read_file_summary(f) is not None


#: A summary with chunk indexes and statistics but no schema or channel records: not what the MCAP
#: specification asks for, but valid everywhere else, and what the writer's options make.
UNREPEATED = {"use_chunking": True, "compression": CompressionType.ZSTD, "index_types": IndexType.ALL,
              "use_summary_offsets": True, "use_statistics": True, "repeat_schemas": False, "repeat_channels": False,
              "chunk_size": 1}


def _opened_chunks(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The offsets of the chunks :class:`McapFile` decompresses from now on, in order."""
    from starlog.io.mcap_file import McapFile

    # private: every chunk McapFile reads is decompressed and checked by _chunk_contents, so its calls count them

    opened: list[int] = []
    contents = McapFile._chunk_contents

    def counting(self: McapFile, ci: Any) -> Any:
        opened.append(ci.chunk_start_offset)
        return contents(self, ci)

    monkeypatch.setattr(McapFile, "_chunk_contents", counting)
    return opened


def test_the_definitions_come_from_the_chunks_where_the_channels_start(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """One message a chunk: the channels registered up front are in the first chunk, one registered late in
    the chunk of its first message; those two chunks are opened, not the 38 others."""
    path = tmp_path / "late.mcap"
    schedule = [0] * 20 + [3] * 10 + [0] * 10
    written = write_log(path, UNREPEATED, schedule, upfront=False, metadata=False, attachment=False)
    opened = _opened_chunks(monkeypatch)
    with LogReader(path) as log:
        assert len(log.files[0].summary.chunk_indexes) == 40 and len(opened) == 2
        assert any("read from the data section (2 chunks opened)" in n and "starlog filter" in n for n in log.notes)
        assert [t for _, t, _ in log.frames(IMAGE)] == [t for t, _ in written.messages[IMAGE]]
    assert len(opened) == 2 + 10  # the image chunks read once, for their frames


def test_without_counts_or_message_indexes_each_chunk_is_read_once_to_open_and_once_to_read(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Neither the statistics nor the message indexes say which channels the chunks hold: opening reads each
    chunk once (learning the channels and counting their messages); the counts are not read again."""
    path = tmp_path / "bare.mcap"
    options = {**UNREPEATED, "index_types": IndexType.ALL & ~IndexType.MESSAGE, "use_statistics": False}
    written = write_log(path, options, [0, 3, 1, 3, 2, 3], upfront=False, metadata=False, attachment=False)
    opened = _opened_chunks(monkeypatch)
    with LogReader(path) as log:
        assert len(opened) == 6
        assert {c.topic: c.message_count for c in log.channels()} == {t: len(m) for t, m in written.messages.items()}
        assert len(opened) == 6
        assert sum(1 for _ in log.messages(log.topics)) == 6 and len(opened) == 12


def test_layers_on_such_a_base_and_their_flattened_log_repeat_every_schema_and_channel(tmp_path: Path) -> None:
    base = tmp_path / "base.mcap"
    written = write_log(base, UNREPEATED, [0, 1, 2, 3] * 3, upfront=False, metadata=True, attachment=True)
    layer = tmp_path / "layer.mcap"
    with LogReader(base) as log:
        layer_base = log.layer_base()
    with LogWriter(layer, layer=layer_base) as writer:
        channel = writer.add_channel("/added", json_message_type("starlog.FrameInfo"))
        for n in range(3):
            writer.write(channel, log_time=(n + 1) * 1_000_000, data=encode_json(
                {"frame": n, "width": 8, "height": 6, "encoding": "mono16", "bit_depth": 16, "source": ""}))
    report = verify_log(layer)
    assert report.ok and report.status == "nonconformant" and report.exit_status == 3, report.lines()
    assert report.verdict().startswith(f"NONCONFORMANT: {layer} is a chain of 2 files, read in full by starlog") \
        and f"{base} does not conform" in report.verdict() and f"starlog filter {layer} -o OUT.mcap" in report.verdict()
    described = CliRunner().invoke(cli, ["verify", str(layer), "--json"])
    assert described.exit_code == 3 and json.loads(described.stdout)["status"] == "nonconformant"
    _check_log_reader(layer, written)  # the base's channels, read through the layer
    with LogReader(layer) as log:
        assert set(log.topics) == set(TOPICS) | {"/added"} and log.channel("/added").message_count == 3
    flat = tmp_path / "flat.mcap"
    flatten_log(layer, flat)
    with open(flat, "rb") as f:
        summary = read_file_summary(f)
    assert summary is not None and {c.topic for c in summary.channels.values()} == set(TOPICS) | {"/added"}
    assert {c.schema_id for c in summary.channels.values()} - {0} <= summary.schemas.keys()
    assert not [p for p in verify_log(flat).problems if p.kind == "definitions_not_in_summary"]
    assert verify_log(flat).status == "valid"
    with open(flat, "rb") as f:  # the mcap library, which needs the copies, reads every message
        counts: dict[str, int] = {}
        for _, channel_record, _ in make_reader(f).iter_messages():
            counts[channel_record.topic] = counts.get(channel_record.topic, 0) + 1
    assert counts == {**{t: len(m) for t, m in written.messages.items()}, "/added": 3}
    _check_log_reader(flat, written)


def test_info_report_and_filter_read_it_and_filter_writes_the_copies(tmp_path: Path) -> None:
    path = tmp_path / "unrepeated.mcap"
    written = write_log(path, UNREPEATED, [3, 0, 1, 3, 2, 3], upfront=True, metadata=True, attachment=False)
    runner = CliRunner()
    info = runner.invoke(cli, ["info", str(path), "--json"])
    assert info.exit_code == 0, info.output
    described = json.loads(info.stdout)
    assert {c["topic"]: c["message_count"] for c in described["channels"]} == \
        {t: len(m) for t, m in written.messages.items()}
    assert any("starlog filter" in note for note in described["notes"])
    report = runner.invoke(cli, ["report", str(path), "-o", str(tmp_path / "r.html"), "-q"])
    assert report.exit_code == 0, report.output
    assert all(topic in (tmp_path / "r.html").read_text() for topic in TOPICS)
    verified = runner.invoke(cli, ["verify", str(path)])  # read in full, but not what the specification asks
    assert verified.exit_code == 3 and "warning definitions_not_in_summary" in verified.output
    verdict = verified.output.splitlines()[-1]
    assert verdict.startswith(f"NONCONFORMANT: starlog reads {path} in full") and verdict.endswith(
        f"Rewrite it conforming with: starlog filter {path} -o OUT.mcap")
    assert '"A Schema and Channel record MUST exist in the summary section for all channels referenced by chunk ' \
           'index records"' in verdict and "Statistics record with a non-empty channel_message_counts" in verdict
    out = tmp_path / "rewritten.mcap"
    filtered = runner.invoke(cli, ["filter", str(path), "-o", str(out), "-q"])
    assert filtered.exit_code == 0, filtered.output
    again = runner.invoke(cli, ["verify", str(out)])
    assert again.exit_code == 0 and "definitions_not_in_summary" not in again.output
    assert _mcap_library_reads(out) and not _mcap_library_reads(path)
    _check_log_reader(out, written)


def test_the_dask_batch_path_exports_such_logs_as_one_process_does(tmp_path: Path) -> None:
    logs = []
    for k, options in enumerate([UNREPEATED, {**UNREPEATED, "use_chunking": False, "use_statistics": False}]):
        logs.append(tmp_path / f"log{k}.mcap")
        write_log(logs[-1], options, [0, 3, 1, 3, 3], upfront=False, metadata=False, attachment=False)
    runner = CliRunner()
    for workers, folder in (("1", "serial"), ("2", "dask")):
        result = runner.invoke(cli, ["export", *map(str, logs), "-o", str(tmp_path / folder), "--workers", workers,
                                     "--topic", JSON, "-q"])
        assert result.exit_code == 0, result.output
    for log in logs:
        for table in ("frames.parquet", "numbers.parquet"):
            serial = pq.read_table(tmp_path / "serial" / log.stem / table)
            assert serial.num_rows == (3 if table == "frames.parquet" else 1)
            assert serial.equals(pq.read_table(tmp_path / "dask" / log.stem / table))


def test_a_channel_no_record_defines_is_refused_by_the_readers_and_by_verify(tmp_path: Path) -> None:
    """The file's only /numbers channel record turned into a record of an unknown kind (which readers skip):
    its messages name a channel nothing defines, and readers and verify both say so."""
    path = tmp_path / "undefined.mcap"
    options = {**UNREPEATED, "compression": CompressionType.NONE, "enable_crcs": False}
    write_log(path, options, [0, 1, 0, 1], upfront=True, metadata=False, attachment=False)
    data = bytearray(path.read_bytes())
    record = data.index(b"/numbers") - 17  # opcode, length, id, schema id, topic length, then the topic
    assert data[record] == 0x04 and data.count(b"/numbers") == 1
    data[record] = 0x80
    path.write_bytes(bytes(data))
    with pytest.raises(CorruptLogError, match="names unknown channel 1.*starlog recover"):
        LogReader(path)
    report = verify_log(path)
    assert not report.ok and "unknown_channel" in {p.kind for p in report.errors}
