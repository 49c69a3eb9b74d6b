"""The checks ``starlog verify`` makes of one file: its footer, its summary section, and a walk of its data section.

The footer is read as every reader reads it (:func:`~starlog.io.layout.read_footer`), the summary
section parsed as :class:`~starlog.io.reader.LogReader` parses it (:mod:`starlog.io.summary_section`;
one it refuses is a ``bad_summary``), a block at a time (once for its CRC, once for its records),
and the data section walked once by the pass the log layer's scans share
(:mod:`starlog.io.data_section`, :class:`FileVerifier` its visitor), chunk by chunk; memory holds one
chunk, per-channel counters (and 8 bytes a frame of each image channel, to compare the frame times
of a topic's channels) and the summary's chunk indexes by column (about 100 bytes a chunk: each is
compared with its chunk as the walk finishes that chunk, :mod:`starlog.io.verify_indexes`). The
messages' contents are checked by :mod:`starlog.io.verify_messages`.
"""

from __future__ import annotations

import os
from array import array
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import numpy as np
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Metadata, Schema, SummaryOffset

from starlog.io.chain import BASE_METADATA_NAME
from starlog.io.checksum import crc32
from starlog.io.chunks import decode_chunk
from starlog.io.data_section import DataVisitor, MessageHead, walk_chunk, walk_data_section
from starlog.io.layout import (
    DATA_END_RECORD_LEN,
    MAGIC,
    MESSAGE_INDEX_BODY,
    RECORD_HEADER,
    U32,
    Footer,
    FooterError,
    chunk_header,
    parse_message_index,
    parse_record,
    read_footer,
    summary_crc,
)
from starlog.io.record_walk import RecordOverrun
from starlog.io.summary_section import SummarySection
from starlog.io.verify_indexes import ChunkIndexCheck, Seen
from starlog.io.verify_messages import ChannelChecks
from starlog.io.verify_report import Problem, VerifyReport

__all__ = ["RULE_CHUNK_INDEXES", "RULE_STATISTICS", "FileVerifier", "verify_one"]

#: The rules of the MCAP specification on the summary's copies of schema and channel records.
RULE_CHUNK_INDEXES = ("A Schema and Channel record MUST exist in the summary section for all channels referenced by "
                      "chunk index records")
RULE_STATISTICS = ("When using a Statistics record with a non-empty channel_message_counts, the Summary Data section "
                   "MUST contain a copy of all Channel records")


MAGIC_LENGTH = len(MAGIC)
_PROGRESS_STEP = 8 << 20  # bytes of the data section between two progress reports
#: The footer's problems, by :attr:`~starlog.io.layout.FooterError.kind`.
_FOOTER_PROBLEMS = {"not_mcap": "bad_magic", "truncated": "truncated", "no_footer": "bad_footer"}


class FileVerifier(DataVisitor):
    """The checks of one file: its footer and summary, then a walk of its data section (the callbacks of
    :class:`~starlog.io.data_section.DataVisitor`), then the indexes and statistics against what the walk found."""

    bodies = frozenset({Opcode.CHUNK, Opcode.MESSAGE_INDEX, Opcode.MESSAGE, Opcode.SCHEMA, Opcode.CHANNEL,
                        Opcode.METADATA, Opcode.ATTACHMENT})

    def __init__(self, path: Path, f: BinaryIO, report: VerifyReport,
                 on_progress: Callable[[int], object] | None = None) -> None:
        self.path, self.f, self.report = path, f, report
        self.on_progress = on_progress
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.messages = ChannelChecks(self.schemas, self.channels, report, self.problem)
        self.indexes = ChunkIndexCheck()
        self.unlisted = array("Q")  # offsets of the chunks no chunk index points at
        self.metadata_names: dict[int, str] = {}  # the name of the metadata record at each offset
        self.section: SummarySection | None = None  # the summary section, once its footer and CRC are checked
        self.summary_damaged = False  # a record of the summary section does not parse
        self.loose = 0
        self.bare_chunks = 0
        self.base_records: list[dict[str, str]] = []
        self.summary_definitions: tuple[set[int], set[int]] = (set(), set())  # schema and channel ids it repeats
        self.current: Seen | None = None  # the chunk whose message indexes may follow
        self.reported = 0  # the offset of the last progress report
        self.position = MAGIC_LENGTH  # the end of the record being checked
        self.expected_end: int | None = None  # where the DataEnd record must be
        self.ended = False  # the DataEnd record was met

    def problem(self, kind: str, detail: str, *, severity: str = "error", offset: int | None = None,
                channel: str | None = None, log_time: int | None = None, rule: str = "") -> None:
        self.report.problems.append(Problem(kind, severity, detail, offset, channel, log_time, rule))

    # ------------------------------------------------------------------ frame of the file
    def footer(self) -> Footer | None:
        """The footer, checked (None, with the problem reported, when there is none to go by)."""
        try:
            footer = read_footer(self.f)
        except FooterError as err:
            self.problem(_FOOTER_PROBLEMS[err.kind], err.detail, offset=err.offset)
            return None
        if footer.length != 20:
            self.problem("bad_footer", f"no footer record before the closing magic (opcode {Opcode.FOOTER:#04x})",
                         offset=footer.offset)
            return None
        return footer

    # ------------------------------------------------------------------ summary section
    def read_summary(self, footer: Footer) -> int | None:
        """Parse and check the summary section; return where the data section must end (its DataEnd)."""
        start, offsets_start, crc, end = footer.summary_start, footer.summary_offset_start, footer.summary_crc, \
            footer.offset
        if start == 0:
            self.problem("no_summary", "the file has no summary section: readers must scan it whole; add one with "
                         f"starlog recover {self.path} -o INDEXED.mcap", severity="note")
            return None
        if not MAGIC_LENGTH + DATA_END_RECORD_LEN <= start <= end or (
                offsets_start and not start <= offsets_start <= end):
            self.problem("bad_footer", f"the footer points outside the file (summary at {start}, summary "
                         f"offsets at {offsets_start})", offset=end)
            return None
        if crc != 0:
            computed = summary_crc(self.f, footer)
            if computed != crc:
                self.problem("summary_crc", f"the summary's CRC {computed:#010x} does not match the footer's "
                             f"{crc:#010x}: the summary section is damaged", offset=start)
        section = self.section = SummarySection(where=True)
        try:
            section.read(self.f, start, end)
        except Exception as err:  # struct.error, EOFError, ValueError, UnicodeDecodeError from a damaged record
            self.problem("bad_summary", f"the summary section cannot be parsed ({type(err).__name__}: {err})",
                         offset=start)
            self.summary_damaged = True
        self.schemas.update(section.summary.schemas)
        self.channels.update(section.summary.channels)
        self.summary_definitions = set(section.summary.schemas), set(section.summary.channels)
        self.indexes = ChunkIndexCheck(section.table, section.chunk_index_offsets)
        for offset, record in section.summary_offsets:
            self.check_summary_offset(offset, record, start, end)
        return start - DATA_END_RECORD_LEN

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

    # ------------------------------------------------------------------ data section
    def walk_data(self, limit: int, expected_end: int | None) -> None:
        """Every record from the header to the DataEnd record, chunks opened and checked."""
        self.expected_end = expected_end
        try:
            walk_data_section(self.f, MAGIC_LENGTH, limit, self)
        except RecordOverrun as err:
            self.position = err.offset
            if not err.cut_header:
                self.problem("bad_record", f"{err} (the data section ends at {limit})", offset=err.offset)
        if self.current is not None:
            self.finish_chunk(self.current)
            self.current = None
        if not self.ended:
            self.problem("no_data_end", "the data section has no DataEnd record where it should end",
                         offset=self.position)

    def record(self, offset: int, opcode: int, length: int) -> None:
        if self.on_progress is not None and offset - self.reported >= _PROGRESS_STEP:
            self.reported = offset
            self.on_progress(offset)
        if offset == MAGIC_LENGTH and opcode != Opcode.HEADER:
            self.problem("no_header", f"the first record is opcode {opcode:#04x}, not a header", offset=offset)
        if self.current is not None and opcode != Opcode.MESSAGE_INDEX:
            self.finish_chunk(self.current)
            self.current = None
        self.position = offset + RECORD_HEADER.size + length

    def damaged(self, offset: int, opcode: int, error: Exception) -> None:
        self.problem("bad_record", f"the record at offset {offset} (opcode {opcode:#04x}) cannot be parsed "
                     f"({type(error).__name__}: {error})", offset=offset)

    def data_end(self, offset: int, length: int) -> None:
        if self.expected_end is not None and offset != self.expected_end:
            self.problem("bad_data_end", f"the data section ends at {offset}, the footer says {self.expected_end}",
                         offset=offset)
        self.done = self.ended = True

    def message(self, offset: int, length: int, head: MessageHead, payload: memoryview | None) -> None:
        self.loose += 1
        self.messages.message(head[0], head[2], bytes(payload or b""), offset)

    def schema(self, offset: int, schema: Schema) -> None:
        self.add_schema(schema, offset)

    def channel(self, offset: int, channel: Channel) -> None:
        self.add_channel(channel, offset)

    def metadata(self, offset: int, length: int, body: memoryview | None) -> None:
        record = parse_record(body, Metadata)  # type: ignore[arg-type]  # its body is read
        self.metadata_names[offset] = record.name
        if record.name == BASE_METADATA_NAME:
            self.base_records.append(dict(record.metadata))

    def attachment(self, offset: int, length: int, body: memoryview | None) -> None:
        assert body is not None
        record = parse_record(body, Attachment)
        (stored,) = U32.unpack_from(body, len(body) - U32.size)
        if stored != 0 and crc32(body[:-4]) != stored:
            self.problem("attachment_crc", f"the attachment {record.name!r} fails its CRC", offset=offset)

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

    def chunk(self, offset: int, length: int, body: memoryview | None) -> None:
        assert body is not None
        self.report.chunks += 1
        try:
            start, end, size, _, compression, compressed_size, _ = chunk_header(body)
        except Exception as err:
            self.problem("bad_chunk", f"the chunk header cannot be parsed ({err})", offset=offset)
            return
        self.current = Seen(offset, RECORD_HEADER.size + length, start, end, compression, compressed_size,
                            size, {})
        try:
            contents = decode_chunk(body)
        except ValueError as err:
            kind = "chunk_crc" if "CRC" in str(err) else "chunk_decompress"
            self.problem(kind, f"the chunk (log_time {start}..{end}) is damaged: {err}", offset=offset)
            return
        except Exception as err:  # zstd / lz4 errors
            self.problem("chunk_decompress", f"the chunk (log_time {start}..{end}) does not decompress "
                         f"({type(err).__name__}: {err})", offset=offset)
            return
        try:
            walk_chunk(contents.data, self, offset)
        except Exception as err:
            self.problem("bad_chunk", f"the chunk's records cannot be parsed ({type(err).__name__}: {err})",
                         offset=offset)

    def chunk_message(self, position: int, head: MessageHead, payload: memoryview) -> None:
        seen = self.current
        assert seen is not None
        cid, _, log_time, _ = head
        seen.positions.setdefault(cid, []).append((log_time, position))
        if not seen.start <= log_time <= seen.end:
            self.problem("chunk_time_range", f"a message at log_time {log_time} lies outside the chunk's range "
                         f"{seen.start}..{seen.end}", offset=seen.offset, log_time=log_time)
        self.messages.message(cid, log_time, bytes(payload), seen.offset)

    def message_index(self, offset: int, length: int, body: memoryview | None) -> None:
        current = self.current
        if current is None:
            self.problem("stray_message_index", "a message index record that follows no chunk", offset=offset)
            return
        cid = MESSAGE_INDEX_BODY.unpack_from(body, 0)[0]  # type: ignore[arg-type]  # its body is read
        topic = self.channels[cid].topic if cid in self.channels else f"#{cid}"
        try:
            entries = sorted(parse_message_index(body)[1])  # type: ignore[arg-type]
        except ValueError as err:
            self.problem("bad_message_index", str(err), offset=offset, channel=topic)
            return
        current.index_offsets[cid] = offset
        current.index_end = offset + RECORD_HEADER.size + length
        if entries != sorted(current.positions.get(cid, [])):
            self.problem("message_index_mismatch", f"the message index of the chunk at {current.offset} does not "
                         "list the chunk's messages of this channel", offset=offset, channel=topic)

    def finish_chunk(self, seen: Seen) -> None:
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

    # ------------------------------------------------------------------ indexes against contents
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
        elif self.unlisted and self.section is not None and not self.summary_damaged:  # else its indexes may be unread
            self.problem("no_chunk_indexes", f"the summary lists none of the {len(self.unlisted)} chunks: readers "
                         "must scan the file", severity="note")
        indexes = self.section.summary.metadata_indexes if self.section is not None else []
        offsets = self.section.metadata_index_offsets if self.section is not None else []
        for offset, mi in zip(offsets, indexes, strict=True):
            if self.metadata_names.get(mi.offset) != mi.name:
                self.problem("metadata_index_mismatch", f"the metadata index {mi.name!r} points at {mi.offset}, where "
                             "no metadata record of that name is", offset=offset)
        self.check_statistics()

    def check_statistics(self) -> None:
        stats = self.section.summary.statistics if self.section is not None else None
        if stats is None:
            if self.section is not None:
                self.problem("no_statistics", "the summary has no statistics record", severity="note")
            return
        start, end = self.messages.times or [0, 0]
        wrong = [name for name, got, want in [
            ("message_count", stats.message_count, self.report.messages),
            ("chunk_count", stats.chunk_count, self.report.chunks),
            ("channel_message_counts", {k: v for k, v in stats.channel_message_counts.items() if v},
             {k: v for k, v in self.messages.counted.items() if v}),
            ("message_start_time", stats.message_start_time, start),
            ("message_end_time", stats.message_end_time, end),
            ("metadata_count", stats.metadata_count, len(self.metadata_names))] if got != want]
        if wrong:
            self.problem("statistics_mismatch", f"the statistics record disagrees with the file in {', '.join(wrong)}")

    def check_definitions(self) -> None:
        """The summary's copies of the schema and channel records. The MCAP specification asks for them where
        chunk indexes name the channels (:data:`RULE_CHUNK_INDEXES`) and, for the channels, where the statistics
        count messages per channel (:data:`RULE_STATISTICS`): a warning when they lack (starlog reads the file in
        full; readers that take them from the summary, the mcap library's and Foxglove's, fail on files with
        chunk indexes). Elsewhere the copies are optional: a note."""
        if self.section is None or self.summary_damaged:
            return
        table = self.indexes.table
        stats = self.section.summary.statistics
        schemas, channels = self.summary_definitions
        indexed = table.channel_ids()
        counted = {c for c, n in (stats.channel_message_counts.items() if stats else ()) if n}
        used = indexed | counted | set(self.messages.counted)
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

    def finish(self) -> None:
        for cid, channel in sorted(self.channels.items()):
            if channel.schema_id != 0 and channel.schema_id not in self.schemas and cid not in self.messages.states:
                self.problem("missing_schema", f"the channel refers to schema {channel.schema_id}, which is not "
                             "defined", channel=channel.topic)
        self.check_indexes()
        self.check_definitions()
        self.messages.check_topics()
        if self.bare_chunks:
            self.problem("no_message_indexes", self.bare_chunks_detail(), severity="note")
        if self.loose:
            self.problem("messages_outside_chunks", f"{self.loose} messages are written outside chunks (valid; no "
                         "index lists them)", severity="note")
        for state in self.messages.states.values():
            if state.out_of_order:
                self.problem("out_of_order", f"{state.out_of_order} messages come before an earlier message of "
                             "their channel in the file (valid; readers deliver them in log_time order)",
                             severity="note", channel=state.topic)
        self.report.channels = len(self.channels)


def verify_one(path: Path, on_progress: Callable[[int], object] | None) -> tuple[VerifyReport, FileVerifier | None]:
    """The report on the file at ``path`` alone, and its verifier (None when the file cannot be opened)."""
    report = VerifyReport(str(path))
    verifier = None
    try:
        with open(path, "rb") as f:
            report.size = size = f.seek(0, os.SEEK_END)
            verifier = FileVerifier(path, f, report, on_progress)
            footer = verifier.footer()
            if footer is None:
                if report.problems[-1].kind != "bad_magic" and size >= MAGIC_LENGTH:
                    verifier.walk_data(size, None)  # a cut-off file: still check what is there
                    report.channels = len(verifier.channels)  # those the records read define
                return report, verifier
            data_end = verifier.read_summary(footer)
            verifier.walk_data(footer.offset if data_end is None else data_end + DATA_END_RECORD_LEN, data_end)
            verifier.finish()
    except OSError as err:
        report.problems.append(Problem("unreadable", "error", f"the file cannot be read ({err.strerror or err})"))
    except Exception as err:  # never a traceback: whatever was not foreseen is still reported
        report.problems.append(Problem("unexpected", "error", f"verification stopped: {type(err).__name__}: {err}"))
    return report, verifier
