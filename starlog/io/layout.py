"""The MCAP file layout, defined once: record formats, the footer, the record walkers, the chunk decoder.

An MCAP file is ``magic, header, data section records..., DataEnd, summary section, summary
offsets, footer, magic``; every record is ``opcode (u8), body length (u64), body``. Every module
of the log layer reads and writes records through the names here.
"""

from __future__ import annotations

import io
import os
import struct
import threading
from collections.abc import Container, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Message

from starlog.errors import CorruptLogError, NotMcapError, TruncatedLogError
from starlog.io.checksum import crc32, file_crc32

__all__ = [
    "CHUNK_HEADER",
    "DATA_END",
    "DATA_END_RECORD_LEN",
    "FOOTER",
    "FOOTER_RECORD_LEN",
    "MAGIC",
    "MESSAGE_HEADER",
    "MESSAGE_INDEX_BODY",
    "MESSAGE_INDEX_ENTRY",
    "RECORD_HEADER",
    "ChunkContents",
    "Footer",
    "RecordOverrun",
    "decode_chunk",
    "decompress",
    "footer_crc",
    "iter_records",
    "locate_data_end",
    "chunk_record",
    "message_index_record",
    "parse_message_index",
    "parse_record",
    "read_footer",
    "summary_crc",
    "walk_records",
]

MAGIC = b"\x89MCAP0\r\n"
RECORD_HEADER = struct.Struct("<BQ")  # opcode, body length
MESSAGE_HEADER = struct.Struct("<HIQQ")  # channel id, sequence, log_time, publish_time
CHUNK_HEADER = struct.Struct("<QQQI")  # message start time, end time, uncompressed size, uncompressed CRC
MESSAGE_INDEX_BODY = struct.Struct("<HI")  # a Message Index record's body: channel id, bytes of the pairs
MESSAGE_INDEX_ENTRY = struct.Struct("<QQ")  # log_time, offset of the message in the uncompressed chunk
FOOTER = struct.Struct("<BQQQI")  # opcode, length (20), summary start, summary offset start, summary CRC
FOOTER_RECORD_LEN = FOOTER.size
DATA_END = struct.Struct("<BQI")  # opcode, length (4), CRC of the data section (0: none)
DATA_END_RECORD_LEN = DATA_END.size


@dataclass(frozen=True)
class Footer:
    """The footer of a complete MCAP file: where its summary starts (0: none) and the summary's CRC (0: none)."""

    summary_start: int
    summary_offset_start: int
    summary_crc: int
    offset: int  # of the footer record
    file_size: int


def read_footer(path: Path, f: BinaryIO) -> Footer:
    """The footer of ``f``. Raises :class:`NotMcapError` (no magic at the start) or :class:`TruncatedLogError`."""
    size = f.seek(0, os.SEEK_END)
    f.seek(0)
    head = f.read(len(MAGIC))
    if head != MAGIC[: len(head)]:  # an empty file or a cut-off magic is a truncated log, not another format
        raise NotMcapError(path)
    if size < 2 * len(MAGIC) + FOOTER_RECORD_LEN + DATA_END_RECORD_LEN:
        raise TruncatedLogError(path, f"only {size} bytes, shorter than any complete MCAP file")
    offset = size - len(MAGIC) - FOOTER_RECORD_LEN
    f.seek(offset)
    tail = f.read(FOOTER_RECORD_LEN + len(MAGIC))
    if tail[-len(MAGIC):] != MAGIC or tail[0] != Opcode.FOOTER:
        raise TruncatedLogError(path, "no footer at the end of the file")
    _, _, summary_start, summary_offset_start, crc = FOOTER.unpack_from(tail)
    return Footer(summary_start, summary_offset_start, crc, offset, size)


def footer_crc(section_crc: int, summary_start: int, summary_offset_start: int) -> int:
    """The CRC an MCAP footer stores: that of the summary section (``section_crc``) continued over the
    footer's own opcode, length and two offsets."""
    return crc32(FOOTER.pack(Opcode.FOOTER, 20, summary_start, summary_offset_start, 0)[:-4], section_crc)


def summary_crc(f: BinaryIO, footer: Footer) -> int:
    """:func:`footer_crc` of the summary section of ``f`` (from its start to the footer), read a block at a time."""
    return footer_crc(file_crc32(f, footer.summary_start, footer.offset - footer.summary_start),
                      footer.summary_start, footer.summary_offset_start)


def locate_data_end(path: Path, f: BinaryIO) -> int:
    """Offset of the DataEnd record of a complete MCAP file (the end of its data section).

    Raises :class:`TruncatedLogError` when the file has no valid footer, :class:`CorruptLogError`
    when no DataEnd record is where the footer says the summary starts.
    """
    footer = read_footer(path, f)
    data_end = (footer.summary_start if footer.summary_start else footer.offset) - DATA_END_RECORD_LEN
    f.seek(max(data_end, 0))
    record = f.read(DATA_END_RECORD_LEN)
    if data_end < len(MAGIC) or len(record) != DATA_END_RECORD_LEN or DATA_END.unpack(record)[:2] != (
            Opcode.DATA_END, 4):
        raise CorruptLogError(path, f"no DataEnd record at offset {data_end} where the footer says the summary starts")
    return data_end


class RecordOverrun(ValueError):
    """A record runs past the end of its section (``cut_header``: not even its nine-byte header fits)."""

    def __init__(self, offset: int, detail: str, *, cut_header: bool = False) -> None:
        self.offset = offset
        self.cut_header = cut_header
        super().__init__(detail)


def iter_records(data: bytes | memoryview, base: int = 0) -> Iterator[tuple[int, int, int, int]]:
    """``(offset, opcode, body_start, body_length)`` of each record in ``data`` (offsets from ``base``;
    ``body_start`` indexes ``data``). Raises :class:`RecordOverrun` when a record runs past its end."""
    pos, size = 0, len(data)
    while pos < size:
        if pos + RECORD_HEADER.size > size:
            raise RecordOverrun(base + pos, f"a record header at offset {base + pos} is cut off", cut_header=True)
        opcode, length = RECORD_HEADER.unpack_from(data, pos)
        body = pos + RECORD_HEADER.size
        if body + length > size:
            raise RecordOverrun(base + pos, f"the record at offset {base + pos} (opcode {opcode:#04x}, {length} "
                                            "bytes) runs past the end of its section")
        yield base + pos, opcode, body, length
        pos = body + length


def walk_records(f: BinaryIO, start: int, end: int, *, bodies: Container[int] | None = None,
                 block: int = 1 << 20) -> Iterator[tuple[int, int, int, bytes | None]]:
    """``(offset, opcode, length, body)`` of each top-level record of ``f`` from ``start`` to ``end``.

    The file is read a block at a time (a section is never held whole). ``body`` is read for the
    opcodes in ``bodies`` (every record when None) and is None for the others, whose bytes are
    skipped unread when they are large. Raises :class:`RecordOverrun` for a record that runs past ``end``.
    """
    buffer, base, pos = b"", start, start  # buffer: the file's bytes from base

    def have(upto: int) -> None:
        nonlocal buffer, base
        if upto > base + len(buffer):
            keep = buffer[pos - base:] if pos < base + len(buffer) else b""
            f.seek(pos + len(keep))
            buffer = keep + f.read(max(block, upto - pos - len(keep)))
            base = pos

    while pos < end:
        body = pos + RECORD_HEADER.size
        if body > end:
            raise RecordOverrun(pos, f"a record header at offset {pos} is cut off", cut_header=True)
        have(body)
        if len(buffer) < body - base:
            raise RecordOverrun(pos, f"a record header at offset {pos} is cut off", cut_header=True)
        opcode, length = RECORD_HEADER.unpack_from(buffer, pos - base)
        if body + length > end:
            raise RecordOverrun(pos, f"the record at offset {pos} (opcode {opcode:#04x}, {length} bytes) runs past "
                                     "the end of its section")
        data: bytes | None = None
        if bodies is None or opcode in bodies:
            have(body + length)
            data = buffer[body - base: body + length - base]
            if len(data) != length:
                raise RecordOverrun(pos, f"the file ends inside the record at offset {pos}")
        yield pos, opcode, length, data
        pos = body + length


def parse_record(body: bytes | memoryview, record_type: Any) -> Any:
    """A record's body parsed as ``record_type`` (a class of :mod:`mcap.records`, e.g. ``Schema``).

    Raises the parser's errors (``struct.error``, ``EOFError``, ``UnicodeDecodeError``, ...) for a damaged body.
    """
    if record_type is Message:
        return Message.read(ReadDataStream(io.BytesIO(body)), len(body))
    return record_type.read(ReadDataStream(io.BytesIO(body)))


def message_index_record(channel_id: int, entries: list[tuple[int, int]]) -> bytes:
    """A Message Index record: ``(log_time, offset in the uncompressed chunk)`` of each message of a channel."""
    array = b"".join(MESSAGE_INDEX_ENTRY.pack(t, o) for t, o in entries)
    return (RECORD_HEADER.pack(Opcode.MESSAGE_INDEX, MESSAGE_INDEX_BODY.size + len(array))
            + MESSAGE_INDEX_BODY.pack(channel_id, len(array)) + array)


def parse_message_index(body: bytes | memoryview) -> tuple[int, list[tuple[int, int]]]:
    """A Message Index record's body (after its opcode and length): its channel id and its ``(log_time, offset)``
    entries. Raises ``ValueError`` / ``struct.error`` when the entries do not fill the record."""
    channel_id, array_len = MESSAGE_INDEX_BODY.unpack_from(body, 0)
    if MESSAGE_INDEX_BODY.size + array_len != len(body) or array_len % MESSAGE_INDEX_ENTRY.size:
        raise ValueError(f"its array length {array_len} does not fit its record")
    return channel_id, list(MESSAGE_INDEX_ENTRY.iter_unpack(body[MESSAGE_INDEX_BODY.size:]))


def chunk_record(start: int, end: int, uncompressed_size: int, crc: int, compression: str,
                 data: bytes | memoryview) -> list[bytes | memoryview]:
    """The pieces of a Chunk record holding ``data`` (compressed with ``compression``, ``""`` for none)."""
    name = compression.encode()
    body_len = CHUNK_HEADER.size + 4 + len(name) + 8 + len(data)
    return [RECORD_HEADER.pack(Opcode.CHUNK, body_len), CHUNK_HEADER.pack(start, end, uncompressed_size, crc),
            struct.pack("<I", len(name)) + name + struct.pack("<Q", len(data)), data]


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


def chunk_header(body: bytes | memoryview, *, whole: bool = True) -> tuple[int, int, int, int, str, int, int]:
    """``(start, end, uncompressed_size, crc, compression, compressed_size, data_offset)`` of a chunk record's
    body (after its opcode and length; with ``whole=False``, only its start). Raises ``ValueError`` /
    ``struct.error`` when they do not fit it (the compressed data must end the record, for a whole body)."""
    start, end, size, crc = CHUNK_HEADER.unpack_from(body, 0)
    pos = CHUNK_HEADER.size
    (name_len,) = struct.unpack_from("<I", body, pos)
    compression = bytes(body[pos + 4: pos + 4 + name_len]).decode()
    pos += 4 + name_len
    (data_len,) = struct.unpack_from("<Q", body, pos)
    pos += 8
    if whole and pos + data_len != len(body):
        raise ValueError(f"its data length {data_len} does not fit its record")
    return start, end, size, crc, compression, data_len, pos


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
