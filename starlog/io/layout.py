"""Where things are in an MCAP file: the magic bytes, the footer, the end of the data section."""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import BinaryIO

from mcap.opcode import Opcode

from starlog.errors import CorruptLogError, NotMcapError, TruncatedLogError

__all__ = ["MCAP_MAGIC", "FOOTER_RECORD_LEN", "DATA_END_RECORD_LEN", "locate_data_end"]

MCAP_MAGIC = b"\x89MCAP0\r\n"
FOOTER_RECORD_LEN = 1 + 8 + 20
DATA_END_RECORD_LEN = 1 + 8 + 4


def locate_data_end(path: Path, f: BinaryIO) -> int:
    """Offset of the DataEnd record of a complete MCAP file (the end of its data section).

    Raises :class:`TruncatedLogError` when the file has no valid footer.
    """
    size = f.seek(0, os.SEEK_END)
    f.seek(0)
    head = f.read(len(MCAP_MAGIC))
    if head != MCAP_MAGIC[: len(head)]:  # an empty file or a cut-off magic is a truncated log, not another format
        raise NotMcapError(path)
    min_size = 2 * len(MCAP_MAGIC) + FOOTER_RECORD_LEN + DATA_END_RECORD_LEN
    if size < min_size:
        raise TruncatedLogError(path, f"only {size} bytes, shorter than any complete MCAP file")
    f.seek(size - len(MCAP_MAGIC) - FOOTER_RECORD_LEN)
    tail = f.read(FOOTER_RECORD_LEN + len(MCAP_MAGIC))
    if tail[-len(MCAP_MAGIC):] != MCAP_MAGIC or tail[0] != Opcode.FOOTER:
        raise TruncatedLogError(path, "no footer at the end of the file")
    (summary_start,) = struct.unpack_from("<Q", tail, 9)
    if summary_start:
        data_end = summary_start - DATA_END_RECORD_LEN
    else:
        data_end = size - len(MCAP_MAGIC) - FOOTER_RECORD_LEN - DATA_END_RECORD_LEN
    f.seek(data_end)
    record = f.read(DATA_END_RECORD_LEN)
    if len(record) != DATA_END_RECORD_LEN or record[0] != Opcode.DATA_END or struct.unpack_from("<Q", record, 1)[0] != 4:
        raise CorruptLogError(path, f"no DataEnd record at offset {data_end} where the footer says the summary starts")
    return data_end
