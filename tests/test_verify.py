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

from starlog.cli import cli
from starlog.io import LogReader, LogWriter, encode_json, encode_raw_image, json_message_type, protobuf_message_type
from starlog.io import topics
from starlog.io.verify import verify_log
from starlog.stages import simulate_log
from starlog.stages.centroid import centroid_log
from tests.conftest import small_config
from tests.foreign_logs import write_foxglove_compressed, write_plain, write_ros1, write_ros2


def _verify_cli(path: Path) -> tuple[int, dict]:
    result = CliRunner().invoke(cli, ["verify", str(path), "--json"])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    return result.exit_code, json.loads(result.output)


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("verify")
    sim = d / "sim.mcap"
    simulate_log(small_config(n_frames=12), sim)
    cen = d / "cen.mcap"
    centroid_log(sim, cen, methods="MOMENT", options={"psf_sigma": 1.2})
    raw = d / "raw.mcap"
    with LogReader(sim) as log, LogWriter(raw, compression="none", chunk_size=4096) as w:  # uncompressed, small chunks
        ids: dict[str, int] = {}
        for schema, channel, message in log.raw_messages(log.topics):
            if channel.topic not in ids:
                from starlog.io.schemas import MessageType

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
        return log.summary.chunk_indexes[nth]


def damage_bad_magic(raw: Path, data: bytearray) -> None:
    data[0:4] = b"GIF8"


def damage_truncated(raw: Path, data: bytearray) -> None:
    del data[len(data) // 2:]


def damage_chunk_crc(raw: Path, data: bytearray) -> None:
    ci = _chunk(raw)
    data[ci.chunk_start_offset + ci.chunk_length - 10] ^= 0xFF  # inside the (uncompressed) records


def damage_chunk_decompress(cen: Path, data: bytearray) -> None:
    ci = _chunk(cen, 0)
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
    source = logs["cen"] if kind == "chunk_decompress" else logs["raw"]
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
