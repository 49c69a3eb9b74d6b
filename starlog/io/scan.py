"""Reading valid MCAP files that lack some of their indexes, by scanning.

The MCAP format makes every index optional: a writer may leave out message index records, the
chunk indexes, the whole summary, or write messages outside chunks. Such a file is still valid
and still holds every message. This module finds what the indexes do not say:

* :func:`find_loose_runs` walks the parts of the data section that the summary's indexes do not
  cover (in a file starlog wrote: only the header) and returns the messages written outside
  chunks as :class:`LooseRun` segments, read like chunks and merged in ``log_time`` order;
* :func:`synthesize_summary` walks a file with no summary (or no chunk indexes) from start to
  end once and builds the summary it should have had (schemas, channels, chunk indexes,
  statistics, metadata indexes), every chunk CRC-checked on the way;
* :func:`find_definitions` finds the schemas and channels a summary does not repeat (the
  ``mcap`` writer's ``repeat_schemas=False`` / ``repeat_channels=False``) in the chunks' records.

The walks are visitors of the one pass over a data section (:mod:`starlog.io.data_section`). They
read record headers (nine bytes each) and a message's fixed fields, and skip the other record bodies
but those of schema, channel, metadata and attachment records (and, rebuilding a summary, of chunks
and message indexes). Memory stays flat: only indexes and counters are kept, never messages.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import numpy.typing as npt
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    ChunkIndex,
    Message,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
)
from mcap.summary import Summary

from starlog.io.chunk_indexes import ChunkIndexTable
from starlog.io.chunks import ChunkContents, decode_chunk
from starlog.io.data_section import DataVisitor, MessageHead, walk_chunk, walk_data_section
from starlog.io.layout import MAGIC, MESSAGE_HEADER, MESSAGE_INDEX_BODY, RECORD_HEADER, parse_record
from starlog.io.record_walk import walk_records
from starlog.io.summary_checks import missing_schemas

__all__ = ["Gaps", "LooseRun", "ScanResult", "find_definitions", "find_loose_runs",
           "read_definitions", "read_loose", "synthesize_summary"]

_RUN_MESSAGES = 1024  # loose messages per segment: bounds what one read holds in memory
_RUN_BYTES = 8 * 1024 * 1024


@dataclass(eq=False)
class LooseRun(ChunkIndex):
    """Consecutive messages written outside chunks, described like a chunk (``compression`` is empty,
    ``message_index_offsets`` lists the channels it holds with offset 0: there is no index record)."""


class _RunBuilder:
    """Groups loose messages into :class:`LooseRun` segments of bounded size."""

    def __init__(self) -> None:
        self.runs: list[LooseRun] = []
        self._open: list[Any] | None = None  # [first offset, end offset, start, end, count, channels]

    def add(self, offset: int, length: int, channel_id: int, log_time: int) -> None:
        run = self._open
        if run is not None and (run[4] >= _RUN_MESSAGES or offset + length - run[0] > _RUN_BYTES):
            self.close()
            run = None
        if run is None:
            self._open = [offset, offset + length, log_time, log_time, 1, {channel_id}]
            return
        run[1] = offset + length
        run[2], run[3] = min(run[2], log_time), max(run[3], log_time)
        run[4] += 1
        run[5].add(channel_id)

    def close(self) -> None:
        if self._open is None:
            return
        first, stop, start, end, _, channels = self._open
        self.runs.append(LooseRun(
            chunk_length=stop - first, chunk_start_offset=first, compression="", compressed_size=stop - first,
            message_end_time=end, message_index_length=0, message_index_offsets={c: 0 for c in sorted(channels)},
            message_start_time=start, uncompressed_size=stop - first))
        self._open = None


def _merged(lo: npt.NDArray[np.uint64], hi: npt.NDArray[np.uint64]
            ) -> tuple[npt.NDArray[np.uint64], npt.NDArray[np.uint64]]:
    """The union of the byte ranges ``[lo, hi)`` as sorted, disjoint ranges (touching ones joined)."""
    order = np.lexsort((hi, lo))
    lo, hi = lo[order], hi[order]
    if not lo.size:
        return lo, hi
    reach = np.maximum.accumulate(hi)
    # a new range starts where it begins after everything before it has ended
    new = np.ones(lo.size, dtype=bool)
    new[1:] = lo[1:] > reach[:-1]
    firsts = np.flatnonzero(new)
    lasts = np.append(firsts[1:], lo.size) - 1
    return lo[firsts], reach[lasts]


def _covered(summary: Summary) -> list[tuple[int, int]]:
    """The byte ranges the summary's indexes account for (chunks, their message indexes, metadata and
    attachments), merged where they touch or overlap: a few ranges for a well-written log, however long.

    A union of unions is the union: the chunks are merged a block at a time, then the blocks' few
    ranges together, so the temporary arrays stay the size of a block.
    """
    table: ChunkIndexTable = summary.chunk_indexes  # type: ignore[assignment]  # as read_summary makes it
    first_index = table.first_index_offsets()
    pieces = []
    for a, b, _, _ in table.row_blocks():
        start = table.column("chunk_start_offset")[a:b]
        first = first_index[a:b]
        indexed = table.entry_counts(a, b) > 0
        lo = np.concatenate([start, first[indexed]])
        hi = np.concatenate([start + table.column("chunk_length")[a:b],
                             first[indexed] + table.column("message_index_length")[a:b][indexed]])
        pieces.append(_merged(lo, hi))
    others = [(m.offset, m.offset + m.length) for m in summary.metadata_indexes]
    others += [(x.offset, x.offset + x.length) for x in summary.attachment_indexes]
    pieces.append((np.array([lo for lo, _ in others], dtype=np.uint64), np.array([hi for _, hi in others],
                                                                                   dtype=np.uint64)))
    lo, hi = _merged(np.concatenate([p[0] for p in pieces]), np.concatenate([p[1] for p in pieces]))
    return list(zip(lo.tolist(), hi.tolist(), strict=True))


@dataclass
class Gaps:
    """What the parts of the data section that the summary's indexes do not cover hold: the messages written
    outside chunks (as runs), whether a chunk is among them, the schema and channel records, and the
    indexes of the metadata and attachment records the summary does not list."""

    runs: list[LooseRun] = field(default_factory=list)
    unlisted_chunk: bool = False
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata_indexes: list[MetadataIndex] = field(default_factory=list)
    attachment_indexes: list[AttachmentIndex] = field(default_factory=list)


def find_loose_runs(f: BinaryIO, summary: Summary, data_end: int) -> Gaps:
    """Messages outside chunks, schema and channel records, and metadata and attachment records, found in the
    gaps the summary's indexes leave in the data section.

    A chunk met there (one the chunk indexes do not list) means the file must be read by
    :func:`synthesize_summary`. Raises ``ValueError`` (``struct.error``, ``EOFError``) for a damaged gap.
    """
    gaps = _GapVisitor()
    pos = len(MAGIC)
    for lo, hi in _covered(summary) + [(data_end, data_end)]:
        if lo > pos:
            walk_data_section(f, pos, lo, gaps)
        pos = max(pos, hi)
    gaps.runs.close()
    gaps.found.runs = gaps.runs.runs
    return gaps.found


class _Found(DataVisitor):
    """What a walk of the data section finds that the scans keep: messages outside chunks (as runs), schema and
    channel records (the first of an id; a schema of id 0 is ignored, as the format says), metadata and
    attachment indexes."""

    bodies = frozenset({Opcode.SCHEMA, Opcode.CHANNEL, Opcode.METADATA, Opcode.ATTACHMENT})

    def __init__(self, summary: Summary | Gaps) -> None:
        self.found = summary
        self.runs = _RunBuilder()

    def record(self, offset: int, opcode: int, length: int) -> None:
        if opcode != Opcode.MESSAGE:
            self.runs.close()

    def message(self, offset: int, length: int, head: MessageHead, payload: memoryview | None) -> None:
        self.runs.add(offset, RECORD_HEADER.size + length, head[0], head[2])

    def schema(self, offset: int, schema: Schema) -> None:
        if schema.id != 0:
            self.found.schemas.setdefault(schema.id, schema)

    def channel(self, offset: int, channel: Channel) -> None:
        self.found.channels.setdefault(channel.id, channel)

    def metadata(self, offset: int, length: int, body: memoryview | None) -> None:
        record = parse_record(body, Metadata)
        self.found.metadata_indexes.append(MetadataIndex(offset=offset, length=RECORD_HEADER.size + length,
                                                         name=record.name))

    def attachment(self, offset: int, length: int, body: memoryview | None) -> None:
        record = parse_record(body, Attachment)
        self.found.attachment_indexes.append(AttachmentIndex(
            offset=offset, length=RECORD_HEADER.size + length, log_time=record.log_time,
            create_time=record.create_time, data_size=len(record.data), name=record.name,
            media_type=record.media_type))


class _GapVisitor(_Found):
    """:func:`find_loose_runs`' walk of a gap: a chunk there is one the summary does not list."""

    found: Gaps

    def __init__(self) -> None:
        super().__init__(Gaps())

    def chunk(self, offset: int, length: int, body: memoryview | None) -> None:
        self.found.unlisted_chunk = True


class _Definitions(DataVisitor):
    """The schema and channel records of a chunk into dicts (the first of an id kept; a schema of id 0 is
    ignored), and each message to ``on_message(channel_id, log_time)``."""

    def __init__(self, schemas: dict[int, Schema] | None, channels: dict[int, Channel] | None,
                 on_message: Callable[[int, int], object] | None) -> None:
        self.schemas, self.channels, self.on_message = schemas, channels, on_message

    def schema(self, offset: int, schema: Schema) -> None:
        if self.schemas is not None and schema.id != 0:
            self.schemas.setdefault(schema.id, schema)

    def channel(self, offset: int, channel: Channel) -> None:
        if self.channels is not None:
            self.channels.setdefault(channel.id, channel)

    def chunk_message(self, position: int, head: MessageHead, payload: memoryview) -> None:
        if self.on_message is not None:
            self.on_message(head[0], head[2])


def read_definitions(data: bytes | memoryview, schemas: dict[int, Schema] | None, channels: dict[int, Channel] | None,
                     on_message: Callable[[int, int], object] | None = None) -> None:
    """The Schema and Channel records among a chunk's records (``data``, decompressed) into ``schemas`` and
    ``channels`` (when given; the first of an id kept), and ``on_message(channel_id, log_time)`` for each message.
    Raises ``ValueError`` / ``struct.error`` (or the record parser's errors) for damaged records."""
    walk_chunk(data, _Definitions(schemas, channels, on_message), 0)


def find_definitions(summary: Summary, wanted: Iterable[int], open_chunk: Callable[[ChunkIndex], ChunkContents]
                     ) -> int:
    """Add to ``summary`` the channels of ``wanted`` (ids) it lacks and the schemas its channels name that it
    lacks, from the records in its chunks (``open_chunk``: a chunk's checked, decompressed contents); return
    how many chunks were opened.

    A channel's record comes before its first message, a schema's before its first channel (MCAP
    specification), and writers put them in the chunk being filled at the time: the chunks opened are
    the first that lists each missing channel, then the one before it, then every chunk in file order,
    until nothing is missing; each at most once. What is still missing then is not in any chunk. Raises
    ``ValueError`` naming a chunk whose records are damaged (and what ``open_chunk`` raises).
    """
    table: ChunkIndexTable = summary.chunk_indexes  # type: ignore[assignment]  # as read_summary makes it
    wanted = set(wanted)

    def missing() -> bool:
        return bool(wanted - summary.channels.keys() or missing_schemas(summary))

    opened: set[int] = set()
    if not missing():
        return 0
    for row in _candidates(table, summary, wanted):
        if not missing():
            break
        if row in opened:
            continue
        opened.add(row)
        ci = table[row]
        try:
            read_definitions(open_chunk(ci).data, summary.schemas, summary.channels)
        except (ValueError, struct.error, EOFError, UnicodeDecodeError, McapError) as err:
            raise ValueError(f"the records of the chunk at offset {ci.chunk_start_offset} are damaged "
                             f"({type(err).__name__}: {err})") from err
    return len(opened)


def _candidates(table: ChunkIndexTable, summary: Summary, wanted: set[int]) -> Iterator[int]:
    """The rows :func:`find_definitions` opens, in its order (each computed when it is reached)."""
    offsets = table.column("chunk_start_offset")
    firsts = table.first_rows(wanted - summary.channels.keys())
    yield from sorted(firsts.values(), key=lambda row: int(offsets[row]))
    for cid, row in sorted(firsts.items()):
        earlier = np.flatnonzero(offsets < offsets[row])
        if cid not in summary.channels and earlier.size:
            yield int(earlier[np.argmax(offsets[earlier])])
    yield from np.argsort(offsets, kind="stable").tolist()


def read_loose(f: BinaryIO, run: LooseRun) -> list[tuple[int, int, int, Message]]:
    """Every message of ``run`` as ``(log_time, position, channel_id, message)``."""
    f.seek(run.chunk_start_offset)
    data = f.read(run.chunk_length)
    if len(data) != run.chunk_length:
        raise ValueError("the file ends inside it")
    out: list[tuple[int, int, int, Message]] = []
    for _, opcode, _, body in walk_records(data, base=run.chunk_start_offset):
        if opcode == Opcode.MESSAGE and body is not None:
            cid, seq, log_time, publish_time = MESSAGE_HEADER.unpack_from(body)
            out.append((log_time, len(out), cid, Message(cid, log_time, body[MESSAGE_HEADER.size:], publish_time,
                                                         seq)))
    return out


@dataclass
class ScanResult:
    """What a full scan found: the summary the file should have had, its loose-message runs and
    each channel's ``(count, first log_time, last log_time)``."""

    summary: Summary
    loose: list[LooseRun]
    extents: dict[int, list[int]]


class _Rebuilt(_Found):
    """:func:`synthesize_summary`'s walk: the summary the file should have had, built as the records come."""

    bodies = _Found.bodies | {Opcode.CHUNK, Opcode.MESSAGE_INDEX}

    def __init__(self) -> None:
        summary = Summary()
        summary.chunk_indexes = ChunkIndexTable()  # type: ignore[assignment]  # a sequence of ChunkIndex
        super().__init__(summary)
        self.summary = summary
        self.extents: dict[int, list[int]] = {}
        self.last_chunk: ChunkIndex | None = None  # until its message indexes, if any, are read

    def record(self, offset: int, opcode: int, length: int) -> None:
        if opcode == Opcode.MESSAGE_INDEX and self.last_chunk is not None:
            return
        self.end_chunk()
        super().record(offset, opcode, length)

    def end_chunk(self) -> None:
        if self.last_chunk is not None:
            self.summary.chunk_indexes.append(self.last_chunk)
            self.last_chunk = None

    def message_index(self, offset: int, length: int, body: memoryview | None) -> None:
        chunk = self.last_chunk
        if chunk is None or body is None or length < MESSAGE_INDEX_BODY.size:
            return
        chunk.message_index_offsets[MESSAGE_INDEX_BODY.unpack_from(body)[0]] = offset
        chunk.message_index_length = offset + RECORD_HEADER.size + length - min(chunk.message_index_offsets.values())

    def message(self, offset: int, length: int, head: MessageHead, payload: memoryview | None) -> None:
        super().message(offset, length, head, payload)
        self.count(head[0], head[2])

    def count(self, channel_id: int, log_time: int) -> None:
        extent = self.extents.get(channel_id)
        if extent is None:
            self.extents[channel_id] = [1, log_time, log_time]
        else:
            extent[0] += 1
            extent[1], extent[2] = min(extent[1], log_time), max(extent[2], log_time)

    def chunk(self, offset: int, length: int, body: memoryview | None) -> None:
        try:
            contents = decode_chunk(body)  # type: ignore[arg-type]  # CHUNK is in bodies
        except (ValueError, struct.error) as err:
            raise ValueError(f"the chunk at offset {offset} is damaged: {err}") from err
        except Exception as err:  # zstd / lz4 errors
            raise ValueError(f"the chunk at offset {offset} is damaged: {type(err).__name__}: {err}") from err
        read_definitions(contents.data, self.summary.schemas, self.summary.channels, self.count)
        self.last_chunk = ChunkIndex(
            chunk_length=RECORD_HEADER.size + length, chunk_start_offset=offset, compression=contents.compression,
            compressed_size=contents.compressed_size, message_end_time=contents.end, message_index_length=0,
            message_index_offsets={}, message_start_time=contents.start, uncompressed_size=contents.uncompressed_size)

    def statistics(self) -> Statistics:
        counts = {cid: e[0] for cid, e in sorted(self.extents.items())}
        summary = self.summary
        return Statistics(
            message_count=sum(counts.values()), schema_count=len(summary.schemas),
            channel_count=len(summary.channels), attachment_count=len(summary.attachment_indexes),
            metadata_count=len(summary.metadata_indexes), chunk_count=len(summary.chunk_indexes),
            message_start_time=min((e[1] for e in self.extents.values()), default=0),
            message_end_time=max((e[2] for e in self.extents.values()), default=0), channel_message_counts=counts)


def synthesize_summary(path: Path, f: BinaryIO, data_end: int, *, known: Summary | None = None) -> ScanResult:
    """Scan the data section once and build the summary the file lacks (chunks CRC-checked).

    ``known``: a summary without chunk indexes whose schemas and channels are kept.
    Raises ``ValueError`` naming the first damaged record.
    """
    rebuilt = _Rebuilt()
    if known is not None:
        for schema in known.schemas.values():
            rebuilt.schema(0, schema)
        for channel in known.channels.values():
            rebuilt.channel(0, channel)
    walk_data_section(f, len(MAGIC), data_end, rebuilt)
    rebuilt.end_chunk()
    rebuilt.runs.close()
    rebuilt.summary.statistics = rebuilt.statistics()
    return ScanResult(rebuilt.summary, rebuilt.runs.runs, rebuilt.extents)
