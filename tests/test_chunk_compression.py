"""Chunk compression: every channel, camera frames and starlog's JSON alike, at the one fast zstd level."""

from __future__ import annotations

from pathlib import Path

import lz4.frame
import numpy as np
import zstandard
from hypothesis import given, settings
from hypothesis import strategies as st

from starlog.io import LogReader, LogWriter
from starlog.codecs import encode_json, encode_raw_image, json_message_type, protobuf_message_type
from starlog.io.chunks import ZSTD_LEVEL, decompress


def _chunks_by_topic(path: Path) -> dict[str, list[tuple[bytes, bytes]]]:
    """``topic -> [(compressed, uncompressed)]`` of every chunk (one channel per chunk)."""
    out: dict[str, list[tuple[bytes, bytes]]] = {}
    with LogReader(path) as log, open(path, "rb") as f:
        summary = log.files[-1].summary
        for ci in summary.chunk_indexes:
            (cid,) = ci.message_index_offsets
            f.seek(ci.chunk_start_offset + ci.chunk_length - ci.compressed_size)
            compressed = f.read(ci.compressed_size)
            data = bytes(decompress(ci.compression, compressed, ci.uncompressed_size))
            out.setdefault(summary.channels[cid].topic, []).append((compressed, data))
    return out


def test_every_chunk_is_compressed_at_the_log_level(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    path = tmp_path / "levels.mcap"
    with LogWriter(path, chunk_size=64 * 1024) as log:
        image = log.add_channel("/camera/image", protobuf_message_type("foxglove.RawImage"))
        info = log.add_channel("/camera/frame", json_message_type("starlog.FrameInfo"))
        for k in range(6):
            frame = rng.normal(200, 10, size=(64, 96)).astype(np.uint16)
            log.write(image, log_time=k + 1, data=encode_raw_image(frame, log_time=k + 1))
            log.write(info, log_time=k + 1, data=encode_json(
                {"frame": k, "width": 96, "height": 64, "encoding": "mono16", "bit_depth": 16, "source": ""}))
    chunks = _chunks_by_topic(path)
    assert ZSTD_LEVEL == 1
    for topic in ("/camera/image", "/camera/frame"):
        assert chunks[topic]
        for compressed, data in chunks[topic]:
            assert compressed == zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(data)
    with LogReader(path) as log:  # and the log reads back
        assert [index for index, _, _ in log.frames()] == list(range(6))


def _lz4_block_size(frame: bytes) -> int:
    """The maximum block size an lz4 frame declares (its descriptor's BD byte), in bytes."""
    assert frame[:4] == b"\x04\x22\x4d\x18"  # lz4 frame magic
    return 1 << (8 + 2 * ((frame[5] >> 4) & 0x7))


def test_frame_logs_are_written_in_lz4_of_one_mebibyte_blocks(tmp_path: Path) -> None:
    """simulate writes frames in lz4 (FRAME_COMPRESSION), in 1 MiB blocks: lz4's default 64 KiB blocks decode at
    half the speed."""
    from click.testing import CliRunner

    from starlog.cli import cli
    from starlog.cli.options import FRAME_COMPRESSION_DEFAULT
    from starlog.io.writer import FRAME_COMPRESSION

    assert FRAME_COMPRESSION_DEFAULT == FRAME_COMPRESSION == "lz4"
    path = tmp_path / "sim.mcap"
    result = CliRunner().invoke(cli, ["simulate", "-o", str(path), "--size", "512x512", "--frames", "20", "-q"])
    assert result.exit_code == 0, result.output
    chunks = _chunks_by_topic(path)
    assert len(chunks["/camera/image"]) > 1
    for topic in ("/camera/image", "/camera/frame", "/sim/truth"):
        for compressed, data in chunks[topic]:  # lz4 declares smaller blocks for what fits in one
            assert _lz4_block_size(compressed) == (1 << 20 if len(data) > 1 << 20 else _lz4_block_size(
                lz4.frame.compress(data, block_size=lz4.frame.BLOCKSIZE_MAX1MB)))
            assert lz4.frame.decompress(compressed) == data
    with LogReader(path) as log:
        assert [index for index, _, _ in log.frames()] == list(range(20))


def test_compression_option_keeps_the_choice_with_the_user(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from starlog.cli import cli

    for compression, expected in [("zstd", "zstd"), ("none", "")]:
        path = tmp_path / f"{compression}.mcap"
        result = CliRunner().invoke(cli, ["simulate", "-o", str(path), "--size", "64x64", "--frames", "3", "-q",
                                           "--compression", compression])
        assert result.exit_code == 0, result.output
        with LogReader(path) as log:
            assert {ci.compression for ci in log.files[-1].summary.chunk_indexes} == {expected}


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 2**63), st.integers(0, 2**63), st.binary(max_size=300)), min_size=1,
                max_size=20))
def test_a_chunk_is_built_as_the_mcap_writer_builds_it(messages: list[tuple[int, int, bytes]]) -> None:
    """An independent oracle: the records, time range and message index of the one chunk of a log written by the
    ``mcap`` library's own writer (no compression) are those starlog's chunk builder makes."""
    import io

    from mcap.opcode import Opcode
    from mcap.records import Channel, Schema
    from mcap.writer import CompressionType, Writer

    from starlog.io.chunks import ChunkBuilder, decode_chunk
    from starlog.io.layout import encode_record, parse_message_index
    from starlog.io.record_walk import walk_records

    out = io.BytesIO()
    writer = Writer(out, chunk_size=1 << 30, compression=CompressionType.NONE)
    writer.start()
    schema_id = writer.register_schema("s", "jsonschema", b"{}")
    channel_id = writer.register_channel("/t", "json", schema_id)
    for sequence, (log_time, publish_time, data) in enumerate(messages):
        writer.add_message(channel_id, log_time, data, publish_time, sequence)
    writer.finish()
    raw = out.getvalue()
    records = {opcode: body for _, opcode, _, body in walk_records(raw, 8, len(raw) - 8)  # between the magics
               if opcode in (Opcode.CHUNK, Opcode.MESSAGE_INDEX)}
    theirs = decode_chunk(records[Opcode.CHUNK])

    ours = ChunkBuilder()
    ours.add_record(encode_record(Schema(id=schema_id, name="s", encoding="jsonschema", data=b"{}")))
    ours.add_record(encode_record(Channel(id=channel_id, topic="/t", message_encoding="json", schema_id=schema_id,
                                          metadata={})))
    for sequence, (log_time, publish_time, data) in enumerate(messages):
        ours.add_message(channel_id, sequence, log_time, publish_time, data)
    data, indices, start, end = ours.take()
    assert bytes(data) == bytes(theirs.data) and (start, end) == (theirs.start, theirs.end)
    assert indices == dict([parse_message_index(records[Opcode.MESSAGE_INDEX])])
    assert ours.take()[0] == bytearray() and ours.num_messages == 0
