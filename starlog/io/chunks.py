"""Chunk contents: building one (the writer's open chunk of a channel, :class:`ChunkBuilder`), compressing
closed chunks (on a thread pool, handed on in order, :class:`CompressionQueue`), and opening one
(decompressed and CRC-checked, :func:`decode_chunk`).

The Chunk record itself is :func:`~starlog.io.layout.chunk_record` / :func:`~starlog.io.layout.chunk_header`.
"""

from __future__ import annotations

import io
import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

from starlog.io.checksum import crc32
from starlog.io.layout import chunk_header, message_record

__all__ = ["ZSTD_LEVEL", "ChunkBuilder", "ChunkContents", "CompressionQueue", "PendingChunk", "compress",
           "decode_chunk", "decompress"]

#: zstd level of every chunk. Camera frames: sensor noise leaves little for the match finder, so
#: level 3 makes 16-bit frames 5 % smaller than level 1 but costs twice the time to compress and a
#: third more to decompress (1024x1024 mono16: 7.1 against 5.3 ms per 4 MB chunk), and every stage
#: that reads frames pays the decompression. starlog's own channels are mostly JSON floats, and on
#: them level 1 is both faster and smaller than level 3 (2 MB pieces of a 512², 40-star log's
#: detections, centroids, tracks and annotations: 106-316 against 36-78 MB/s, 4-16 % smaller); only
#: the simulator's truth packs tighter at level 3 (88x against 61x), a few kB a second.
ZSTD_LEVEL = 1


class ChunkBuilder:
    """The open chunk of a channel: its records' bytes, its messages' time range and its message index entries
    (``(log_time, offset in the chunk)`` per channel)."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.message_indices: dict[int, list[tuple[int, int]]] = {}
        self.message_start_time = 0
        self.message_end_time = 0
        self.num_messages = 0

    def add_record(self, record: bytes) -> None:
        """Add a whole record (a schema or channel, :func:`encode_record`)."""
        self.data += record

    def add_message(self, channel_id: int, sequence: int, log_time: int, publish_time: int,
                    payload: bytes | memoryview) -> None:
        if self.num_messages == 0:
            self.message_start_time = self.message_end_time = log_time
        else:
            self.message_start_time = min(self.message_start_time, log_time)
            self.message_end_time = max(self.message_end_time, log_time)
        entries = self.message_indices.get(channel_id)
        if entries is None:
            entries = self.message_indices[channel_id] = []
        entries.append((log_time, len(self.data)))
        self.num_messages += 1
        self.data += message_record(channel_id, sequence, log_time, publish_time, len(payload))
        self.data += payload

    def take(self) -> tuple[bytearray, dict[int, list[tuple[int, int]]], int, int]:
        """The chunk's bytes, message indices, start and end time; the builder is empty again."""
        taken = self.data, self.message_indices, self.message_start_time, self.message_end_time
        self.data, self.message_indices = bytearray(), {}
        self.message_start_time = self.message_end_time = self.num_messages = 0
        return taken


def compress(data: bytes | bytearray, compression: str) -> tuple[bytes | bytearray, int]:
    """``data`` compressed (``"zstd"``, ``"lz4"``; anything else: as it is) and its CRC-32."""
    crc = crc32(data)
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(data), crc
    if compression == "lz4":
        import lz4.frame

        # 1 MiB blocks: python-lz4 decodes them at twice the speed of its default 64 KiB blocks (slower than
        # zstd) or of 4 MiB ones, for the same size (``python tools/bench_io.py``'s frame table)
        return lz4.frame.compress(data, block_size=lz4.frame.BLOCKSIZE_MAX1MB), crc
    return data, crc


@dataclass
class PendingChunk:
    """A closed chunk on its way to the file: its compression (the compressed bytes and the CRC of the
    uncompressed ones, when done), its uncompressed size, message indices and time range."""

    future: Future[tuple[bytes | bytearray, int]]
    uncompressed_size: int
    message_indices: dict[int, list[tuple[int, int]]]
    start_time: int
    end_time: int


class CompressionQueue:
    """Closed chunks compressed on a thread pool (zstd and lz4 release the GIL; with one worker, at once) and
    handed to ``write`` in the order they were closed, so the bytes written do not depend on the workers."""

    def __init__(self, compression: str, workers: int, write: Callable[[PendingChunk], object]) -> None:
        self.compression, self.workers, self._write = compression, workers, write
        self._pending: deque[PendingChunk] = deque()
        self._executor = ThreadPoolExecutor(max_workers=workers) if workers > 1 else None

    def put(self, data: bytes | bytearray, indices: dict[int, list[tuple[int, int]]], start: int, end: int, *,
            now: bool = False) -> None:
        """Queue a chunk's records for compression; ``now``: compress it here and write every queued chunk."""
        if self._executor is None or now:
            future: Future[tuple[bytes | bytearray, int]] = Future()
            future.set_result(compress(data, self.compression))
        else:
            future = self._executor.submit(compress, data, self.compression)
        self._pending.append(PendingChunk(future, len(data), indices, start, end))
        self.drain(all_of_them=now)

    def drain(self, *, all_of_them: bool) -> None:
        """Write the chunks whose compression is done, in order (``all_of_them``: every chunk, waiting for them;
        else at most twice the workers stay queued)."""
        limit = 0 if all_of_them else 2 * self.workers
        while self._pending and (len(self._pending) > limit or self._pending[0].future.done()):
            self._write(self._pending.popleft())

    def shutdown(self, *, cancel: bool = False) -> None:
        """Stop the workers (``cancel``: the chunks not yet compressed are dropped)."""
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=cancel)


@dataclass(frozen=True)
class ChunkContents:
    """A chunk record's header fields and its decompressed, CRC-checked records."""

    start: int
    end: int
    uncompressed_size: int
    crc: int
    compression: str
    compressed_size: int
    data: bytes | memoryview
    crc_checked: bool


_ZSTD = threading.local()  # a decompression context per thread (one is not safe to share between threads)


def _zstd_one_shot(data: bytes | memoryview, size: int) -> bytes | None:
    """Decompress a zstd frame that says it holds exactly ``size`` bytes in one call, reusing this thread's
    decompressor; None for anything else (the frame says another size or nothing, or does not decode)."""
    import zstandard

    decompressor = getattr(_ZSTD, "decompressor", None)
    if decompressor is None:
        decompressor = _ZSTD.decompressor = zstandard.ZstdDecompressor()
    try:
        if zstandard.frame_content_size(data) != size:
            return None
        return decompressor.decompress(data)
    except zstandard.ZstdError:
        return None


def decompress(compression: str, data: bytes | memoryview, size: int) -> bytes | memoryview:
    """Decompress at most ``size`` + 1 bytes (a damaged frame header cannot make us allocate more).

    A zstd chunk written whole (its frame header gives its size, as every MCAP writer's does) is
    decompressed in one call; any other, or one that fails to, goes through the stream reader,
    which reads the same bytes and gives the same errors. ``compression == ""`` returns ``data``.
    """
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard

        whole = _zstd_one_shot(data, size)
        if whole is not None:
            return whole
        with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data)) as reader:
            return reader.read(size + 1)
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=size + 1)
    raise ValueError(f"unsupported chunk compression {compression!r}")


def decode_chunk(body: bytes | memoryview, *, check_crc: bool = True) -> ChunkContents:
    """Parse a chunk record's body (after its opcode and length), decompress it and check its CRC
    (a stored CRC of 0 means none, as the format allows).

    Raises ``ValueError`` / ``struct.error`` (or the decompressor's error) naming what is wrong.
    """
    start, end, size, crc, compression, data_len, pos = chunk_header(body)
    data = decompress(compression, memoryview(body)[pos:], size)
    if len(data) != size:
        raise ValueError(f"it decompresses to {len(data)} bytes, not {size}")
    checked = check_crc and crc != 0
    if checked and crc32(data) != crc:
        raise ValueError(f"CRC mismatch (stored {crc:#010x}, computed {crc32(data):#010x})")
    return ChunkContents(start, end, size, crc, compression, int(data_len), data, checked)
