"""Writing starlog logs: chunked, compressed, fully indexed MCAP, written atomically.

Why not :class:`mcap.writer.Writer` directly? Three things it does not do:

* **write a layer** — given the :class:`~starlog.io.chain.LayerBase` of the log a stage extends,
  the output holds only the stage's records, its schema and channel ids follow the chain's,
  its topics must be new to the chain, and it ends with the record naming its base
  (:mod:`starlog.io.chain`);
* **compress on several cores** — chunks are compressed on a thread pool (zstd and lz4
  release the GIL) and written in order, so the bytes do not depend on the number of workers;
* **copy records of other files** as they are (chunks, message indexes, metadata), for
  ``filter`` and ``flatten`` (:mod:`starlog.io.copying`);
* **be read while it is written** — :meth:`LogWriter.flush` closes the open chunks and hands them
  to the system, so a reader following the file (``starlog live``) sees every message written so
  far; ``in_place`` writes under the final name from the start (a camera's log), and a layer may
  learn its base only when it is closed (:meth:`LogWriter.attach_base`: ``starlog live`` writes its
  layers while the log below them is still being recorded).

Each channel gets chunks of its own, so a reader of small channels (centroids, truth) never
decompresses image chunks; the open chunks of all channels are closed together. Every JSON
message is checked against its channel's JSON Schema as it is written (a compiled checker,
see :func:`~starlog.io.json_schema.compile_json_schema`; or where it was encoded, e.g. in a worker
process, see :mod:`starlog.io.checked`), and the channel is marked so (metadata
``starlog.validated``): a reader then need not check those messages again when their chunk's
CRC vouches for the bytes.

The output goes to a temporary file beside the destination and is renamed over it only
when :meth:`LogWriter.close` completes, so a killed stage leaves either no output or the
previous file, never a half-written one under the final name (``in_place`` aside).

One module of over 500 lines: :class:`LogWriter`'s chunking, indexing, summary and atomic rename
share one open file's state (open chunks, indexes, offsets), so they are one class.
"""

from __future__ import annotations

import errno
import os
import tempfile
from collections import defaultdict, deque
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager, suppress
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, BinaryIO

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

from starlog.version import __version__
from starlog.errors import (
    CorruptLogError,
    FileAccessError,
    InvalidInputError,
    InvalidParameterError,
    OutputChangedError,
    OutputExistsError,
    OutputFolderError,
    file_errors,
)
from starlog.io.chain import BASE_METADATA_NAME
from starlog.io.checked import CheckedJson, schema_checker, schema_digest
from starlog.io.checksum import crc32
from starlog.io.chunk_indexes import ChunkIndexTable
from starlog.io.layout import MAGIC, chunk_record, footer_crc, message_index_record
from starlog.io.messages import decode_json
from starlog.io.schemas import MessageType

if TYPE_CHECKING:
    from starlog.io.chain import LayerBase
    from starlog.io.mcap_file import McapFile

__all__ = ["FRAME_COMPRESSION", "Compression", "LogWriter", "VALIDATED_METADATA_KEY", "atomic_output", "commit_output",
           "output_identity", "temporary_folder", "temporary_output"]

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

#: Chunk compression of the logs that hold camera frames (``simulate``, ``ingest``): the stages that read frames pay
#: its decompression on every frame. lz4 decodes a 1024x1024 mono16 frame about twice as fast as zstd for
#: files about 1.6 times as large; uncompressed chunks decode fastest and are 2.6 times as large
#: (``python tools/bench_io.py``, docs/BENCHMARKS.md). ``--compression`` keeps the choice with the user.
FRAME_COMPRESSION = "lz4"


def _compress(data: bytes, compression: Compression) -> tuple[bytes, int]:
    crc = crc32(data)
    if compression is Compression.ZSTD:
        import zstandard

        return zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(data), crc
    if compression is Compression.LZ4:
        import lz4.frame

        # 1 MiB blocks: python-lz4 decodes them at twice the speed of its default 64 KiB blocks (slower than
        # zstd) or of 4 MiB ones, for the same size (``python tools/bench_io.py``'s frame table)
        return lz4.frame.compress(data, block_size=lz4.frame.BLOCKSIZE_MAX1MB), crc
    return data, crc


def temporary_output(output: Path) -> tuple[int, Path]:
    """A new file beside ``output`` to write it in, renamed over it when complete: its descriptor and path.

    Its permissions are those of a file the user creates (``mkstemp``'s 0600 would survive the rename
    and make every log private). An OS error (read-only or full file system, no permission) is a
    :class:`~starlog.errors.FileAccessError` naming ``output``.
    """
    with file_errors(output):
        fd, tmp = tempfile.mkstemp(prefix=f".{output.name}.", suffix=".partial", dir=output.parent or ".")
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
    except BaseException:
        os.close(fd)
        Path(tmp).unlink(missing_ok=True)
        raise
    return fd, Path(tmp)


def _open_in_place(output: Path) -> tuple[int, Path]:
    """``output`` itself, created or emptied (the caller refused an existing one without ``force``); an OS error
    is a :class:`~starlog.errors.FileAccessError` naming it."""
    with file_errors(output):
        return os.open(output, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o666), output


Identity = tuple[int, int, int, int]


def output_identity(path: Path) -> Identity | None:
    """Which file is at ``path`` (device, inode, size, modification time), or None when there is none."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return None
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


def commit_output(tmp: Path, output: Path, *, seen: Identity | None) -> None:
    """Put the finished file ``tmp`` in place as ``output``, which held ``seen`` when the output was opened.

    When another command has written ``output`` meanwhile (two commands writing the same path at once),
    its file is kept and :class:`~starlog.errors.OutputChangedError` raised: the first to finish wins. The
    check and the rename are one step for starlog commands (a lock on the folder), and an output that did
    not exist is never written over, whoever created it (a hard link, which fails on an existing name).
    """
    with _folder_lock(output.parent):
        now = output_identity(output)
        if now is not None and now != seen:
            raise OutputChangedError(output)
        if seen is None and _link(tmp, output):
            tmp.unlink()
        else:
            os.replace(tmp, output)


def _link(tmp: Path, output: Path) -> bool:
    """Hard-link ``tmp`` as ``output`` (False where the file system has no hard links)."""
    try:
        os.link(tmp, output)
    except FileExistsError:
        raise OutputChangedError(output) from None
    except OSError as err:
        if err.errno in _NO_HARD_LINKS:
            return False
        raise
    return True


_NO_HARD_LINKS = {errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK}


@contextmanager
def _folder_lock(folder: Path) -> Iterator[None]:
    """An exclusive lock on ``folder`` among starlog commands (``flock`` of its descriptor); none where the
    platform or the file system has none, or the folder is gone (the rename then says so)."""
    fd = None
    with suppress(ImportError, OSError):
        import fcntl

        fd = os.open(folder, os.O_RDONLY)
        with suppress(OSError):
            fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        yield
    finally:
        if fd is not None:
            os.close(fd)


@contextmanager
def atomic_output(output: Path, *, force: bool = True) -> Iterator[Path]:
    """A temporary file beside ``output`` for the block to write: put in place as ``output`` when the block
    succeeds (:func:`commit_output`), removed whatever else happens. Refuses an existing ``output`` without
    ``force``; an OS error is a :class:`~starlog.errors.FileAccessError` naming ``output``."""
    output = Path(output)
    if output.exists() and not force:
        raise OutputExistsError(output)
    OutputFolderError.check(output)
    seen = output_identity(output)
    fd, tmp = temporary_output(output)
    os.close(fd)
    try:
        with file_errors(output):
            yield tmp
            _fsync(tmp)
            commit_output(tmp, output, seen=seen)
    finally:
        with suppress(OSError):
            tmp.unlink(missing_ok=True)


def _fsync(path: Path) -> None:
    """Make the bytes written to ``path`` durable before it is renamed into place (as the log writer does)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def temporary_folder(beside: Path) -> Iterator[Path]:
    """A new hidden folder beside ``beside`` (e.g. for the layers of a chain that is then flattened into
    ``beside``), removed at the end whatever happens. A failure to write in it names ``beside``, the output
    the user asked for."""
    OutputFolderError.check(beside)
    with file_errors(beside):
        folder = tempfile.TemporaryDirectory(prefix=f".{beside.name}.", suffix=".layers", dir=beside.parent or ".",
                                             ignore_cleanup_errors=True)
    with folder as name:
        try:
            yield Path(name)
        except FileAccessError as err:
            if Path(name) not in err.path.parents:
                raise
            raise FileAccessError(beside, err.action, err.errno, err.detail) from err


@dataclass
class _PendingChunk:
    future: Future[tuple[bytes, int]]
    uncompressed_size: int
    message_indices: dict[int, list[tuple[int, int]]]
    start_time: int
    end_time: int


class LogWriter:
    """Write a new MCAP log, or a layer on an existing one.

    Parameters
    ----------
    path : path-like
        Destination. Written via a temporary file in the same folder and renamed on close (``in_place`` aside).
    compression : Compression or str
        Chunk compression, ``"zstd"`` (default), ``"lz4"`` or ``"none"``.
    chunk_size : int
        Uncompressed bytes per chunk before it is closed.
    workers : int
        Threads compressing chunks (the bytes written do not depend on it).
    force : bool
        Overwrite an existing ``path``; otherwise :class:`OutputExistsError`.
    layer : LayerBase, optional
        The log this output extends (:meth:`~starlog.io.reader.LogReader.layer_base`): the output is
        a layer on it — its ids follow the chain's, its topics must be new to the chain, and
        :meth:`close` adds the record naming the base (:mod:`starlog.io.chain`).
    validate : bool
        Check every message of a JSON channel against the channel's JSON Schema as it is written
        (:class:`InvalidInputError` on a violation), and mark the channel as checked. Off only
        for tools that must copy messages as they are (``recover``).
    profile : str
        The header's profile (e.g. ``ros2`` for a copy of a ROS 2 log).
    first_ids : (int, int), optional
        The first schema and channel ids to use, for a layer whose base is attached when it is closed
        (:meth:`attach_base`); default 1 (or those following ``layer``'s).
    in_place : bool
        Write under ``path`` itself from the start instead of a temporary file renamed at the end: the one
        output written where it will stay, for a log read while it is written (a camera's recording that
        ``starlog live`` follows). A kill or :meth:`abort` leaves what was flushed under ``path`` (``starlog
        recover`` completes it), and there is no first-writer-wins check: the file is its writer's alone.

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
        layer: LayerBase | None = None,
        validate: bool = True,
        profile: str = "",
        inputs: Iterable[str | os.PathLike[str]] = (),
        first_ids: tuple[int, int] | None = None,
        in_place: bool = False,
    ) -> None:
        self.path = Path(path)
        try:
            self._check_options(compression, chunk_size, workers, force, [*(layer.chain_paths if layer else ()),
                                                                           *inputs])
        except BaseException:
            if layer is not None:
                layer.cancel()
            raise
        self.compression = Compression(compression)
        self.chunk_size = chunk_size
        self.workers = workers
        self.validate = validate
        self.layer = layer
        self._next_schema_id, self._next_channel_id = (
            first_ids if first_ids is not None else (layer.next_schema_id, layer.next_channel_id) if layer else (1, 1))
        self._checkers: dict[int, Callable[[Any], str | None]] = {}
        self._schema_digests: dict[int, bytes] = {}  # of the checked channels' schemas (see CheckedJson)
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._topics: dict[str, int] = {}
        self._chunk_indexes = ChunkIndexTable()
        self._metadata_indexes: list[MetadataIndex] = []
        self._attachment_indexes: list[AttachmentIndex] = []
        self._stats = Statistics(message_count=0, schema_count=0, channel_count=0, attachment_count=0,
                                 metadata_count=0, chunk_count=0, message_start_time=0, message_end_time=0,
                                 channel_message_counts=defaultdict(int))
        self._sequence: dict[int, int] = defaultdict(int)
        self._last_time: dict[int, int] = {}
        self._builders: dict[int, ChunkBuilder] = {}
        self._open_bytes = 0  # message bytes in the open chunks of all channels
        self._records = RecordBuilder()
        self._pending: deque[_PendingChunk] = deque()
        self._executor = ThreadPoolExecutor(max_workers=workers) if workers > 1 else None
        self._closed = False
        self.in_place = in_place
        try:
            self._seen = output_identity(self.path)
            fd, self._tmp_path = _open_in_place(self.path) if in_place else temporary_output(self.path)
        except BaseException:
            self._closed = True
            if self._executor is not None:
                self._executor.shutdown(wait=False)
            if layer is not None:
                layer.cancel()
            raise
        self._file = _DataSectionFile(os.fdopen(fd, "w+b", buffering=1024 * 1024), self.path)
        try:
            self._file.write(MAGIC)
            Header(profile=profile, library=LIBRARY).write(self._records)
            self._flush_records()
        except BaseException:
            self.abort()
            raise

    def _check_options(self, compression: Compression | str, chunk_size: int, workers: int, force: bool,
                       inputs: list[str | os.PathLike[str]]) -> None:
        """Refuse what cannot be written: bad options, an existing output (without ``force``), an output that is
        one of the files it is written from (the files of a layer's chain, ``inputs``), a missing folder."""
        if compression not in [c.value for c in Compression] + list(Compression):
            raise InvalidParameterError(
                f"unknown compression {compression!r}; choose one of {[c.value for c in Compression]}.")
        if chunk_size < 1024:
            raise InvalidParameterError(f"chunk_size must be at least 1024 bytes, got {chunk_size}.")
        if workers < 1:
            raise InvalidParameterError(f"workers must be >= 1, got {workers}.")
        if self.path.exists() and any(os.path.exists(p) and os.path.samefile(self.path, p) for p in inputs):
            raise InvalidParameterError(f"the output {self.path} is one of the files it is written from; choose "
                                        "another name (an input is never overwritten).")
        if self.path.exists() and not force:
            raise OutputExistsError(self.path)
        OutputFolderError.check(self.path)

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
        """Channel id of every topic this file holds (of its first channel, for a topic of several)."""
        return dict(self._topics)

    def add_channel(self, topic: str, message_type: MessageType, *, metadata: dict[str, str] | None = None,
                    monotonic: bool = False, shared_topic: bool = False) -> int:
        """Register a channel and return its id.

        With ``monotonic=True``, :meth:`write` refuses a ``log_time`` that is not after the
        channel's previous one (:class:`InvalidInputError`): per-frame channels use it, so a
        non-monotonic timestamp never reaches a log silently.

        Raises :class:`InvalidInputError` if the log (the chain, for a layer) already has ``topic``
        (a stage run twice on the same log): run the stage on the log before it, or use another
        channel name. ``shared_topic``: this file may hold ``topic`` already (a second channel on it, as
        ``recover`` keeps one of another schema); the chain below a layer still may not.
        """
        if (topic in self._topics and not shared_topic) or (self.layer is not None and topic in self.layer.topics):
            raise InvalidInputError(
                f"the log already has a channel {topic!r}; run this stage on a log without it "
                "(for example the stage's own input) or choose another name."
            )
        schema_id = self._schema_id(message_type)
        channel_id = self._next_channel_id
        meta = {k: v for k, v in (metadata or {}).items() if k != VALIDATED_METADATA_KEY}
        checker = self._message_checker(message_type)
        if checker is not None:
            self._checkers[channel_id] = checker
            self._schema_digests[channel_id] = schema_digest(message_type.schema_data)
            meta[VALIDATED_METADATA_KEY] = "jsonschema"
        channel = Channel(id=channel_id, topic=topic, message_encoding=message_type.message_encoding,
                          schema_id=schema_id, metadata=meta)
        self._register_channel(channel)
        if monotonic:
            self._last_time[channel_id] = -1
        builder = self._builders[channel_id] = ChunkBuilder()
        builder.add_schema(self._schemas[schema_id])  # each channel's first chunk names its schema
        builder.add_channel(channel)
        return channel_id

    def _register_channel(self, channel: Channel) -> None:
        self._channels[channel.id] = channel
        self._topics.setdefault(channel.topic, channel.id)
        self._next_channel_id = max(self._next_channel_id, channel.id + 1)
        self._stats.channel_count += 1

    def _message_checker(self, message_type: MessageType) -> Callable[[Any], str | None] | None:
        if not self.validate or message_type.message_encoding != "json" or \
                message_type.schema_encoding != "jsonschema":
            return None
        try:
            return schema_checker(message_type.schema_data)
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
        schema = Schema(id=self._next_schema_id, name=message_type.schema_name,
                        encoding=message_type.schema_encoding, data=message_type.schema_data)
        self._register_schema(schema)
        return schema.id

    def _register_schema(self, schema: Schema) -> None:
        self._schemas[schema.id] = schema
        self._next_schema_id = max(self._next_schema_id, schema.id + 1)
        self._stats.schema_count += 1

    # ------------------------------------------------------------------ writing
    def write(self, channel: int | str, *, log_time: int, data: bytes, publish_time: int | None = None) -> None:
        """Add one message. ``channel`` is an id from :meth:`add_channel` or a topic.

        A message of a JSON channel that does not decode or does not match the channel's schema
        raises :class:`InvalidInputError` (unless the writer was made with ``validate=False``). A
        :class:`~starlog.io.checked.CheckedJson` checked against the channel's own schema is not checked again.
        """
        channel_id = self._topics[channel] if isinstance(channel, str) else channel
        builder = self._builders.get(channel_id)
        if builder is None:
            raise InvalidParameterError(f"channel id {channel_id} was never registered with add_channel.")
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
        message = Message(channel_id=channel_id, log_time=log_time,
                          publish_time=log_time if publish_time is None else int(publish_time),
                          sequence=seq & 0xFFFFFFFF, data=data)
        self._count(channel_id, 1, log_time, log_time)
        before = builder.count
        builder.add_message(message)
        self._open_bytes += builder.count - before
        if self._open_bytes >= self.chunk_size:
            self._close_chunk()

    def flush(self) -> None:
        """Close the open chunk of every channel and hand what is written to the system: a reader of the
        growing file sees every message written so far (each flush ends the chunks, so flush at the pace a
        reader needs, not per message)."""
        self._close_chunk()
        self._drain(all_of_them=True)
        self._file.flush()

    def attach_base(self, layer: LayerBase) -> None:
        """Make this output, written without knowing its base, a layer on ``layer`` (the record naming it is
        written at :meth:`close`): its ids must follow the chain's and its topics be new to it.

        Raises :class:`InvalidInputError` when they do not (the caller then writes its messages into a new
        layer), leaving this output as it was.
        """
        clash = sorted(set(self._topics) & layer.topics)
        low = (min(self._schemas, default=layer.next_schema_id), min(self._channels, default=layer.next_channel_id))
        if clash or low[0] < layer.next_schema_id or low[1] < layer.next_channel_id:
            raise InvalidInputError(f"{self.path} cannot be a layer on {layer.path}: "
                                    + (f"both have the channel(s) {clash}." if clash else
                                       "its schema or channel ids do not follow those of the log below it."))
        self.layer = layer

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Add an MCAP Metadata record (indexed)."""
        self._close_chunk()
        self._drain(all_of_them=True)
        offset = self._file.tell()
        Metadata(name=name, metadata=dict(data)).write(self._records)
        length = self._records.count
        self._flush_records()
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))
        self._stats.metadata_count += 1

    def close(self) -> Path:
        """Finish the file (a layer's base record, the summary, the footer), fsync it and rename it into place."""
        if self._closed:
            return self.path
        try:
            if self.layer is not None:
                self.add_metadata(BASE_METADATA_NAME, self.layer.reference(self.path).to_metadata())
            self._close_chunk()
            self._drain(all_of_them=True)
            self._write_summary()
            with file_errors(self.path):
                self._file.flush()
                os.fsync(self._file.fileno())
                self._file.close()
                if not self.in_place:
                    commit_output(self._tmp_path, self.path, seen=self._seen)
        except BaseException:
            self.abort()
            raise
        finally:
            if self._executor is not None:
                self._executor.shutdown(wait=True)
        self._closed = True
        return self.path

    def abort(self) -> None:
        """Discard the output: nothing is left under the destination name (``in_place``: what was flushed is)."""
        if self._closed:
            return
        self._closed = True
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
        if self.layer is not None:
            self.layer.cancel()
        try:
            self._file.close()
        except OSError:  # its buffered bytes cannot be written (disk full): the file is discarded anyway
            pass
        finally:
            if not self.in_place:
                with suppress(OSError):  # its folder is gone, say: nothing is left to remove
                    self._tmp_path.unlink(missing_ok=True)

    # ------------------------------------------------------------------ copying records of other files
    def copy_schema(self, schema: Schema) -> None:
        """Write ``schema`` as it is (its id kept), for the copied records that name it."""
        schema.write(self._records)
        self._flush_records()
        self._register_schema(schema)

    def copy_channel(self, channel: Channel) -> None:
        """Write ``channel`` as it is (its id, topic and metadata kept), for the copied records that name it; its
        topic may be another copied channel's (valid MCAP: one channel per publisher)."""
        channel.write(self._records)
        self._flush_records()
        self._register_channel(channel)

    def copy_chunk(self, source: McapFile, ci: ChunkIndex, counts: dict[int, int]) -> int:
        """Copy the chunk ``ci`` of ``source`` and its message index records byte for byte (``counts``: its
        messages per channel, for the statistics); returns the bytes copied."""
        self._drain(all_of_them=True)
        chunk = source.read_bytes(ci.chunk_start_offset, ci.chunk_length)
        first_index = min(ci.message_index_offsets.values())
        indexes = source.read_bytes(first_index, ci.message_index_length)
        if len(chunk) != ci.chunk_length or len(indexes) != ci.message_index_length:
            raise source.chunk_error(ci, "the file ends inside it")
        chunk_start = self._file.tell()
        self._file.write(chunk)
        index_start = self._file.tell()
        self._file.write(indexes)
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=ci.message_start_time, message_end_time=ci.message_end_time,
            chunk_start_offset=chunk_start, chunk_length=ci.chunk_length,
            message_index_offsets={c: o - first_index + index_start for c, o in ci.message_index_offsets.items()},
            message_index_length=ci.message_index_length, compression=ci.compression,
            compressed_size=ci.compressed_size, uncompressed_size=ci.uncompressed_size))
        self._stats.chunk_count += 1
        for cid, n in counts.items():
            self._count(cid, n, ci.message_start_time, ci.message_end_time)
        return len(chunk) + len(indexes)

    def copy_chunk_record(self, raw: bytes, ci: ChunkIndex, indices: dict[int, list[tuple[int, int]]]) -> None:
        """Write a chunk record as it is (``raw``) followed by new message index records (``indices``: the
        ``(log_time, offset)`` of its messages per channel)."""
        self._drain(all_of_them=True)
        chunk_start = self._file.tell()
        self._file.write(raw)
        self._write_chunk_index(chunk_start, len(raw), ci.message_start_time, ci.message_end_time, indices,
                                ci.compression, ci.compressed_size, ci.uncompressed_size)
        self._count_indexed(indices)

    def copy_messages(self, data: bytes, indices: dict[int, list[tuple[int, int]]]) -> None:
        """Write message records (``data``, their bytes as read) as one new chunk, compressed as this log's
        (``indices``: the ``(log_time, offset in data)`` of each message, per channel)."""
        self._drain(all_of_them=True)
        times = [t for records in indices.values() for t, _ in records]
        future: Future[tuple[bytes, int]] = Future()
        future.set_result(_compress(data, self.compression))
        self._write_chunk(_PendingChunk(future, len(data), indices, min(times), max(times)))
        self._count_indexed(indices)

    def copy_record(self, source: McapFile, offset: int, length: int) -> int:
        """Copy one top-level record (metadata, attachment) of ``source`` byte for byte; returns its offset here."""
        self._drain(all_of_them=True)
        data = source.read_bytes(offset, length)
        if len(data) != length:
            raise CorruptLogError(source.path, f"the record at offset {offset} is cut off")
        start = self._file.tell()
        self._file.write(data)
        return start

    def message_counts(self) -> dict[int, int]:
        """Messages written so far per channel id (copied ones included)."""
        return dict(self._stats.channel_message_counts)

    def index_metadata(self, index: MetadataIndex) -> None:
        """List a metadata record copied with :meth:`copy_record` in the summary."""
        self._metadata_indexes.append(index)
        self._stats.metadata_count += 1

    def index_attachment(self, index: AttachmentIndex) -> None:
        """List an attachment copied with :meth:`copy_record` in the summary."""
        self._attachment_indexes.append(index)
        self._stats.attachment_count += 1

    # ------------------------------------------------------------------ internals
    def _flush_records(self) -> None:
        self._file.write(self._records.end())

    def _count(self, channel_id: int, n: int, first: int, last: int) -> None:
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

    def _count_indexed(self, indices: dict[int, list[tuple[int, int]]]) -> None:
        for cid, records in indices.items():
            self._count(cid, len(records), min(t for t, _ in records), max(t for t, _ in records))

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
        compression = "" if self.compression is Compression.NONE else self.compression.value
        chunk_start = self._file.tell()
        for piece in chunk_record(pending.start_time, pending.end_time, pending.uncompressed_size, crc, compression,
                                  compressed):
            self._file.write(piece)
        self._write_chunk_index(chunk_start, self._file.tell() - chunk_start, pending.start_time, pending.end_time,
                                pending.message_indices, compression, len(compressed), pending.uncompressed_size)

    def _write_chunk_index(self, chunk_start: int, chunk_length: int, start_time: int, end_time: int,
                           indices: dict[int, list[tuple[int, int]]], compression: str, compressed_size: int,
                           uncompressed_size: int) -> None:
        """Write the message index records of the chunk just written, list it, count its messages."""
        index_start = self._file.tell()
        offsets: dict[int, int] = {}
        for channel_id in sorted(indices):
            records = indices[channel_id]
            offsets[channel_id] = self._file.tell()
            self._file.write(message_index_record(channel_id, records))
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=start_time, message_end_time=end_time, chunk_start_offset=chunk_start,
            chunk_length=chunk_length, message_index_offsets=offsets,
            message_index_length=self._file.tell() - index_start, compression=compression,
            compressed_size=compressed_size, uncompressed_size=uncompressed_size))
        self._stats.chunk_count += 1

    def _write_summary(self) -> None:
        DataEnd(data_section_crc=self._file.crc).write(self._records)
        self._flush_records()
        summary_start = self._file.tell()
        out = _SummarySink(self._file)
        offsets: list[SummaryOffset] = []

        def group(opcode: Opcode, records: list[Any], table: ChunkIndexTable | None = None) -> None:
            if not records and not table:
                return
            start = out.count
            out.write_records(records)
            if table is not None:
                table.write_records(out.write)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + start,
                                         group_length=out.count - start))

        group(Opcode.SCHEMA, [self._schemas[k] for k in sorted(self._schemas)])
        group(Opcode.CHANNEL, [self._channels[k] for k in sorted(self._channels)])
        self._stats.channel_message_counts = defaultdict(
            int, {k: v for k, v in sorted(self._stats.channel_message_counts.items())}
        )
        group(Opcode.STATISTICS, [self._stats])
        group(Opcode.CHUNK_INDEX, [], self._chunk_indexes)
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
        self._file.write(MAGIC)


class _DataSectionFile:
    """The output file, keeping the CRC-32 of every byte written to it (until the summary, that of the data
    section, which the DataEnd record stores: the reference MCAP writers do the same). A failed write is a
    :class:`~starlog.errors.FileAccessError` naming the output (``path``), not its temporary file."""

    def __init__(self, file: BinaryIO, path: Path) -> None:
        self._file = file
        self._path = path
        self.crc = 0

    def write(self, data: bytes | memoryview) -> int:
        self.crc = crc32(data, self.crc)
        with file_errors(self._path):
            return self._file.write(data)

    def tell(self) -> int:
        return self._file.tell()

    def flush(self) -> None:
        with file_errors(self._path):
            self._file.flush()

    def fileno(self) -> int:
        return self._file.fileno()

    def close(self) -> None:
        self._file.close()


class _SummarySink:
    """The summary section written to the file as it is made (a few MiB at a time), with its CRC:
    the summary of an hour-long log (millions of chunk indexes) is never held whole."""

    _FLUSH_AT = 4 << 20

    def __init__(self, file: _DataSectionFile) -> None:
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
