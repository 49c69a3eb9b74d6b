"""Rebuild a readable, fully indexed log from a truncated, unfinished or damaged one.

The file is scanned record by record in file order (no summary needed). Every complete record
is kept: schemas, channels, messages of every chunk whose bytes are whole and whose CRC checks,
and metadata (provenance). A chunk cut off by the end of the file, or whose CRC does not match,
is dropped and reported — with its offset, time range and, from the message-index records that
follow it when they survived, how many messages of which channels it held.
"""

from __future__ import annotations

import io
import os
import struct
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message, MessageIndex, Metadata, Schema
from mcap.stream_reader import breakup_chunk

from starlog import __version__
from starlog.errors import CorruptLogError, LogNotFoundError
from starlog.io.checksum import summary_crc
from starlog.io.chunk_indexes import read_file_summary
from starlog.io.provenance import PROVENANCE_METADATA_NAME, Provenance, file_digest
from starlog.io.schemas import MessageType
from starlog.io.writer import MCAP_MAGIC, LogWriter

__all__ = ["RecoveryReport", "recover_log"]

_RECORD_HEADER = struct.Struct("<BQ")


@dataclass
class LostChunk:
    """A chunk that could not be recovered."""

    offset: int
    reason: str
    message_start_time: int = 0
    message_end_time: int = 0
    messages_by_topic: dict[str, int] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "offset": self.offset,
            "reason": self.reason,
            "message_start_time": self.message_start_time,
            "message_end_time": self.message_end_time,
            "messages_by_topic": dict(self.messages_by_topic),
        }


@dataclass
class RecoveryReport:
    """What :func:`recover_log` kept and what was lost."""

    output: Path
    input_size: int = 0
    bytes_scanned: int = 0
    had_footer: bool = False
    kept_by_topic: dict[str, int] = field(default_factory=dict)
    kept_time_range: dict[str, tuple[int, int]] = field(default_factory=dict)
    metadata_kept: int = 0
    lost_chunks: list[LostChunk] = field(default_factory=list)
    tail_bytes_lost: int = 0
    skipped_records: dict[str, int] = field(default_factory=dict)

    @property
    def lost_by_topic(self) -> dict[str, int]:
        lost: dict[str, int] = defaultdict(int)
        for chunk in self.lost_chunks:
            for topic, n in chunk.messages_by_topic.items():
                lost[topic] += n
        return dict(lost)

    def to_dict(self) -> dict[str, Any]:
        return {
            "output": str(self.output),
            "input_size": self.input_size,
            "bytes_scanned": self.bytes_scanned,
            "had_footer": self.had_footer,
            "kept_by_topic": dict(self.kept_by_topic),
            "kept_time_range": {k: list(v) for k, v in self.kept_time_range.items()},
            "metadata_kept": self.metadata_kept,
            "lost_chunks": [c.to_dict() for c in self.lost_chunks],
            "lost_by_topic": self.lost_by_topic,
            "tail_bytes_lost": self.tail_bytes_lost,
            "skipped_records": dict(self.skipped_records),
        }


class _Rebuilder:
    def __init__(self, writer: LogWriter, report: RecoveryReport) -> None:
        self.writer = writer
        self.report = report
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.out_ids: dict[int, int] = {}
        self.by_topic: dict[str, tuple[MessageType, int]] = {}

    def skip(self, what: str) -> None:
        self.report.skipped_records[what] = self.report.skipped_records.get(what, 0) + 1

    def schema(self, schema: Schema) -> None:
        self.schemas[schema.id] = schema

    def channel(self, channel: Channel) -> None:
        if self.channels.get(channel.id, channel) != channel:
            self.out_ids.pop(channel.id, None)  # a later, different definition of the id wins for what follows
        self.channels[channel.id] = channel

    def message(self, message: Message) -> None:
        out_id = self.out_ids.get(message.channel_id)
        if out_id is None:
            channel = self.channels.get(message.channel_id)
            if channel is None:
                self.skip("message without channel")
                return
            schema = self.schemas.get(channel.schema_id)
            if channel.schema_id != 0 and schema is None:
                self.skip("message whose channel's schema is lost")
                return
            mtype = MessageType(
                schema.name if schema else "",
                schema.encoding if schema else "",
                schema.data if schema else b"",
                channel.message_encoding,
            )
            known = self.by_topic.get(channel.topic)
            if known is None:
                out_id = self.writer.add_channel(channel.topic, mtype, metadata=dict(channel.metadata))
                self.by_topic[channel.topic] = (mtype, out_id)
            elif known[0] == mtype:
                out_id = known[1]
            else:
                self.skip("message of a second, different channel with the same topic")
                return
            self.out_ids[message.channel_id] = out_id
        topic = self.channels[message.channel_id].topic
        self.writer.write(out_id, log_time=message.log_time, data=message.data, publish_time=message.publish_time)
        kept = self.report.kept_by_topic
        kept[topic] = kept.get(topic, 0) + 1
        lo, hi = self.report.kept_time_range.get(topic, (message.log_time, message.log_time))
        self.report.kept_time_range[topic] = (min(lo, message.log_time), max(hi, message.log_time))


_KNOWN_OPCODES = {int(op) for op in Opcode}
_COMPRESSIONS = {b"", b"zstd", b"lz4"}


def _plausible_chunk(f: BinaryIO, offset: int, size: int) -> bool:
    """Whether a whole, self-consistent chunk record starts at ``offset`` (used to resynchronise)."""
    f.seek(offset)
    head = f.read(9 + 28 + 4)
    if len(head) < 41 or head[0] != Opcode.CHUNK:
        return False
    (length,) = struct.unpack_from("<Q", head, 1)
    (name_len,) = struct.unpack_from("<I", head, 37)
    if name_len > 4 or offset + 9 + length > size:
        return False
    rest = f.read(name_len + 8)
    if len(rest) < name_len + 8 or rest[:name_len] not in _COMPRESSIONS:
        return False
    (data_len,) = struct.unpack_from("<Q", rest, name_len)
    return 28 + 4 + name_len + 8 + data_len == length


def _resync(f: BinaryIO, start: int, size: int, hints: list[int]) -> int | None:
    """Offset of the next whole chunk record at or after ``start`` (summary hints first, then a scan)."""
    for hint in hints:
        if hint >= start and _plausible_chunk(f, hint, size):
            return hint
    window = 1 << 20
    pos = start
    while pos < size:
        f.seek(pos)
        block = f.read(window + 64)
        i = block.find(bytes([Opcode.CHUNK]))
        while i != -1 and i < window:
            if _plausible_chunk(f, pos + i, size):
                return pos + i
            i = block.find(bytes([Opcode.CHUNK]), i + 1)
        pos += window
    return None


def _replay_chunk(stream: ReadDataStream, length: int, offset: int, report: RecoveryReport,
                  rebuild: _Rebuilder) -> LostChunk | None:
    """Hand the records of the chunk record at ``offset`` to ``rebuild``; a damaged chunk is reported lost.

    Returns the :class:`LostChunk` (its message index records that follow then name what it held).
    """
    chunk = Chunk.read(stream)
    if stream.count != length:
        raise ValueError(f"its fields take {stream.count} bytes, its record {length}")
    try:
        if chunk.compression not in ("", "zstd", "lz4"):
            raise ValueError(f"unknown compression {chunk.compression!r}")
        records = breakup_chunk(chunk, validate_crc=True)
    except Exception as err:  # CRC mismatch, damaged compressed data, bad inner record
        lost = LostChunk(offset, f"{type(err).__name__}: {err}", chunk.message_start_time, chunk.message_end_time)
        report.lost_chunks.append(lost)
        return lost
    for record in records:
        if isinstance(record, Schema):
            rebuild.schema(record)
        elif isinstance(record, Channel):
            rebuild.channel(record)
        elif isinstance(record, Message):
            rebuild.message(record)
    return None


def _read_records(f: BinaryIO, size: int, report: RecoveryReport, rebuild: _Rebuilder,
                  hints: list[int] | None = None) -> None:
    offset = len(MCAP_MAGIC)
    pending_lost: LostChunk | None = None
    hints = sorted(hints or [])
    skipped_by_length: int | None = None  # start of the previous record if only its length was trusted
    while offset < size:
        f.seek(offset)
        head = f.read(_RECORD_HEADER.size)
        if len(head) < _RECORD_HEADER.size:
            break
        opcode, length = _RECORD_HEADER.unpack(head)
        damaged: str | None = None
        if opcode not in _KNOWN_OPCODES:
            damaged = f"unknown record type {opcode:#04x}"
        elif offset + _RECORD_HEADER.size + length > size:
            damaged = f"a {Opcode(opcode).name} record of {length} bytes runs past the end of the file"
        else:
            body = f.read(length)
            stream = ReadDataStream(io.BytesIO(body))
            try:
                if opcode == Opcode.SCHEMA:
                    rebuild.schema(Schema.read(stream))
                elif opcode == Opcode.CHANNEL:
                    rebuild.channel(Channel.read(stream))
                elif opcode == Opcode.MESSAGE:
                    rebuild.message(Message.read(stream, length))
                elif opcode == Opcode.CHUNK:
                    pending_lost = _replay_chunk(stream, length, offset, report, rebuild)
                elif opcode == Opcode.MESSAGE_INDEX:
                    if pending_lost is not None:
                        index = MessageIndex.read(stream)
                        channel = rebuild.channels.get(index.channel_id)
                        topic = channel.topic if channel else f"channel {index.channel_id}"
                        pending_lost.messages_by_topic[topic] = len(index.records)
                elif opcode == Opcode.METADATA:
                    metadata = Metadata.read(stream)
                    rebuild.writer.add_metadata(metadata.name, dict(metadata.metadata))
                    report.metadata_kept += 1
                elif opcode == Opcode.DATA_END:
                    offset += _RECORD_HEADER.size + length
                    break
                elif opcode not in (Opcode.HEADER, Opcode.FOOTER):
                    rebuild.skip(Opcode(opcode).name)
            except (struct.error, ValueError, UnicodeDecodeError, EOFError, McapError, MemoryError) as err:
                damaged = f"damaged {Opcode(opcode).name} record: {type(err).__name__}: {err}"
        if damaged is None:
            skipped_by_length = offset if opcode == Opcode.MESSAGE_INDEX and pending_lost is None else None
            offset += _RECORD_HEADER.size + length
            continue
        # The bytes at `offset` are not a whole record: find the next chunk and go on from there. When the
        # record before was only skipped by its length, that length may be the damage: look inside it too.
        pending_lost = None
        found = _resync(f, offset + 1 if skipped_by_length is None else skipped_by_length + 1, size, hints)
        if found is None:
            if report.had_footer or offset + _RECORD_HEADER.size + length <= size or opcode not in _KNOWN_OPCODES:
                report.lost_chunks.append(LostChunk(offset, f"{damaged}; nothing readable after it"))
            break  # else: the record cut off by the end of a truncated file (counted in tail_bytes_lost)
        if found > offset:
            report.lost_chunks.append(LostChunk(offset, f"{damaged}; skipped {found - offset} bytes to the next chunk"))
        else:
            report.lost_chunks.append(LostChunk(offset, f"{damaged}; the record before overran it: resumed at the "
                                                        f"chunk at offset {found}"))
        offset = found
    report.bytes_scanned = offset


def _summary_crc_ok(f: BinaryIO, size: int) -> bool:
    """Whether the footer's summary CRC matches (a damaged summary must not name channels)."""
    footer = struct.Struct("<BQQQI")
    if size < len(MCAP_MAGIC) * 2 + footer.size:
        return False
    f.seek(size - len(MCAP_MAGIC) - footer.size)
    opcode, _, start, offsets_start, crc = footer.unpack(f.read(footer.size))
    end = size - len(MCAP_MAGIC) - footer.size
    if opcode != Opcode.FOOTER or not len(MCAP_MAGIC) < start <= end:
        return False
    computed = summary_crc(f, start, offsets_start, end)
    return crc == 0 or computed == crc


def _seed_from_summary(f: BinaryIO, rebuild: _Rebuilder, size: int) -> list[int]:
    """Schemas and channels from the summary when it survived intact (a chunk holding them may not have).

    Returns the chunk offsets the summary lists (used to resynchronise after a damaged record).
    """
    if not _summary_crc_ok(f, size):
        rebuild.skip("damaged summary section (rebuilt from the data section)")
        return []
    try:
        summary = read_file_summary(f)
    except Exception:  # a damaged summary is simply not used; the scan finds the records in the chunks
        rebuild.skip("damaged summary section (rebuilt from the data section)")
        return []
    if summary is None:
        return []
    for schema in summary.schemas.values():
        rebuild.schema(schema)
    for channel in summary.channels.values():
        rebuild.channel(channel)
    return summary.chunk_indexes.column("chunk_start_offset").tolist()


def recover_log(
    path: str | os.PathLike[str],
    output: str | os.PathLike[str],
    *,
    force: bool = False,
    compression: str = "zstd",
) -> RecoveryReport:
    """Rebuild ``path`` into a complete, indexed log at ``output`` and report what was lost.

    The input is only read. Messages are written in the order they appear in the file.
    """
    source = Path(path)
    if not source.is_file():
        raise LogNotFoundError(source)
    report = RecoveryReport(output=Path(output), input_size=source.stat().st_size)
    with open(source, "rb") as f:
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise CorruptLogError(source, "does not start with the MCAP magic bytes; nothing can be recovered.")
        footer_at = report.input_size - len(MCAP_MAGIC) - 29
        if footer_at >= len(MCAP_MAGIC):
            f.seek(footer_at)
            tail = f.read()
            report.had_footer = tail[0] == Opcode.FOOTER and tail[-len(MCAP_MAGIC):] == MCAP_MAGIC
        with LogWriter(output, force=force, compression=compression, validate=False) as writer:  # bytes as found
            rebuild = _Rebuilder(writer, report)
            hints = _seed_from_summary(f, rebuild, report.input_size) if report.had_footer else []
            _read_records(f, report.input_size, report, rebuild, hints)
            report.tail_bytes_lost = 0 if report.had_footer else report.input_size - report.bytes_scanned
            writer.add_metadata(
                PROVENANCE_METADATA_NAME,
                Provenance(stage="recover", version=__version__, parameters={"source": source.name},
                           input_digest=file_digest(source), channels=[]).to_metadata(),
            )
    return report
