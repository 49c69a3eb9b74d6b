"""Topics of several channels (one per publisher: two recorders, a restarted publisher): every command reads the
union of their messages, and ``verify`` says what the readers do.

The logs are written by the ``mcap`` library's own writer over its options, with two or three channels on
a topic sharing one schema record, each registering an identical one, carrying another image type, or
carrying messages of another type (a JSON channel on an image topic, a protobuf channel on a JSON
topic); what was written is the known answer. Each channel variant below declares the type of message it
carries: channels of one declared type read as one series, others are refused as a series with the line
``verify`` reports too.
"""

from __future__ import annotations

import base64
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
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from starlog.cli import cli
from starlog.errors import InvalidInputError, InvalidMessageError, MixedTopicError
from starlog.parquet.tables import export_log
from starlog.io import LogReader, LogWriter
from starlog.codecs import encode_json, json_message_type
from starlog.io.copying import flatten_log
from starlog.codecs.images import choose_image_topic
from starlog.io.recover import recover_log
from starlog.io.verify import verify_log
from starlog.replay.blocks import channel_blocks
from starlog.excerpt import filter_log

CAM, NUM = "/cam", "/numbers"
#: Channel variant -> (its topic, the type of message it carries).
VARIANTS = {
    "raw": (CAM, "image"),  # foxglove.RawImage, protobuf, the first such schema record
    "raw_again": (CAM, "image"),  # foxglove.RawImage, protobuf, its own (identical) schema record
    "raw_json": (CAM, "image"),  # foxglove.RawImage, JSON
    "cam_numbers": (CAM, "numbers"),  # JSON numbers on the image topic
    "numbers": (NUM, "numbers"),
    "numbers_again": (NUM, "numbers"),  # its own (identical) schema record
    "vector": (NUM, "vector"),  # protobuf foxglove.Vector3 on the JSON topic
}
RAW_SCHEMA = build_file_descriptor_set(RawImage).SerializeToString()


def _image(n: int) -> np.ndarray:
    return (np.arange(6 * 8, dtype=np.uint16).reshape(6, 8) * 31 + n * 977) % 4096


@dataclass
class Written:
    """What a test log holds: per topic, ``(log_time, channel index, value)`` in log_time order."""

    channels: list[str]
    messages: dict[str, list[tuple[int, int, Any]]] = field(default_factory=lambda: {CAM: [], NUM: []})

    def kinds(self, topic: str) -> set[str]:
        """The declared types of the channels of ``topic`` that hold messages."""
        return {VARIANTS[self.channels[c]][1] for _, c, _ in self.messages[topic]}

    def mixed(self, topic: str) -> bool:
        return len(self.kinds(topic)) > 1

    def held(self) -> set[str]:
        return {t for t, items in self.messages.items() if items}


def _register(writer: Writer, variant: str, k: int, shared: dict[str, int]) -> int:
    """Register the ``k``-th channel, of ``variant``; ``shared`` holds the schema ids registered once."""
    def schema(key: str, name: str, encoding: str, data: bytes, *, again: bool = False) -> int:
        if again or key not in shared:
            shared[key] = writer.register_schema(name, encoding, data)
        return shared[key]

    topic = VARIANTS[variant][0]
    meta = {"publisher": f"recorder {k}"}
    if variant in ("raw", "raw_again"):
        return writer.register_channel(topic, "protobuf", schema("raw", "foxglove.RawImage", "protobuf", RAW_SCHEMA,
                                                                 again=variant == "raw_again"), meta)
    if variant == "raw_json":
        return writer.register_channel(topic, "json", schema("raw_json", "foxglove.RawImage", "jsonschema", b"{}"),
                                       meta)
    if variant == "vector":
        data = build_file_descriptor_set(Vector3).SerializeToString()
        return writer.register_channel(topic, "protobuf", schema("vector", "foxglove.Vector3", "protobuf", data), meta)
    numbers = schema("numbers", "numbers", "jsonschema", b'{"type": "object"}', again=variant == "numbers_again")
    return writer.register_channel(topic, "json", numbers, meta)


def _payload(variant: str, n: int) -> tuple[bytes, Any]:
    """The bytes of the n-th message of ``variant``'s topic and the value a reader gives back."""
    kind = VARIANTS[variant][1]
    if kind == "image":
        image = _image(n)
        if variant == "raw_json":
            return encode_json({"width": 8, "height": 6, "encoding": "mono16", "step": 16,
                                "data": base64.b64encode(image.tobytes()).decode()}), image
        return RawImage(width=8, height=6, encoding="mono16", step=16, data=image.tobytes()).SerializeToString(), image
    if kind == "vector":
        return Vector3(x=n, y=-n, z=0.25).SerializeToString(), (float(n), float(-n), 0.25)
    return encode_json({"n": n}), {"n": n}


def write_log(path: Path, options: dict[str, Any], channels: list[str], schedule: list[int], *,
              upfront: bool = True, times: list[int] | None = None) -> Written:
    """A log of the ``mcap`` writer with ``options``: message k on ``channels[schedule[k]]`` at log_time
    ``times[k]`` (default ``(k + 1) ms``); channels registered up front or before their first message."""
    written = Written(list(channels))
    with open(path, "wb") as f:
        writer = Writer(f, **options)
        writer.start(profile="", library="shared-topics-test")
        shared: dict[str, int] = {}
        ids: dict[int, int] = {}
        for k in range(len(channels)) if upfront else ():
            ids[k] = _register(writer, channels[k], k, shared)
        for k, pick in enumerate(schedule):
            if pick not in ids:
                ids[pick] = _register(writer, channels[pick], pick, shared)
            variant = channels[pick]
            topic = VARIANTS[variant][0]
            data, value = _payload(variant, len(written.messages[topic]))
            t = times[k] if times is not None else (k + 1) * 1_000_000
            writer.add_message(ids[pick], log_time=t, publish_time=t, data=data, sequence=k)
            written.messages[topic].append((t, pick, value))
        writer.finish()
    return written


writer_options = st.fixed_dictionaries({
    "use_chunking": st.booleans(),
    "compression": st.sampled_from([CompressionType.NONE, CompressionType.ZSTD]),
    "index_types": st.sampled_from([IndexType.ALL, IndexType.ALL & ~IndexType.MESSAGE, IndexType.NONE]),
    "use_statistics": st.booleans(),
    "repeat_schemas": st.booleans(),
    "repeat_channels": st.booleans(),
    "chunk_size": st.sampled_from([1, 300, 1 << 20]),
})


@st.composite
def layouts(draw: st.DrawFn) -> tuple[list[str], list[int]]:
    """Channels (at least two on one topic) and which of them each message goes to."""
    cam = draw(st.lists(st.sampled_from(["raw", "raw_again", "raw_json", "cam_numbers"]), max_size=3))
    num = draw(st.lists(st.sampled_from(["numbers", "numbers_again", "vector"]), max_size=3))
    assume(len(cam) > 1 or len(num) > 1)
    channels = cam + num
    return channels, draw(st.lists(st.integers(0, len(channels) - 1), min_size=1, max_size=20))


@contextmanager
def _folder() -> Iterator[Path]:
    with tempfile.TemporaryDirectory() as d:
        yield Path(d)


def _same(got: Any, want: Any) -> bool:
    if isinstance(want, np.ndarray):
        return isinstance(got, np.ndarray) and np.array_equal(got, want)
    if isinstance(want, tuple):
        return (got.x, got.y, got.z) == want
    return bool(got == want)


def _check_log_reader(path: Path, written: Written) -> None:
    """Each topic whose channels carry one type: every message in log_time order, each decoded by its own
    channel's schema, counted together; a mixed topic: refused as a series with verify's line."""
    with LogReader(path) as log:
        assert written.held() <= set(log.topics) and len(log.topics) == len(set(log.topics))
        for topic in written.held():
            want = written.messages[topic]
            assert log.channel(topic).message_count == len(want)
            if written.mixed(topic):
                with pytest.raises(MixedTopicError, match=f"topic {topic!r} have schemas"):
                    list(log.messages(topic))
                continue
            got = [(m.log_time, m.payload) for m in log.messages(topic)]
            assert [t for t, _ in got] == [t for t, _, _ in want]
            assert all(_same(a, b) for (_, a), (_, _, b) in zip(got, want, strict=True))


def _check_cat(path: Path, written: Written) -> None:
    """cat prints every message, each by its own schema, mixed topics too."""
    result = CliRunner().invoke(cli, ["cat", str(path), "-q"])
    assert result.exit_code == 0, result.output
    lines = [json.loads(line) for line in result.stdout.splitlines()]
    want = sorted((t, topic, c) for topic, items in written.messages.items() for t, c, _ in items)
    assert [(line["log_time"], line["topic"]) for line in lines] == [(t, topic) for t, topic, _ in want]
    for line, (_, _, c) in zip(lines, want, strict=True):
        kind, message = VARIANTS[written.channels[c]][1], line["message"]
        assert (message["width"], message["height"]) == (8, 6) if kind == "image" else \
            ("n" in message if kind == "numbers" else message["z"] == 0.25)


def _check_export(path: Path, written: Written, out: Path) -> None:
    """export: the JSON topic as a table and the image topic's frames; a mixed topic asked for: its line."""
    flat = [NUM] if written.messages[NUM] and written.kinds(NUM) == {"numbers"} else []
    mixed = [t for t in written.held() if written.mixed(t)]
    for topic in mixed:
        with pytest.raises(MixedTopicError, match=f"topic {topic!r} have schemas"):
            export_log(path, out, tables=[], topics=[topic])
    if mixed:
        return
    if not flat and written.kinds(CAM) != {"image"}:
        return  # no frames, no JSON numbers: nothing export writes
    result = export_log(path, out, topics=flat)
    if flat:
        assert pq.read_table(out / "numbers.parquet").column("n").to_pylist() == list(range(len(written.messages[NUM])))
    if written.kinds(CAM) == {"image"}:
        assert pq.read_table(out / "frames.parquet").column("log_time").to_pylist() == \
            [t for t, _, _ in written.messages[CAM]]
        assert result["frames"] == len(written.messages[CAM])


def _check_frames(path: Path, written: Written) -> None:
    """The centroid stage's reading: the image topic it chooses, its frames (every channel's, each by its own
    schema), and its blocks of whole chunks."""
    if written.kinds(CAM) != {"image"}:
        return
    with LogReader(path) as log:
        assert choose_image_topic(log.path, log.channels(), None)[0] == CAM
        frames = [(t, image) for _, t, image in log.frames(CAM)]
        blocks = channel_blocks(log, CAM, 2) if log.fully_indexed else None
        if blocks is not None:
            by_block = [t for start, end, first in blocks
                        for _, t, _ in log.frames(CAM, start=start, end=end, first_index=first)]
            assert by_block == [t for t, _ in frames]
    assert [t for t, _ in frames] == [t for t, _, _ in written.messages[CAM]]
    assert all(np.array_equal(a, b) for (_, a), (_, _, b) in zip(frames, written.messages[CAM], strict=True))


def _check_verify(path: Path, written: Written) -> None:
    """verify agrees with the readers: an error naming each mixed topic (the readers' line), else valid or
    nonconformant (read in full either way)."""
    report = verify_log(path)
    refused = {p.channel: p.detail for p in report.errors if p.kind == "topic_schemas_differ"}
    assert set(refused) == {t for t in written.held() if written.mixed(t)}, report.lines()
    with LogReader(path) as log:
        for topic, detail in refused.items():
            assert detail.startswith(log.topic_conflict(topic) or "?") and "Foxglove" in detail
    if refused:
        assert report.status == "refused" and report.exit_status == 1 and report.verdict().startswith("REFUSED")
    else:
        assert report.ok and report.status in ("valid", "nonconformant"), report.lines()


#: A summary with chunk indexes and statistics, without the schema and channel records.
UNREPEATED = {"use_chunking": True, "compression": CompressionType.ZSTD, "index_types": IndexType.ALL,
              "use_statistics": True, "repeat_schemas": False, "repeat_channels": False, "chunk_size": 300}


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(writer_options, layouts(), st.booleans())
@example(UNREPEATED, (["raw", "raw_again", "raw_json"], [0, 1, 2, 0, 1, 2, 2]), False)  # three image channels
@example(UNREPEATED, (["raw", "cam_numbers", "numbers"], [0, 1, 2, 0, 1]), True)  # an image and a JSON channel
@example({**UNREPEATED, "use_chunking": False}, (["numbers", "vector", "numbers_again"], [0, 1, 2, 1]), True)
def test_every_layout_of_shared_topics_reads_in_full_and_verify_agrees(
        options: dict[str, Any], layout: tuple[list[str], list[int]], upfront: bool) -> None:
    channels, schedule = layout
    with _folder() as d:
        path = d / "shared.mcap"
        written = write_log(path, options, channels, schedule, upfront=upfront)
        _check_verify(path, written)
        _check_log_reader(path, written)
        _check_cat(path, written)
        _check_export(path, written, d / "export")
        _check_frames(path, written)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(writer_options, layouts())
@example(UNREPEATED, (["raw", "raw_json", "numbers", "numbers_again"], [0, 1, 2, 3, 1, 0]))
@example(UNREPEATED, (["raw", "cam_numbers"], [0, 1, 1, 0]))
def test_filter_and_flatten_copy_every_channel_of_a_topic(options: dict[str, Any],
                                                         layout: tuple[list[str], list[int]]) -> None:
    """The copies hold each channel as it was (id, topic, schema, messages), conform to the specification (the
    mcap library reads every message of each channel), and read back as the original does."""
    channels, schedule = layout
    with _folder() as d:
        path = d / "shared.mcap"
        written = write_log(path, options, channels, schedule)
        for out in (filter_log(path, d / "filtered.mcap").output, flatten_log(path, d / "flat.mcap").output):
            report = verify_log(out)
            assert report.status == ("refused" if any(written.mixed(t) for t in written.held()) else "valid"), \
                report.lines()
            with open(out, "rb") as f:
                counts: dict[tuple[str, str], int] = {}
                for _, channel, _ in make_reader(f).iter_messages():
                    key = (channel.topic, channel.metadata["publisher"])
                    counts[key] = counts.get(key, 0) + 1
            want: dict[tuple[str, str], int] = {}
            for topic, items in written.messages.items():
                for _, c, _ in items:
                    want[(topic, f"recorder {c}")] = want.get((topic, f"recorder {c}"), 0) + 1
            assert counts == want
            _check_log_reader(out, written)
            _check_frames(out, written)


def _frames_log(path: Path, times: list[int], sizes: list[tuple[int, int]] | None = None) -> Path:
    """Two RawImage channels on /cam, message k on channel k % 2 at ``times[k]`` (of ``sizes[k]``)."""
    with open(path, "wb") as f:
        writer = Writer(f, chunk_size=1)
        writer.start()
        schema = writer.register_schema("foxglove.RawImage", "protobuf", RAW_SCHEMA)
        ids = [writer.register_channel(CAM, "protobuf", schema, {"publisher": str(k)}) for k in range(2)]
        for k, t in enumerate(times):
            h, w = sizes[k] if sizes else (6, 8)
            image = np.full((h, w), k, dtype=np.uint16)
            data = RawImage(width=w, height=h, encoding="mono16", step=2 * w, data=image.tobytes())
            writer.add_message(ids[k % 2], log_time=t, publish_time=t, data=data.SerializeToString())
        writer.finish()
    return path


def test_frames_of_two_channels_at_one_time_or_of_two_sizes_are_refused_by_the_readers_and_by_verify(
        tmp_path: Path) -> None:
    """A topic's image channels are one series of frames: one size, strictly increasing times."""
    both = _frames_log(tmp_path / "same_time.mcap", [10, 10, 20, 30])  # the channels' first frames at one time
    with LogReader(both) as log, pytest.raises(InvalidMessageError, match="does not come after the previous frame"):
        list(log.frames(CAM))
    report = verify_log(both)
    assert [(p.kind, p.channel, p.log_time) for p in report.errors] == [("duplicate_frame_time", CAM, 10)]
    assert report.status == "refused" and report.exit_status == 1
    sizes = _frames_log(tmp_path / "sizes.mcap", [10, 20, 30], [(6, 8), (6, 9), (6, 8)])
    with LogReader(sizes) as log, pytest.raises(InvalidMessageError, match="every frame of a log must match"):
        list(log.frames(CAM))
    assert [(p.kind, p.log_time) for p in verify_log(sizes).errors] == [("image_size_changed", 20)]
    fine = _frames_log(tmp_path / "fine.mcap", [10, 15, 20, 25])
    assert verify_log(fine).status == "valid"
    with LogReader(fine) as log:
        assert [t for _, t, _ in log.frames(CAM)] == [10, 15, 20, 25]


def test_a_channel_without_messages_does_not_make_its_topic_mixed(tmp_path: Path) -> None:
    """A JSON channel registered on the image topic that never published: nothing to merge."""
    path = tmp_path / "idle.mcap"
    written = write_log(path, {"chunk_size": 300}, ["raw", "cam_numbers"], [0, 0, 0])
    assert verify_log(path).ok
    with LogReader(path) as log:
        assert log.topic_conflict(CAM) is None and len(list(log.frames(CAM))) == 3
        assert log.channel(CAM).channel_ids == (1, 2) and log.channel(CAM).message_count == 3
    assert [t for t, _, _ in written.messages[CAM]] == [1_000_000, 2_000_000, 3_000_000]


def test_info_lists_each_channel_of_a_topic_and_says_which_cannot_be_read_as_one(tmp_path: Path) -> None:
    path = tmp_path / "mixed.mcap"
    write_log(path, {"chunk_size": 300}, ["raw", "raw_again", "numbers", "vector"], [0, 1, 2, 3, 0, 2, 3, 1])
    runner = CliRunner()
    described = json.loads(runner.invoke(cli, ["info", str(path), "--json"]).stdout)
    by_topic = {c["topic"]: c for c in described["channels"]}
    assert by_topic[CAM]["message_count"] == 4 and by_topic[CAM]["channel_ids"] == [1, 2]
    assert [p["message_count"] for p in by_topic[CAM]["per_channel"]] == [2, 2]
    assert [p["schema"] for p in by_topic[NUM]["per_channel"]] == ["numbers", "foxglove.Vector3"]
    with LogReader(path) as log:
        line = log.topic_conflict(NUM)
    assert line is not None and "'numbers' (jsonschema; channel 3) and 'foxglove.Vector3' (protobuf; channel 4)" in line
    assert described["notes"] == [line] and log.topic_conflict(CAM) is None
    text = runner.invoke(cli, ["info", str(path)]).output
    assert "  channel 3 " in text and "  channel 4 " in text
    verified = runner.invoke(cli, ["verify", str(path)])
    assert verified.exit_code == 1 and f"error topic_schemas_differ (channel {NUM}): {line}" in verified.output
    assert f"note shared_topic (channel {CAM})" in verified.output
    stage = runner.invoke(cli, ["export", str(path), "-o", str(tmp_path / "x"), "--topic", NUM, "-q"])
    assert stage.exit_code == 1 and stage.output.strip() == f"Error: {path}: {line}."


def test_layers_on_a_base_with_a_shared_topic_add_only_new_topics(tmp_path: Path) -> None:
    base = tmp_path / "base.mcap"
    written = write_log(base, {"chunk_size": 300}, ["raw", "raw_json", "numbers"], [0, 1, 2, 1, 0])
    with LogReader(base) as log:
        layer_base = log.layer_base()
    with LogWriter(tmp_path / "refused.mcap", layer=layer_base) as writer, \
            pytest.raises(InvalidInputError, match="already has a channel '/cam'"):
        writer.add_channel(CAM, json_message_type("starlog.FrameInfo"))
    with LogReader(base) as log:
        layer_base = log.layer_base()
    layer = tmp_path / "layer.mcap"
    with LogWriter(layer, layer=layer_base) as writer:
        writer.add_channel("/added", json_message_type("starlog.FrameInfo"))
    assert verify_log(layer).status == "valid"
    _check_log_reader(layer, written)
    _check_frames(layer, written)
    flat = flatten_log(layer, tmp_path / "flat.mcap").output
    with LogReader(flat) as log:
        assert log.channel(CAM).channel_ids == (1, 2) and log.topics == [CAM, NUM, "/added"]
    _check_log_reader(flat, written)


def test_recover_keeps_a_channel_of_another_schema_on_a_topic_as_its_own(tmp_path: Path) -> None:
    path = tmp_path / "cut.mcap"
    write_log(path, {"chunk_size": 300}, ["raw", "raw_again", "cam_numbers"], [0, 1, 2, 0, 1, 2])
    cut = tmp_path / "cut_short.mcap"
    cut.write_bytes(path.read_bytes()[:-40])  # the footer lost
    report = recover_log(cut, tmp_path / "recovered.mcap")
    assert report.kept_by_topic == {CAM: 6} and not report.skipped_records
    with LogReader(tmp_path / "recovered.mcap") as log:
        summary = log.channel(CAM)
        assert [p.schema_name for p in summary.per_channel] == ["foxglove.RawImage", "numbers"]
        assert [p.message_count for p in summary.per_channel] == [4, 2]  # one RawImage channel for both
        assert log.topic_conflict(CAM) is not None
        assert len(list(log.raw_messages([CAM], mixed=True))) == 6


def test_the_centroid_stage_reads_the_frames_of_every_image_channel_of_a_topic(tmp_path: Path) -> None:
    """End to end: frames of three image channels (two schema records, protobuf and JSON) are one series; a JSON
    channel among them stops the stage with the line verify reports."""
    path = tmp_path / "cameras.mcap"
    write_log(path, UNREPEATED, ["raw", "raw_again", "raw_json"], [0, 1, 2, 0, 2, 1, 0])
    runner = CliRunner()
    result = runner.invoke(cli, ["centroid", str(path), "-o", str(tmp_path / "cen.mcap"), "--method", "MOMENT",
                                 "--json", "-q"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout[result.stdout.index("{"):])
    assert (summary["image_topic"], summary["frames"], summary["channel_messages"]) == (CAM, 7, 7)
    with LogReader(tmp_path / "cen.mcap") as log:
        assert log.channel("/stars/detections").message_count == 7
        assert [m.log_time for m in log.messages("/stars/detections")] == [(k + 1) * 1_000_000 for k in range(7)]
    mixed = tmp_path / "mixed.mcap"
    write_log(mixed, UNREPEATED, ["raw", "cam_numbers"], [0, 1, 0])
    refused = runner.invoke(cli, ["centroid", str(mixed), "-o", str(tmp_path / "no.mcap"), "--image-topic", CAM,
                                  "--method", "MOMENT", "-q"])
    with LogReader(mixed) as log:
        line = log.topic_conflict(CAM)
    assert refused.exit_code == 1 and refused.output.strip() == f"Error: {mixed}: {line}."
    assert not (tmp_path / "no.mcap").exists()
    assert [p.detail.startswith(line or "?") for p in verify_log(mixed).errors] == [True]
