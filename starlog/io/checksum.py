"""CRC-32 of chunk bytes: MCAP's chunk and summary checksum (the zlib polynomial).

Every chunk is checksummed when it is written and again whenever it is read: 4 MB of image
chunk costs zlib about 1 ms, a fifth of its decompression. ISA-L (the ``isal`` package)
computes the same CRC with carry-less multiplication in about a tenth of that. zlib stays
the reference and is used wherever ``isal`` is not installed.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
import struct
from typing import BinaryIO

__all__ = ["crc32", "file_crc32", "footer_crc", "summary_crc"]

try:
    from isal.isal_zlib import crc32 as _isal_crc32
except ImportError:  # pragma: no cover - isal is a dependency; a platform without its wheel falls back
    _isal_crc32 = None

_CRC32: Callable[[bytes | memoryview, int], int] = _isal_crc32 or zlib.crc32


def crc32(data: bytes | bytearray | memoryview, value: int = 0) -> int:
    """``zlib.crc32(data, value)``, by ISA-L when it is installed (same result, unsigned 32-bit)."""
    return _CRC32(data, value)


def file_crc32(f: BinaryIO, offset: int, length: int, block: int = 1 << 20) -> int:
    """CRC-32 of ``length`` bytes of ``f`` from ``offset`` (fewer if the file ends), read a block at a time."""
    f.seek(offset)
    value = 0
    while length > 0:
        data = f.read(min(block, length))
        if not data:
            break
        value = crc32(data, value)
        length -= len(data)
    return value


_FOOTER_FIELDS = struct.Struct("<BQQQ")  # the footer's opcode (0x02), length (20) and its two offsets
_FOOTER_OPCODE, _FOOTER_LENGTH = 0x02, 20


def footer_crc(section_crc: int, summary_start: int, summary_offset_start: int) -> int:
    """The CRC an MCAP footer stores: that of the summary section (``section_crc``) continued over the
    footer's own opcode, length and two offsets."""
    return crc32(_FOOTER_FIELDS.pack(_FOOTER_OPCODE, _FOOTER_LENGTH, summary_start, summary_offset_start),
                 section_crc)


def summary_crc(f: BinaryIO, summary_start: int, summary_offset_start: int, footer: int) -> int:
    """:func:`footer_crc` of the summary section of ``f`` (from ``summary_start`` to the footer at ``footer``),
    read a block at a time."""
    return footer_crc(file_crc32(f, summary_start, footer - summary_start), summary_start, summary_offset_start)
