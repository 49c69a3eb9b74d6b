"""Rebuild a readable, fully indexed log from a truncated, unfinished or damaged one.

The file is scanned record by record in file order (no summary needed). Every complete record
is kept: schemas, channels, messages of every chunk whose bytes are whole and whose CRC checks,
and metadata (provenance); a topic's channels of one type of message become one channel, those of
another type a channel of their own on the same topic. A chunk cut off by the end of the file, or
whose CRC does not match, is dropped and reported — with its offset, time range and, from the
message-index records that follow it when they survived, how many messages of which channels it
held.

A layer (:mod:`starlog.io.chain`) is recovered as a layer on the same base when its base record
survived and its base is there, unchanged; otherwise its own records are recovered into a file
that opens alone, and the report says why.
"""

from __future__ import annotations

import os
import struct
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Message, MessageIndex, Metadata, Schema

from starlog.version import __version__
from starlog.errors import BaseMismatchError, CorruptLogError, LogError, LogNotFoundError
from starlog.io.chain import BASE_METADATA_NAME, LayerBase, base_reference
from starlog.io.chunk_indexes import read_file_summary
from starlog.io.layout import (
    CHUNK_HEADER,
    MAGIC,
    RECORD_HEADER,
    RecordOverrun,
    chunk_header,
    decode_chunk,
    iter_records,
    parse_record,
    read_footer,
    summary_crc,
    walk_records,
)
from starlog.io.provenance import PROVENANCE_METADATA_NAME, Provenance, file_digest
from starlog.io.reader import LogReader
from starlog.io.schemas import MessageType
from starlog.io.writer import LogWriter

__all__ = ["RecoveryReport", "recover_log"]


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
    base: str = ""  # the base of the recovered layer ("": the output opens alone)
    base_note: str = ""  # why a layer's base was not kept

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
            "base": self.base,
            "base_note": self.base_note,
        }

    def lines(self) -> list[str]:
        """Messages kept, the base, what each channel kept, the chunks lost and the records skipped."""
        lines = [f"{sum(self.kept_by_topic.values())} messages kept"
                 f"{'' if self.had_footer else f', the last {self.tail_bytes_lost} bytes were unreadable'}"]
        if self.base:
            lines.append(f"  a layer on {self.base}, as the input was")
        if self.base_note:
            lines.append(f"  note: {self.base_note}")
        for topic, count in sorted(self.kept_by_topic.items()):
            lo, hi = self.kept_time_range[topic]
            lines.append(f"  kept {topic}: {count} messages, log_time {lo}..{hi}")
        for chunk in self.lost_chunks:
            what = ", ".join(f"{t}: {n}" for t, n in chunk.messages_by_topic.items()) or "channels unknown"
            lines.append(f"  lost chunk at offset {chunk.offset} (log_time {chunk.message_start_time}.."
                         f"{chunk.message_end_time}; {what}): {chunk.reason}")
        for what, n in sorted(self.skipped_records.items()):
            lines.append(f"  skipped {n} x {what}")
        return lines


class _Rebuilder:
    """The records of a file, handed over in file order, written again; damaged chunks reported lost."""

    def __init__(self, writer: LogWriter, report: RecoveryReport) -> None:
        self.writer = writer
        self.report = report
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.out_ids: dict[int, int] = {}
        self.by_topic: dict[str, list[tuple[MessageType, int]]] = {}  # the output channels of each topic
        self.pending_lost: LostChunk | None = None  # the chunk just lost: its message indexes say what it held
        self.last_whole: int | None = None  # the last record trusted by its length alone (see _read_records)
        self.base_record: dict[str, str] | None = None  # a layer's record naming its base, when met

    def record(self, offset: int, opcode: int, body: bytes | memoryview) -> bool:
        """Hand one record on; False at the DataEnd record."""
        if opcode == Opcode.SCHEMA:
            self.schema(parse_record(body, Schema))
        elif opcode == Opcode.CHANNEL:
            self.channel(parse_record(body, Channel))
        elif opcode == Opcode.MESSAGE:
            self.message(parse_record(body, Message))
        elif opcode == Opcode.CHUNK:
            self.pending_lost = self.chunk(body, offset)
        elif opcode == Opcode.MESSAGE_INDEX and self.pending_lost is not None:
            self.lost_index(self.pending_lost, parse_record(body, MessageIndex))
        elif opcode == Opcode.METADATA:
            self.metadata(parse_record(body, Metadata))
        elif opcode == Opcode.DATA_END:
            return False
        elif opcode not in (Opcode.HEADER, Opcode.FOOTER, Opcode.MESSAGE_INDEX):
            self.skip(Opcode(opcode).name)
        return True

    def chunk(self, body: bytes | memoryview, offset: int) -> LostChunk | None:
        """Hand on the records of the chunk record at ``offset``; a damaged chunk is reported lost and returned
        (its message index records that follow then name what it held)."""
        start, end = CHUNK_HEADER.unpack_from(body)[:2]
        try:
            contents = decode_chunk(body)
            records = [(opcode, contents.data[at: at + n]) for _, opcode, at, n in iter_records(contents.data)]
        except Exception as err:  # CRC mismatch, damaged compressed data, a record past the chunk's end
            lost = LostChunk(offset, f"{type(err).__name__}: {err}", start, end)
            self.report.lost_chunks.append(lost)
            return lost
        for opcode, record in records:
            if opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
                self.record(offset, opcode, record)
        return None

    def lost_index(self, lost: LostChunk, index: MessageIndex) -> None:
        """A message index record of the chunk just lost: what it held."""
        channel = self.channels.get(index.channel_id)
        topic = channel.topic if channel else f"channel {index.channel_id}"
        lost.messages_by_topic[topic] = len(index.records)

    def metadata(self, record: Metadata) -> None:
        if record.name == BASE_METADATA_NAME:  # the writer names the base of the recovered layer itself
            self.base_record = dict(record.metadata)
            return
        self.writer.add_metadata(record.name, dict(record.metadata))
        self.report.metadata_kept += 1

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
            known = self.by_topic.setdefault(channel.topic, [])
            out_id = next((out for kind, out in known if kind == mtype), None)
            if out_id is None:  # a topic's channels of one type become one channel; of another type, their own
                out_id = self.writer.add_channel(channel.topic, mtype, metadata=dict(channel.metadata),
                                                 shared_topic=True)
                known.append((mtype, out_id))
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
    head = f.read(RECORD_HEADER.size + CHUNK_HEADER.size + 4 + max(map(len, _COMPRESSIONS)) + 8)
    try:
        opcode, length = RECORD_HEADER.unpack_from(head)
        *_, compression, data_len, data_at = chunk_header(memoryview(head)[RECORD_HEADER.size:], whole=False)
    except (struct.error, UnicodeDecodeError):
        return False
    return (opcode == Opcode.CHUNK and compression.encode() in _COMPRESSIONS and data_at + data_len == length
            and offset + RECORD_HEADER.size + length <= size)


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


def _read_records(f: BinaryIO, size: int, report: RecoveryReport, rebuild: _Rebuilder,
                  hints: list[int] | None = None) -> dict[str, str] | None:
    """Replay every readable record of the file; the base record of a layer, when one was met."""
    replay = rebuild
    offset = len(MAGIC)
    hints = sorted(hints or [])
    while offset < size:
        damaged, cut_off = _replay_until_damage(f, offset, size, replay)
        if damaged is None:  # the end: a DataEnd record, or the end of the file (cut_off: inside a header)
            report.bytes_scanned = cut_off
            return replay.base_record
        offset, detail = damaged
        skipped_by_length = replay.last_whole
        # The bytes at `offset` are not a whole record: find the next chunk and go on from there. When the
        # record before was only skipped by its length, that length may be the damage: look inside it too.
        replay.pending_lost = None
        found = _resync(f, offset + 1 if skipped_by_length is None else skipped_by_length + 1, size, hints)
        if found is None:
            if report.had_footer or not cut_off:
                report.lost_chunks.append(LostChunk(offset, f"{detail}; nothing readable after it"))
            break  # else: the record cut off by the end of a truncated file (counted in tail_bytes_lost)
        if found > offset:
            report.lost_chunks.append(LostChunk(offset, f"{detail}; skipped {found - offset} bytes to the next chunk"))
        else:
            report.lost_chunks.append(LostChunk(offset, f"{detail}; the record before overran it: resumed at the "
                                                        f"chunk at offset {found}"))
        offset = found
    report.bytes_scanned = offset
    return replay.base_record


def _replay_until_damage(f: BinaryIO, offset: int, size: int, replay: _Rebuilder) -> tuple[Any, Any]:
    """Replay the records from ``offset``: ``((offset, what), runs past the end)`` of the first damaged record,
    or ``(None, where reading stopped)`` at the DataEnd record or the end of the file."""
    replay.last_whole = None
    try:
        for offset, opcode, length, body in walk_records(f, offset, size):
            if opcode not in _KNOWN_OPCODES:
                return (offset, f"unknown record type {opcode:#04x}"), False
            try:
                going_on = replay.record(offset, opcode, body or b"")
            except (struct.error, ValueError, UnicodeDecodeError, EOFError, McapError, MemoryError) as err:
                return (offset, f"damaged {Opcode(opcode).name} record: {type(err).__name__}: {err}"), False
            # a message index that named no lost chunk was trusted by its length alone
            replay.last_whole = offset if opcode == Opcode.MESSAGE_INDEX and replay.pending_lost is None else None
            if not going_on:
                return None, offset + RECORD_HEADER.size + length
        return None, size
    except RecordOverrun as err:
        if err.cut_header:
            return None, err.offset
        f.seek(err.offset)
        opcode, length = RECORD_HEADER.unpack(f.read(RECORD_HEADER.size))
        if opcode not in _KNOWN_OPCODES:
            return (err.offset, f"unknown record type {opcode:#04x}"), False
        return (err.offset, f"a {Opcode(opcode).name} record of {length} bytes runs past the end of the file"), True


def _summary_crc_ok(f: BinaryIO, path: Path) -> bool:
    """Whether the footer's summary CRC matches (a damaged summary must not name channels)."""
    try:
        footer = read_footer(path, f)
    except LogError:
        return False
    if not len(MAGIC) < footer.summary_start <= footer.offset:
        return False
    return footer.summary_crc == 0 or summary_crc(f, footer) == footer.summary_crc


def _seed_from_summary(f: BinaryIO, path: Path, rebuild: _Rebuilder) -> list[int]:
    """Schemas and channels from the summary when it survived intact (a chunk holding them may not have).

    Returns the chunk offsets the summary lists (used to resynchronise after a damaged record).
    """
    if not _summary_crc_ok(f, path):
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
        if f.read(len(MAGIC)) != MAGIC:
            raise CorruptLogError(source, "does not start with the MCAP magic bytes; nothing can be recovered.")
        try:
            read_footer(source, f)
            report.had_footer = True
        except LogError:
            report.had_footer = False
        layer = _layer_base(source, report) if report.had_footer else None
        with LogWriter(output, force=force, compression=compression, validate=False,  # bytes as found
                       layer=layer, inputs=[source]) as writer:
            rebuild = _Rebuilder(writer, report)
            hints = _seed_from_summary(f, source, rebuild) if report.had_footer else []
            found_base = _read_records(f, report.input_size, report, rebuild, hints)
            if found_base is not None and layer is None and not report.base_note:
                report.base_note = (f"it was a layer on {found_base.get('path', '?')!r} "
                                    f"({found_base.get('sha256', '')}); its summary is lost, so the output holds the "
                                    "layer's own records and opens alone")
            report.tail_bytes_lost = 0 if report.had_footer else report.input_size - report.bytes_scanned
            writer.add_metadata(
                PROVENANCE_METADATA_NAME,
                Provenance(stage="recover", version=__version__, parameters={"source": source.name},
                           input_digest=file_digest(source), channels=[]).to_metadata(),
            )
    return report


def _layer_base(source: Path, report: RecoveryReport) -> LayerBase | None:
    """The base to write the recovered layer on: the one ``source`` names, when its summary is intact and the
    base is there, the very file the layer recorded (size, CRCs and SHA-256)."""
    try:
        with LogReader(source) as log:
            reference = base_reference(log.files[-1])
            if reference is None:
                return None
            base = LayerBase.of(log.files[:-1])
    except BaseMismatchError as err:
        report.base_note = f"it is a layer whose base {err.base} {err.problem}: the output holds the layer's own " \
                           "records and opens alone"
        return None
    except LogError:  # a damaged summary: the base record cannot be trusted
        report.base_note = "its summary is damaged, so the base it names is not known: the output opens alone"
        return None
    if (base.digest(), base.chain) != (reference.sha256, reference.chain):
        report.base_note = f"it is a layer on {base.path}, which has changed (its SHA-256 is not the one the layer " \
                           "recorded): the output holds the layer's own records and opens alone"
        return None
    report.base = str(base.path)
    return base
