"""``starlog verify``: every kind of damage is reported by name; healthy logs (native or foreign) are clean."""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.data_stream import RecordBuilder
from mcap.records import ChunkIndex

from starlog.cli import cli
from starlog.io import LogReader, LogWriter
from starlog.codecs import encode_json, encode_raw_image, json_message_type, protobuf_message_type
from starlog import topics
from starlog.io.verify import verify_file, verify_log
from starlog.io.verify_indexes import ChunkIndexCheck, Seen, disagreement
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log
from tests.foreign_logs import write_foxglove_compressed, write_numbers, write_plain, write_ros1, write_ros2
from tests.helpers import small_config


def _verify_cli(path: Path) -> tuple[int, dict]:
    result = CliRunner().invoke(cli, ["verify", str(path), "--json"])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    return result.exit_code, json.loads(result.output)


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("verify")
    sim = d / "sim.mcap"
    simulate_log(small_config(n_frames=12), sim, compression="zstd")  # damage_chunk_decompress breaks a zstd frame
    cen = d / "cen.mcap"
    centroid_log(sim, cen, methods="MOMENT", options={"psf_sigma": 1.2})
    raw = d / "raw.mcap"
    with LogReader(sim) as log, LogWriter(raw, compression="none", chunk_size=4096) as w:  # uncompressed, small chunks
        ids: dict[str, int] = {}
        for schema, channel, message in log.raw_messages(log.topics):
            if channel.topic not in ids:
                from starlog.codecs.schemas import MessageType

                ids[channel.topic] = w.add_channel(channel.topic, MessageType(
                    schema.name, schema.encoding, schema.data, channel.message_encoding))  # type: ignore[union-attr]
            w.write(ids[channel.topic], log_time=message.log_time, data=message.data)
    return {"sim": sim, "cen": cen, "raw": raw, "dir": d}


HEALTHY: dict[str, Callable[[Path, Path], Path]] = {
    "ros2": lambda s, d: write_ros2(s, d),
    "ros2 png": lambda s, d: write_ros2(s, d, compressed="png"),
    "ros1": lambda s, d: write_ros1(s, d),
    "foxglove png": lambda s, d: write_foxglove_compressed(s, d),
    "no chunks": lambda s, d: write_plain(s, d, use_chunking=False),
    "no message indexes": lambda s, d: write_plain(s, d, message_indexes=False, chunk_size=4096),
    "no summary": lambda s, d: write_plain(s, d, summary=False, chunk_size=4096),
    "shuffled": lambda s, d: write_plain(s, d, shuffle=True, chunk_size=4096),
}
UNUSUAL_NOTE = {"no chunks": "messages_outside_chunks", "no message indexes": "no_message_indexes",
                "no summary": "no_summary", "shuffled": "out_of_order"}


@pytest.mark.parametrize("name", ["sim", "cen", "raw"])
def test_native_logs_are_clean(logs: dict[str, Path], name: str) -> None:
    code, report = _verify_cli(logs[name])
    assert code == 0 and report["ok"] and report["problems"] == [], report["problems"]
    assert report["verdict"].startswith("OK") and report["messages"] > 0


@pytest.mark.parametrize("kind", list(HEALTHY))
def test_foreign_and_unusual_logs_are_clean_with_notes(logs: dict[str, Path], tmp_path: Path, kind: str) -> None:
    path = HEALTHY[kind](logs["sim"], tmp_path / "f.mcap")
    code, report = _verify_cli(path)
    assert code == 0 and report["ok"], report["problems"]
    assert {p["kind"] for p in report["problems"]} == ({UNUSUAL_NOTE[kind]} if kind in UNUSUAL_NOTE else set())
    out = tmp_path / "cen.mcap"  # what a stage writes from it is healthy too
    centroid_log(path, out, methods="MOMENT", options={"psf_sigma": 1.2})
    assert verify_log(out).ok


def test_the_note_on_chunks_without_message_indexes_says_foxglove_refuses_them_and_how_to_rewrite(
        logs: dict[str, Path], tmp_path: Path) -> None:
    bare = write_plain(logs["sim"], tmp_path / "bare.mcap", message_indexes=False, chunk_size=4096)
    code, report = _verify_cli(bare)
    assert code == 0 and report["ok"]
    (note,) = report["problems"]
    assert note["kind"] == "no_message_indexes" and note["severity"] == "note"
    assert "Foxglove will not open this file" in note["detail"]
    assert f"starlog filter {bare} -o INDEXED.mcap rewrites it with them" in note["detail"]
    rewritten = tmp_path / "indexed.mcap"
    assert CliRunner().invoke(cli, ["filter", str(bare), "-o", str(rewritten), "-q"]).exit_code == 0
    assert _verify_cli(rewritten)[1]["problems"] == []
    # without a summary, no chunk index lists the bare chunks: Foxglove's indexed reader is not what reads them
    unlisted = write_plain(logs["sim"], tmp_path / "unlisted.mcap", message_indexes=False, summary=False)
    notes = {p["kind"]: p["detail"] for p in _verify_cli(unlisted)[1]["problems"]}
    assert set(notes) == {"no_summary", "no_message_indexes"} and "Foxglove" not in notes["no_message_indexes"]


# ---------------------------------------------------------------- the damaged corpus
def _summary_crc(data: bytearray) -> None:
    """Recompute the footer's summary CRC, so only the planted damage remains."""
    footer = len(data) - 8 - 29
    summary_start, offset_start = struct.unpack_from("<QQ", data, footer + 9)
    crc = zlib.crc32(bytes(data[summary_start:footer]))
    crc = zlib.crc32(struct.pack("<BQQQ", 0x02, 20, summary_start, offset_start), crc)
    struct.pack_into("<I", data, footer + 25, crc)


def _summary_record(data: bytearray, opcode: int, nth: int = 0) -> int:
    """Offset of the nth summary record of ``opcode``."""
    footer = len(data) - 8 - 29
    pos = struct.unpack_from("<Q", data, footer + 9)[0]
    found = 0
    while pos < footer:
        op, length = struct.unpack_from("<BQ", data, pos)
        if op == opcode:
            if found == nth:
                return pos
            found += 1
        pos += 9 + length
    raise AssertionError("no such summary record")


def _chunk(path: Path, nth: int = 1):  # type: ignore[no-untyped-def]
    with LogReader(path) as log:
        return log.files[-1].summary.chunk_indexes[nth]


def damage_bad_magic(raw: Path, data: bytearray) -> None:
    data[0:4] = b"GIF8"


def damage_truncated(raw: Path, data: bytearray) -> None:
    del data[len(data) // 2:]


def damage_chunk_crc(raw: Path, data: bytearray) -> None:
    ci = _chunk(raw)
    data[ci.chunk_start_offset + ci.chunk_length - 10] ^= 0xFF  # inside the (uncompressed) records


def damage_chunk_decompress(sim: Path, data: bytearray) -> None:
    ci = _chunk(sim, 0)
    data[ci.chunk_start_offset + ci.chunk_length // 2] ^= 0xFF  # zstd data


def damage_summary_crc(raw: Path, data: bytearray) -> None:
    at = _summary_record(data, 0x08)  # a chunk index
    data[at + 20] ^= 0x01


def damage_message_index_mismatch(raw: Path, data: bytearray) -> None:
    ci = _chunk(raw)
    offset = min(ci.message_index_offsets.values())
    struct.pack_into("<Q", data, offset + 15, struct.unpack_from("<Q", data, offset + 15)[0] + 1)  # first entry's time


def damage_chunk_index_mismatch(raw: Path, data: bytearray) -> None:
    at = _summary_record(data, 0x08, 1)
    struct.pack_into("<Q", data, at + 9 + 8, struct.unpack_from("<Q", data, at + 17)[0] + 5)  # message_end_time
    _summary_crc(data)


def damage_statistics_mismatch(raw: Path, data: bytearray) -> None:
    at = _summary_record(data, 0x0B)
    struct.pack_into("<Q", data, at + 9, struct.unpack_from("<Q", data, at + 9)[0] + 1)  # message_count
    _summary_crc(data)


def damage_chunk_time_range(raw: Path, data: bytearray) -> None:
    ci = _chunk(raw)
    struct.pack_into("<Q", data, ci.chunk_start_offset + 9, ci.message_start_time + 1)  # chunk header start


DAMAGE = {f.__name__[len("damage_"):]: f for f in [
    damage_bad_magic, damage_truncated, damage_chunk_crc, damage_chunk_decompress, damage_summary_crc,
    damage_message_index_mismatch, damage_chunk_index_mismatch, damage_statistics_mismatch, damage_chunk_time_range]}


@pytest.mark.parametrize("kind", list(DAMAGE))
def test_damaged_container_is_reported_by_kind(logs: dict[str, Path], tmp_path: Path, kind: str) -> None:
    source = logs["sim"] if kind == "chunk_decompress" else logs["raw"]
    data = bytearray(source.read_bytes())
    DAMAGE[kind](source, data)
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(bytes(data))
    code, report = _verify_cli(broken)
    kinds = {p["kind"] for p in report["problems"] if p["severity"] == "error"}
    assert code == 1 and not report["ok"] and kind in kinds, report["problems"]
    assert report["verdict"].startswith("DAMAGED") and "starlog recover" in report["verdict"]
    assert all(p["offset"] is not None for p in report["problems"] if p["kind"] == kind and kind != "statistics_mismatch")


def _bad_log(path: Path, images: list[tuple[int, bytes]], infos: list[tuple[int, bytes]]) -> Path:
    with LogWriter(path, validate=False) as w:  # deliberately bad messages
        image = w.add_channel(topics.IMAGE, protobuf_message_type("foxglove.RawImage"))
        info = w.add_channel(topics.FRAME_INFO, json_message_type("starlog.FrameInfo"))
        for t, data in images:
            w.write(image, log_time=t, data=data)
        for t, data in infos:
            w.write(info, log_time=t, data=data)
    return path


def test_bad_messages_are_each_reported(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    frame = lambda shape=(16, 16): rng.integers(0, 4000, size=shape, dtype=np.uint16)  # noqa: E731
    info = lambda n: encode_json({"frame": n, "width": 16, "height": 16, "encoding": "mono16", "bit_depth": 16,  # noqa: E731
                                  "source": ""})
    images = [(0, encode_raw_image(frame(), log_time=0)), (10, b"\xff\xff\xff\x07garbage"),
              (20, encode_raw_image(frame((16, 15)), log_time=20)), (20, encode_raw_image(frame(), log_time=20))]
    infos = [(0, info(0)), (10, b"{not json"), (20, b'{"frame":"two"}')]
    code, report = _verify_cli(_bad_log(tmp_path / "bad.mcap", images, infos))
    found = {(p["kind"], p["channel"], p["log_time"]) for p in report["problems"]}
    assert code == 1
    assert ("decode_error", topics.IMAGE, 10) in found and ("decode_error", topics.FRAME_INFO, 10) in found
    assert ("image_size_changed", topics.IMAGE, 20) in found and ("duplicate_frame_time", topics.IMAGE, 20) in found
    assert ("json_schema", topics.FRAME_INFO, 20) in found


def test_broken_references_and_foreign_decoding(logs: dict[str, Path], tmp_path: Path) -> None:
    from mcap.writer import Writer

    from tests.foreign_logs import ROS2_IMAGE

    path = tmp_path / "refs.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        ros = w.register_schema("sensor_msgs/msg/Image", "ros2msg", ROS2_IMAGE.encode())
        good = w.register_channel("/ros/image", "cdr", ros)
        orphan = w.register_channel("/orphan", "json", 99)
        w.add_message(good, log_time=1, publish_time=1, data=b"\x00\x01\x00\x00short")
        w.add_message(orphan, log_time=2, publish_time=2, data=b"{}")
        w.finish()
    code, report = _verify_cli(path)
    found = {(p["kind"], p["channel"]) for p in report["problems"]}
    assert code == 1 and ("decode_error", "/ros/image") in found and ("missing_schema", "/orphan") in found


def test_verify_never_raises(tmp_path: Path) -> None:
    for content in (b"", b"\x89MCAP0\r\n", b"\x89MCAP0\r\n" + bytes(100) + b"\x89MCAP0\r\n", bytes(range(256)) * 3):
        path = tmp_path / "junk.mcap"
        path.write_bytes(content)
        code, report = _verify_cli(path)
        assert code == 1 and report["problems"]


def test_an_index_that_points_where_no_chunk_starts_leaves_its_chunk_unlisted(logs: dict[str, Path],
                                                                            tmp_path: Path) -> None:
    data = bytearray(logs["raw"].read_bytes())
    at = _summary_record(data, 0x08, 1)
    (chunk,) = struct.unpack_from("<Q", data, at + 9 + 16)  # chunk_start_offset
    struct.pack_into("<Q", data, at + 9 + 16, chunk + 1)
    _summary_crc(data)
    broken = tmp_path / "moved.mcap"
    broken.write_bytes(bytes(data))
    errors = [(p.kind, p.offset, p.detail) for p in verify_log(broken).errors]
    assert errors == [
        ("chunk_index_mismatch", at, f"a chunk index points at {chunk + 1}, where no chunk starts"),
        ("chunk_not_indexed", chunk, "the summary's chunk indexes do not list this chunk"),
    ]


def test_a_summary_without_chunk_indexes_is_a_note_that_counts_the_chunks(tmp_path: Path) -> None:
    from mcap.writer import IndexType

    path = write_numbers(tmp_path / "unindexed.mcap", 3, padding=80, index_types=IndexType.ALL & ~IndexType.CHUNK)
    report = verify_log(path)
    assert report.ok and report.chunks == 3
    assert [(p.kind, p.detail) for p in report.problems] == [
        ("no_chunk_indexes", "the summary lists none of the 3 chunks: readers must scan the file")]


def _seen_chunk(offset: int, field: int) -> Seen:
    return Seen(offset, 100 + field, field, field + 5, "zstd" if field % 2 else "", 50 + field, 90 + field, {},
                 {1: offset + 200} if field % 3 else {}, offset + 250 if field % 3 else 0)


def _index_of(seen: Seen, changed: str | None) -> ChunkIndex:
    ci = ChunkIndex(chunk_start_offset=seen.offset, chunk_length=seen.length, message_start_time=seen.start,
                    message_end_time=seen.end, compression=seen.compression, compressed_size=seen.compressed_size,
                    uncompressed_size=seen.uncompressed_size, message_index_offsets=dict(seen.index_offsets),
                    message_index_length=seen.index_end - min(seen.index_offsets.values()) if seen.index_offsets else 0)
    if changed == "elsewhere":
        ci.chunk_start_offset += 7  # where no chunk starts (the chunks are 1000 bytes apart)
    elif changed is not None:
        setattr(ci, changed, getattr(ci, changed) + 1)
    return ci


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 8), st.lists(st.tuples(st.integers(0, 9), st.sampled_from(
    [None, None, "elsewhere", "chunk_length", "message_end_time", "compressed_size", "message_index_length"])),
    max_size=12))
def test_chunk_indexes_checked_as_the_walk_meets_the_chunks_find_what_a_lookup_at_the_end_finds(
        chunks: int, indexes: list[tuple[int, str | None]]) -> None:
    """Indexes in any order, duplicated, disagreeing or pointing nowhere: the same problems, in the
    summary's order, as comparing every index with a dictionary of every chunk once the walk is over."""
    seen = [_seen_chunk(1000 * (k + 1), k) for k in range(chunks)]
    table = [_index_of(seen[k % chunks] if chunks else _seen_chunk(500, k), changed) for k, changed in indexes]
    from array import array

    from starlog.io.chunk_indexes import ChunkIndexTable

    parsed = ChunkIndexTable()
    for ci in table:
        out = RecordBuilder()
        ci.write(out)
        parsed.append_record(out.end()[9:])  # the record's body
    check = ChunkIndexCheck(parsed, array("Q", range(10_000, 10_000 + len(table))))
    unlisted = [s.offset for s in seen if not check.compare(s)]

    by_offset = {s.offset: s for s in seen}
    expected = []
    for row, ci in enumerate(table):
        chunk = by_offset.get(ci.chunk_start_offset)
        if chunk is None:
            expected.append((10_000 + row, f"a chunk index points at {ci.chunk_start_offset}, where no chunk starts"))
        elif wrong := disagreement(ci, chunk):
            expected.append((10_000 + row, f"the chunk index disagrees with the chunk at {ci.chunk_start_offset} "
                                           f"in {', '.join(wrong)}"))
    assert list(check.problems()) == expected
    assert unlisted == [s.offset for s in seen if s.offset not in {ci.chunk_start_offset for ci in table}]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 255), st.binary(max_size=40)), max_size=8), st.integers(0, 12),
       st.integers(1, 64), st.integers(0, 5))
def test_summary_records_read_a_block_at_a_time_are_those_of_the_whole_section(
        records: list[tuple[int, bytes]], cut: int, block: int, lead: int) -> None:
    import io

    from starlog.io.record_walk import walk_records

    section = b"".join(struct.pack("<BQ", opcode, len(body)) + body for opcode, body in records)
    section = section[:max(0, len(section) - cut)]  # perhaps a record cut off
    data = b"\0" * lead + section + b"\xff" * 9  # what lies before and after the section

    def read(parse):  # type: ignore[no-untyped-def]
        try:
            return list(parse()), None
        except ValueError as err:
            return None, str(err)

    whole = read(lambda: ((o, op, bytes(body)) for o, op, _, body in walk_records(section, base=lead)))
    blocks = read(lambda: ((o, op, bytes(body)) for o, op, _, body in walk_records(io.BytesIO(data), lead,
                                                                                 lead + len(section), block=block)))
    assert blocks == whole


def test_a_chunk_index_the_reader_refuses_is_a_damaged_summary(tmp_path: Path) -> None:
    """Its channel list of 8 bytes cannot hold (channel id, offset) pairs of 10: the reader refuses
    the summary, and so does verify, without claiming that the summary lists no chunk index."""
    path = write_numbers(tmp_path / "odd.mcap", 3, padding=80)
    data = bytearray(path.read_bytes())
    at = _summary_record(data, 0x08)
    struct.pack_into("<I", data, at + 9 + 32, 8)  # the first chunk index's pairs take 8 bytes
    struct.pack_into("<I", data, len(data) - 8 - 4, 0)  # no summary CRC: only the record is wrong
    path.write_bytes(bytes(data))
    problems = [(p.kind, p.detail) for p in verify_log(path).problems]
    assert ("bad_summary", "the summary section cannot be parsed (ValueError: a chunk index's message index offsets "
            "take 8 bytes, not a multiple of 10 (a channel id and an offset each))") in problems
    assert "no_chunk_indexes" not in {kind for kind, _ in problems}
    with pytest.raises(Exception, match="not a multiple of 10"):
        with LogReader(path) as log:
            list(log.messages("/numbers"))


# private _PROGRESS_STEP: progress comes every 8 MiB, with no public setting; 1 byte makes a small log report
def test_progress_is_reported_in_bytes_of_the_data_section(logs: dict[str, Path],
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    import starlog.io.verify_walk as verify_module

    monkeypatch.setattr(verify_module, "_PROGRESS_STEP", 1)  # every record
    done: list[int] = []
    report = verify_file(logs["raw"], on_progress=done.append)
    assert report.ok and len(done) > report.chunks  # a report before each record after the first
    assert done == sorted(set(done)) and 0 < done[0] and done[-1] < report.size
    result = CliRunner().invoke(cli, ["verify", str(logs["raw"]), "-q"])
    assert result.exit_code == 0 and result.output.startswith("OK: ")


def test_a_truncated_log_counts_the_channels_read_as_recover_keeps_them(logs: dict[str, Path], tmp_path: Path) -> None:
    from starlog.io.recover import recover_log

    data = logs["sim"].read_bytes()
    broken = tmp_path / "cut.mcap"
    broken.write_bytes(data[: int(len(data) * 0.8)])
    report = verify_log(broken)
    kept = recover_log(broken, tmp_path / "rec.mcap").kept_by_topic
    assert not report.ok and report.channels == len(kept) > 0 and report.messages >= sum(kept.values())
