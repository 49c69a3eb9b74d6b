"""``starlog verify``: read every record of an MCAP file and report every problem found.

Checked: the magic bytes, header and footer; the summary section and its CRC; every chunk's
header, decompression and CRC; the message index records against the chunk contents; the
chunk indexes against the chunks; the statistics against the messages counted; schema and
channel references; JSON messages against their JSON Schemas; protobuf, ROS 1 and ROS 2
messages decode; images decode with one size per channel; ``log_time`` order per channel.

Each problem has a ``kind`` (a stable name), a severity (``error``: the file is damaged, or starlog
refuses part of it, such as a topic whose channels' schemas cannot be read as one series;
``warning``: starlog reads the file in full, but it breaks a rule of the MCAP specification, quoted
in :attr:`Problem.rule`, such as a summary without the Channel records its chunk indexes name, and
``starlog filter LOG -o OUT`` rewrites it conforming; ``note``: a file every starlog command reads in
full but that is unusual, such as chunks without message indexes, no summary, or channels sharing a
topic; where Foxglove or the ``mcap`` library cannot read it, the note says so and names the command
that rewrites it), the file ``offset`` of the record, and the ``channel`` and ``log_time`` where
they apply. The report's :attr:`~VerifyReport.status` follows: ``damaged`` or ``refused`` (an error;
exit status 1), ``nonconformant`` (warnings only; exit status 3), ``valid`` (notes at most; 0).
The data section is read once, chunk by chunk, and the summary section a block at a time (once
for its CRC, once for its records); memory holds one chunk, per-channel counters (and 8 bytes a
frame of each image channel, to compare the frame times of a topic's channels) and the summary's
chunk indexes by column (about 100 bytes a chunk: each is compared with its chunk as the walk
finishes that chunk). Chunk indexes are parsed
as :class:`~starlog.io.reader.LogReader` parses them: one that it refuses is a ``bad_summary``.

One module of over 500 lines: the checks are the methods of one walk over the file
(:class:`_Verifier`), which share its state, and the reports are what that walk fills in.
"""

from __future__ import annotations

import json
import os
import struct
from array import array
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, ChunkIndex, Metadata, MetadataIndex, Schema, Statistics, SummaryOffset

from starlog.errors import BaseMismatchError, CorruptLogError
from starlog.io.chain import BASE_METADATA_NAME, BaseReference, id_collisions, open_base
from starlog.io.checksum import crc32
from starlog.io.chunk_indexes import ChunkIndexTable
from starlog.codecs.foreign_decoders import message_decoder
from starlog.io.frames import cached_image_decoder
from starlog.codecs.images import is_image_schema
from starlog.io.layout import (
    DATA_END_RECORD_LEN,
    FOOTER,
    MAGIC,
    MESSAGE_HEADER,
    MESSAGE_INDEX_BODY,
    RECORD_HEADER,
    Footer,
    RecordOverrun,
    chunk_header,
    decode_chunk,
    iter_records,
    parse_message_index,
    parse_record,
    summary_crc,
    walk_records,
)
from starlog.codecs.json_schema import compile_json_schema
from starlog.codecs.json_messages import decode_json
from starlog.io.provenance import BackgroundDigest
from starlog.io.shared_topics import OTHER_READERS, topic_conflict

__all__ = ["EXIT_STATUS", "ChainReport", "Problem", "VerifyReport", "verify_file", "verify_log"]

#: ``starlog verify``'s exit status for each :attr:`VerifyReport.status`.
EXIT_STATUS = {"valid": 0, "nonconformant": 3, "refused": 1, "damaged": 1}
#: Errors of valid MCAP files that starlog refuses (its frames, tables, stages), as opposed to damage.
REFUSALS = frozenset({"topic_schemas_differ", "image_size", "image_size_changed", "duplicate_frame_time"})
#: The rules of the MCAP specification on the summary's copies of schema and channel records.
RULE_CHUNK_INDEXES = ("A Schema and Channel record MUST exist in the summary section for all channels referenced by "
                      "chunk index records")
RULE_STATISTICS = ("When using a Statistics record with a non-empty channel_message_counts, the Summary Data section "
                   "MUST contain a copy of all Channel records")

MAGIC_LENGTH = len(MAGIC)
_FOOTER = FOOTER
_DATA_END_LENGTH = DATA_END_RECORD_LEN
_PROGRESS_STEP = 8 << 20  # bytes of the data section between two progress reports


@dataclass(frozen=True)
class Problem:
    """One problem: ``kind`` (stable name), ``severity`` (error / warning / note), where, and what; a warning's
    ``rule`` quotes the rules of the MCAP specification the file breaks (each in double quotes)."""

    kind: str
    severity: str
    detail: str
    offset: int | None = None
    channel: str | None = None
    log_time: int | None = None
    rule: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "severity": self.severity, "offset": self.offset, "channel": self.channel,
                "log_time": self.log_time, "detail": self.detail, "rule": self.rule or None}

    def line(self) -> str:
        where = [f"offset {self.offset}" if self.offset is not None else "",
                 f"channel {self.channel}" if self.channel else "",
                 f"log_time {self.log_time}" if self.log_time is not None else ""]
        place = ", ".join(w for w in where if w)
        return f"{self.severity} {self.kind}{f' ({place})' if place else ''}: {self.detail}"


@dataclass
class VerifyReport:
    """What :func:`verify_log` found."""

    path: str
    size: int = 0
    messages: int = 0
    chunks: int = 0
    channels: int = 0
    problems: list[Problem] = field(default_factory=list)

    @property
    def errors(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == "error"]

    @property
    def warnings(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == "warning"]

    @property
    def ok(self) -> bool:
        """No error: every starlog command reads the file in full (it may still break the specification)."""
        return not self.errors

    @property
    def status(self) -> str:
        """:func:`_status` of the file's problems."""
        return _status(self.problems)

    @property
    def exit_status(self) -> int:
        """``starlog verify``'s exit status: 0 valid, 3 nonconformant, 1 refused or damaged."""
        return EXIT_STATUS[self.status]

    def verdict(self) -> str:
        """One line: valid, nonconformant, refused or damaged, with counts."""
        notes = len(self.problems) - len(self.errors) - len(self.warnings)
        what = f"{self.messages} messages, {self.channels} channels, {self.chunks} chunks"
        also = f", {notes} notes" if notes else ""
        status = self.status
        if status == "valid":
            return f"OK: {self.path} is a valid MCAP file ({what}{also})."
        if status == "nonconformant":
            rules = "; ".join(dict.fromkeys(p.rule for p in self.warnings))
            return (f"NONCONFORMANT: starlog reads {self.path} in full ({what}{also}), but it does not conform to the "
                    f"MCAP specification: {rules}. Rewrite it conforming with: starlog filter {self.path} -o OUT.mcap")
        kinds = ", ".join(sorted({p.kind for p in self.errors}))
        if status == "refused":
            return (f"REFUSED: {self.path} is valid MCAP ({what}{also}), but starlog refuses part of it: "
                    f"{len(self.errors)} errors ({kinds}; see above).")
        return (f"DAMAGED: {self.path} has {len(self.errors)} errors ({kinds}){also}"
                f"; read {what}. Keep what is intact with: starlog recover {self.path} -o RECOVERED.mcap")

    def to_dict(self) -> dict[str, Any]:
        return {"path": self.path, "ok": self.ok, "status": self.status, "size_bytes": self.size,
                "messages": self.messages, "chunks": self.chunks, "channels": self.channels,
                "verdict": self.verdict(), "problems": [p.to_dict() for p in self.problems]}


def _status(problems: list[Problem]) -> str:
    """``damaged`` (an error other than a refusal), ``refused`` (valid MCAP, part of which starlog refuses:
    :data:`REFUSALS`), ``nonconformant`` (read in full, but it breaks a rule of the MCAP specification) or
    ``valid``."""
    errors = {p.kind for p in problems if p.severity == "error"}
    if errors:
        return "refused" if errors <= REFUSALS else "damaged"
    return "nonconformant" if any(p.severity == "warning" for p in problems) else "valid"


@dataclass
class _Seen:
    """A chunk as found in the data section."""

    offset: int
    length: int
    start: int
    end: int
    compression: str
    compressed_size: int
    uncompressed_size: int
    positions: dict[int, list[tuple[int, int]]]
    index_offsets: dict[int, int] = field(default_factory=dict)
    index_end: int = 0


def _disagreement(ci: ChunkIndex, seen: _Seen) -> list[str]:
    """The fields in which a chunk index disagrees with the chunk it points at."""
    index_length = seen.index_end - min(seen.index_offsets.values()) if seen.index_offsets else 0
    return [name for name, got, want in [
        ("chunk_length", ci.chunk_length, seen.length), ("message_start_time", ci.message_start_time, seen.start),
        ("message_end_time", ci.message_end_time, seen.end), ("compression", ci.compression, seen.compression),
        ("compressed_size", ci.compressed_size, seen.compressed_size),
        ("uncompressed_size", ci.uncompressed_size, seen.uncompressed_size),
        ("message_index_offsets", dict(ci.message_index_offsets), seen.index_offsets),
        ("message_index_length", ci.message_index_length, index_length)] if got != want]


class _ChunkIndexCheck:
    """The summary's chunk indexes, each compared with the chunk it points at when the walk of the
    data section finishes that chunk: neither the indexes nor the chunks are kept as objects."""

    def __init__(self) -> None:
        self.table = ChunkIndexTable()
        self.record_offsets = array("Q")  # of each chunk index record, in the summary
        self._by_chunk: tuple[np.ndarray, np.ndarray] | None = None  # rows sorted by chunk offset, and the offsets
        self._matched = np.zeros(0, dtype=bool)
        self._next = 0  # in the sorted offsets: where the next chunk of the walk is expected
        self._disagreements: dict[int, list[str]] = {}

    def add(self, record_offset: int, body: bytes) -> None:
        if self._by_chunk is not None:
            raise RuntimeError("every chunk index is added before the first chunk is compared")
        self.table.append_record(body)
        self.record_offsets.append(record_offset)

    def compare(self, seen: _Seen) -> bool:
        """Compare the chunk with every index that points at it; False when none does."""
        if self._by_chunk is None:
            starts = self.table.column("chunk_start_offset")
            order = np.argsort(starts, kind="stable")
            self._by_chunk = order, starts[order]
            self._matched = np.zeros(len(self.table), dtype=bool)
        order, starts = self._by_chunk
        # the walk meets the chunks in file order: usually the index after the last one matched
        lo = self._next
        if not (lo < starts.size and starts[lo] == seen.offset):
            lo = int(np.searchsorted(starts, np.uint64(seen.offset)))
        hi = lo
        while hi < starts.size and starts[hi] == seen.offset:
            hi += 1
        self._next = hi
        for row in order[lo:hi].tolist():
            self._matched[row] = True
            wrong = _disagreement(self.table[row], seen)
            if wrong:
                self._disagreements[row] = wrong
        return hi > lo

    def problems(self) -> Iterator[tuple[int, str]]:
        """``(record offset, detail)`` of each index that points where no chunk starts, or that disagrees
        with its chunk, in the summary's order."""
        matched = self._matched if self._matched.size else np.zeros(len(self.table), dtype=bool)
        for row in sorted({*np.flatnonzero(~matched).tolist(), *self._disagreements}):
            start = int(self.table.column("chunk_start_offset")[row])
            if row in self._disagreements:
                detail = f"the chunk index disagrees with the chunk at {start} in {', '.join(self._disagreements[row])}"
            else:
                detail = f"a chunk index points at {start}, where no chunk starts"
            yield self.record_offsets[row], detail


@dataclass
class _ChannelState:
    topic: str
    count: int = 0
    last: int = -1
    out_of_order: int = 0
    frame_times: array | None = None  # an image channel's log_times, to compare with its topic's other channels
    checker: Callable[[Any], str | None] | None = None
    decode: Callable[[bytes], Any] | None = None
    kind: str = "bytes"


class _Verifier:
    def __init__(self, path: Path, f: BinaryIO, report: VerifyReport,
                 on_progress: Callable[[int], object] | None = None) -> None:
        self.path, self.f, self.report = path, f, report
        self.on_progress = on_progress
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.states: dict[int, _ChannelState] = {}
        self.indexes = _ChunkIndexCheck()
        self.unlisted = array("Q")  # offsets of the chunks no chunk index points at
        self.metadata: dict[int, str] = {}
        self.summary: dict[str, Any] = {}
        self.summary_damaged = False  # a record of the summary section does not parse
        self.counted: dict[int, int] = {}
        self.times: list[int] = []  # [first, last] over every message
        self.loose = 0
        self.unknown_channels: set[int] = set()
        self.bare_chunks = 0
        self.base_records: list[dict[str, str]] = []
        self.summary_definitions: tuple[set[int], set[int]] = (set(), set())  # schema and channel ids it repeats
        self.frame_shapes: dict[str, tuple[Any, ...]] = {}  # per image topic: its first frame's shape and dtype

    def problem(self, kind: str, detail: str, *, severity: str = "error", offset: int | None = None,
                channel: str | None = None, log_time: int | None = None, rule: str = "") -> None:
        self.report.problems.append(Problem(kind, severity, detail, offset, channel, log_time, rule))

    # ------------------------------------------------------------------ frame of the file
    def envelope(self, size: int) -> tuple[int, int, int, int] | None:
        """Check the magic bytes and footer; return ``(summary_start, summary_offset_start, crc, footer)``."""
        f = self.f
        f.seek(0)
        if f.read(MAGIC_LENGTH) != MAGIC:
            self.problem("bad_magic", "the file does not start with the MCAP magic bytes; is it an MCAP file?",
                         offset=0)
            return None
        footer = size - MAGIC_LENGTH - _FOOTER.size
        if footer < MAGIC_LENGTH:
            self.problem("truncated", f"only {size} bytes: shorter than any complete MCAP file", offset=size)
            return None
        f.seek(footer)
        tail = f.read(_FOOTER.size + MAGIC_LENGTH)
        if tail[-MAGIC_LENGTH:] != MAGIC:
            self.problem("truncated", "the file does not end with the MCAP magic bytes: cut off or never finished",
                         offset=size - MAGIC_LENGTH)
            return None
        opcode, length, summary_start, summary_offset_start, crc = _FOOTER.unpack(tail[:_FOOTER.size])
        if opcode != Opcode.FOOTER or length != 20:
            self.problem("bad_footer", f"no footer record before the closing magic (opcode {opcode:#04x})",
                         offset=footer)
            return None
        return summary_start, summary_offset_start, crc, footer

    # ------------------------------------------------------------------ summary section
    def read_summary(self, summary_start: int, summary_offset_start: int, crc: int, footer: int) -> int | None:
        """Parse and check the summary section; return where the data section must end (its DataEnd)."""
        if summary_start == 0:
            self.problem("no_summary", "the file has no summary section: readers must scan it whole; add one with "
                         f"starlog recover {self.path} -o INDEXED.mcap", severity="note")
            return None
        if not MAGIC_LENGTH + _DATA_END_LENGTH <= summary_start <= footer or (
                summary_offset_start and not summary_start <= summary_offset_start <= footer):
            self.problem("bad_footer", f"the footer points outside the file (summary at {summary_start}, summary "
                         f"offsets at {summary_offset_start})", offset=footer)
            return None
        if crc != 0:
            computed = summary_crc(self.f, Footer(summary_start, summary_offset_start, crc, footer, 0))
            if computed != crc:
                self.problem("summary_crc", f"the summary's CRC {computed:#010x} does not match the footer's "
                             f"{crc:#010x}: the summary section is damaged", offset=summary_start)
        groups: dict[str, list[Any]] = {"metadata_indexes": [], "offsets": []}
        readers = {Opcode.SCHEMA: ("schemas", Schema), Opcode.CHANNEL: ("channels", Channel),
                   Opcode.METADATA_INDEX: ("metadata_indexes", MetadataIndex),
                   Opcode.STATISTICS: ("statistics", Statistics), Opcode.SUMMARY_OFFSET: ("offsets", SummaryOffset)}
        try:
            for offset, opcode, _, body in walk_records(self.f, summary_start, footer):
                if opcode == Opcode.CHUNK_INDEX:
                    self.indexes.add(offset, body)
                elif opcode in readers:
                    name, cls = readers[opcode]
                    record = parse_record(body, cls)
                    if name == "schemas":
                        self.schemas.setdefault(record.id, record)
                        self.summary_definitions[0].add(record.id)
                    elif name == "channels":
                        self.channels.setdefault(record.id, record)
                        self.summary_definitions[1].add(record.id)
                    elif name == "statistics":
                        groups["statistics"] = record
                    else:
                        groups[name].append((offset, record))
        except Exception as err:  # struct.error, EOFError, ValueError, UnicodeDecodeError from a damaged record
            self.problem("bad_summary", f"the summary section cannot be parsed ({type(err).__name__}: {err})",
                         offset=summary_start)
            self.summary_damaged = True
        for offset, record in groups["offsets"]:
            self.check_summary_offset(offset, record, summary_start, footer)
        self.summary = groups
        return summary_start - _DATA_END_LENGTH

    def check_summary_offset(self, offset: int, record: SummaryOffset, start: int, footer: int) -> None:
        if not start <= record.group_start <= record.group_start + record.group_length <= footer:
            self.problem("bad_summary_offset", f"a summary offset record points outside the summary section "
                         f"({record.group_start}+{record.group_length})", offset=offset)
            return
        if record.group_length == 0:  # an empty group (some writers list those too)
            return
        self.f.seek(record.group_start)
        head = self.f.read(1)
        if head and head[0] != record.group_opcode:
            self.problem("bad_summary_offset", f"a summary offset record for opcode {record.group_opcode:#04x} "
                         f"points at a record of opcode {head[0]:#04x}", offset=offset)

    # ------------------------------------------------------------------ data section
    def walk_data(self, limit: int, expected_end: int | None) -> None:
        """Every record from the header to the DataEnd record, chunks opened and checked."""
        current, reported, pos = None, 0, MAGIC_LENGTH
        bodies = {Opcode.CHUNK, Opcode.MESSAGE_INDEX, Opcode.MESSAGE, Opcode.SCHEMA, Opcode.CHANNEL,
                  Opcode.METADATA, Opcode.ATTACHMENT}
        try:
            for pos, opcode, length, body in walk_records(self.f, MAGIC_LENGTH, limit, bodies=bodies):
                if self.on_progress is not None and pos - reported >= _PROGRESS_STEP:
                    self.on_progress(reported := pos)
                if pos == MAGIC_LENGTH and opcode != Opcode.HEADER:
                    self.problem("no_header", f"the first record is opcode {opcode:#04x}, not a header", offset=pos)
                if current is not None and opcode != Opcode.MESSAGE_INDEX:
                    self.finish_chunk(current)
                    current = None
                if opcode == Opcode.DATA_END:
                    if expected_end is not None and pos != expected_end:
                        self.problem("bad_data_end", f"the data section ends at {pos}, the footer says {expected_end}",
                                     offset=pos)
                    return
                try:
                    current = self.record(pos, opcode, body or b"", current)
                except Exception as err:  # a record whose fields do not parse
                    self.problem("bad_record", f"the record at offset {pos} (opcode {opcode:#04x}) cannot be parsed "
                                 f"({type(err).__name__}: {err})", offset=pos)
                pos += RECORD_HEADER.size + length
        except RecordOverrun as err:
            pos = err.offset
            if not err.cut_header:
                self.problem("bad_record", f"{err} (the data section ends at {limit})", offset=err.offset)
        if current is not None:
            self.finish_chunk(current)
        self.problem("no_data_end", "the data section has no DataEnd record where it should end", offset=pos)

    def record(self, offset: int, opcode: int, body: bytes, current: _Seen | None) -> _Seen | None:
        if opcode == Opcode.CHUNK:
            return self.chunk(offset, body)
        if opcode == Opcode.MESSAGE_INDEX:
            self.message_index(offset, body, current)
            return current
        if opcode == Opcode.MESSAGE:
            cid, _, log_time, _ = MESSAGE_HEADER.unpack_from(body, 0)
            self.loose += 1
            self.message(cid, log_time, body[MESSAGE_HEADER.size:], offset)
        elif opcode == Opcode.SCHEMA:
            self.add_schema(parse_record(body, Schema), offset)
        elif opcode == Opcode.CHANNEL:
            self.add_channel(parse_record(body, Channel), offset)
        elif opcode == Opcode.METADATA:
            record = parse_record(body, Metadata)
            self.metadata[offset] = record.name
            if record.name == BASE_METADATA_NAME:
                self.base_records.append(dict(record.metadata))
        elif opcode == Opcode.ATTACHMENT:
            record = parse_record(body, Attachment)
            (stored,) = struct.unpack_from("<I", body, len(body) - 4)
            if stored != 0 and crc32(body[:-4]) != stored:
                self.problem("attachment_crc", f"the attachment {record.name!r} fails its CRC", offset=offset)
        return None

    def add_schema(self, schema: Schema, offset: int) -> None:
        known = self.schemas.setdefault(schema.id, schema)
        if (known.name, known.encoding, bytes(known.data)) != (schema.name, schema.encoding, bytes(schema.data)):
            self.problem("schema_conflict", f"schema {schema.id} is defined twice, differently", offset=offset)

    def add_channel(self, channel: Channel, offset: int) -> None:
        known = self.channels.setdefault(channel.id, channel)
        if (known.topic, known.schema_id, known.message_encoding) != (channel.topic, channel.schema_id,
                                                                       channel.message_encoding):
            self.problem("channel_conflict", f"channel {channel.id} is defined twice, differently", offset=offset,
                         channel=channel.topic)

    def chunk(self, offset: int, body: bytes) -> _Seen | None:
        self.report.chunks += 1
        try:
            start, end, size, _, compression, compressed_size, _ = chunk_header(body)
        except Exception as err:
            self.problem("bad_chunk", f"the chunk header cannot be parsed ({err})", offset=offset)
            return None
        seen = _Seen(offset, RECORD_HEADER.size + len(body), start, end, compression, compressed_size, size, {})
        try:
            contents = decode_chunk(body)
        except ValueError as err:
            kind = "chunk_crc" if "CRC" in str(err) else "chunk_decompress"
            self.problem(kind, f"the chunk (log_time {start}..{end}) is damaged: {err}", offset=offset)
            return seen
        except Exception as err:  # zstd / lz4 errors
            self.problem("chunk_decompress", f"the chunk (log_time {start}..{end}) does not decompress "
                         f"({type(err).__name__}: {err})", offset=offset)
            return seen
        data = bytes(contents.data)
        try:
            for rel, opcode, at, length in iter_records(data):
                if opcode == Opcode.MESSAGE:
                    cid, _, log_time, _ = MESSAGE_HEADER.unpack_from(data, at)
                    seen.positions.setdefault(cid, []).append((log_time, rel))
                    if not start <= log_time <= end:
                        self.problem("chunk_time_range", f"a message at log_time {log_time} lies outside the "
                                     f"chunk's range {start}..{end}", offset=offset, log_time=log_time)
                    self.message(cid, log_time, data[at + MESSAGE_HEADER.size: at + length], offset)
                elif opcode == Opcode.SCHEMA:
                    self.add_schema(parse_record(data[at: at + length], Schema), offset)
                elif opcode == Opcode.CHANNEL:
                    self.add_channel(parse_record(data[at: at + length], Channel), offset)
        except Exception as err:
            self.problem("bad_chunk", f"the chunk's records cannot be parsed ({type(err).__name__}: {err})",
                         offset=offset)
        return seen

    def message_index(self, offset: int, body: bytes, current: _Seen | None) -> None:
        if current is None:
            self.problem("stray_message_index", "a message index record that follows no chunk", offset=offset)
            return
        cid = MESSAGE_INDEX_BODY.unpack_from(body, 0)[0]
        topic = self.channels[cid].topic if cid in self.channels else f"#{cid}"
        try:
            entries = sorted(parse_message_index(body)[1])
        except ValueError as err:
            self.problem("bad_message_index", str(err), offset=offset, channel=topic)
            return
        current.index_offsets[cid] = offset
        current.index_end = offset + RECORD_HEADER.size + len(body)
        if entries != sorted(current.positions.get(cid, [])):
            self.problem("message_index_mismatch", f"the message index of the chunk at {current.offset} does not "
                         "list the chunk's messages of this channel", offset=offset, channel=topic)

    def finish_chunk(self, seen: _Seen) -> None:
        if not self.indexes.compare(seen):
            self.unlisted.append(seen.offset)
        if not seen.index_offsets:
            if seen.positions:
                self.bare_chunks += 1
            return
        for cid in sorted(set(seen.positions) - set(seen.index_offsets)):
            topic = self.channels[cid].topic if cid in self.channels else f"#{cid}"
            self.problem("message_index_missing", "the chunk has message indexes, but none for this channel",
                         offset=seen.offset, channel=topic)

    # ------------------------------------------------------------------ messages
    def state(self, cid: int, offset: int) -> _ChannelState | None:
        if cid in self.states:
            return self.states[cid]
        channel = self.channels.get(cid)
        if channel is None:
            if cid not in self.unknown_channels:
                self.unknown_channels.add(cid)
                self.problem("unknown_channel", f"messages of channel id {cid}, which no channel record defines",
                             offset=offset)
            return None
        state = self.states[cid] = _ChannelState(channel.topic)
        schema = self.schemas.get(channel.schema_id)
        if channel.schema_id != 0 and schema is None:
            self.problem("missing_schema", f"the channel refers to schema {channel.schema_id}, which is not defined",
                         offset=offset, channel=channel.topic)
            return state
        try:
            self.prepare(state, schema, channel.message_encoding)
        except Exception as err:
            self.problem("bad_schema", f"its schema {schema.name if schema else ''!r} cannot be used to decode "
                         f"({type(err).__name__}: {err})", offset=offset, channel=channel.topic)
        return state

    def prepare(self, state: _ChannelState, schema: Schema | None, encoding: str) -> None:
        if schema is not None and is_image_schema(schema.name):
            state.decode, state.kind = cached_image_decoder(schema, encoding), "image"
            if state.decode is not None:
                state.frame_times = array("q")
                return
        if encoding == "json":
            state.kind = "json"
            if schema is not None and schema.encoding == "jsonschema":
                try:
                    state.checker = compile_json_schema(json.loads(schema.data))
                except (ValueError, TypeError, KeyError) as err:
                    self.problem("schema_not_checked", f"JSON messages are decoded but not checked against schema "
                                 f"{schema.name!r} ({err})", severity="note", channel=state.topic)
            return
        state.decode = message_decoder(schema, encoding)
        state.kind = "decoded" if state.decode is not None else "bytes"
        if state.decode is None:
            self.problem("not_decoded", f"message encoding {encoding!r} with schema "
                         f"{schema.name if schema else 'none'!r}: starlog checks only the container",
                         severity="note", channel=state.topic)

    def message(self, cid: int, log_time: int, data: bytes, offset: int) -> None:
        self.report.messages += 1
        self.counted[cid] = self.counted.get(cid, 0) + 1
        self.times = [min(self.times[0], log_time), max(self.times[1], log_time)] if self.times else [log_time] * 2
        state = self.state(cid, offset)
        if state is None:
            return
        state.count += 1
        if log_time < state.last:
            state.out_of_order += 1
        elif log_time == state.last and state.kind == "image":
            self.problem("duplicate_frame_time", "two frames at one log_time (stages need strictly increasing "
                         "frame times)", offset=offset, channel=state.topic, log_time=log_time)
        state.last = max(state.last, log_time)
        if state.frame_times is not None:
            state.frame_times.append(log_time)
        try:
            self.content(state, data, offset, log_time)
        except Exception as err:  # protobuf DecodeError, ROS deserialisation errors, InvalidInputError ...
            self.problem("decode_error", f"the message does not decode: {type(err).__name__}: {err}", offset=offset,
                         channel=state.topic, log_time=log_time)

    def content(self, state: _ChannelState, data: bytes, offset: int, log_time: int) -> None:
        if state.kind == "image" and state.decode is not None:
            image = state.decode(data).image
            shape = (image.shape, image.dtype)
            first = self.frame_shapes.setdefault(state.topic, shape)  # a topic's channels are one series of frames
            if image.ndim != 2:
                self.problem("image_size", "the frame is not a 2-D image", offset=offset, channel=state.topic,
                             log_time=log_time)
            elif shape != first:
                self.problem("image_size_changed", f"a {image.shape[1]}x{image.shape[0]} {image.dtype} frame in a "
                             f"channel of {first[0][1]}x{first[0][0]} {first[1]} frames",
                             offset=offset, channel=state.topic, log_time=log_time)
        elif state.kind == "json":
            value = decode_json(data)
            if state.checker is not None:
                problem = state.checker(value)
                if problem:
                    self.problem("json_schema", f"the message does not match its schema ({problem})", offset=offset,
                                 channel=state.topic, log_time=log_time)
        elif state.decode is not None:
            state.decode(data)

    def bare_chunks_detail(self) -> str:
        """The note on chunks without message indexes; when the summary's chunk indexes list such chunks (with
        messages), the TypeScript indexed reader Foxglove uses refuses to read them: say so, and how to rewrite."""
        detail = f"{self.bare_chunks} chunks have no message index records (valid; readers scan those chunks)"
        table = self.indexes.table
        if self.summary_damaged or not len(table):
            return detail
        bare = table.column("message_index_length") == 0
        timed = (table.column("message_start_time") != 0) | (table.column("message_end_time") != 0)
        if not np.any(bare & timed):
            return detail
        return (f"{detail}; Foxglove will not open this file (its reader refuses a chunk index without message "
                f"indexes): starlog filter {self.path} -o INDEXED.mcap rewrites it with them")

    # ------------------------------------------------------------------ indexes against contents
    def check_indexes(self) -> None:
        for offset, detail in self.indexes.problems():
            self.problem("chunk_index_mismatch", detail, offset=offset)
        if self.indexes.table and self.unlisted:
            for o in self.unlisted:
                self.problem("chunk_not_indexed", "the summary's chunk indexes do not list this chunk", offset=o)
        elif self.unlisted and self.summary and not self.summary_damaged:  # else its indexes may be unread
            self.problem("no_chunk_indexes", f"the summary lists none of the {len(self.unlisted)} chunks: readers "
                         "must scan the file", severity="note")
        names = {o: n for o, n in self.metadata.items()}
        for offset, mi in self.summary.get("metadata_indexes", []):
            if names.get(mi.offset) != mi.name:
                self.problem("metadata_index_mismatch", f"the metadata index {mi.name!r} points at {mi.offset}, where "
                             "no metadata record of that name is", offset=offset)
        self.check_statistics()

    def check_statistics(self) -> None:
        stats: Statistics | None = self.summary.get("statistics")
        if stats is None:
            if self.summary:
                self.problem("no_statistics", "the summary has no statistics record", severity="note")
            return
        start, end = self.times or [0, 0]
        wrong = [name for name, got, want in [
            ("message_count", stats.message_count, self.report.messages),
            ("chunk_count", stats.chunk_count, self.report.chunks),
            ("channel_message_counts", {k: v for k, v in stats.channel_message_counts.items() if v},
             {k: v for k, v in self.counted.items() if v}),
            ("message_start_time", stats.message_start_time, start),
            ("message_end_time", stats.message_end_time, end),
            ("metadata_count", stats.metadata_count, len(self.metadata))] if got != want]
        if wrong:
            self.problem("statistics_mismatch", f"the statistics record disagrees with the file in {', '.join(wrong)}")

    def check_definitions(self) -> None:
        """The summary's copies of the schema and channel records. The MCAP specification asks for them where
        chunk indexes name the channels (:data:`RULE_CHUNK_INDEXES`) and, for the channels, where the statistics
        count messages per channel (:data:`RULE_STATISTICS`): a warning when they lack (starlog reads the file in
        full; readers that take them from the summary, the mcap library's and Foxglove's, fail on files with
        chunk indexes). Elsewhere the copies are optional: a note."""
        if not self.summary or self.summary_damaged:
            return
        table = self.indexes.table
        stats: Statistics | None = self.summary.get("statistics")
        schemas, channels = self.summary_definitions
        indexed = table.channel_ids()
        counted = {c for c, n in (stats.channel_message_counts.items() if stats else ()) if n}
        used = indexed | counted | set(self.counted)
        every = set(self.channels) if stats and stats.channel_message_counts else set()  # RULE_STATISTICS: all
        unrepeated = self.schemas.keys() - schemas
        lacking = {cid: (cid not in channels, cid in used and self.channels[cid].schema_id in unrepeated)
                   for cid in sorted(used | every) if cid in self.channels}
        lacking = {cid: flags for cid, flags in lacking.items() if any(flags)}
        if not lacking:
            return
        rules = [rule for rule, broken in (
            (RULE_CHUNK_INDEXES, any(cid in indexed for cid in lacking)),
            (RULE_STATISTICS, bool(stats and stats.channel_message_counts) and any(f[0] for f in lacking.values())),
        ) if broken]
        what = " and ".join(kind for k, kind in enumerate(("channel", "schema")) if any(f[k] for f in lacking.values()))
        topics = list(dict.fromkeys(self.channels[cid].topic for cid in lacking))
        readers = (f"; readers that take them from the summary (the mcap library's, Foxglove's) cannot read these "
                   f"channels: starlog filter {self.path} -o OUT.mcap rewrites the file with them") if table else ""
        quoted = "; ".join(f'"{rule}"' for rule in rules)
        spec = f"the MCAP specification requires them there: {quoted}" if rules else \
            "valid MCAP: the summary's copies are optional"
        self.problem("definitions_not_in_summary", f"the summary does not repeat the {what} records of "
                     f"{len(lacking)} channels ({', '.join(topics[:5])}{', ...' if len(topics) > 5 else ''}), which "
                     f"starlog reads from the data section ({spec}){readers}",
                     severity="warning" if rules else "note", rule=quoted)

    def check_topics(self) -> None:
        """Channels sharing a topic: an error when the schemas of those with messages cannot be read as one series
        (the readers refuse such a topic as a series, :mod:`starlog.io.shared_topics`), else a note; image
        channels' frames of one topic must not share a log_time (the stages read them as one series of strictly
        increasing times)."""
        by_topic: dict[str, list[int]] = {}
        for cid in sorted(self.channels):
            by_topic.setdefault(self.channels[cid].topic, []).append(cid)
        for topic, ids in by_topic.items():
            if len(ids) < 2:
                continue
            channels = [self.channels[cid] for cid in ids if self.counted.get(cid)]  # as the readers count them
            conflict = topic_conflict(topic, [(c, self.schemas.get(c.schema_id) if c.schema_id else None)
                                              for c in channels])
            if conflict is not None:
                self.problem("topic_schemas_differ", f"{conflict}; {OTHER_READERS}", channel=topic)
                continue
            self.problem("shared_topic", f"channels {', '.join(map(str, ids))} share the topic (valid; read as one "
                         "series in log_time order, each message by its own channel's schema, as the mcap library "
                         "and Foxglove read it)", severity="note", channel=topic)
            self.check_frame_times(topic, [self.states[c] for c in ids if c in self.states])

    def check_frame_times(self, topic: str, states: list[_ChannelState]) -> None:
        """Frames of two channels of one image topic at one log_time (each channel's own are checked as read)."""
        times = [np.unique(np.frombuffer(s.frame_times, dtype=np.int64)) for s in states if s.frame_times]
        if len(times) < 2:
            return
        values, counts = np.unique(np.concatenate(times), return_counts=True)
        shared = counts > 1
        if np.any(shared):
            self.problem("duplicate_frame_time", f"{int(np.sum(counts[shared] - 1))} frames share a log_time with a "
                         "frame of another channel of the topic (stages read its channels' frames as one series, "
                         "whose times must increase strictly)", channel=topic, log_time=int(values[shared][0]))

    def finish(self) -> None:
        for cid, channel in sorted(self.channels.items()):
            if channel.schema_id != 0 and channel.schema_id not in self.schemas and cid not in self.states:
                self.problem("missing_schema", f"the channel refers to schema {channel.schema_id}, which is not "
                             "defined", channel=channel.topic)
        self.check_indexes()
        self.check_definitions()
        self.check_topics()
        if self.bare_chunks:
            self.problem("no_message_indexes", self.bare_chunks_detail(), severity="note")
        if self.loose:
            self.problem("messages_outside_chunks", f"{self.loose} messages are written outside chunks (valid; no "
                         "index lists them)", severity="note")
        for state in self.states.values():
            if state.out_of_order:
                self.problem("out_of_order", f"{state.out_of_order} messages come before an earlier message of "
                             "their channel in the file (valid; readers deliver them in log_time order)",
                             severity="note", channel=state.topic)
        self.report.channels = len(self.channels)


def verify_file(path: str | os.PathLike[str], *, on_progress: Callable[[int], object] | None = None) -> VerifyReport:
    """Check every record of the MCAP file at ``path`` alone; never raises for a damaged file.

    ``on_progress`` is called with the bytes of the data section checked so far, every few MB
    (for a progress bar).
    """
    return _verify_file(Path(path), on_progress)[0]


def _verify_file(path: Path, on_progress: Callable[[int], object] | None) -> tuple[VerifyReport, _Verifier | None]:
    report = VerifyReport(str(path))
    verifier = None
    try:
        with open(path, "rb") as f:
            report.size = size = f.seek(0, os.SEEK_END)
            verifier = _Verifier(path, f, report, on_progress)
            envelope = verifier.envelope(size)
            if envelope is None:
                if not report.problems or report.problems[0].kind != "bad_magic":
                    verifier.walk_data(size, None)  # a cut-off file: still check what is there
                    report.channels = len(verifier.channels)  # those the records read define
                return report, verifier
            summary_start, summary_offset_start, crc, footer = envelope
            data_end = verifier.read_summary(summary_start, summary_offset_start, crc, footer)
            verifier.walk_data(footer if data_end is None else data_end + _DATA_END_LENGTH, data_end)
            verifier.finish()
    except OSError as err:
        report.problems.append(Problem("unreadable", "error", f"the file cannot be read ({err.strerror or err})"))
    except Exception as err:  # never a traceback: whatever was not foreseen is still reported
        report.problems.append(Problem("unexpected", "error", f"verification stopped: {type(err).__name__}: {err}"))
    return report, verifier


@dataclass
class ChainReport:
    """What :func:`verify_log` found: each file of the chain (first log first) and the chain's own problems.

    ``problems``, ``errors`` and the counts cover every file, so a report of a whole log (one file)
    reads as that file's :class:`VerifyReport`.
    """

    path: str
    files: list[VerifyReport] = field(default_factory=list)
    chain_problems: list[Problem] = field(default_factory=list)
    base_checked: bool = True  # False when the newest file is a layer checked alone
    missing_base: str = ""  # the base that is missing (or a file of its own chain), when one is

    @property
    def problems(self) -> list[Problem]:
        return [p for f in self.files for p in f.problems] + self.chain_problems

    @property
    def errors(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == "error"]

    @property
    def ok(self) -> bool:
        """No error: every starlog command reads the log in full."""
        return not self.errors

    @property
    def status(self) -> str:
        """The log's status, as :attr:`VerifyReport.status` says it of a file (a chain's own errors are damage)."""
        return _status(self.problems)

    @property
    def exit_status(self) -> int:
        """``starlog verify``'s exit status (:data:`EXIT_STATUS`)."""
        return EXIT_STATUS[self.status]

    @property
    def size(self) -> int:
        return sum(f.size for f in self.files)

    @property
    def messages(self) -> int:
        return sum(f.messages for f in self.files)

    @property
    def chunks(self) -> int:
        return sum(f.chunks for f in self.files)

    @property
    def channels(self) -> int:
        return sum(f.channels for f in self.files)

    def verdict(self) -> str:
        """One line for the whole log."""
        if len(self.files) == 1 and self.base_checked and not self.chain_problems:
            return self.files[0].verdict()
        what = (f"a layer checked alone (its base was not checked: verify {self.path} without --file-only)"
                if not self.base_checked else
                f"a chain of {len(self.files)} files whose base {self.missing_base} could not be checked"
                if self.missing_base else f"a chain of {len(self.files)} files")
        status = self.status
        checked = "" if not self.base_checked else ", every base the file its layer was written on"
        if status == "valid":
            return f"OK: {self.path} is {what}: every file valid{checked}."
        if status == "nonconformant":
            files = ", ".join(f.path for f in self.files if f.status == "nonconformant")
            return (f"NONCONFORMANT: {self.path} is {what}, read in full by starlog{checked}; {files} does not "
                    "conform to the MCAP specification (see above). Write the log as one conforming file with: "
                    f"starlog filter {self.path} -o OUT.mcap")
        parts = [f"{kind} files: {', '.join(f.path for f in self.files if f.status == kind)}{why}"
                 for kind, why in (("damaged", " (keep what is intact with starlog recover)"),
                                   ("refused", " (valid MCAP, part of which starlog refuses: see above)"))
                 if any(f.status == kind for f in self.files)]
        errors = sorted({p.kind for p in self.chain_problems if p.severity == "error"})
        parts += [f"chain errors: {', '.join(errors)} (see above)"] if errors else []
        return f"{status.upper()}: {self.path} is {what}; {'; '.join(parts)}."

    def to_dict(self) -> dict[str, Any]:
        problems = [{**p.to_dict(), "file": f.path} for f in self.files for p in f.problems]
        problems += [{**p.to_dict(), "file": self.path} for p in self.chain_problems]
        return {"path": self.path, "ok": self.ok, "status": self.status, "verdict": self.verdict(),
                "size_bytes": self.size,
                "messages": self.messages, "chunks": self.chunks, "channels": self.channels,
                "problems": problems, "files": [f.to_dict() for f in self.files]}

    def lines(self, per_kind: int = 20) -> list[str]:
        """Every problem, at most ``per_kind`` of a kind per file (and of the chain), each file's verdict when
        there are several, and the verdict."""
        several = len(self.files) > 1
        lines = []
        for file in self.files:
            lines += [f"{file.path}:"] if several else []
            lines += _problem_lines(file.problems, per_kind)
            lines += [f"  {file.verdict()}"] if several else []
        return lines + _problem_lines(self.chain_problems, per_kind) + [self.verdict()]


def _problem_lines(problems: list[Problem], per_kind: int) -> list[str]:
    """One line per problem, at most ``per_kind`` of a kind, then how many more of each kind (all with --json)."""
    shown: dict[str, int] = {}
    lines = []
    for problem in problems:
        shown[problem.kind] = shown.get(problem.kind, 0) + 1
        if shown[problem.kind] <= per_kind:
            lines.append(problem.line())
    for kind, count in shown.items():
        if count > per_kind:
            lines.append(f"... {count - per_kind} more {kind} problems (all of them with --json)")
    return lines


def verify_log(path: str | os.PathLike[str], *, chain: bool = True,
               on_progress: Callable[[int, int], object] | None = None) -> ChainReport:
    """Check every record of the log at ``path`` and, for a layer, of every file of its chain (``chain=False``:
    the file alone); never raises for a damaged file.

    Besides each file's own checks (:func:`verify_file`): each base is the file its layer recorded (where,
    size, CRCs, SHA-256), the digests of its own chain are those the layer recorded, and schema ids, channel
    ids and topics are unique across the chain. ``on_progress`` is called with the bytes checked so far and
    the bytes of the files found so far.
    """
    report = ChainReport(str(path))
    layer, verified, done = Path(path), [], 0
    total = layer.stat().st_size if layer.is_file() else 0

    def progress(offset: int) -> None:
        if on_progress is not None:
            on_progress(done + offset, total)

    expected: tuple[Path, BaseReference, BackgroundDigest] | None = None
    while True:
        file_report, verifier = _verify_file(layer, progress)
        report.files.insert(0, file_report)
        verified.append(verifier)
        done += file_report.size
        reference = _base_record(report, layer, verifier)
        if expected is not None:
            _check_base(report, *expected, reference)
        if reference is None:
            break
        if not chain:
            report.base_checked = False
            break
        base = _followable_base(report, layer, reference, [Path(f.path) for f in report.files])
        if base is None:
            break
        total += base.stat().st_size
        expected = (layer, reference, BackgroundDigest(base))
        layer = base
    _check_ids(report, [v for v in reversed(verified) if v is not None])
    return report


def _followable_base(report: ChainReport, layer: Path, reference: BaseReference, seen: list[Path]) -> Path | None:
    """The base of ``layer`` when it can be checked next; else None, with the problem reported."""
    base = reference.resolve(layer)
    problem = ("is missing" if not base.is_file() else
               "is a file of its own chain" if any(os.path.samefile(base, p) for p in seen if p.is_file()) else None)
    if problem is not None:
        report.chain_problems.append(_base_problem("base_missing" if problem == "is missing" else "base_cycle",
                                                   layer, base, reference, problem))
        report.missing_base = str(base)
        return None
    return base


def _base_problem(kind: str, layer: Path, base: Path, reference: BaseReference, problem: str) -> Problem:
    return Problem(kind, "error", str(BaseMismatchError(layer, base, reference.describe(), problem)))


def _base_record(report: ChainReport, layer: Path, verifier: _Verifier | None) -> BaseReference | None:
    records = [] if verifier is None else verifier.base_records
    if len(records) > 1:
        report.chain_problems.append(Problem("bad_base_record", "error", f"{layer} has {len(records)} base records"))
    try:
        return BaseReference.from_metadata(records[0], layer) if records else None
    except CorruptLogError as err:
        report.chain_problems.append(Problem("bad_base_record", "error", str(err)))
        return None


def _check_base(report: ChainReport, layer: Path, reference: BaseReference, digest: BackgroundDigest,
                base_reference: BaseReference | None) -> None:
    """Size, CRCs, SHA-256 and chain digests of the base of ``layer`` against what the layer recorded of it."""
    base = reference.resolve(layer)
    try:
        open_base(layer, reference).close()
    except BaseMismatchError as err:
        report.chain_problems.append(_base_problem("base_changed", layer, base, reference, err.problem))
    try:
        sha256 = digest.result()
    except OSError as err:
        sha256 = f"unreadable ({err.strerror or err})"
    if sha256 != reference.sha256:
        report.chain_problems.append(_base_problem("base_digest", layer, base, reference, f"has SHA-256 {sha256}"))
    below = () if base_reference is None else (base_reference.sha256, *base_reference.chain)
    if below != reference.chain:
        report.chain_problems.append(_base_problem("chain_mismatch", layer, base, reference,
                                                   f"stands on files of SHA-256 {list(below)}, not the "
                                                   f"{list(reference.chain)} recorded"))


def _check_ids(report: ChainReport, verifiers: list[_Verifier]) -> None:
    files = [(v.path, v.schemas, v.channels, [c.topic for c in v.channels.values()]) for v in verifiers]
    for collision in id_collisions(files):
        report.chain_problems.append(Problem("chain_collision", "error", collision))
