"""Chunk compression: every channel, camera frames and starlog's JSON alike, at the one fast zstd level."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import zstandard

from starlog.io import LogReader, LogWriter, encode_json, encode_raw_image, json_message_type, protobuf_message_type
from starlog.io.layout import decompress
from starlog.io.writer import ZSTD_LEVEL


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
