"""Copying a log into one file: all of it (``starlog flatten``), or some channels (topic globs), a
time range, or both (``starlog filter``) — chunk by chunk.

The input may be a chain (a base and its layers, :mod:`starlog.io.chain`); the output is a new,
self-contained, fully indexed log holding the chain's files one after the other, each in its
record order:

* the header (with the first file's profile, e.g. ``ros2``), then the schemas and channels kept
  (their ids kept: a chain's are unique across it; a topic's channels are all kept, or none);
* every chunk whose messages are all kept (its channels all selected, its time range inside the
  range) is **copied byte for byte** with its message index records (never decompressed, never
  re-compressed); a chunk without message indexes is read once and gets them;
* a chunk only part of which is kept (a boundary of the range, or channels mixed in one chunk)
  is re-encoded: its kept messages, unchanged, in one new chunk; a chunk with nothing kept is
  left out unread when its index says so;
* messages written outside chunks (valid MCAP) that are kept go into new chunks;
* every metadata record (provenance included) is copied, but the records by which layers name their
  bases; attachments inside the range too.

The summary is rebuilt from what was written (statistics count the kept messages).
"""

from __future__ import annotations

import fnmatch
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.opcode import Opcode
from mcap.records import AttachmentIndex, ChunkIndex, MetadataIndex

from starlog.errors import InvalidParameterError
from starlog.io.chain import BASE_METADATA_NAME
from starlog.io.chunks import decode_chunk
from starlog.io.layout import MESSAGE_HEADER, RECORD_HEADER, message_record
from starlog.io.mcap_file import McapFile
from starlog.io.record_walk import Record, walk_records
from starlog.io.provenance import PROVENANCE_METADATA_NAME, Provenance
from starlog.io.reader import LogReader, LogView
from starlog.io.scan import LooseRun
from starlog.io.timerange import ResolvedRange
from starlog.io.writer import LogWriter

__all__ = ["CopyReport", "TopicSelection", "check_topics_exist", "flatten_log", "frame_time_lookup", "copy_log"]


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
class CopyReport:
    """What :func:`copy_log` wrote: messages kept per topic and how each chunk was handled."""

    output: Path
    messages: dict[str, int] = field(default_factory=dict)
    chunks_copied: int = 0
    chunks_reencoded: int = 0
    chunks_dropped: int = 0
    bytes_copied: int = 0
    time_range: ResolvedRange | None = None

    def lines(self) -> list[str]:
        """What ``starlog flatten`` says it wrote."""
        return [f"wrote {self.output}: {sum(self.messages.values())} messages of {len(self.messages)} topics, "
                f"{self.chunks_copied} chunks copied as they are"]

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
                every.extend(m.log_time for _, _, m in log.raw_messages([topic], views=True, mixed=True))
            return every[index] if index < len(every) else None
        before = 0
        for start, end, count in chunks:
            if index < before + count:
                times = [m.log_time for _, _, m in log.raw_messages([topic], start=start, end=end + 1, views=True,
                                                                     mixed=True)]
                return times[index - before]
            before += count
        return None

    return lookup


class _Slicer:
    """Walks one file's indexed records in file order and writes what is kept."""

    def __init__(self, file: McapFile, writer: LogWriter, kept: set[int], time_range: ResolvedRange | None,
                 report: CopyReport) -> None:
        self.file, self.writer, self.kept, self.range, self.report = file, writer, kept, time_range, report

    def keeps(self, cid: int, log_time: int) -> bool:
        return cid in self.kept and (self.range is None or self.range.contains(log_time))

    def record(self, kind: str, index: Any) -> None:
        """Handle one record of :meth:`~starlog.io.mcap_file.McapFile.records_in_file_order`."""
        handlers = {"chunk": self.chunk, "loose": self.loose, "metadata": self.metadata, "attachment": self.attachment}
        handlers[kind](index)

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
            self.report.bytes_copied += self.writer.copy_chunk(self.file, ci, self.file.index_counts(ci))
            self.report.chunks_copied += 1
            return
        raw = self.file.read_bytes(ci.chunk_start_offset, ci.chunk_length)
        try:
            data = decode_chunk(memoryview(raw)[RECORD_HEADER.size:]).data
            records = list(walk_records(data))
        except Exception as err:  # struct.error, ValueError, zstd / lz4 errors
            raise self.file.chunk_error(ci, f"{type(err).__name__}: {err}") from err
        self.select(data, records, ci, raw if not channels else None)

    def select(self, data: bytes | memoryview, records: list[Record], ci: ChunkIndex, raw: bytes | None) -> None:
        """Keep the chunk's kept messages: the chunk as it is (``raw``, when every one is kept), else a new one."""
        kept = bytearray()
        indices: dict[int, list[tuple[int, int]]] = {}
        original: dict[int, list[tuple[int, int]]] = {}
        total = 0
        for offset, opcode, length, body in records:
            if opcode != Opcode.MESSAGE or body is None:
                continue
            total += 1
            cid, _, log_time, _ = MESSAGE_HEADER.unpack_from(body)
            if not self.keeps(cid, log_time):
                continue
            original.setdefault(cid, []).append((log_time, offset))
            indices.setdefault(cid, []).append((log_time, len(kept)))
            kept += data[offset: offset + RECORD_HEADER.size + length]
        if not indices:
            self.report.chunks_dropped += 1
        elif raw is not None and sum(len(v) for v in original.values()) == total:
            self.writer.copy_chunk_record(raw, ci, original)
            self.report.bytes_copied += len(raw)
            self.report.chunks_copied += 1
        else:
            self.writer.copy_messages(bytes(kept), indices)
            self.report.chunks_reencoded += 1

    def loose(self, run: LooseRun) -> None:
        messages, _ = self.file.read_chunk(run)
        kept = bytearray()
        indices: dict[int, list[tuple[int, int]]] = {}
        for log_time, _, cid, message in messages:
            if self.keeps(cid, log_time):
                indices.setdefault(cid, []).append((log_time, len(kept)))
                kept += message_record(cid, message.sequence, log_time, message.publish_time, len(message.data))
                kept += message.data
        if indices:
            self.writer.copy_messages(bytes(kept), indices)
            self.report.chunks_reencoded += 1

    def metadata(self, index: MetadataIndex) -> None:
        if index.name == BASE_METADATA_NAME:  # a layer's link to its base: the output holds the base itself
            return
        offset = self.writer.copy_record(self.file, index.offset, index.length)
        self.writer.index_metadata(MetadataIndex(offset=offset, length=index.length, name=index.name))

    def attachment(self, index: AttachmentIndex) -> None:
        if self.range is not None and not self.range.contains(index.log_time):
            return
        offset = self.writer.copy_record(self.file, index.offset, index.length)
        self.writer.index_attachment(AttachmentIndex(
            offset=offset, length=index.length, log_time=index.log_time, create_time=index.create_time,
            data_size=index.data_size, name=index.name, media_type=index.media_type))


def copy_log(
    input_path: str | os.PathLike[str],
    output_path: str | os.PathLike[str],
    *,
    topics: TopicSelection | None = None,
    time_range: ResolvedRange | None = None,
    force: bool = False,
    compression: str = "zstd",
    provenance: Callable[[], Provenance] | None = None,
) -> CopyReport:
    """Write the channels of ``topics`` (default: all) and the messages in ``time_range`` (default: all) of a log
    (a whole chain: every file's records, the first file's first) to one self-contained file.

    Chunks kept whole are copied byte for byte; re-encoded chunks use ``compression``. Every schema of the
    chain is kept when every channel is, else those of the kept channels. ``provenance``: makes the record
    added last (the ``filter`` command's own; called at the end, so a digest of the input can be computed
    meanwhile). Raises :class:`InvalidParameterError` when no channel is selected, or when the output is
    one of the chain's files.
    """
    if isinstance(input_path, LogView):
        raise InvalidParameterError(f"{input_path}: give the range as time_range, not as a window of the input.")
    selection = topics or TopicSelection()
    report = CopyReport(Path(output_path), time_range=time_range)
    with LogReader(input_path) as log:
        channels = [c for f in log.files for _, c in sorted(f.summary.channels.items()) if selection.keeps(c.topic)]
        if not channels:
            raise InvalidParameterError(
                f"{log.path}: no channel matches the topic selection {selection.to_dict()} "
                f"(channels: {', '.join(log.topics) or 'none'}).")
        kept = {c.id for c in channels}
        with LogWriter(output_path, force=force, compression=compression, validate=False,
                       profile=log.files[0].profile(), inputs=[f.path for f in log.files]) as writer:
            every = len(channels) == sum(len(f.summary.channels) for f in log.files)
            _copy_definitions(log, channels, writer, every_schema=every)
            for file in log.files:
                slicer = _Slicer(file, writer, kept, time_range, report)
                for _, kind, index in file.records_in_file_order():
                    slicer.record(kind, index)
            if provenance is not None:
                writer.add_metadata(PROVENANCE_METADATA_NAME, provenance().to_metadata())
            counts = writer.message_counts()
        for ch in channels:  # a topic of several channels counts them all
            report.messages[ch.topic] = report.messages.get(ch.topic, 0) + int(counts.get(ch.id, 0))
    return report


def _copy_definitions(log: LogReader, channels: list[Any], writer: LogWriter, *, every_schema: bool) -> None:
    """Write the schemas (all of the chain's, or those the channels use) and the channels, their ids kept."""
    used = {c.schema_id for c in channels}
    for file in log.files:
        for schema_id, schema in sorted(file.summary.schemas.items()):
            if every_schema or schema_id in used:
                writer.copy_schema(schema)
    for channel in channels:
        writer.copy_channel(channel)


def flatten_log(input_path: str | os.PathLike[str], output_path: str | os.PathLike[str], *,
                force: bool = False) -> CopyReport:
    """Write the log at ``input_path`` (a chain: its base and every layer) as one self-contained file.

    Every message, schema, metadata and attachment record of the chain's files is kept, each chunk
    copied byte for byte (nothing is re-compressed); the records by which layers name their bases are
    left out, since the file holds the bases themselves.
    """
    return copy_log(input_path, output_path, force=force)


def check_topics_exist(log: LogReader, patterns: Sequence[str]) -> None:
    """Each ``--topic`` pattern must match a channel (a typo should not silently keep nothing)."""
    for pattern in patterns:
        if not any(fnmatch.fnmatchcase(t, pattern) for t in log.topics):
            raise InvalidParameterError(f"{log.path}: --topic {pattern!r} matches no channel "
                                        f"(channels: {', '.join(log.topics) or 'none'}).")
