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
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message, MessageIndex, Metadata, Schema
from mcap.stream_reader import breakup_chunk

from starlog import __version__
from starlog.errors import CorruptLogError, LogNotFoundError
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

    def schema(self, schema: Schema) -> None:
        self.schemas[schema.id] = schema

    def channel(self, channel: Channel) -> None:
        self.channels[channel.id] = channel

    def message(self, message: Message) -> None:
        out_id = self.out_ids.get(message.channel_id)
        if out_id is None:
            channel = self.channels.get(message.channel_id)
            if channel is None:
                self.report.skipped_records["message without channel"] = (
                    self.report.skipped_records.get("message without channel", 0) + 1
                )
                return
            schema = self.schemas.get(channel.schema_id)
            mtype = MessageType(
                schema.name if schema else "",
                schema.encoding if schema else "",
                schema.data if schema else b"",
                channel.message_encoding,
            )
            out_id = self.writer.add_channel(channel.topic, mtype, metadata=dict(channel.metadata))
            self.out_ids[message.channel_id] = out_id
        topic = self.channels[message.channel_id].topic
        self.writer.write(out_id, log_time=message.log_time, data=message.data, publish_time=message.publish_time)
        kept = self.report.kept_by_topic
        kept[topic] = kept.get(topic, 0) + 1
        lo, hi = self.report.kept_time_range.get(topic, (message.log_time, message.log_time))
        self.report.kept_time_range[topic] = (min(lo, message.log_time), max(hi, message.log_time))


def _read_records(f: BinaryIO, size: int, report: RecoveryReport, rebuild: _Rebuilder) -> None:
    offset = len(MCAP_MAGIC)
    f.seek(offset)
    pending_lost: LostChunk | None = None
    while offset < size:
        head = f.read(_RECORD_HEADER.size)
        if len(head) < _RECORD_HEADER.size:
            break
        opcode, length = _RECORD_HEADER.unpack(head)
        if offset + _RECORD_HEADER.size + length > size:
            break  # record cut off by the end of the file
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
                chunk = Chunk.read(stream)
                pending_lost = None
                try:
                    records = breakup_chunk(chunk, validate_crc=True)
                except Exception as err:  # CRC mismatch, damaged compressed data, bad inner record
                    pending_lost = LostChunk(offset, f"{type(err).__name__}: {err}", chunk.message_start_time,
                                             chunk.message_end_time)
                    report.lost_chunks.append(pending_lost)
                else:
                    for record in records:
                        if isinstance(record, Schema):
                            rebuild.schema(record)
                        elif isinstance(record, Channel):
                            rebuild.channel(record)
                        elif isinstance(record, Message):
                            rebuild.message(record)
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
                name = Opcode(opcode).name if opcode in Opcode._value2member_map_ else f"opcode {opcode}"
                report.skipped_records[name] = report.skipped_records.get(name, 0) + 1
        except (struct.error, ValueError, UnicodeDecodeError, EOFError) as err:
            report.lost_chunks.append(LostChunk(offset, f"damaged {Opcode(opcode).name if opcode in Opcode._value2member_map_ else opcode} record: {err}"))
        offset += _RECORD_HEADER.size + length
    report.bytes_scanned = offset


def _seed_from_summary(f: BinaryIO, rebuild: _Rebuilder) -> None:
    """Take schemas and channels from the summary when it survived (a chunk holding them may not have)."""
    from mcap.reader import make_reader

    try:
        f.seek(0)
        summary = make_reader(f).get_summary()
    except Exception:  # a damaged summary is simply not used; the scan finds the records in the chunks
        return
    if summary is not None:
        for schema in summary.schemas.values():
            rebuild.schema(schema)
        for channel in summary.channels.values():
            rebuild.channel(channel)


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
        f.seek(max(0, report.input_size - len(MCAP_MAGIC)))
        report.had_footer = f.read() == MCAP_MAGIC
        with LogWriter(output, force=force, compression=compression) as writer:
            rebuild = _Rebuilder(writer, report)
            if report.had_footer:
                _seed_from_summary(f, rebuild)
            _read_records(f, report.input_size, report, rebuild)
            report.tail_bytes_lost = 0 if report.had_footer else report.input_size - report.bytes_scanned
            writer.add_metadata(
                PROVENANCE_METADATA_NAME,
                Provenance(stage="recover", version=__version__, parameters={"source": source.name},
                           input_digest=file_digest(source), channels=[]).to_metadata(),
            )
    return report
