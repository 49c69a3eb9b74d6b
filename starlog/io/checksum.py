"""CRC-32 of chunk bytes: MCAP's chunk and summary checksum (the zlib polynomial).

Every chunk is checksummed when it is written and again whenever it is read: 4 MB of image
chunk costs zlib about 1 ms, a fifth of its decompression. ISA-L (the ``isal`` package)
computes the same CRC with carry-less multiplication in about a tenth of that. zlib stays
the reference and is used wherever ``isal`` is not installed.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from typing import BinaryIO

__all__ = ["crc32", "file_crc32"]

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
