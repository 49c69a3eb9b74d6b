"""Writing starlog logs: chunked, compressed, fully indexed MCAP, written atomically.

Why not :class:`mcap.writer.Writer` directly? Two things it cannot do:

* **append without re-compressing** — the Python writer has no append mode. A stage that adds
  a few kilobytes of centroids to a gigabyte of images must not decompress and re-compress
  the images. :class:`LogWriter` started with ``base=INPUT`` copies the input's data section
  byte for byte (every chunk, message index and metadata record keeps its offset; the kernel
  copies it on a thread while the stage works, see :class:`~starlog.io.bytecopy.BackgroundCopy`),
  writes the new chunks after it,
  and ends with a summary that merges the input's (schemas, channels, chunk/metadata/attachment
  indexes, statistics) with the new records — what the
  MCAP specification allows and what the TypeScript library's ``InitializeForAppending``
  does, except that the result goes to a *new* file so the input is never touched;
* **compress on several cores** — chunks are compressed on a thread pool (zstd and lz4
  release the GIL) and written in order, so the bytes do not depend on the number of workers.

Each channel gets chunks of its own, so a reader of small channels (centroids, truth) never
decompresses image chunks; the open chunks of all channels are closed together. Every JSON
message is checked against its channel's JSON Schema as it is written (a compiled checker,
see :func:`~starlog.io.messages.compile_json_schema`; or where it was encoded, e.g. in a worker
process, see :mod:`starlog.io.checked`), and the channel is marked so (metadata
``starlog.validated``): a reader then need not check those messages again when their chunk's
CRC vouches for the bytes. Given a
:class:`~starlog.io.stack.StackedLog` as ``base``, the writer writes only its new records and
the summary (a sidecar), every offset counted as if the stack's data were before it.

The output goes to a temporary file beside the destination and is renamed over it only
when :meth:`LogWriter.close` completes, so a killed stage leaves either no output or the
previous file, never a half-written one under the final name.
"""

from __future__ import annotations

import os
import struct
from collections import defaultdict, deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO

from mcap._chunk_builder import ChunkBuilder
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    AttachmentIndex,
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from starlog import __version__
from starlog.errors import (
    CorruptLogError,
    InvalidInputError,
    InvalidParameterError,
    OutputExistsError,
    OutputFolderError,
    TruncatedLogError,
)
from starlog.io.bytecopy import BackgroundCopy
from starlog.io.checked import CheckedJson, schema_checker, schema_digest
from starlog.io.checksum import crc32, footer_crc
from starlog.io.chunk_indexes import ChunkIndexTable, read_file_summary
from starlog.io.layout import MCAP_MAGIC, locate_data_end
from starlog.io.messages import decode_json
from starlog.io.schemas import MessageType
from starlog.io.stack import StackedLog, temporary_output

__all__ = ["Compression", "LogWriter", "MCAP_MAGIC", "VALIDATED_METADATA_KEY", "locate_data_end"]

#: Channel metadata key set by :class:`LogWriter` on the JSON channels whose every message it
#: checked against the channel's JSON Schema while writing.
VALIDATED_METADATA_KEY = "starlog.validated"

LIBRARY = f"starlog/{__version__}"


class Compression(str, Enum):
    """Chunk compression."""

    ZSTD = "zstd"
    LZ4 = "lz4"
    NONE = "none"


#: zstd level of every chunk. Camera frames: sensor noise leaves little for the match finder, so
#: level 3 makes 16-bit frames 5 % smaller than level 1 but costs twice the time to compress and a
#: third more to decompress (1024x1024 mono16: 7.1 against 5.3 ms per 4 MB chunk), and every stage
#: that reads frames pays the decompression. starlog's own channels are mostly JSON floats, and on
#: them level 1 is both faster and smaller than level 3 (2 MB pieces of a 512², 40-star log's
#: detections, centroids, tracks and annotations: 106-316 against 36-78 MB/s, 4-16 % smaller); only
#: the simulator's truth packs tighter at level 3 (88x against 61x), a few kB a second.
ZSTD_LEVEL = 1


def _compress(data: bytes, compression: Compression) -> tuple[bytes, int]:
    crc = crc32(data)
    if compression is Compression.ZSTD:
        import zstandard

        return zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(data), crc
    if compression is Compression.LZ4:
        import lz4.frame

        return lz4.frame.compress(data), crc
    return data, crc


@dataclass
class _PendingChunk:
    future: Future[tuple[bytes, int]]
    uncompressed_size: int
    message_indices: dict[int, list[tuple[int, int]]]
    start_time: int
    end_time: int


class LogWriter:
    """Write a new MCAP log, or a copy of ``base`` with new channels appended.

    Parameters
    ----------
    path : path-like
        Destination. Written via a temporary file in the same folder and renamed on close.
    compression : Compression or str
        Chunk compression, ``"zstd"`` (default), ``"lz4"`` or ``"none"``.
    chunk_size : int
        Uncompressed bytes per chunk before it is closed.
    workers : int
        Threads compressing chunks (the bytes written do not depend on it).
    force : bool
        Overwrite an existing ``path``; otherwise :class:`OutputExistsError`.
    base : path-like or StackedLog, optional
        A complete log whose data section is copied unchanged to the start of the output; its
        schemas, channels, indexes, metadata and statistics are carried into the new summary.
        With a :class:`~starlog.io.stack.StackedLog`, nothing is copied: the output is a sidecar
        holding only the new records and the summary, to be stacked on ``base``.
    validate : bool
        Check every message of a JSON channel against the channel's JSON Schema as it is written
        (:class:`InvalidInputError` on a violation), and mark the channel as checked. Off only
        for tools that must copy messages as they are (``recover``).

    Examples
    --------
    >>> from starlog.io import LogWriter, json_message_type
    >>> with LogWriter(tmp / "a.mcap") as log:  # doctest: +SKIP
    ...     ch = log.add_channel("/demo", json_message_type("starlog.FrameInfo"))
    ...     log.write(ch, log_time=0, data=b'{"frame":0}')
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        compression: Compression | str = Compression.ZSTD,
        chunk_size: int = 4 * 1024 * 1024,
        workers: int = 1,
        force: bool = False,
        base: str | os.PathLike[str] | StackedLog | None = None,
        validate: bool = True,
    ) -> None:
        self.path = Path(path)
        try:
            self.compression = Compression(compression)
        except ValueError as err:
            raise InvalidParameterError(
                f"unknown compression {compression!r}; choose one of {[c.value for c in Compression]}."
            ) from err
        if chunk_size < 1024:
            raise InvalidParameterError(f"chunk_size must be at least 1024 bytes, got {chunk_size}.")
        if workers < 1:
            raise InvalidParameterError(f"workers must be >= 1, got {workers}.")
        if self.path.exists() and not force:
            raise OutputExistsError(self.path)
        if base is not None and (base.path if isinstance(base, StackedLog) else Path(base)).resolve() \
                == self.path.resolve():
            raise InvalidParameterError(f"the output {self.path} must differ from the input log.")
        self.chunk_size = chunk_size
        self.workers = workers
        self.validate = validate
        self._checkers: dict[int, Callable[[Any], str | None]] = {}
        self._schema_digests: dict[int, bytes] = {}  # of the checked channels' schemas (see CheckedJson)
        self._origin = 0  # offset in the complete log of this file's first byte (non-zero for a sidecar)
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._topics: dict[str, int] = {}
        self._chunk_indexes = ChunkIndexTable()
        # the base's chunk indexes, which this log's summary repeats first (its largest part, kept compact)
        self._base_chunk_indexes = ChunkIndexTable()
        self._metadata_indexes: list[MetadataIndex] = []
        self._attachment_indexes: list[AttachmentIndex] = []
        self._stats = Statistics(
            message_count=0,
            schema_count=0,
            channel_count=0,
            attachment_count=0,
            metadata_count=0,
            chunk_count=0,
            message_start_time=0,
            message_end_time=0,
            channel_message_counts=defaultdict(int),
        )
        self._sequence: dict[int, int] = defaultdict(int)
        self._last_time: dict[int, int] = {}
        self._builders: dict[int, ChunkBuilder] = {}
        self._open_bytes = 0  # message bytes in the open chunks of all channels
        self._records = RecordBuilder()
        self._pending: deque[_PendingChunk] = deque()
        self._executor = ThreadPoolExecutor(max_workers=workers) if workers > 1 else None
        self._closed = False
        self._writeback: BackgroundCopy | None = None
        OutputFolderError.check(self.path)
        fd, self._tmp_path = temporary_output(self.path)
        self._file: BinaryIO = os.fdopen(fd, "w+b", buffering=1024 * 1024)
        try:
            if base is None:
                self._file.write(MCAP_MAGIC)
                Header(profile="", library=LIBRARY).write(self._records)
                self._flush_records()
            elif isinstance(base, StackedLog):
                self._start_from_stack(base)
            else:
                self._start_from(Path(base))
        except BaseException:
            self.abort()
            raise

    # ------------------------------------------------------------------ context manager
    def __enter__(self) -> LogWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    # ------------------------------------------------------------------ registration
    @property
    def topics(self) -> dict[str, int]:
        """Channel id of every topic in the output (inherited ones included)."""
        return dict(self._topics)

    def add_channel(self, topic: str, message_type: MessageType, *, metadata: dict[str, str] | None = None,
                    monotonic: bool = False) -> int:
        """Register a channel and return its id.

        With ``monotonic=True``, :meth:`write` refuses a ``log_time`` that is not after the
        channel's previous one (:class:`InvalidInputError`): per-frame channels use it, so a
        non-monotonic timestamp never reaches a log silently.

        Raises :class:`InvalidInputError` if the log already has ``topic`` (a stage run twice on
        the same log): run the stage on the log before it, or use another channel name.
        """
        if topic in self._topics:
            raise InvalidInputError(
                f"the log already has a channel {topic!r}; run this stage on a log without it "
                "(for example the stage's own input) or choose another name."
            )
        schema_id = self._schema_id(message_type)
        channel_id = max(self._channels, default=0) + 1
        meta = {k: v for k, v in (metadata or {}).items() if k != VALIDATED_METADATA_KEY}
        checker = self._message_checker(message_type)
        if checker is not None:
            self._checkers[channel_id] = checker
            self._schema_digests[channel_id] = schema_digest(message_type.schema_data)
            meta[VALIDATED_METADATA_KEY] = "jsonschema"
        channel = Channel(
            id=channel_id,
            topic=topic,
            message_encoding=message_type.message_encoding,
            schema_id=schema_id,
            metadata=meta,
        )
        self._channels[channel_id] = channel
        self._topics[topic] = channel_id
        if monotonic:
            self._last_time[channel_id] = -1
        self._stats.channel_count += 1
        builder = self._builders[channel_id] = ChunkBuilder()
        builder.add_schema(self._schemas[schema_id])  # each channel's first chunk names its schema
        builder.add_channel(channel)
        return channel_id

    def _adopt(self, channel_id: int) -> None:
        """Start chunks for a channel inherited from the base (its records are already in the base)."""
        channel = self._channels[channel_id]
        schema = self._schemas.get(channel.schema_id)
        if schema is not None:
            checker = self._message_checker(MessageType(schema.name, schema.encoding, schema.data,
                                                        channel.message_encoding))
            if checker is not None:
                self._checkers[channel_id] = checker
                self._schema_digests[channel_id] = schema_digest(schema.data)
        self._builders[channel_id] = ChunkBuilder()

    def _message_checker(self, message_type: MessageType) -> Callable[[Any], str | None] | None:
        if not self.validate or message_type.message_encoding != "json" or \
                message_type.schema_encoding != "jsonschema":
            return None
        try:
            return _checker_of(message_type.schema_data)
        except (ValueError, InvalidInputError) as err:
            raise InvalidParameterError(f"the JSON Schema {message_type.schema_name!r} cannot be compiled "
                                        f"({err}).") from err

    def _schema_id(self, message_type: MessageType) -> int:
        for schema in self._schemas.values():
            if (schema.name, schema.encoding, schema.data) == (
                message_type.schema_name,
                message_type.schema_encoding,
                message_type.schema_data,
            ):
                return schema.id
        schema_id = max(self._schemas, default=0) + 1
        schema = Schema(
            id=schema_id,
            name=message_type.schema_name,
            encoding=message_type.schema_encoding,
            data=message_type.schema_data,
        )
        self._schemas[schema_id] = schema
        self._stats.schema_count += 1
        return schema_id

    # ------------------------------------------------------------------ writing
    def write(self, channel: int | str, *, log_time: int, data: bytes, publish_time: int | None = None) -> None:
        """Add one message. ``channel`` is an id from :meth:`add_channel` or a topic.

        A message of a JSON channel that does not decode or does not match the channel's schema
        raises :class:`InvalidInputError` (unless the writer was made with ``validate=False``). A
        :class:`~starlog.io.checked.CheckedJson` checked against the channel's own schema is not checked again.
        """
        channel_id = self._topics[channel] if isinstance(channel, str) else channel
        if channel_id not in self._builders:
            if channel_id not in self._channels:
                raise InvalidParameterError(f"channel id {channel_id} was never registered.")
            self._adopt(channel_id)
        log_time = int(log_time)
        if not 0 <= log_time < 2**64:
            raise InvalidInputError(f"log_time must be a non-negative 64-bit integer of nanoseconds, got {log_time}.")
        checker = self._checkers.get(channel_id)
        if type(data) is CheckedJson:
            if data.schema_digest == self._schema_digests.get(channel_id):
                checker = None  # checked against this channel's schema where it was encoded
            data = bytes(data)  # what the chunk holds is plain bytes (orjson, too, reads no subclass)
        if checker is not None:
            problem = checker(decode_json(data))
            if problem:
                raise InvalidInputError(
                    f"the message on {self._channels[channel_id].topic!r} at log_time {log_time} does not match "
                    f"its schema {self._schemas[self._channels[channel_id].schema_id].name!r} ({problem}).")
        last = self._last_time.get(channel_id)
        if last is not None:
            if log_time <= last:
                raise InvalidInputError(
                    f"log_time {log_time} on {self._channels[channel_id].topic!r} is not after the previous "
                    f"message's ({last}); timestamps of a frame channel must increase.")
            self._last_time[channel_id] = log_time
        seq = self._sequence[channel_id]
        self._sequence[channel_id] = seq + 1
        message = Message(
            channel_id=channel_id,
            log_time=log_time,
            publish_time=log_time if publish_time is None else int(publish_time),
            sequence=seq & 0xFFFFFFFF,
            data=data,
        )
        stats = self._stats
        if stats.message_count == 0:
            stats.message_start_time = stats.message_end_time = log_time
        else:
            stats.message_start_time = min(stats.message_start_time, log_time)
            stats.message_end_time = max(stats.message_end_time, log_time)
        stats.message_count += 1
        stats.channel_message_counts[channel_id] += 1
        builder = self._builders[channel_id]
        before = builder.count
        builder.add_message(message)
        self._open_bytes += builder.count - before
        if self._open_bytes >= self.chunk_size:
            self._close_chunk()

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Add an MCAP Metadata record (indexed)."""
        self._close_chunk()
        self._drain(all_of_them=True)
        offset = self._tell()
        Metadata(name=name, metadata=dict(data)).write(self._records)
        length = self._records.count
        self._flush_records()
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))
        self._stats.metadata_count += 1

    def close(self) -> Path:
        """Finish the file (summary, footer), fsync it and rename it to its destination."""
        if self._closed:
            return self.path
        try:
            self._close_chunk()
            self._drain(all_of_them=True)
            self._write_summary()
            self._file.flush()
            if self._writeback is not None:
                self._writeback.wait()
            os.fsync(self._file.fileno())
            self._file.close()
            os.replace(self._tmp_path, self.path)
        except BaseException:
            self.abort()
            raise
        finally:
            if self._executor is not None:
                self._executor.shutdown(wait=True)
        self._closed = True
        return self.path

    def abort(self) -> None:
        """Discard the output: nothing is left under the destination name."""
        if self._closed:
            return
        self._closed = True
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
        try:
            if self._writeback is not None:
                self._writeback.cancel()
            self._file.close()
        finally:
            self._tmp_path.unlink(missing_ok=True)

    # ------------------------------------------------------------------ internals
    def _flush_records(self) -> None:
        self._file.write(self._records.end())

    def _tell(self) -> int:
        """Offset of the next byte in the complete log."""
        return self._origin + self._file.tell()

    def _close_chunk(self) -> None:
        """Close the open chunk of every channel (in channel order).

        All at once, when their messages add up to ``chunk_size``: the file stays in time order
        chunk group by chunk group, so a killed writer loses no more than with mixed chunks.
        """
        for channel_id in sorted(self._builders):
            self._close_builder(self._builders[channel_id])
        self._open_bytes = 0

    def _close_builder(self, builder: ChunkBuilder) -> None:
        if builder.num_messages == 0:
            return
        data = builder.end()
        indices = {cid: list(index.records) for cid, index in builder.message_indices.items()}
        start, end = builder.message_start_time, builder.message_end_time
        builder.reset()
        if self._executor is None:
            future: Future[tuple[bytes, int]] = Future()
            future.set_result(_compress(data, self.compression))
        else:
            future = self._executor.submit(_compress, data, self.compression)
        self._pending.append(_PendingChunk(future, len(data), indices, start, end))
        self._drain(all_of_them=False)

    def _drain(self, *, all_of_them: bool) -> None:
        limit = 0 if all_of_them else 2 * self.workers
        while self._pending and (len(self._pending) > limit or self._pending[0].future.done()):
            self._write_chunk(self._pending.popleft())

    def _write_chunk(self, pending: _PendingChunk) -> None:
        compressed, crc = pending.future.result()
        f = self._file
        compression = b"" if self.compression is Compression.NONE else self.compression.value.encode()
        body_len = 8 + 8 + 8 + 4 + 4 + len(compression) + 8 + len(compressed)
        chunk_start = self._tell()
        f.write(struct.pack("<BQQQQI", Opcode.CHUNK, body_len, pending.start_time, pending.end_time,
                            pending.uncompressed_size, crc))
        f.write(struct.pack("<I", len(compression)))
        f.write(compression)
        f.write(struct.pack("<Q", len(compressed)))
        f.write(compressed)
        chunk_length = self._tell() - chunk_start
        index_start = self._tell()
        offsets: dict[int, int] = {}
        for channel_id in sorted(pending.message_indices):
            records = pending.message_indices[channel_id]
            offsets[channel_id] = self._tell()
            f.write(struct.pack("<BQHI", Opcode.MESSAGE_INDEX, 2 + 4 + 16 * len(records), channel_id, 16 * len(records)))
            f.write(b"".join(struct.pack("<QQ", t, o) for t, o in records))
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=pending.start_time,
                message_end_time=pending.end_time,
                chunk_start_offset=chunk_start,
                chunk_length=chunk_length,
                message_index_offsets=offsets,
                message_index_length=self._tell() - index_start,
                compression=compression.decode(),
                compressed_size=len(compressed),
                uncompressed_size=pending.uncompressed_size,
            )
        )
        self._stats.chunk_count += 1

    def _start_from(self, base: Path) -> None:
        if not base.is_file():
            from starlog.errors import LogNotFoundError

            raise LogNotFoundError(base)
        with open(base, "rb") as src:
            data_end = locate_data_end(base, src)
            try:
                summary = read_file_summary(src)
            except Exception as err:  # ValueError, struct.error, or mcap's McapError for another record
                raise CorruptLogError(base, f"its summary section cannot be read ({err}).") from err
            if summary is None or not summary.chunk_indexes:  # a valid file without indexes: scan it
                from starlog.io.scan import synthesize_summary

                try:
                    summary = synthesize_summary(base, src, data_end, known=summary).summary
                except ValueError as err:
                    raise CorruptLogError(base, f"it has no summary and cannot be scanned ({err}).") from err
            # the thread copies from this very file (not the path: it may be replaced meanwhile)
            self._writeback = BackgroundCopy(src.fileno(), self._file.fileno(), base, data_end)
        self._file.seek(data_end)  # the new records go after the base's data section
        self._inherit(summary)

    def _start_from_stack(self, base: StackedLog) -> None:
        """Sidecar mode: nothing copied, offsets continue after the stack's data section."""
        with base.open() as f:
            try:
                summary = read_file_summary(f)
            except Exception as err:  # ValueError, struct.error, or mcap's McapError for another record
                raise CorruptLogError(base.path, f"its summary section cannot be read ({err}).") from err
        if summary is None:
            raise TruncatedLogError(base.path, "it has no summary section")
        self._origin = base.data_end
        self._inherit(summary)

    def _inherit(self, summary: Any) -> None:
        """Carry the base's schemas, channels, indexes and statistics into this log's summary."""
        self._schemas = dict(summary.schemas)
        self._channels = dict(summary.channels)
        self._topics = {c.topic: c.id for c in summary.channels.values()}
        self._base_chunk_indexes = summary.chunk_indexes  # a ChunkIndexTable, as read_summary makes it
        self._chunk_indexes = ChunkIndexTable()
        self._attachment_indexes = list(summary.attachment_indexes)
        self._metadata_indexes = list(summary.metadata_indexes)
        s = summary.statistics
        if s is not None:
            counts: defaultdict[int, int] = defaultdict(int)
            counts.update(s.channel_message_counts)
            self._stats = Statistics(
                message_count=s.message_count,
                schema_count=s.schema_count,
                channel_count=s.channel_count,
                attachment_count=s.attachment_count,
                metadata_count=s.metadata_count,
                chunk_count=s.chunk_count,
                message_start_time=s.message_start_time,
                message_end_time=s.message_end_time,
                channel_message_counts=counts,
            )
        for cid in self._channels:
            self._sequence[cid] = self._stats.channel_message_counts.get(cid, 0)

    def _write_summary(self) -> None:
        DataEnd(data_section_crc=0).write(self._records)
        self._flush_records()
        summary_start = self._tell()
        out = _SummarySink(self._file)
        offsets: list[SummaryOffset] = []

        def group(opcode: Opcode, records: list[Any], *tables: ChunkIndexTable) -> None:
            if not records and not any(tables):
                return
            start = out.count
            out.write_records(records)
            for table in tables:
                table.write_records(out.write)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + start,
                                         group_length=out.count - start))

        group(Opcode.SCHEMA, [self._schemas[k] for k in sorted(self._schemas)])
        group(Opcode.CHANNEL, [self._channels[k] for k in sorted(self._channels)])
        self._stats.channel_message_counts = defaultdict(
            int, {k: v for k, v in sorted(self._stats.channel_message_counts.items())}
        )
        group(Opcode.STATISTICS, [self._stats])
        group(Opcode.CHUNK_INDEX, [], self._base_chunk_indexes, self._chunk_indexes)
        group(Opcode.ATTACHMENT_INDEX, list(self._attachment_indexes))
        group(Opcode.METADATA_INDEX, list(self._metadata_indexes))
        summary_offset_start = summary_start + out.count
        out.write_records(offsets)
        out.flush()
        crc = footer_crc(out.crc, summary_start, summary_offset_start)
        Footer(summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=crc).write(
            self._records
        )
        self._flush_records()
        self._file.write(MCAP_MAGIC)


class _SummarySink:
    """The summary section written to the file as it is made (a few MiB at a time), with its CRC:
    the summary of an hour-long log (millions of chunk indexes) is never held whole."""

    _FLUSH_AT = 4 << 20

    def __init__(self, file: BinaryIO) -> None:
        self._file = file
        self._parts: list[bytes] = []
        self._pending = 0
        self.count = 0
        self.crc = 0

    def write(self, data: bytes) -> None:
        self._parts.append(data)
        self._pending += len(data)
        self.count += len(data)
        if self._pending >= self._FLUSH_AT:
            self.flush()

    def write_records(self, records: list[Any]) -> None:
        """MCAP records (objects of ``mcap.records``), serialised."""
        builder = RecordBuilder()
        for record in records:
            record.write(builder)
        self.write(builder.end())

    def flush(self) -> None:
        data = b"".join(self._parts)
        self.crc = crc32(data, self.crc)  # ISA-L when installed, as for the chunks
        self._file.write(data)
        self._parts, self._pending = [], 0


_checker_of = schema_checker
