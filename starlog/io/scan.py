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

They read record headers (nine bytes each) and skip record bodies, except schema, channel,
metadata and attachment records and the chunks whose channels must be learnt. Memory stays flat: only indexes and
counters are kept, never messages.
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
from starlog.io.layout import (
    MAGIC,
    MESSAGE_HEADER,
    MESSAGE_INDEX_BODY,
    RECORD_HEADER,
    ChunkContents,
    decode_chunk,
    iter_records,
    parse_record,
    walk_records,
)

__all__ = ["Gaps", "LooseRun", "ScanResult", "find_definitions", "find_loose_runs", "missing_schemas",
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


def _message_head(f: BinaryIO, offset: int) -> tuple[int, int]:
    f.seek(offset + RECORD_HEADER.size)
    channel_id, _, log_time, _ = MESSAGE_HEADER.unpack(f.read(MESSAGE_HEADER.size))
    return channel_id, log_time


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
    builder = _RunBuilder()
    gaps = Gaps()
    pos = len(MAGIC)
    for lo, hi in _covered(summary) + [(data_end, data_end)]:
        if lo > pos:
            for offset, opcode, length, body in walk_records(f, pos, lo, bodies=(Opcode.SCHEMA, Opcode.CHANNEL)):
                if opcode == Opcode.MESSAGE:
                    channel_id, log_time = _message_head(f, offset)
                    builder.add(offset, RECORD_HEADER.size + length, channel_id, log_time)
                    continue
                builder.close()
                if opcode == Opcode.CHUNK:
                    gaps.unlisted_chunk = True
                elif opcode in (Opcode.METADATA, Opcode.ATTACHMENT):
                    _add_index(gaps, f, opcode, offset, length)
                elif body is not None:
                    _definition(opcode, body, gaps.schemas, gaps.channels)
        pos = max(pos, hi)
    builder.close()
    gaps.runs = builder.runs
    return gaps


def _add_index(summary: Summary | Gaps, f: BinaryIO, opcode: int, offset: int, length: int) -> None:
    """Add the index of the metadata or attachment record at ``offset`` (body ``length`` bytes) to ``summary``."""
    if opcode == Opcode.METADATA:
        record = parse_record(_body(f, offset, length), Metadata)
        summary.metadata_indexes.append(MetadataIndex(offset=offset, length=RECORD_HEADER.size + length,
                                                      name=record.name))
    else:
        record = parse_record(_body(f, offset, length), Attachment)
        summary.attachment_indexes.append(AttachmentIndex(
            offset=offset, length=RECORD_HEADER.size + length, log_time=record.log_time,
            create_time=record.create_time, data_size=len(record.data), name=record.name,
            media_type=record.media_type))


def _definition(opcode: int, body: bytes | memoryview, schemas: dict[int, Schema], channels: dict[int, Channel]
                ) -> None:
    """A Schema or Channel record's body into ``schemas`` / ``channels`` (the first of an id kept; a schema
    of id 0 is ignored, as the format says)."""
    if opcode == Opcode.SCHEMA:
        schema = parse_record(body, Schema)
        if schema.id != 0:
            schemas.setdefault(schema.id, schema)
    else:
        channel = parse_record(body, Channel)
        channels.setdefault(channel.id, channel)


def read_definitions(data: bytes | memoryview, schemas: dict[int, Schema] | None, channels: dict[int, Channel] | None,
                     on_message: Callable[[int, int], object] | None = None) -> None:
    """The Schema and Channel records among a chunk's records (``data``, decompressed) into ``schemas`` and
    ``channels`` (when given; the first of an id kept), and ``on_message(channel_id, log_time)`` for each message.
    Raises ``ValueError`` / ``struct.error`` (or the record parser's errors) for damaged records."""
    for _, opcode, body, size in iter_records(data):
        if opcode == Opcode.MESSAGE:
            if on_message is not None:
                cid, _, log_time, _ = MESSAGE_HEADER.unpack_from(data, body)
                on_message(cid, log_time)
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL) and schemas is not None and channels is not None:
            _definition(opcode, data[body: body + size], schemas, channels)


def missing_schemas(summary: Summary) -> set[int]:
    """The schema ids the summary's channels name that its schemas do not hold."""
    return {ch.schema_id for ch in summary.channels.values() if ch.schema_id} - summary.schemas.keys()


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
    for _, opcode, body, length in iter_records(data, run.chunk_start_offset):
        if opcode == Opcode.MESSAGE:
            cid, seq, log_time, publish_time = MESSAGE_HEADER.unpack_from(data, body)
            payload = data[body + MESSAGE_HEADER.size: body + length]
            out.append((log_time, len(out), cid, Message(cid, log_time, payload, publish_time, seq)))
    return out


@dataclass
class ScanResult:
    """What a full scan found: the summary the file should have had, its loose-message runs and
    each channel's ``(count, first log_time, last log_time)``."""

    summary: Summary
    loose: list[LooseRun]
    extents: dict[int, list[int]]


def _body(f: BinaryIO, offset: int, length: int) -> bytes:
    f.seek(offset + RECORD_HEADER.size)
    data = f.read(length)
    if len(data) != length:
        raise ValueError(f"the file ends inside the record at offset {offset}")
    return data


class _Tally:
    def __init__(self) -> None:
        self.summary = Summary()
        self.summary.chunk_indexes = ChunkIndexTable()  # type: ignore[assignment]  # a sequence of ChunkIndex
        self.extents: dict[int, list[int]] = {}

    def schema(self, record: Schema) -> None:
        if record.id != 0:
            self.summary.schemas.setdefault(record.id, record)

    def channel(self, record: Channel) -> None:
        self.summary.channels.setdefault(record.id, record)

    def message(self, channel_id: int, log_time: int) -> None:
        extent = self.extents.get(channel_id)
        if extent is None:
            self.extents[channel_id] = [1, log_time, log_time]
        else:
            extent[0] += 1
            extent[1], extent[2] = min(extent[1], log_time), max(extent[2], log_time)

    def chunk(self, offset: int, length: int, contents: ChunkContents) -> ChunkIndex:
        read_definitions(contents.data, self.summary.schemas, self.summary.channels, self.message)
        return ChunkIndex(
            chunk_length=length, chunk_start_offset=offset, compression=contents.compression,
            compressed_size=contents.compressed_size, message_end_time=contents.end, message_index_length=0,
            message_index_offsets={}, message_start_time=contents.start, uncompressed_size=contents.uncompressed_size)

    def statistics(self) -> Statistics:
        counts = {cid: e[0] for cid, e in sorted(self.extents.items())}
        starts = [e[1] for e in self.extents.values()]
        ends = [e[2] for e in self.extents.values()]
        return Statistics(
            message_count=sum(counts.values()), schema_count=len(self.summary.schemas),
            channel_count=len(self.summary.channels), attachment_count=len(self.summary.attachment_indexes),
            metadata_count=len(self.summary.metadata_indexes), chunk_count=len(self.summary.chunk_indexes),
            message_start_time=min(starts, default=0), message_end_time=max(ends, default=0),
            channel_message_counts=counts)


def synthesize_summary(path: Path, f: BinaryIO, data_end: int, *, known: Summary | None = None) -> ScanResult:
    """Scan the data section once and build the summary the file lacks (chunks CRC-checked).

    ``known``: a summary without chunk indexes whose schemas and channels are kept.
    Raises ``ValueError`` naming the first damaged record.
    """
    tally = _Tally()
    if known is not None:
        for schema in known.schemas.values():
            tally.schema(schema)
        for channel in known.channels.values():
            tally.channel(channel)
    runs = _RunBuilder()
    last_chunk: ChunkIndex | None = None
    index_end = 0
    for offset, opcode, length, _ in walk_records(f, len(MAGIC), data_end, bodies=()):
        if opcode == Opcode.MESSAGE_INDEX and last_chunk is not None:
            size = MESSAGE_INDEX_BODY.size
            channel_id = MESSAGE_INDEX_BODY.unpack(_body(f, offset, size))[0] if length >= size else None
            if channel_id is not None:
                last_chunk.message_index_offsets[channel_id] = offset
                index_end = offset + RECORD_HEADER.size + length
                first = min(last_chunk.message_index_offsets.values())
                last_chunk.message_index_length = index_end - first
            continue
        if last_chunk is not None:  # its message indexes, if any, are all read
            tally.summary.chunk_indexes.append(last_chunk)
        last_chunk = None
        if opcode == Opcode.MESSAGE:
            channel_id, log_time = _message_head(f, offset)
            runs.add(offset, RECORD_HEADER.size + length, channel_id, log_time)
            tally.message(channel_id, log_time)
            continue
        runs.close()
        if opcode == Opcode.CHUNK:
            try:
                contents = decode_chunk(_body(f, offset, length))
            except (ValueError, struct.error) as err:
                raise ValueError(f"the chunk at offset {offset} is damaged: {err}") from err
            except Exception as err:  # zstd / lz4 errors
                raise ValueError(f"the chunk at offset {offset} is damaged: {type(err).__name__}: {err}") from err
            last_chunk = tally.chunk(offset, RECORD_HEADER.size + length, contents)
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
            _definition(opcode, _body(f, offset, length), tally.summary.schemas, tally.summary.channels)
        elif opcode in (Opcode.METADATA, Opcode.ATTACHMENT):
            _add_index(tally.summary, f, opcode, offset, length)
    if last_chunk is not None:
        tally.summary.chunk_indexes.append(last_chunk)
    runs.close()
    tally.summary.statistics = tally.statistics()
    return ScanResult(tally.summary, runs.runs, tally.extents)
