"""The MCAP record layouts, defined once, and the footer reader.

An MCAP file is ``magic, header, data section records..., DataEnd, summary section, summary
offsets, footer, magic``; every record is ``opcode (u8), body length (u64), body``. The fixed
parts of the records starlog reads or writes field by field are the ``struct`` layouts here (the
numpy layout of a whole Chunk Index record is derived from them, :func:`chunk_index_dtype`); the
records starlog only passes through (schemas, channels, metadata, ...) are parsed and written by
``mcap.records`` (:func:`parse_record`). Every module of the log layer reads and writes records
through the names here; :mod:`starlog.io.record_walk` walks a section record by record.
"""

from __future__ import annotations

import io
import os
import struct
from dataclasses import dataclass
from typing import Any, BinaryIO

import numpy as np
from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.opcode import Opcode
from mcap.records import Message

from starlog.errors import CorruptLogError, LogError, NotMcapError, TruncatedLogError
from starlog.io.checksum import crc32, file_crc32

__all__ = [
    "CHUNK_HEADER",
    "CHUNK_INDEX_HEAD",
    "CHUNK_INDEX_PAIR",
    "CHUNK_INDEX_SIZES",
    "CHUNK_INDEX_TAIL_MIN",
    "DATA_END",
    "DATA_END_RECORD_LEN",
    "FOOTER",
    "FOOTER_RECORD_LEN",
    "MAGIC",
    "MESSAGE_HEADER",
    "MESSAGE_INDEX_BODY",
    "MESSAGE_INDEX_ENTRY",
    "RECORD_HEADER",
    "U32",
    "U64",
    "Footer",
    "FooterError",
    "chunk_header",
    "chunk_index_dtype",
    "chunk_index_record",
    "chunk_record",
    "encode_record",
    "footer_crc",
    "locate_data_end",
    "message_index_record",
    "message_record",
    "parse_chunk_index",
    "parse_message_index",
    "parse_record",
    "read_footer",
    "summary_crc",
]

MAGIC = b"\x89MCAP0\r\n"
U32 = struct.Struct("<I")
U64 = struct.Struct("<Q")
RECORD_HEADER = struct.Struct("<BQ")  # opcode, body length
MESSAGE_HEADER = struct.Struct("<HIQQ")  # channel id, sequence, log_time, publish_time
CHUNK_HEADER = struct.Struct("<QQQI")  # message start time, end time, uncompressed size, uncompressed CRC
MESSAGE_INDEX_BODY = struct.Struct("<HI")  # a Message Index record's body: channel id, bytes of the pairs
MESSAGE_INDEX_ENTRY = struct.Struct("<QQ")  # log_time, offset of the message in the uncompressed chunk
#: A Chunk Index record's body: these fields, ``pairs_bytes`` of :data:`CHUNK_INDEX_PAIR`, the message index
#: length (u64), the compression name (u32 length, bytes) and :data:`CHUNK_INDEX_SIZES`.
CHUNK_INDEX_HEAD = struct.Struct("<QQQQI")  # message start time, end time, chunk offset, chunk length, pairs_bytes
CHUNK_INDEX_PAIR = struct.Struct("<HQ")  # channel id, offset of its message index record
CHUNK_INDEX_SIZES = struct.Struct("<QQ")  # compressed size, uncompressed size
CHUNK_INDEX_TAIL_MIN = U64.size + U32.size + CHUNK_INDEX_SIZES.size  # what follows the pairs, for an empty name
FOOTER = struct.Struct("<BQQQI")  # opcode, length (20), summary start, summary offset start, summary CRC
FOOTER_RECORD_LEN = FOOTER.size
DATA_END = struct.Struct("<BQI")  # opcode, length (4), CRC of the data section (0: none)
DATA_END_RECORD_LEN = DATA_END.size
#: The shortest complete MCAP file: the two magics, a DataEnd record and the footer.
SHORTEST_FILE = 2 * len(MAGIC) + FOOTER_RECORD_LEN + DATA_END_RECORD_LEN

_NUMPY_TYPES = {"B": "u1", "H": "<u2", "I": "<u4", "Q": "<u8"}


def _dtype_fields(layout: struct.Struct, *names: str) -> list[tuple[str, str]]:
    """The fields of a ``struct`` layout as numpy fields named ``names``."""
    return [(name, _NUMPY_TYPES[code]) for name, code in zip(names, layout.format.lstrip("<"), strict=True)]


def chunk_index_dtype(pairs: int, name_length: int) -> np.dtype[Any]:
    """The layout of a whole Chunk Index record (its header included) with ``pairs`` message index offsets and a
    compression name of ``name_length`` bytes, as a numpy dtype whose fields are named as ``ChunkIndex``'s."""
    return np.dtype([
        *_dtype_fields(RECORD_HEADER, "opcode", "length"),
        *_dtype_fields(CHUNK_INDEX_HEAD, "message_start_time", "message_end_time", "chunk_start_offset",
                       "chunk_length", "pairs_bytes"),
        ("pairs", _dtype_fields(CHUNK_INDEX_PAIR, "channel", "offset"), (pairs,)),
        *_dtype_fields(U64, "message_index_length"), *_dtype_fields(U32, "name_length"),
        *([("name", f"V{name_length}")] if name_length else []),
        *_dtype_fields(CHUNK_INDEX_SIZES, "compressed_size", "uncompressed_size"),
    ])


# ---------------------------------------------------------------------- the footer
@dataclass(frozen=True)
class Footer:
    """The footer of a complete MCAP file: where its summary starts (0: none) and the summary's CRC (0: none)."""

    summary_start: int
    summary_offset_start: int
    summary_crc: int
    offset: int  # of the footer record
    file_size: int
    length: int = 20  # the footer record's length field (20 in a valid file)


class FooterError(ValueError):
    """Why the end of a file is not a footer: ``kind`` is ``"not_mcap"`` (no MCAP magic at its start),
    ``"truncated"`` (too short, or no magic at its end) or ``"no_footer"`` (no footer record before the
    closing magic)."""

    def __init__(self, kind: str, detail: str, offset: int) -> None:
        self.kind, self.detail, self.offset = kind, detail, offset
        super().__init__(detail)

    def log_error(self, path: str | os.PathLike[str]) -> LogError:
        """The error a reader raises for it: :class:`NotMcapError` or :class:`TruncatedLogError`."""
        return NotMcapError(path) if self.kind == "not_mcap" else TruncatedLogError(path, self.detail)


def read_footer(f: BinaryIO) -> Footer:
    """The footer of the MCAP file ``f``. Raises :class:`FooterError` when it has none.

    A file that starts with a part of the magic (an empty file, say) is a cut-off MCAP file, not another format.
    """
    size = f.seek(0, os.SEEK_END)
    f.seek(0)
    head = f.read(len(MAGIC))
    if head != MAGIC[: len(head)]:
        raise FooterError("not_mcap", "the file does not start with the MCAP magic bytes; is it an MCAP file?", 0)
    if size < SHORTEST_FILE:
        raise FooterError("truncated", f"only {size} bytes: shorter than any complete MCAP file", size)
    offset = size - len(MAGIC) - FOOTER_RECORD_LEN
    f.seek(offset)
    tail = f.read(FOOTER_RECORD_LEN + len(MAGIC))
    if tail[-len(MAGIC):] != MAGIC:
        raise FooterError("truncated", "the file does not end with the MCAP magic bytes: cut off or never finished",
                          size - len(MAGIC))
    opcode, length, summary_start, summary_offset_start, crc = FOOTER.unpack_from(tail)
    if opcode != Opcode.FOOTER:
        raise FooterError("no_footer", f"no footer record before the closing magic (opcode {opcode:#04x})", offset)
    return Footer(summary_start, summary_offset_start, crc, offset, size, length)


def footer_crc(section_crc: int, summary_start: int, summary_offset_start: int) -> int:
    """The CRC an MCAP footer stores: that of the summary section (``section_crc``) continued over the
    footer's own opcode, length and two offsets."""
    return crc32(FOOTER.pack(Opcode.FOOTER, 20, summary_start, summary_offset_start, 0)[:-4], section_crc)


def summary_crc(f: BinaryIO, footer: Footer) -> int:
    """:func:`footer_crc` of the summary section of ``f`` (from its start to the footer), read a block at a time."""
    return footer_crc(file_crc32(f, footer.summary_start, footer.offset - footer.summary_start),
                      footer.summary_start, footer.summary_offset_start)


def locate_data_end(path: str | os.PathLike[str], f: BinaryIO, footer: Footer) -> int:
    """Offset of the DataEnd record of the complete MCAP file ``f`` (the end of its data section), whose footer
    is ``footer``. Raises :class:`CorruptLogError` when no DataEnd record is where the footer says the summary
    starts."""
    data_end = (footer.summary_start if footer.summary_start else footer.offset) - DATA_END_RECORD_LEN
    f.seek(max(data_end, 0))
    record = f.read(DATA_END_RECORD_LEN)
    if data_end < len(MAGIC) or len(record) != DATA_END_RECORD_LEN or DATA_END.unpack(record)[:2] != (
            Opcode.DATA_END, 4):
        raise CorruptLogError(path, f"no DataEnd record at offset {data_end} where the footer says the summary starts")
    return data_end


# ---------------------------------------------------------------------- records
class _StrictBytes(io.BytesIO):
    """A record's bytes whose ``read`` refuses to come back short (``mcap``'s parsers do not check)."""

    def read(self, size: int | None = -1) -> bytes:
        data = super().read(size)
        if size is not None and size >= 0 and len(data) != size:
            raise ValueError(f"a record is cut short ({len(data)} of {size} bytes)")
        return data


def parse_record(body: bytes | memoryview, record_type: Any, *, strict: bool = False) -> Any:
    """A record's body parsed as ``record_type`` (a class of :mod:`mcap.records`, e.g. ``Schema``); ``strict``:
    a field that runs past the body is an error, not cut short.

    Raises the parser's errors (``struct.error``, ``EOFError``, ``UnicodeDecodeError``, ...) for a damaged body.
    """
    stream = ReadDataStream(_StrictBytes(bytes(body)) if strict else io.BytesIO(body))
    if record_type is Message:
        return Message.read(stream, len(body))
    return record_type.read(stream)


def encode_record(record: Any) -> bytes:
    """A record of :mod:`mcap.records` (``Schema``, ``Channel``, ...) as the bytes of an MCAP record."""
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


def message_record(channel_id: int, sequence: int, log_time: int, publish_time: int, length: int) -> bytes:
    """The header and fixed fields of a Message record whose payload is ``length`` bytes (the payload follows)."""
    return (RECORD_HEADER.pack(Opcode.MESSAGE, MESSAGE_HEADER.size + length)
            + MESSAGE_HEADER.pack(channel_id, sequence, log_time, publish_time))


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
                 data: bytes | bytearray | memoryview) -> list[bytes | bytearray | memoryview]:
    """The pieces of a Chunk record holding ``data`` (compressed with ``compression``, ``""`` for none)."""
    name = compression.encode()
    body_len = CHUNK_HEADER.size + U32.size + len(name) + U64.size + len(data)
    return [RECORD_HEADER.pack(Opcode.CHUNK, body_len), CHUNK_HEADER.pack(start, end, uncompressed_size, crc),
            U32.pack(len(name)) + name + U64.pack(len(data)), data]


def chunk_header(body: bytes | memoryview, *, whole: bool = True) -> tuple[int, int, int, int, str, int, int]:
    """``(start, end, uncompressed_size, crc, compression, compressed_size, data_offset)`` of a chunk record's
    body (after its opcode and length; with ``whole=False``, only its start). Raises ``ValueError`` /
    ``struct.error`` when they do not fit it (the compressed data must end the record, for a whole body)."""
    start, end, size, crc = CHUNK_HEADER.unpack_from(body, 0)
    pos = CHUNK_HEADER.size
    (name_len,) = U32.unpack_from(body, pos)
    compression = bytes(body[pos + U32.size: pos + U32.size + name_len]).decode()
    pos += U32.size + name_len
    (data_len,) = U64.unpack_from(body, pos)
    pos += U64.size
    if whole and pos + data_len != len(body):
        raise ValueError(f"its data length {data_len} does not fit its record")
    return start, end, size, crc, compression, data_len, pos


#: A chunk index's fields, as :func:`parse_chunk_index` gives them: start and end time, chunk offset and
#: length, message index length, compressed and uncompressed size, compression, channel ids, index offsets.
ChunkIndexFields = tuple[int, int, int, int, int, int, int, str, list[int], list[int]]


def parse_chunk_index(body: bytes | memoryview) -> ChunkIndexFields:
    """A Chunk Index record's body (after its opcode and length), field by field. Raises ``ValueError`` /
    ``struct.error`` naming what does not fit."""
    start, end, offset, length, pairs_bytes = CHUNK_INDEX_HEAD.unpack_from(body)
    q = CHUNK_INDEX_HEAD.size
    if pairs_bytes % CHUNK_INDEX_PAIR.size:
        raise ValueError(f"a chunk index's message index offsets take {pairs_bytes} bytes, not a multiple of "
                         f"{CHUNK_INDEX_PAIR.size} (a channel id and an offset each)")
    if q + pairs_bytes + CHUNK_INDEX_TAIL_MIN > len(body):
        raise ValueError(f"a chunk index's message index offsets take {pairs_bytes} bytes, which do not fit "
                         f"its record of {len(body)}")
    pairs = list(CHUNK_INDEX_PAIR.iter_unpack(body[q:q + pairs_bytes]))
    q += pairs_bytes
    (index_length,) = U64.unpack_from(body, q)
    (name_length,) = U32.unpack_from(body, q + U64.size)
    q += U64.size + U32.size
    if q + name_length + CHUNK_INDEX_SIZES.size > len(body):
        raise ValueError(f"a chunk index's compression name of {name_length} bytes does not fit its record")
    name = bytes(body[q:q + name_length]).decode()
    compressed, uncompressed = CHUNK_INDEX_SIZES.unpack_from(body, q + name_length)
    return (start, end, offset, length, index_length, compressed, uncompressed, name,
            [cid for cid, _ in pairs], [at for _, at in pairs])


def chunk_index_record(start: int, end: int, offset: int, length: int, index_length: int, compressed: int,
                       uncompressed: int, name: bytes, pairs: bytes) -> bytes:
    """A Chunk Index record (header included); ``pairs``: its :data:`CHUNK_INDEX_PAIR` entries, packed."""
    body = b"".join((CHUNK_INDEX_HEAD.pack(start, end, offset, length, len(pairs)), pairs, U64.pack(index_length),
                     U32.pack(len(name)), name, CHUNK_INDEX_SIZES.pack(compressed, uncompressed)))
    return RECORD_HEADER.pack(Opcode.CHUNK_INDEX, len(body)) + body
