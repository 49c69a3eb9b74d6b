"""The summary section: the one parser of it (read a block at a time, its chunk indexes stored by column), and
its writer.

As ``mcap``'s own summary reader, but the chunk indexes go into a
:class:`~starlog.io.chunk_indexes.ChunkIndexTable` (runs of records of one layout parsed at once)
and the section is never held whole. :class:`~starlog.io.mcap_file.McapFile` opens a file with it,
``starlog recover`` takes schemas and channels from it, and ``starlog verify`` checks what it
parsed (asking for where each record lies, :class:`SummarySection`). :func:`write_summary` writes
one as it is made, for :class:`~starlog.io.writer.LogWriter`.
"""

from __future__ import annotations

from array import array
from collections.abc import Callable
from typing import Any, BinaryIO

from mcap.opcode import Opcode
from mcap.records import AttachmentIndex, Channel, Footer, MetadataIndex, Schema, Statistics, SummaryOffset
from mcap.summary import Summary

from starlog.io.checksum import crc32
from starlog.io.chunk_indexes import ChunkIndexTable
from starlog.io.layout import MAGIC, RECORD_HEADER, encode_record, footer_crc, parse_record, read_footer
from starlog.io.record_walk import walk_records

__all__ = ["SummarySection", "read_file_summary", "read_summary", "write_summary"]

#: The records a summary keeps, by opcode (chunk indexes aside; the rest, e.g. summary offsets, are skipped).
_KEPT: dict[int, Any] = {Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel, Opcode.STATISTICS: Statistics,
                         Opcode.ATTACHMENT_INDEX: AttachmentIndex, Opcode.METADATA_INDEX: MetadataIndex}


class SummarySection:
    """A summary section as it is parsed: the :class:`~mcap.summary.Summary` (its chunk indexes a
    :class:`ChunkIndexTable`) and, with ``where``, the offsets of its chunk index and metadata index records and
    its summary offset records. What was parsed before a damaged record stays."""

    def __init__(self, *, where: bool = False) -> None:
        self.summary = Summary()
        self.table = ChunkIndexTable()
        self.summary.chunk_indexes = self.table  # type: ignore[assignment]  # a sequence of ChunkIndex, by column
        self.where = where
        self.chunk_index_offsets = array("Q")  # of each chunk index record (with ``where``)
        self.metadata_index_offsets: list[int] = []  # of each metadata index record (with ``where``)
        self.summary_offsets: list[tuple[int, SummaryOffset]] = []  # with ``where``

    def read(self, f: BinaryIO, start: int, end: int | None = None, *, block: int = 1 << 20) -> None:
        """Parse the records of ``f`` from ``start`` to ``end`` (None: up to a footer record, which must come).

        Raises ``ValueError`` or ``struct.error`` for a damaged or cut section (``mcap``'s errors for a
        damaged record of another kind than a chunk index).
        """
        wanted = {*_KEPT, Opcode.SUMMARY_OFFSET} if self.where else _KEPT
        for offset, opcode, length, body in walk_records(f, start, end, bodies=wanted, runs=(Opcode.CHUNK_INDEX,),
                                                         block=block):
            if opcode == Opcode.FOOTER and end is None:
                return
            if opcode == Opcode.CHUNK_INDEX:
                self._chunk_indexes(offset, RECORD_HEADER.size + length, body)
            elif body is not None:
                self._record(offset, opcode, parse_record(body, _KEPT.get(opcode, SummaryOffset), strict=True))
        if end is None:
            raise ValueError("the summary section ends without a footer")

    def _chunk_indexes(self, offset: int, size: int, records: Any) -> None:
        before = len(self.table)
        try:
            self.table.append_records(records)
        finally:
            if self.where:
                self.chunk_index_offsets.extend(range(offset, offset + (len(self.table) - before) * size, size))

    def _record(self, offset: int, opcode: int, record: Any) -> None:
        summary = self.summary
        if opcode == Opcode.STATISTICS:
            summary.statistics = record
        elif opcode == Opcode.SCHEMA:
            summary.schemas[record.id] = record
        elif opcode == Opcode.CHANNEL:
            summary.channels[record.id] = record
        elif opcode == Opcode.ATTACHMENT_INDEX:
            summary.attachment_indexes.append(record)
        elif opcode == Opcode.METADATA_INDEX:
            summary.metadata_indexes.append(record)
            if self.where:
                self.metadata_index_offsets.append(offset)
        else:
            self.summary_offsets.append((offset, record))


def read_summary(f: BinaryIO, start: int, end: int | None = None, *, block: int = 1 << 20) -> Summary:
    """The summary section of ``f`` from ``start`` to ``end`` (None: up to its footer record), as
    :meth:`SummarySection.read` parses it."""
    section = SummarySection()
    section.read(f, start, end, block=block)
    return section.summary


def read_file_summary(f: BinaryIO) -> Summary | None:
    """The summary of the MCAP file ``f`` (found through its footer); None when it has none. Raises
    :class:`~starlog.io.layout.FooterError` when the file has no footer, and as :func:`read_summary`."""
    footer = read_footer(f)
    if footer.summary_start == 0:
        return None
    return read_summary(f, footer.summary_start, footer.offset)



# ---------------------------------------------------------------------- writing
class _SummarySink:
    """The summary section written as it is made (a few MiB at a time), with its CRC and length: the summary of
    an hour-long log (millions of chunk indexes) is never held whole."""

    _FLUSH_AT = 4 << 20

    def __init__(self, write: Callable[[bytes], object]) -> None:
        self._write = write
        self._parts: list[bytes] = []
        self._pending = 0
        self.count = 0
        self.crc = 0

    def write(self, data: bytes) -> None:
        self._parts.append(data)
        self._pending += len(data)
        self.count += len(data)
        if self._pending >= self._FLUSH_AT:
            self.flush()

    def write_records(self, records: list[Any]) -> None:
        """MCAP records (objects of ``mcap.records``), serialised."""
        self.write(b"".join(map(encode_record, records)))

    def flush(self) -> None:
        data = b"".join(self._parts)
        self.crc = crc32(data, self.crc)  # ISA-L when installed, as for the chunks
        self._write(data)
        self._parts, self._pending = [], 0


def write_summary(write: Callable[[bytes], object], summary_start: int, schemas: list[Schema], channels: list[Channel],
                  statistics: Statistics, chunk_indexes: ChunkIndexTable, attachment_indexes: list[AttachmentIndex],
                  metadata_indexes: list[MetadataIndex]) -> None:
    """Write (``write``) a summary section that starts at offset ``summary_start`` of its file: each kind of record
    a group, listed by a summary offset record; then the footer and the closing magic."""
    out = _SummarySink(write)
    offsets: list[SummaryOffset] = []

    def group(opcode: Opcode, records: list[Any], table: ChunkIndexTable | None = None) -> None:
        if not records and not table:
            return
        start = out.count
        out.write_records(records)
        if table is not None:
            table.write_records(out.write)
        offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + start,
                                     group_length=out.count - start))

    group(Opcode.SCHEMA, schemas)
    group(Opcode.CHANNEL, channels)
    group(Opcode.STATISTICS, [statistics])
    group(Opcode.CHUNK_INDEX, [], chunk_indexes)
    group(Opcode.ATTACHMENT_INDEX, attachment_indexes)
    group(Opcode.METADATA_INDEX, metadata_indexes)
    summary_offset_start = summary_start + out.count
    out.write_records(offsets)
    out.flush()
    crc = footer_crc(out.crc, summary_start, summary_offset_start)
    write(encode_record(Footer(summary_start=summary_start, summary_offset_start=summary_offset_start,
                               summary_crc=crc)))
    write(MAGIC)
