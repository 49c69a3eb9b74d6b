"""One MCAP file, opened with every check: its summary, its chunks and their indexes.

Nothing damaged is passed on. On opening, the footer, the summary's CRC and the consistency of
its indexes are checked; while reading, every chunk's CRC, its records, and its message index are
checked against each other. A problem raises :class:`~starlog.errors.TruncatedLogError` (file
cut off or never finished), :class:`~starlog.errors.CorruptChunkError` (naming the chunk's offset,
channels and time range) or :class:`~starlog.errors.CorruptLogError`, each pointing to
``starlog recover``. Valid files that lack some indexes (no summary, chunks without message
indexes, messages outside chunks) are read in full by scanning (:mod:`starlog.io.scan`); the
schemas and channels a summary does not repeat are read from the data section.

:class:`~starlog.io.reader.LogReader` reads a log, which is one file or a chain of them, through
this class; the log layer's other tools (chains, copying, info) use its public methods.

One module of over 500 lines: :class:`McapFile`'s opening (footer, summary, the indexes it lacks)
and its chunk reads share the parsed summary and the open file, so they are one class; the checks of
the summary are :mod:`starlog.io.summary_checks`.
"""

from __future__ import annotations

import heapq
import itertools
import os
import struct
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO

import numpy as np
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import ChunkIndex, Header, Message, Metadata, MetadataIndex
from mcap.summary import Summary

from starlog.errors import CorruptChunkError, CorruptLogError, LogNotFoundError
from starlog.io.chunk_indexes import ChunkIndexTable
from starlog.io.chunks import ChunkContents, decode_chunk
from starlog.io.layout import (
    DATA_END,
    MAGIC,
    MESSAGE_HEADER,
    MESSAGE_INDEX_BODY,
    MESSAGE_INDEX_ENTRY,
    RECORD_HEADER,
    Footer,
    FooterError,
    locate_data_end,
    parse_message_index,
    parse_record,
    read_footer,
    summary_crc,
)
from starlog.io.record_walk import walk_records
from starlog.io.scan import (
    Gaps,
    LooseRun,
    find_definitions,
    find_loose_runs,
    read_definitions,
    read_loose,
    synthesize_summary,
)
from starlog.io.channel_summary import add_extent
from starlog.io.summary_checks import layout_problems, reference_problems
from starlog.io.summary_section import read_summary
from starlog.io.timerange import END_OF_TIME

__all__ = ["McapFile", "recover_hint"]

#: ``(log_time, position in its chunk, channel id, message)`` of a message read from a chunk.
ChunkMessage = tuple[int, int, int, Message]


def recover_hint(path: Path) -> str:
    """The sentence every error about a damaged file ends with."""
    return f"Rebuild a readable copy with: starlog recover {path} -o RECOVERED.mcap"






class _Peekable:
    """An iterator whose next item can be looked at (``peek``; None at the end) before it is taken."""

    def __init__(self, items: Iterator[Any]) -> None:
        self._items = items
        self.peek = next(items, None)

    def pop(self) -> Any:
        item, self.peek = self.peek, next(self._items, None)
        return item


class McapFile:
    """One MCAP file, its summary checked (or, for a file without indexes, rebuilt by a scan).

    Parameters
    ----------
    path : path-like
        The file.
    validate_crcs : bool
        Check the summary's and every chunk's CRC (default). A mismatch raises
        :class:`CorruptLogError` / :class:`CorruptChunkError`.
    """

    def __init__(self, path: str | os.PathLike[str], *, validate_crcs: bool = True) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise LogNotFoundError(self.path)
        self.validate_crcs = validate_crcs
        self.notes: list[str] = []
        self.summary_verified = False
        self._loose: list[LooseRun] = []
        self._extents: dict[int, list[int]] | None = None  # count, first, last per channel (unindexed parts)
        self._indexed = True
        self._file: BinaryIO = open(self.path, "rb")
        try:
            self.data_end = self._open()
            self.data_section_crc: int = DATA_END.unpack(self.read_bytes(self.data_end, DATA_END.size))[2]
        except BaseException:
            self._file.close()
            raise

    # ------------------------------------------------------------------ opening
    def _open(self) -> int:
        f = self._file
        try:
            self.footer: Footer = read_footer(f)
            data_end = locate_data_end(self.path, f, self.footer)
        except FooterError as err:
            raise err.log_error(self.path) from err
        except CorruptLogError as err:
            raise CorruptLogError(self.path, f"{err.reason} {recover_hint(self.path)}") from err
        except (ValueError, OSError, struct.error) as err:  # footer pointing before the file start
            raise CorruptLogError(self.path, f"its footer is damaged ({err}). {recover_hint(self.path)}") from err
        footer = self.footer
        if footer.summary_start == 0:
            self._scan_everything(data_end, "it has no summary section")
            return data_end
        if not data_end < footer.summary_start <= footer.offset or not (
            footer.summary_offset_start == 0 or footer.summary_start <= footer.summary_offset_start <= footer.offset
        ):
            raise CorruptLogError(self.path, f"its footer points outside the file (summary at {footer.summary_start}, "
                                             f"summary offsets at {footer.summary_offset_start}). "
                                             f"{recover_hint(self.path)}")
        if self.validate_crcs and footer.summary_crc != 0:
            crc = summary_crc(f, footer)
            if crc != footer.summary_crc:
                raise CorruptLogError(
                    self.path, f"its summary section (offset {footer.summary_start}..{footer.offset}) is damaged: "
                    f"CRC {crc:#010x} does not match the footer's {footer.summary_crc:#010x}. "
                    f"{recover_hint(self.path)}")
            self.summary_verified = True
        try:
            self.summary: Summary = read_summary(f, footer.summary_start, footer.offset)
        except (McapError, ValueError, EOFError, OSError, struct.error, KeyError, MemoryError) as err:
            raise CorruptLogError(self.path, f"its summary cannot be read ({type(err).__name__}: {err}). "
                                             f"{recover_hint(self.path)}") from err
        self._check_layout(data_end)
        self._find_unindexed(data_end)
        return data_end

    def _scan_everything(self, data_end: int, why: str, known: Summary | None = None) -> None:
        """Build the missing summary by one linear scan of the data section (every chunk CRC-checked)."""
        try:
            result = synthesize_summary(self.path, self._file, data_end, known=known)
        except (ValueError, struct.error, McapError, EOFError, UnicodeDecodeError) as err:
            raise CorruptLogError(self.path, f"{why}, and a linear scan of it stops: {err}. "
                                             f"{recover_hint(self.path)}") from err
        self.summary = result.summary
        self._loose = result.loose
        self._extents = result.extents
        self._indexed = False
        self._check_summary(data_end)
        self.add_note(f"{why}: read by a linear scan of the whole file; add the indexes with: "
                      f"starlog recover {self.path} -o INDEXED.mcap")

    def _find_unindexed(self, data_end: int) -> None:
        """Messages outside chunks, chunks the summary does not list, chunks without message indexes, and the
        schemas and channels the summary does not repeat."""
        try:
            gaps = find_loose_runs(self._file, self.summary, data_end)
        except (ValueError, struct.error, EOFError, UnicodeDecodeError, McapError) as err:
            raise CorruptLogError(self.path, f"its data section is damaged outside every indexed record ({err}). "
                                             f"{recover_hint(self.path)}") from err
        self._loose = gaps.runs
        self.summary.metadata_indexes += gaps.metadata_indexes
        self.summary.attachment_indexes += gaps.attachment_indexes
        if gaps.unlisted_chunk:
            why = "its summary lists no chunk indexes" if not self.summary.chunk_indexes else \
                "it has chunks its summary does not list"
            self._scan_everything(data_end, why, known=self.summary)
            return
        bare = int(np.count_nonzero(self.summary.chunk_indexes.entry_counts() == 0))
        if bare:
            self.add_note(f"{bare} of {len(self.summary.chunk_indexes)} chunks have no message indexes: each is "
                          "read by scanning it whole.")
        if self._loose:
            self.add_note("some messages lie outside chunks (no index lists them): they are found by walking the "
                          "data section and read in log_time order with the rest.")
        self._indexed = not bare and not self._loose
        self._complete_definitions(gaps)
        self._check_references()

    def _complete_definitions(self, gaps: Gaps) -> None:
        """Add to the summary the schemas and channels it does not repeat (valid MCAP: they are in the data
        section), found between the indexed records, then in the chunks (:func:`find_definitions`). Without
        per-channel statistics, chunks without message indexes may hold any channel: they are read whole
        once, their extents kept for :meth:`channel_extents`."""
        summary = self.summary
        known = len(summary.schemas) + len(summary.channels)
        for schema in gaps.schemas.values():
            summary.schemas.setdefault(schema.id, schema)
        for channel in gaps.channels.values():
            summary.channels.setdefault(channel.id, channel)
        table: ChunkIndexTable = summary.chunk_indexes
        opened = 0
        if not self._counted and np.any(table.entry_counts() == 0):
            opened = self._read_unindexed(learn=True)
        wanted = table.channel_ids() | {c for run in self._loose for c in run.message_index_offsets}
        if summary.statistics is not None:
            wanted |= {c for c, n in summary.statistics.channel_message_counts.items() if n}
        try:
            opened += find_definitions(summary, wanted, self._chunk_contents)
        except (ValueError, struct.error, EOFError, UnicodeDecodeError, McapError) as err:
            raise CorruptLogError(self.path, f"{err}. {recover_hint(self.path)}") from err
        if len(summary.schemas) + len(summary.channels) > known:
            self.add_note(self._definitions_note(opened))

    def _definitions_note(self, opened: int) -> str:
        where = f"{opened} chunk{'s' if opened != 1 else ''} opened" if opened else "no chunk opened"
        readers = ("; Foxglove and the mcap library need them in the summary: starlog filter "
                   f"{self.path} -o OUT.mcap writes a copy with them") if len(self.summary.chunk_indexes) else ""
        return (f"its summary does not repeat every schema and channel record, so they are read from the data "
                f"section ({where}){readers}")

    def _check_summary(self, data_end: int) -> None:
        """The indexes must point inside the data section and name known channels and schemas."""
        self._check_layout(data_end)
        self._check_references()

    def _check_references(self) -> None:
        """Every channel must name a defined schema, every channel id the indexes, statistics or messages name
        a defined channel (:func:`~starlog.io.summary_checks.reference_problems`)."""
        self._refuse(reference_problems(self.summary, self._loose, self._extents or {}))

    def _check_layout(self, data_end: int) -> None:
        """The indexes must point inside the data section (:func:`~starlog.io.summary_checks.layout_problems`)."""
        self._refuse(layout_problems(self.summary, data_end))

    def _refuse(self, problems: list[str]) -> None:
        if problems:
            raise CorruptLogError(self.path, f"its summary is inconsistent ({'; '.join(problems[:3])}). "
                                             f"{recover_hint(self.path)}")

    def add_note(self, note: str) -> None:
        """Record a one-line note about how the file was read (shown once, in reading order)."""
        if note not in self.notes:
            self.notes.append(note)

    def __enter__(self) -> McapFile:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Close the file."""
        self._file.close()

    # ------------------------------------------------------------------ what the file holds
    @property
    def size(self) -> int:
        """The file's size in bytes."""
        return self.footer.file_size

    @property
    def fully_indexed(self) -> bool:
        """Whether every message is reachable through the summary's indexes (chunk and message indexes)."""
        return self._indexed

    def profile(self) -> str:
        """The header's profile (e.g. ``ros2``; ``""`` when the header cannot be read)."""
        try:
            self._file.seek(len(MAGIC))
            opcode, length = RECORD_HEADER.unpack(self._file.read(RECORD_HEADER.size))
            if opcode != Opcode.HEADER:
                return ""
            return parse_record(self._file.read(length), Header).profile
        except (struct.error, ValueError, UnicodeDecodeError, EOFError):
            return ""

    def read_bytes(self, offset: int, length: int) -> bytes:
        """``length`` bytes of the file from ``offset`` (fewer only where the file ends)."""
        self._file.seek(offset)
        return self._file.read(length)

    def channel_extents(self, lo: int = 0, hi: int = END_OF_TIME) -> dict[int, list[int]]:
        """``[count, first log_time, last log_time]`` per channel id of the messages with ``lo <= log_time < hi``.

        The whole file's come from the statistics and chunk indexes; a window's from the message index
        records of the chunks it overlaps (chunks without them are read).
        """
        if lo <= 0 and hi >= END_OF_TIME:
            return self._whole_extents()
        extents: dict[int, list[int]] = {}
        table: ChunkIndexTable = self.summary.chunk_indexes
        rows = table.rows_for_channels(self.summary.channels, lo, hi)
        for ci in itertools.chain(table.indexes_at(rows), self._loose_in(set(self.summary.channels), lo, hi)):
            for cid, times in self._message_times(ci).items():
                inside = [t for t in times if lo <= t < hi]
                if inside:
                    add_extent(extents, cid, len(inside), min(inside), max(inside))
        return extents

    def _whole_extents(self) -> dict[int, list[int]]:
        summary = self.summary
        counts = summary.statistics.channel_message_counts if self._counted else {}
        out = {cid: [int(counts.get(cid, 0)), lo, hi]
               for cid, (lo, hi) in summary.chunk_indexes.channel_time_ranges().items()}
        if not self._indexed or not self._counted:
            for cid, (count, lo, hi) in self._unindexed_extents().items():
                e = out.setdefault(cid, [int(counts.get(cid, 0)), lo, hi])
                e[1], e[2] = min(e[1], lo), max(e[2], hi)
                if not self._counted:
                    e[0] = count
        for cid in summary.channels:
            out.setdefault(cid, [int(counts.get(cid, 0)), 0, 0])
        return out

    @property
    def _counted(self) -> bool:
        """Whether the statistics count each channel's messages (an empty count map means they do not)."""
        stats = self.summary.statistics
        return stats is not None and bool(stats.channel_message_counts or stats.message_count == 0)

    def _unindexed_extents(self) -> dict[int, list[int]]:
        """``[count, first, last]`` per channel over what the indexes do not describe (scanned once, lazily).

        Covers every segment when the statistics do not count each channel's messages.
        """
        if self._extents is None:
            self._read_unindexed(learn=False)
        assert self._extents is not None
        return self._extents

    def _read_unindexed(self, *, learn: bool) -> int:
        """Read the segments :meth:`_unindexed_extents` covers, in file order, and keep their extents; with
        ``learn``, add their schema and channel records to the summary. Returns the chunks read."""
        table: ChunkIndexTable = self.summary.chunk_indexes
        rows = np.arange(len(table)) if not self._counted else np.flatnonzero(table.entry_counts() == 0)
        rows = rows[np.argsort(table.column("chunk_start_offset")[rows], kind="stable")]
        extents: dict[int, list[int]] = {}

        def count(cid: int, log_time: int) -> None:
            add_extent(extents, cid, 1, log_time, log_time)

        schemas, channels = (self.summary.schemas, self.summary.channels) if learn else (None, None)
        for ci in table.indexes_at(rows):
            try:
                read_definitions(self._chunk_contents(ci).data, schemas, channels, count)
            except (ValueError, struct.error, EOFError, UnicodeDecodeError, McapError) as err:
                raise self.chunk_error(ci, f"its records are damaged ({err})") from err
        for run in self._loose:
            for log_time, _, cid, _ in self.read_chunk(run)[0]:
                count(cid, log_time)
        self._extents = extents
        return len(rows)

    def _message_times(self, ci: ChunkIndex) -> dict[int, list[int]]:
        """The ``log_time`` of each message of the chunk ``ci``, per channel (from its message indexes when it
        has them)."""
        if not ci.message_index_offsets or isinstance(ci, LooseRun):
            times: dict[int, list[int]] = {}
            for log_time, _, cid, _ in self.read_chunk(ci)[0]:
                times.setdefault(cid, []).append(log_time)
            return times
        return {cid: [t for t, _ in entries] for cid, entries in self.message_index(ci).items()}

    def time_range(self) -> tuple[int, int]:
        """First and last ``log_time`` of the file (0, 0 when it holds no message)."""
        stats = self.summary.statistics
        if stats is None:
            extents = self._unindexed_extents().values()
            return (min((e[1] for e in extents), default=0), max((e[2] for e in extents), default=0))
        if stats.message_count == 0:
            return (0, 0)
        return (stats.message_start_time, stats.message_end_time)

    def metadata_indexes(self) -> list[MetadataIndex]:
        """The metadata indexes in file order."""
        return sorted(self.summary.metadata_indexes, key=lambda m: m.offset)

    def metadata(self, name: str | None = None) -> list[tuple[str, dict[str, str]]]:
        """MCAP Metadata records ``(name, map)`` in file order, optionally only those named ``name``."""
        return [(index.name, self.read_metadata(index)) for index in self.metadata_indexes()
                if name is None or index.name == name]

    def read_metadata(self, index: MetadataIndex) -> dict[str, str]:
        """The map of the metadata record ``index`` points at."""
        raw = self.read_bytes(index.offset, index.length)
        try:
            opcode, length = RECORD_HEADER.unpack_from(raw)
            if opcode != Opcode.METADATA or RECORD_HEADER.size + length != index.length:
                raise ValueError(f"no metadata record there (opcode {opcode:#04x})")
            record = parse_record(raw[RECORD_HEADER.size:], Metadata)
            if record.name != index.name:
                raise ValueError(f"it is named {record.name!r}, its index says {index.name!r}")
        except (struct.error, ValueError, EOFError, McapError) as err:
            raise CorruptLogError(self.path, f"the metadata record {index.name!r} at offset {index.offset} is "
                                             f"damaged ({err}). {recover_hint(self.path)}") from err
        return dict(record.metadata)

    # ------------------------------------------------------------------ chunks
    def chunk_error(self, ci: ChunkIndex, detail: str) -> CorruptChunkError:
        """The error that names the chunk ``ci`` as damaged (its offset, channels and time range)."""
        channels = self.summary.channels
        names = [channels[c].topic if c in channels else f"channel {c}" for c in sorted(ci.message_index_offsets)]
        return CorruptChunkError(self.path, ci.chunk_start_offset, names, ci.message_start_time,
                                 ci.message_end_time, detail)

    def read_chunk(self, ci: ChunkIndex) -> tuple[list[ChunkMessage], bool]:
        """Every message of the chunk ``ci`` as ``(log_time, position, channel_id, message)``, fully checked,
        and whether its CRC was verified (never for messages outside chunks). Payloads are read-only views
        of the decompressed chunk."""
        if isinstance(ci, LooseRun):
            try:
                return read_loose(self._file, ci), False
            except (ValueError, struct.error) as err:
                raise CorruptLogError(self.path, f"the messages outside chunks at offset {ci.chunk_start_offset} "
                                                 f"are damaged ({err}). {recover_hint(self.path)}") from err
        contents = self._chunk_contents(ci)
        data = contents.data
        messages: list[ChunkMessage] = []
        offsets: dict[int, list[tuple[int, int]]] = {}
        view = memoryview(data).toreadonly()  # payloads are slices of it, not copies
        known = ci.message_index_offsets or self.summary.channels
        try:
            for pos, opcode, _, body in walk_records(view):
                if opcode != Opcode.MESSAGE or body is None:
                    continue
                cid, seq, log_time, publish_time = MESSAGE_HEADER.unpack_from(body)
                if cid not in known:
                    raise ValueError(f"it holds a message of channel {cid}, which "
                                     f"{'its index' if ci.message_index_offsets else 'the log'} does not list")
                if not contents.start <= log_time <= contents.end:
                    raise ValueError(f"a message at log_time {log_time} lies outside its range "
                                     f"{contents.start}..{contents.end}")
                messages.append((log_time, len(messages), cid, Message(cid, log_time, body[MESSAGE_HEADER.size:],
                                                                       publish_time, seq)))
                offsets.setdefault(cid, []).append((log_time, pos))
        except (struct.error, ValueError) as err:
            raise self.chunk_error(ci, str(err)) from err
        if ci.message_index_offsets and {c: sorted(v) for c, v in self.message_index(ci).items()} != \
                {c: sorted(offsets.get(c, [])) for c in ci.message_index_offsets}:
            raise self.chunk_error(ci, "its message indexes do not match the chunk's messages")
        return messages, contents.crc_checked

    def _chunk_contents(self, ci: ChunkIndex) -> ChunkContents:
        """The decompressed, CRC-checked contents of the chunk ``ci``, its header checked against the index."""
        raw = self.read_bytes(ci.chunk_start_offset, ci.chunk_length)
        if len(raw) != ci.chunk_length:
            raise self.chunk_error(ci, "the file ends inside it")
        opcode, length = RECORD_HEADER.unpack_from(raw)
        if opcode != Opcode.CHUNK or RECORD_HEADER.size + length != ci.chunk_length:
            raise self.chunk_error(ci, f"no chunk record there (opcode {opcode:#04x}, length {length})")
        try:
            contents = decode_chunk(memoryview(raw)[RECORD_HEADER.size:], check_crc=self.validate_crcs)
        except Exception as err:  # struct.error, ValueError, UnicodeDecodeError, ZstdError, lz4 RuntimeError ...
            raise self.chunk_error(ci, f"{type(err).__name__}: {err}") from err
        if (contents.start, contents.end, contents.uncompressed_size, contents.compression) != \
                (ci.message_start_time, ci.message_end_time, ci.uncompressed_size, ci.compression):
            raise self.chunk_error(ci, "its header disagrees with the summary's chunk index")
        return contents

    def message_index(self, ci: ChunkIndex) -> dict[int, list[tuple[int, int]]]:
        """The ``(log_time, offset)`` entries of each message index record of the chunk ``ci``, per channel."""
        if not ci.message_index_offsets:
            return {}
        first = min(ci.message_index_offsets.values())
        block = self.read_bytes(first, ci.message_index_length)
        out = {}
        for cid, offset in ci.message_index_offsets.items():
            rel = offset - first
            try:
                opcode, length = RECORD_HEADER.unpack_from(block, rel)
                body = block[rel + RECORD_HEADER.size: rel + RECORD_HEADER.size + length]
                if opcode != Opcode.MESSAGE_INDEX or len(body) != length:
                    raise ValueError("not a message index record")
                channel_id, out[cid] = parse_message_index(body)
                if channel_id != cid:
                    raise ValueError(f"it is channel {channel_id}'s")
            except (struct.error, ValueError) as err:
                raise self.chunk_error(ci, f"its message index for channel {cid} at offset {offset} is damaged "
                                           f"({err})") from err
        return out

    def index_counts(self, ci: ChunkIndex) -> dict[int, int]:
        """Messages per channel of a chunk, from the headers of its message index records (no decompression)."""
        counts = {}
        for cid, offset in ci.message_index_offsets.items():
            head = self.read_bytes(offset, RECORD_HEADER.size + MESSAGE_INDEX_BODY.size)
            try:
                opcode, _ = RECORD_HEADER.unpack_from(head, 0)
                channel_id, array_len = MESSAGE_INDEX_BODY.unpack_from(head, RECORD_HEADER.size)
            except struct.error as err:
                raise self.chunk_error(ci, f"its message index is cut short ({err})") from err
            if opcode != Opcode.MESSAGE_INDEX or channel_id != cid or array_len % MESSAGE_INDEX_ENTRY.size:
                raise self.chunk_error(ci, f"its message index for channel {cid} is damaged")
            counts[cid] = array_len // MESSAGE_INDEX_ENTRY.size
        return counts

    def chunk_message_counts(self, channel_ids: set[int], lo: int = 0, hi: int = END_OF_TIME
                             ) -> list[tuple[int, int, int]]:
        """``(message_start_time, message_end_time, count)`` of the messages of ``channel_ids`` with
        ``lo <= log_time < hi`` in each chunk holding some, in time order (from the message index records; no
        chunk is decompressed unless it lies across a bound)."""
        table: ChunkIndexTable = self.summary.chunk_indexes
        rows, channels, _ = table.entries()
        out = []
        for ci in table.indexes_at(np.unique(rows[np.isin(channels, list(channel_ids))])):
            if not (ci.message_end_time >= lo and ci.message_start_time < hi):
                continue
            if lo <= ci.message_start_time and ci.message_end_time < hi:
                counts = self.index_counts(ci)
                out.append((ci.message_start_time, ci.message_end_time, sum(counts.get(c, 0) for c in channel_ids)))
                continue
            indexes = self.message_index(ci)
            times = [t for c in channel_ids for t, _ in indexes.get(c, ()) if lo <= t < hi]
            if times:
                out.append((min(times), max(times), len(times)))
        return sorted(out)

    def messages(self, ids: set[int], lo: int, hi: int) -> Iterator[tuple[ChunkMessage, bool]]:
        """The messages of the channels ``ids`` with ``lo <= log_time < hi``, in ``log_time`` order (ties: file
        order), streamed chunk by chunk; each with whether its chunk's CRC was verified. Only the chunks
        whose time ranges overlap are held in memory at once."""
        chunks = _Peekable(self._chunks_in_time_order(ids, lo, hi))
        heap: list[tuple[int, int, int, int, Message, bool]] = []
        last = -1
        while heap or chunks.peek is not None:
            while chunks.peek is not None and (not heap or chunks.peek.message_start_time <= heap[0][0]):
                ci = chunks.pop()
                messages, verified = self.read_chunk(ci)
                for log_time, position, cid, message in messages:
                    if cid in ids and lo <= log_time < hi:
                        heapq.heappush(heap, (log_time, ci.chunk_start_offset, position, cid, message, verified))
            if not heap:  # the last chunks held none of the wanted messages
                break
            log_time, offset, position, cid, message, verified = heapq.heappop(heap)
            if log_time < last:  # cannot happen with consistent indexes; never pass on a wrong order
                raise CorruptLogError(self.path, f"messages come out of log_time order at {log_time}. "
                                                 f"{recover_hint(self.path)}")
            last = log_time
            yield (log_time, position, cid, message), verified

    def _chunks_in_time_order(self, ids: set[int], lo: int, hi: int) -> Iterator[ChunkIndex]:
        """The chunks (and runs of messages outside chunks) that may hold a message of ``ids`` with
        ``lo <= log_time < hi``, by ``(message_start_time, offset)``; the chunk indexes are made one at a time."""
        table: ChunkIndexTable = self.summary.chunk_indexes
        chunks = table.indexes_at(table.rows_for_channels(ids, lo, hi))
        return heapq.merge(chunks, self._loose_in(ids, lo, hi),
                           key=lambda ci: (ci.message_start_time, ci.chunk_start_offset))

    def _loose_in(self, ids: set[int], lo: int, hi: int) -> list[LooseRun]:
        return sorted((run for run in self._loose
                       if (not run.message_index_offsets or not ids.isdisjoint(run.message_index_offsets))
                       and run.message_end_time >= lo and run.message_start_time < hi),
                      key=lambda run: (run.message_start_time, run.chunk_start_offset))

    def records_in_file_order(self) -> Iterator[tuple[int, str, Any]]:
        """``(offset, kind, index)`` of every chunk (``"chunk"``), run of messages outside chunks (``"loose"``),
        metadata record (``"metadata"``) and attachment (``"attachment"``) of the file, by offset; the chunk
        indexes are made one at a time."""
        table: ChunkIndexTable = self.summary.chunk_indexes
        chunks = ((ci.chunk_start_offset, "chunk", ci)
                  for ci in table.indexes_at(np.argsort(table.column("chunk_start_offset"), kind="stable")))
        others: list[tuple[int, str, Any]] = [(run.chunk_start_offset, "loose", run) for run in self._loose]
        others += [(m.offset, "metadata", m) for m in self.summary.metadata_indexes]
        others += [(a.offset, "attachment", a) for a in self.summary.attachment_indexes]
        others.sort(key=lambda item: item[0])
        return heapq.merge(chunks, others, key=lambda item: item[0])




