"""Copying part of a log: some channels (topic globs), a time range, or both — chunk by chunk.

One implementation serves ``starlog filter`` and the ``--start`` / ``--end`` of every stage.
The output is a new, fully indexed log written in the input's record order:

* the header (with the input's profile, e.g. ``ros2``), then the schemas and channels kept;
* every chunk whose messages are all kept (its channels all selected, its time range inside the
  range) is **copied byte for byte** with its message index records (by the kernel, see
  :func:`~starlog.io.bytecopy.copy_range`: never decompressed, never re-compressed); a chunk
  without message indexes is read once and gets them;
* a chunk only part of which is kept (a boundary of the range, or channels mixed in one chunk)
  is re-encoded: its kept messages, unchanged, in one new chunk; a chunk with nothing kept is
  left out unread when its index says so;
* messages written outside chunks (valid MCAP) that are kept go into new chunks;
* every metadata record (provenance included) is copied; attachments inside the range too.

The summary is rebuilt from what was written (statistics count the kept messages).
"""

from __future__ import annotations

import fnmatch
import heapq
import io
import os
import struct
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import AttachmentIndex, ChunkIndex, Header, MetadataIndex, Schema

from starlog.errors import CorruptChunkError, CorruptLogError, InvalidParameterError
from starlog.io.bytecopy import copy_range
from starlog.io.layout import MCAP_MAGIC
from starlog.io.provenance import PROVENANCE_METADATA_NAME, Provenance
from starlog.io.reader import LogReader
from starlog.io.scan import MESSAGE_HEADER, RECORD_HEADER, LooseRun, chunk_record, iter_records, read_loose
from starlog.io.stack import StackedLog
from starlog.io.timerange import ResolvedRange
from starlog.io.writer import LIBRARY, LogWriter, _PendingChunk, _compress

__all__ = ["SliceReport", "TopicSelection", "check_topics_exist", "frame_time_lookup", "slice_log"]

LogSource = str | os.PathLike[str] | StackedLog


@dataclass(frozen=True)
class TopicSelection:
    """Channels kept: those matching any ``include`` glob (all when there is none) and no ``exclude`` glob
    (:mod:`fnmatch` patterns: ``*`` matches ``/`` too, so ``/camera/*`` is every channel under ``/camera``)."""

    include: tuple[str, ...] = ()
    exclude: tuple[str, ...] = ()

    def keeps(self, topic: str) -> bool:
        """Whether the channel ``topic`` is kept."""
        if self.include and not any(fnmatch.fnmatchcase(topic, p) for p in self.include):
            return False
        return not any(fnmatch.fnmatchcase(topic, p) for p in self.exclude)

    def to_dict(self) -> dict[str, Any]:
        return {"topics": list(self.include), "exclude_topics": list(self.exclude)}


@dataclass
class SliceReport:
    """What :func:`slice_log` wrote: messages kept per topic and how each chunk was handled."""

    output: Path
    messages: dict[str, int] = field(default_factory=dict)
    chunks_copied: int = 0
    chunks_reencoded: int = 0
    chunks_dropped: int = 0
    bytes_copied: int = 0
    time_range: ResolvedRange | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"output": str(self.output), "messages": dict(self.messages),
                "chunks_copied": self.chunks_copied, "chunks_reencoded": self.chunks_reencoded,
                "chunks_dropped": self.chunks_dropped, "bytes_copied": self.bytes_copied,
                "range": None if self.time_range is None else self.time_range.to_dict()}


def frame_time_lookup(log: LogReader, topic: str) -> Callable[[int], int | None]:
    """``n -> log_time`` of the n-th message (0-based, ``log_time`` order) of ``topic``, None past its last.

    With message indexes and chunks in time order only the chunk holding message n is read;
    otherwise the channel's times are read once.
    """
    total = log.channel(topic).message_count
    chunks = log.chunk_message_counts(topic) if log.fully_indexed else []
    ordered = sum(c[2] for c in chunks) == total and all(b[0] > a[1] for a, b in zip(chunks, chunks[1:]))
    every: list[int] = []

    def lookup(index: int) -> int | None:
        if index < 0 or index >= total:
            return None
        if not ordered:
            if not every:
                every.extend(m.log_time for _, _, m in log.raw_messages([topic], views=True))
            return every[index] if index < len(every) else None
        before = 0
        for start, end, count in chunks:
            if index < before + count:
                times = [m.log_time for _, _, m in log.raw_messages([topic], start=start, end=end + 1, views=True)]
                return times[index - before]
            before += count
        return None

    return lookup


class _SliceWriter(LogWriter):
    """A :class:`LogWriter` that copies records of another log: the input's channel ids, schemas, chunks and
    metadata records are kept as they are, so copied chunks stay valid."""

    def __init__(self, path: str | os.PathLike[str], *, profile: str, force: bool, compression: str) -> None:
        super().__init__(path, force=force, compression=compression, validate=False)
        if profile:  # the input's profile (ros2, ros1, ...): restart the file with it in the header
            self._file.seek(0)
            self._file.truncate()
            self._file.write(MCAP_MAGIC)
            Header(profile=profile, library=LIBRARY).write(self._records)
            self._flush_records()

    def declare(self, schemas: list[Schema], channels: list[Any]) -> None:
        """Write the kept schemas and channels (input ids) before any message."""
        for schema in schemas:
            self._schemas[schema.id] = schema
            schema.write(self._records)
        for channel in channels:
            self._channels[channel.id] = channel
            self._topics[channel.topic] = channel.id
            channel.write(self._records)
        self._flush_records()
        self._stats.schema_count = len(schemas)
        self._stats.channel_count = len(channels)

    def write_back(self) -> None:
        """Flush what is written and wait for the disk, so the final ``fsync`` has only the tail left.

        Called before the provenance's input digest is awaited: the disk writes of the copied
        chunks then overlap the hashing thread instead of following it.
        """
        self._flush_records()
        self._file.flush()
        getattr(os, "fdatasync", os.fsync)(self._file.fileno())  # macOS has no fdatasync

    def count(self, channel_id: int, n: int, first: int, last: int) -> None:
        """Add ``n`` messages of a channel spanning ``first..last`` to the statistics."""
        if n <= 0:
            return
        stats = self._stats
        if stats.message_count == 0:
            stats.message_start_time, stats.message_end_time = first, last
        else:
            stats.message_start_time = min(stats.message_start_time, first)
            stats.message_end_time = max(stats.message_end_time, last)
        stats.message_count += n
        stats.channel_message_counts[channel_id] += n

    def copy_chunk(self, src: BinaryIO, ci: ChunkIndex, counts: dict[int, int]) -> int:
        """Copy a chunk and its message index records byte for byte; returns the bytes copied."""
        chunk_start = self._tell()
        copied = copy_range(src, self._file, ci.chunk_start_offset, ci.chunk_length)
        first_index = min(ci.message_index_offsets.values())
        index_start = self._tell()
        copied += copy_range(src, self._file, first_index, ci.message_index_length)
        if copied != ci.chunk_length + ci.message_index_length:
            raise CorruptChunkError(getattr(src, "name", "input"), ci.chunk_start_offset, [], ci.message_start_time,
                                    ci.message_end_time, "the file ends inside it")
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=ci.message_start_time, message_end_time=ci.message_end_time,
            chunk_start_offset=chunk_start, chunk_length=ci.chunk_length,
            message_index_offsets={c: o - first_index + index_start for c, o in ci.message_index_offsets.items()},
            message_index_length=ci.message_index_length, compression=ci.compression,
            compressed_size=ci.compressed_size, uncompressed_size=ci.uncompressed_size))
        self._stats.chunk_count += 1
        for cid, n in counts.items():
            self.count(cid, n, ci.message_start_time, ci.message_end_time)
        return copied

    def copy_raw_chunk(self, raw: bytes, ci: ChunkIndex, indices: dict[int, list[tuple[int, int]]]) -> None:
        """Write a chunk record as it is (``raw``) followed by new message index records."""
        chunk_start = self._tell()
        self._file.write(raw)
        index_start = self._tell()
        offsets: dict[int, int] = {}
        for cid in sorted(indices):
            records = indices[cid]
            offsets[cid] = self._tell()
            self._file.write(struct.pack("<BQHI", Opcode.MESSAGE_INDEX, 6 + 16 * len(records), cid, 16 * len(records)))
            self._file.write(b"".join(struct.pack("<QQ", t, o) for t, o in records))
            self.count(cid, len(records), min(t for t, _ in records), max(t for t, _ in records))
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=ci.message_start_time, message_end_time=ci.message_end_time,
            chunk_start_offset=chunk_start, chunk_length=len(raw), message_index_offsets=offsets,
            message_index_length=self._tell() - index_start, compression=ci.compression,
            compressed_size=ci.compressed_size, uncompressed_size=ci.uncompressed_size))
        self._stats.chunk_count += 1

    def write_records(self, data: bytes, indices: dict[int, list[tuple[int, int]]]) -> None:
        """Write message records (``data``, their bytes as read) as one new chunk, compressed as this log's."""
        times = [t for records in indices.values() for t, _ in records]
        future: Future[tuple[bytes, int]] = Future()
        future.set_result(_compress(data, self.compression))
        self._write_chunk(_PendingChunk(future, len(data), indices, min(times), max(times)))
        for cid, records in indices.items():
            self.count(cid, len(records), min(t for t, _ in records), max(t for t, _ in records))

    def copy_record(self, src: BinaryIO, offset: int, length: int) -> int:
        """Copy one top-level record (metadata, attachment) byte for byte; returns its new offset."""
        start = self._tell()
        if copy_range(src, self._file, offset, length) != length:
            raise CorruptLogError(getattr(src, "name", "the input"), f"the record at offset {offset} is cut off")
        return start

    def add_metadata_index(self, index: MetadataIndex) -> None:
        self._metadata_indexes.append(index)
        self._stats.metadata_count += 1

    def add_attachment_index(self, index: AttachmentIndex) -> None:
        self._attachment_indexes.append(index)
        self._stats.attachment_count += 1


def _profile(f: BinaryIO) -> str:
    """The input's header profile (``""`` when its header cannot be read)."""
    try:
        f.seek(len(MCAP_MAGIC))
        opcode, length = RECORD_HEADER.unpack(f.read(RECORD_HEADER.size))
        if opcode != Opcode.HEADER:
            return ""
        return Header.read(ReadDataStream(io.BytesIO(f.read(length)))).profile
    except (struct.error, ValueError, UnicodeDecodeError):
        return ""


def _index_counts(f: BinaryIO, ci: ChunkIndex) -> dict[int, int]:
    """Messages per channel of a chunk, from its message index records (no decompression)."""
    counts = {}
    for cid, offset in ci.message_index_offsets.items():
        f.seek(offset + RECORD_HEADER.size + 2)
        (array_len,) = struct.unpack("<I", f.read(4))
        counts[cid] = array_len // 16
    return counts


class _Slicer:
    """Walks the input's indexed records in file order and writes what is kept."""

    def __init__(self, log: LogReader, writer: _SliceWriter, kept: set[int], time_range: ResolvedRange | None,
                 report: SliceReport) -> None:
        self.log, self.writer, self.kept, self.range, self.report = log, writer, kept, time_range, report
        self.src: BinaryIO = log._file

    def keeps(self, cid: int, log_time: int) -> bool:
        return cid in self.kept and (self.range is None or self.range.contains(log_time))

    def chunk(self, ci: ChunkIndex) -> None:
        if self.range is not None and not self.range.overlaps(ci.message_start_time, ci.message_end_time):
            self.report.chunks_dropped += 1
            return
        channels = set(ci.message_index_offsets)
        if channels and channels.isdisjoint(self.kept):
            self.report.chunks_dropped += 1
            return
        whole = self.range is None or self.range.covers(ci.message_start_time, ci.message_end_time)
        if channels and channels <= self.kept and whole:
            self.report.bytes_copied += self.writer.copy_chunk(self.src, ci, _index_counts(self.src, ci))
            self.report.chunks_copied += 1
            return
        self.src.seek(ci.chunk_start_offset)
        raw = self.src.read(ci.chunk_length)
        try:
            data = chunk_record(memoryview(raw)[RECORD_HEADER.size:]).data
            records = list(iter_records(data))
        except Exception as err:  # struct.error, ValueError, zstd / lz4 errors
            raise self.log._chunk_error(ci, f"{type(err).__name__}: {err}") from err
        self.select(data, records, ci, raw if not channels else None)

    def select(self, data: bytes | memoryview, records: list[tuple[int, int, int, int]], ci: ChunkIndex,
               raw: bytes | None) -> None:
        """Keep the chunk's kept messages: the chunk as it is (``raw``, when every one is kept), else a new one."""
        kept = bytearray()
        indices: dict[int, list[tuple[int, int]]] = {}
        original: dict[int, list[tuple[int, int]]] = {}
        total = 0
        for offset, opcode, body, length in records:
            if opcode != Opcode.MESSAGE:
                continue
            total += 1
            cid, _, log_time, _ = MESSAGE_HEADER.unpack_from(data, body)
            if not self.keeps(cid, log_time):
                continue
            original.setdefault(cid, []).append((log_time, offset))
            indices.setdefault(cid, []).append((log_time, len(kept)))
            kept += data[offset: body + length]
        if not indices:
            self.report.chunks_dropped += 1
        elif raw is not None and sum(len(v) for v in original.values()) == total:
            self.writer.copy_raw_chunk(raw, ci, original)
            self.report.bytes_copied += len(raw)
            self.report.chunks_copied += 1
        else:
            self.writer.write_records(bytes(kept), indices)
            self.report.chunks_reencoded += 1

    def loose(self, run: LooseRun) -> None:
        messages = read_loose(self.src, run)
        kept = bytearray()
        indices: dict[int, list[tuple[int, int]]] = {}
        for log_time, _, cid, message in messages:
            if self.keeps(cid, log_time):
                indices.setdefault(cid, []).append((log_time, len(kept)))
                body = MESSAGE_HEADER.pack(cid, message.sequence, log_time, message.publish_time) + bytes(message.data)
                kept += RECORD_HEADER.pack(Opcode.MESSAGE, len(body)) + body
        if indices:
            self.writer.write_records(bytes(kept), indices)
            self.report.chunks_reencoded += 1

    def metadata(self, index: MetadataIndex) -> None:
        offset = self.writer.copy_record(self.src, index.offset, index.length)
        self.writer.add_metadata_index(MetadataIndex(offset=offset, length=index.length, name=index.name))

    def attachment(self, index: AttachmentIndex) -> None:
        if self.range is not None and not self.range.contains(index.log_time):
            return
        offset = self.writer.copy_record(self.src, index.offset, index.length)
        self.writer.add_attachment_index(AttachmentIndex(
            offset=offset, length=index.length, log_time=index.log_time, create_time=index.create_time,
            data_size=index.data_size, name=index.name, media_type=index.media_type))


def slice_log(
    input_path: LogSource,
    output_path: str | os.PathLike[str],
    *,
    topics: TopicSelection | None = None,
    time_range: ResolvedRange | None = None,
    force: bool = False,
    compression: str = "zstd",
    provenance: Callable[[], Provenance] | None = None,
) -> SliceReport:
    """Write the channels of ``topics`` (default: all) and the messages in ``time_range`` (default: all) of a log.

    Chunks kept whole are copied byte for byte; re-encoded chunks use ``compression``.
    ``provenance``: makes the record added last (the ``filter`` command's own; called at the end, so
    a digest of the input can be computed meanwhile). Raises
    :class:`InvalidParameterError` when no channel is selected.
    """
    selection = topics or TopicSelection()
    report = SliceReport(Path(output_path), time_range=time_range)
    with LogReader(input_path) as log:
        summary = log.summary
        kept = {cid for cid, ch in summary.channels.items() if selection.keeps(ch.topic)}
        if not kept:
            raise InvalidParameterError(
                f"{log.path}: no channel matches the topic selection {selection.to_dict()} "
                f"(channels: {', '.join(log.topics) or 'none'}).")
        channels = [summary.channels[c] for c in sorted(kept)]
        schema_ids = sorted({c.schema_id for c in channels if c.schema_id in summary.schemas})
        with _SliceWriter(output_path, profile=_profile(log._file), force=force, compression=compression) as writer:
            writer.declare([summary.schemas[s] for s in schema_ids], channels)
            slicer = _Slicer(log, writer, kept, time_range, report)
            for _, write, record in _in_file_order(log, slicer):
                write(record)
            if provenance is not None:
                writer.write_back()
                writer.add_metadata(PROVENANCE_METADATA_NAME, provenance().to_metadata())
            counts = dict(writer._stats.channel_message_counts)
        report.messages = {ch.topic: int(counts.get(ch.id, 0)) for ch in channels}
    return report


def _in_file_order(log: LogReader, slicer: _Slicer) -> Iterator[tuple[int, Callable[[Any], None], Any]]:
    """``(offset, handler, record)`` of every chunk, run of messages outside chunks, metadata and
    attachment of the log, by offset; the chunk indexes are made one at a time."""
    summary = log.summary
    table = summary.chunk_indexes
    chunks = ((ci.chunk_start_offset, slicer.chunk, ci)
              for ci in table.indexes_at(np.argsort(table.column("chunk_start_offset"), kind="stable")))
    others = [(run.chunk_start_offset, slicer.loose, run) for run in log._loose]
    others += [(m.offset, slicer.metadata, m) for m in summary.metadata_indexes]
    others += [(a.offset, slicer.attachment, a) for a in summary.attachment_indexes]
    others.sort(key=lambda item: item[0])
    return heapq.merge(chunks, others, key=lambda item: item[0])


def check_topics_exist(log: LogReader, patterns: Sequence[str]) -> None:
    """Each ``--topic`` pattern must match a channel (a typo should not silently keep nothing)."""
    for pattern in patterns:
        if not any(fnmatch.fnmatchcase(t, pattern) for t in log.topics):
            raise InvalidParameterError(f"{log.path}: --topic {pattern!r} matches no channel "
                                        f"(channels: {', '.join(log.topics) or 'none'}).")
