"""Reading starlog logs: channel summaries, decoded messages streamed in constant memory, provenance.

Nothing damaged is passed on. On opening, the footer, the summary's CRC and the consistency of
its indexes are checked; while reading, every chunk's CRC, its records, and its message index are
checked against each other. A problem raises :class:`~starlog.errors.TruncatedLogError` (file
cut off or never finished), :class:`~starlog.errors.CorruptChunkError` (naming the chunk's offset,
channels and time range) or :class:`~starlog.errors.CorruptLogError`, each pointing to
``starlog recover``; a message whose payload does not decode or does not satisfy its schema
raises :class:`~starlog.errors.MessageDecodeError` / :class:`~starlog.errors.InvalidMessageError`
naming its topic and ``log_time``. Messages that starlog's writer checked against their schema
(their channel is marked ``starlog.validated``) are not checked again when their chunk's CRC and
the summary's CRC were verified: the bytes are those that passed the check. Every other JSON
message (foreign logs, logs of older versions, ``validate_crcs=False``) is checked as it is decoded.
"""

from __future__ import annotations

import heapq
import io
import itertools
import json
import os
import struct
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, ChunkIndex, Message, Metadata, Schema
from mcap.summary import Summary

from starlog.errors import (
    ChannelNotFoundError,
    CorruptChunkError,
    CorruptLogError,
    InvalidInputError,
    InvalidMessageError,
    InvalidParameterError,
    LogNotFoundError,
    MessageDecodeError,
    NotMcapError,
    TruncatedLogError,
)
from starlog.io.checksum import crc32
from starlog.io.checksum import summary_crc as computed_summary_crc
from starlog.io.chunk_indexes import ChunkIndexTable, read_summary
from starlog.io.foreign import message_decoder
from starlog.io.frames import Frame, SkippedFrame, decode_image_message, iter_frames
from starlog.io.images import is_image_schema
from starlog.io.layout import MCAP_MAGIC, locate_data_end
from starlog.io.messages import compile_json_schema, decode_json
from starlog.io.provenance import PROVENANCE_METADATA_NAME, Provenance
from starlog.io.scan import LooseRun, decompress, find_loose_runs, read_loose, synthesize_summary
from starlog.io.stack import StackedLog
from starlog.io.writer import VALIDATED_METADATA_KEY

_RECORD_HEADER = struct.Struct("<BQ")
_MESSAGE_HEADER = struct.Struct("<HIQQ")  # channel id, sequence, log_time, publish_time
_CHUNK_HEADER = struct.Struct("<QQQI")  # start, end, uncompressed size, uncompressed CRC
_FOOTER = struct.Struct("<BQQQI")  # opcode, length, summary_start, summary_offset_start, summary_crc


def _hint(path: Path) -> str:
    return f"Rebuild a readable copy with: starlog recover {path} -o RECOVERED.mcap"


__all__ = ["ChannelSummary", "DecodedMessage", "LogReader"]


@dataclass(frozen=True)
class ChannelSummary:
    """One channel of a log, as :meth:`LogReader.channels` lists it.

    ``rate_hz`` is ``(count - 1) / (last - first)`` in Hz (0 for fewer than two messages).
    """

    topic: str
    schema_name: str
    schema_encoding: str
    message_encoding: str
    message_count: int
    first_log_time: int
    last_log_time: int

    @property
    def rate_hz(self) -> float:
        span = self.last_log_time - self.first_log_time
        return (self.message_count - 1) / (span * 1e-9) if self.message_count > 1 and span > 0 else 0.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "topic": self.topic,
            "schema": self.schema_name,
            "schema_encoding": self.schema_encoding,
            "message_encoding": self.message_encoding,
            "message_count": self.message_count,
            "first_log_time": self.first_log_time,
            "last_log_time": self.last_log_time,
            "rate_hz": self.rate_hz,
        }


@dataclass(frozen=True)
class DecodedMessage:
    """A message and its decoded payload: a dict (JSON), a 2-D array (an image; read-only when it is a view of
    the log's bytes) or a protobuf object."""

    topic: str
    log_time: int
    sequence: int
    payload: Any


def _chunk_index_problems(table: ChunkIndexTable, channels: set[int], data_end: int) -> list[str]:
    """What is wrong with the chunk indexes (at most three of each kind): ranges outside the data
    section, reversed time ranges, unknown channels, message indexes outside the data section.

    Checked a block of chunks at a time, so the temporary arrays stay the size of a block.
    """
    kinds: list[list[str]] = [[], [], [], []]
    known = np.fromiter(channels, dtype=np.int64, count=len(channels))
    for block in table.row_blocks():
        for kind, found in zip(kinds, _block_problems(table, block, known, data_end), strict=True):
            kind.extend(found[:3 - len(kind)])
        if all(len(kind) == 3 for kind in kinds):
            break
    return [problem for kind in kinds for problem in kind]


def _block_problems(table: ChunkIndexTable, block: tuple[int, int, int, int], known: np.ndarray,
                    data_end: int) -> tuple[list[str], list[str], list[str], list[str]]:
    """:func:`_chunk_index_problems` of each kind among the chunks of one of ``table.row_blocks()``."""
    a, b, e0, e1 = block
    start = table.column("chunk_start_offset")[a:b]
    end = start + table.column("chunk_length")[a:b]  # wraps past 2**64 for a damaged length: then end <= start

    def chunks_where(bad: np.ndarray, what: str) -> list[str]:
        return [f"chunk index for offset {int(start[k])} {what}" for k in np.flatnonzero(bad)[:3]]

    rows, channel, offset = table.entries()
    rows, channel, offset = rows[e0:e1] - a, channel[e0:e1], offset[e0:e1]
    first = table.first_index_offsets()[a:b]
    index_end = first + table.column("message_index_length")[a:b]
    outside = (table.entry_counts(a, b) > 0) & (
        (first < end) | (first >= data_end) | (index_end < first) | (index_end > data_end))
    outside[rows[(offset < end[rows]) | (offset >= data_end)]] = True
    return (
        chunks_where((start < len(MCAP_MAGIC)) | (end <= start) | (end > data_end), "points outside the data section"),
        chunks_where(table.column("message_start_time")[a:b] > table.column("message_end_time")[a:b],
                     "has its time range reversed"),
        [f"chunk index for offset {int(start[rows[k]])} names unknown channel {int(channel[k])}"
         for k in np.flatnonzero(~np.isin(channel, known))[:3]],
        chunks_where(outside, "has a message index outside the data section"),
    )


class _Peekable:
    """An iterator whose next item can be looked at (``peek``; None at the end) before it is taken."""

    def __init__(self, items: Iterator[Any]) -> None:
        self._items = items
        self.peek = next(items, None)

    def pop(self) -> Any:
        item, self.peek = self.peek, next(self._items, None)
        return item


def decode_payload(
    path: Path, schema: Schema | None, channel: Channel, message: Message,
    check: Callable[[Any], str | None] | None = None,
) -> Any:
    """Decode one message by its schema.

    JSON → dict; an image type (:mod:`starlog.io.images`) → 2-D mono ndarray; other protobuf,
    ROS 2 (cdr) and ROS 1 messages → the object their support library decodes; anything else → bytes.
    ``check`` (a :func:`~starlog.io.messages.compile_json_schema` checker) validates a JSON
    payload; a violation raises :class:`InvalidMessageError`.
    """
    try:
        if schema is not None and is_image_schema(schema.name):
            decoded = decode_image_message(schema, channel.message_encoding, message.data)
            if decoded is not None:
                return decoded.image
        if channel.message_encoding == "json":
            value = decode_json(message.data)
            if check is not None:
                problem = check(value)
                if problem:
                    raise InvalidMessageError(path, channel.topic, message.log_time,
                                              f"it does not match its schema {schema.name if schema else ''!r} "
                                              f"({problem}).")
            return value
        decoder = message_decoder(schema, channel.message_encoding)
        if decoder is not None:
            return decoder(bytes(message.data))
    except InvalidMessageError:
        raise
    except (InvalidInputError, ValueError) as err:
        raise MessageDecodeError(path, channel.topic, message.log_time, str(err)) from err
    except Exception as err:  # protobuf's DecodeError is not a ValueError subclass on every backend
        raise MessageDecodeError(path, channel.topic, message.log_time, f"{type(err).__name__}: {err}") from err
    return bytes(message.data)


class LogReader:
    """Open a starlog log for reading.

    Parameters
    ----------
    path : path-like
        An MCAP file with a summary section (every file starlog writes has one).
    validate_crcs : bool
        Check the summary's and every chunk's CRC (default). A mismatch raises
        :class:`CorruptLogError` / :class:`CorruptChunkError`.
    validate_messages : bool or "all"
        Check JSON messages against their embedded JSON Schema as they are decoded (default):
        those that starlog checked when writing them only when their CRCs could not be verified;
        ``"all"``: every one, whoever wrote it.

    Raises
    ------
    LogNotFoundError, TruncatedLogError, CorruptLogError

    Examples
    --------
    >>> with LogReader("sim.mcap") as log:  # doctest: +SKIP
    ...     for message in log.messages("/camera/image"):
    ...         image = message.payload  # 2-D uint16 array
    """

    def __init__(self, path: str | os.PathLike[str] | StackedLog, *, validate_crcs: bool = True,
                 validate_messages: bool | str = True) -> None:
        if validate_messages not in (True, False, "all"):
            raise ValueError(f"validate_messages must be True, False or 'all', got {validate_messages!r}.")
        self._validate_crcs = validate_crcs
        self._validate_messages = validate_messages
        self._checkers: dict[int, Callable[[Any], str | None] | None] = {}
        self.notes: list[str] = []
        self._summary: Summary
        self._loose: list[LooseRun] = []
        self._extents: dict[int, list[int]] | None = None  # count, first, last per channel (unindexed parts)
        self._indexed = True
        self._summary_verified = False
        if isinstance(path, StackedLog):
            self.path = path.path
            self._file: BinaryIO = path.open()
        else:
            self.path = Path(path)
            if not self.path.is_file():
                raise LogNotFoundError(self.path)
            self._file = open(self.path, "rb")
        try:
            self._data_end = self._open()
        except BaseException:
            self._file.close()
            raise

    def _open(self) -> int:
        f = self._file
        try:
            data_end = locate_data_end(self.path, f)
        except (TruncatedLogError, NotMcapError):
            raise
        except CorruptLogError as err:
            raise CorruptLogError(self.path, f"{err.reason} {_hint(self.path)}") from err
        except (ValueError, OSError, struct.error) as err:  # footer pointing before the file start
            raise CorruptLogError(self.path, f"its footer is damaged ({err}). {_hint(self.path)}") from err
        size = f.seek(0, os.SEEK_END)
        f.seek(size - len(MCAP_MAGIC) - _FOOTER.size)
        _, _, summary_start, summary_offset_start, summary_crc = _FOOTER.unpack(f.read(_FOOTER.size))
        if summary_start == 0:
            self._scan_everything(data_end, "it has no summary section")
            return data_end
        footer_start = size - len(MCAP_MAGIC) - _FOOTER.size
        if not data_end < summary_start <= footer_start or not (
            summary_offset_start == 0 or summary_start <= summary_offset_start <= footer_start
        ):
            raise CorruptLogError(self.path, f"its footer points outside the file (summary at {summary_start}, "
                                             f"summary offsets at {summary_offset_start}). {_hint(self.path)}")
        if self._validate_crcs and summary_crc != 0:
            crc = computed_summary_crc(f, summary_start, summary_offset_start, footer_start)
            if crc != summary_crc:
                raise CorruptLogError(
                    self.path, f"its summary section (offset {summary_start}..{footer_start}) is damaged: "
                    f"CRC {crc:#010x} does not match the footer's {summary_crc:#010x}. {_hint(self.path)}")
            self._summary_verified = True
        try:
            self._summary = read_summary(f, summary_start)
        except (McapError, ValueError, EOFError, OSError, struct.error, KeyError, MemoryError) as err:
            raise CorruptLogError(self.path, f"its summary cannot be read ({type(err).__name__}: {err}). "
                                             f"{_hint(self.path)}") from err
        self._check_summary(data_end)
        self._find_unindexed(data_end)
        return data_end

    def _scan_everything(self, data_end: int, why: str, known: Summary | None = None) -> None:
        """Build the missing summary by one linear scan of the data section (every chunk CRC-checked)."""
        try:
            result = synthesize_summary(self.path, self._file, data_end, known=known)
        except (ValueError, struct.error, McapError, EOFError, UnicodeDecodeError) as err:
            raise CorruptLogError(self.path, f"{why}, and a linear scan of it stops: {err}. {_hint(self.path)}"
                                  ) from err
        self._summary = result.summary
        self._loose = result.loose
        self._extents = result.extents
        self._indexed = False
        self._check_summary(data_end)
        self.add_note(f"{why}: read by a linear scan of the whole file; add the indexes with: "
                      f"starlog recover {self.path} -o INDEXED.mcap")

    def _find_unindexed(self, data_end: int) -> None:
        """Messages outside chunks, chunks the summary does not list, chunks without message indexes."""
        try:
            self._loose, unlisted_chunk = find_loose_runs(self._file, self._summary, data_end)
        except (ValueError, struct.error) as err:
            raise CorruptLogError(self.path, f"its data section is damaged outside every indexed record ({err}). "
                                             f"{_hint(self.path)}") from err
        if unlisted_chunk:
            why = "its summary lists no chunk indexes" if not self._summary.chunk_indexes else \
                "it has chunks its summary does not list"
            self._scan_everything(data_end, why, known=self._summary)
            return
        bare = int(np.count_nonzero(self._summary.chunk_indexes.entry_counts() == 0))
        if bare:
            self.add_note(f"{bare} of {len(self._summary.chunk_indexes)} chunks have no message indexes: each is "
                          "read by scanning it whole.")
        if self._loose:
            self.add_note("some messages lie outside chunks (no index lists them): they are found by walking the "
                          "data section and read in log_time order with the rest.")
        self._indexed = not bare and not self._loose

    def _check_summary(self, data_end: int) -> None:
        """The indexes must point inside the data section and name known channels and schemas."""
        summary = self._summary
        problems: list[str] = []
        for ch in summary.channels.values():
            if ch.schema_id != 0 and ch.schema_id not in summary.schemas:
                problems.append(f"channel {ch.topic!r} refers to missing schema {ch.schema_id}")
        topics = [ch.topic for ch in summary.channels.values()]
        if len(set(topics)) != len(topics):
            problems.append("two channels have the same topic")
        problems += _chunk_index_problems(summary.chunk_indexes, set(summary.channels), data_end)
        for mi in summary.metadata_indexes:
            if not len(MCAP_MAGIC) <= mi.offset < mi.offset + mi.length <= data_end:
                problems.append(f"metadata index {mi.name!r} points outside the data section")
        for ai in summary.attachment_indexes:
            if not len(MCAP_MAGIC) <= ai.offset < ai.offset + ai.length <= data_end:
                problems.append(f"attachment index {ai.name!r} points outside the data section")
        if summary.statistics is not None:
            unknown = set(summary.statistics.channel_message_counts) - set(summary.channels)
            if unknown:
                problems.append(f"statistics count messages of unknown channels {sorted(unknown)}")
        if problems:
            raise CorruptLogError(self.path, f"its summary is inconsistent ({'; '.join(problems[:3])}). "
                                             f"{_hint(self.path)}")

    def add_note(self, note: str) -> None:
        """Record a one-line note about how the log was read (shown once, in reading order)."""
        if note not in self.notes:
            self.notes.append(note)

    def __enter__(self) -> LogReader:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Close the file."""
        self._file.close()

    @property
    def summary(self) -> Summary:
        """The MCAP summary (schemas, channels, chunk indexes, statistics). Its ``chunk_indexes`` is a
        :class:`~starlog.io.chunk_indexes.ChunkIndexTable`: a sequence whose items are made on access."""
        return self._summary

    @property
    def fully_indexed(self) -> bool:
        """Whether every message is reachable through the summary's indexes (chunk and message indexes).

        False for valid but unusual files: no summary, chunks without message indexes, messages
        outside chunks. Such files are read in full all the same, by scanning.
        """
        return self._indexed

    def _unindexed_extents(self) -> dict[int, list[int]]:
        """``[count, first, last]`` per channel over what the indexes do not describe (scanned once, lazily).

        Covers every segment when the summary has no statistics.
        """
        if self._extents is None:
            table = self._summary.chunk_indexes
            every = self._summary.statistics is None
            segments = table if every else table.indexes_at(np.flatnonzero(table.entry_counts() == 0))
            extents: dict[int, list[int]] = {}
            for ci in itertools.chain(segments, self._loose):
                for log_time, _, cid, _ in self._read_chunk(ci)[0]:
                    e = extents.get(cid)
                    if e is None:
                        extents[cid] = [1, log_time, log_time]
                    else:
                        e[0] += 1
                        e[1], e[2] = min(e[1], log_time), max(e[2], log_time)
            self._extents = extents
        return self._extents

    @property
    def topics(self) -> list[str]:
        """Topics of every channel, in channel-id order."""
        return [self._summary.channels[k].topic for k in sorted(self._summary.channels)]

    def has_topic(self, topic: str) -> bool:
        """Whether the log has a channel named ``topic``."""
        return topic in self.topics

    def channels(self) -> list[ChannelSummary]:
        """Every channel with its schema, message count and time range (from the indexes)."""
        summary = self._summary
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        ranges = summary.chunk_indexes.channel_time_ranges()
        first = {cid: lo for cid, (lo, _) in ranges.items()}
        last = {cid: hi for cid, (_, hi) in ranges.items()}
        if not self._indexed or summary.statistics is None:
            extents = self._unindexed_extents()
            for cid, (count, lo, hi) in extents.items():
                first[cid] = min(first.get(cid, lo), lo)
                last[cid] = max(last.get(cid, hi), hi)
            if summary.statistics is None:
                counts = {cid: e[0] for cid, e in extents.items()}
        out = []
        for cid in sorted(summary.channels):
            ch = summary.channels[cid]
            schema = summary.schemas.get(ch.schema_id)
            out.append(
                ChannelSummary(
                    topic=ch.topic,
                    schema_name=schema.name if schema else "",
                    schema_encoding=schema.encoding if schema else "",
                    message_encoding=ch.message_encoding,
                    message_count=int(counts.get(cid, 0)),
                    first_log_time=first.get(cid, 0),
                    last_log_time=last.get(cid, 0),
                )
            )
        return out

    def channel(self, topic: str) -> ChannelSummary:
        """The :class:`ChannelSummary` of ``topic``; :class:`ChannelNotFoundError` if absent."""
        for ch in self.channels():
            if ch.topic == topic:
                return ch
        raise ChannelNotFoundError(self.path, topic, self.topics)

    def time_range(self) -> tuple[int, int]:
        """First and last ``log_time`` of the whole log (0, 0 when empty)."""
        stats = self._summary.statistics
        if stats is None:
            extents = self._unindexed_extents().values()
            return (min((e[1] for e in extents), default=0), max((e[2] for e in extents), default=0))
        if stats.message_count == 0:
            return (0, 0)
        return (stats.message_start_time, stats.message_end_time)

    # ------------------------------------------------------------------ chunks
    def _chunk_error(self, ci: ChunkIndex, detail: str) -> CorruptChunkError:
        channels = self._summary.channels
        names = [channels[c].topic if c in channels else f"channel {c}" for c in sorted(ci.message_index_offsets)]
        return CorruptChunkError(self.path, ci.chunk_start_offset, names, ci.message_start_time,
                                 ci.message_end_time, detail)

    def _read_chunk(self, ci: ChunkIndex) -> tuple[list[tuple[int, int, int, Message]], bool]:
        """Every message of the chunk ``ci`` as ``(log_time, position, channel_id, message)``, fully checked,
        and whether its CRC was verified (never for messages outside chunks)."""
        if isinstance(ci, LooseRun):
            try:
                return read_loose(self._file, ci), False
            except (ValueError, struct.error) as err:
                raise CorruptLogError(self.path, f"the messages outside chunks at offset {ci.chunk_start_offset} are "
                                                 f"damaged ({err}). {_hint(self.path)}") from err
        f = self._file
        f.seek(ci.chunk_start_offset)
        raw = f.read(ci.chunk_length)
        if len(raw) != ci.chunk_length:
            raise self._chunk_error(ci, "the file ends inside it")
        opcode, length = _RECORD_HEADER.unpack_from(raw)
        if opcode != Opcode.CHUNK or _RECORD_HEADER.size + length != ci.chunk_length:
            raise self._chunk_error(ci, f"no chunk record there (opcode {opcode:#04x}, length {length})")
        try:
            start, end, size, crc = _CHUNK_HEADER.unpack_from(raw, 9)
            pos = 9 + _CHUNK_HEADER.size
            (name_len,) = struct.unpack_from("<I", raw, pos)
            compression = raw[pos + 4: pos + 4 + name_len].decode()
            pos += 4 + name_len
            (data_len,) = struct.unpack_from("<Q", raw, pos)
            pos += 8
            if pos + data_len != len(raw):
                raise ValueError(f"its data length {data_len} does not fit its record")
            if (start, end) != (ci.message_start_time, ci.message_end_time) or size != ci.uncompressed_size \
                    or compression != ci.compression:
                raise ValueError("its header disagrees with the summary's chunk index")
            data = decompress(compression, memoryview(raw)[pos:], size)
        except Exception as err:  # struct.error, UnicodeDecodeError, ZstdError, lz4 RuntimeError ...
            raise self._chunk_error(ci, f"{type(err).__name__}: {err}") from err
        if len(data) != size:
            raise self._chunk_error(ci, f"it decompresses to {len(data)} bytes, not {size}")
        verified = self._validate_crcs and crc != 0
        if verified and crc32(data) != crc:
            raise self._chunk_error(ci, f"CRC mismatch (stored {crc:#010x}, computed {crc32(data):#010x})")
        messages: list[tuple[int, int, int, Message]] = []
        offsets: dict[int, list[tuple[int, int]]] = {}
        view = memoryview(data).toreadonly()  # payloads are slices of it, not copies
        pos = 0
        try:
            while pos < size:
                opcode, length = _RECORD_HEADER.unpack_from(data, pos)
                body = pos + _RECORD_HEADER.size
                if body + length > size:
                    raise ValueError(f"a record at chunk offset {pos} runs past the chunk's end")
                if opcode == Opcode.MESSAGE:
                    cid, seq, log_time, publish_time = _MESSAGE_HEADER.unpack_from(data, body)
                    if cid not in (ci.message_index_offsets or self._summary.channels):
                        raise ValueError(f"it holds a message of channel {cid}, which "
                                         f"{'its index' if ci.message_index_offsets else 'the log'} does not list")
                    if not start <= log_time <= end:
                        raise ValueError(f"a message at log_time {log_time} lies outside its range {start}..{end}")
                    payload = view[body + _MESSAGE_HEADER.size: body + length]
                    messages.append((log_time, len(messages), cid, Message(cid, log_time, payload, publish_time, seq)))
                    offsets.setdefault(cid, []).append((log_time, pos))
                pos = body + length
        except (struct.error, ValueError) as err:
            raise self._chunk_error(ci, str(err)) from err
        self._check_message_index(ci, offsets)
        return messages, verified

    def _check_message_index(self, ci: ChunkIndex, offsets: dict[int, list[tuple[int, int]]]) -> None:
        """The message index records after the chunk must list exactly the chunk's messages."""
        if not ci.message_index_offsets:  # valid MCAP: the chunk has no message index records
            return
        f = self._file
        first = min(ci.message_index_offsets.values())
        f.seek(first)
        block = f.read(ci.message_index_length)
        for cid, offset in ci.message_index_offsets.items():
            rel = offset - first
            try:
                opcode, length = _RECORD_HEADER.unpack_from(block, rel)
                channel_id, array_len = struct.unpack_from("<HI", block, rel + 9)
                if opcode != Opcode.MESSAGE_INDEX or length != 6 + array_len or array_len % 16 \
                        or channel_id != cid or rel + 9 + length > len(block):
                    raise ValueError("not a message index record of this channel")
                records = sorted(struct.iter_unpack("<QQ", block[rel + 15: rel + 15 + array_len]))
            except (struct.error, ValueError) as err:
                raise self._chunk_error(ci, f"its message index for channel {cid} at offset {offset} is damaged "
                                            f"({err})") from err
            if records != sorted(offsets.get(cid, [])):
                raise self._chunk_error(ci, f"its message index for channel {cid} at offset {offset} does not match "
                                            "the chunk's messages")

    def raw_messages(
        self, topics: Iterable[str], *, start: int | None = None, end: int | None = None, views: bool = False,
    ) -> Iterator[tuple[Schema | None, Channel, Message]]:
        """Undecoded messages of ``topics`` in ``log_time`` order (ties: file order), streamed chunk by chunk.

        ``start`` is inclusive, ``end`` exclusive. Only the chunks holding these topics are read,
        and only those whose time ranges overlap are held in memory at once. A damaged chunk
        raises :class:`CorruptChunkError` naming it. Each ``message.data`` is ``bytes``; with
        ``views``, a read-only ``memoryview`` into the decompressed chunk instead (no copy; it
        keeps the chunk's bytes alive as long as it lives).
        """
        for schema, channel, message, _ in self._merged_messages(topics, start=start, end=end):
            if not views and not isinstance(message.data, bytes):
                message.data = bytes(message.data)
            yield schema, channel, message

    def _merged_messages(
        self, topics: Iterable[str], *, start: int | None, end: int | None
    ) -> Iterator[tuple[Schema | None, Channel, Message, bool]]:
        """:meth:`raw_messages`, each with whether its chunk's CRC was verified."""
        wanted = list(topics)
        for topic in wanted:
            if topic not in self.topics:
                raise ChannelNotFoundError(self.path, topic, self.topics)
        summary = self._summary
        ids = {cid for cid, ch in summary.channels.items() if ch.topic in wanted}
        lo = 0 if start is None else start
        hi = 2**64 if end is None else end
        chunks = _Peekable(self._chunks_in_time_order(ids, lo, hi))
        heap: list[tuple[int, int, int, int, Message, bool]] = []
        last = -1
        while heap or chunks.peek is not None:
            while chunks.peek is not None and (not heap or chunks.peek.message_start_time <= heap[0][0]):
                ci = chunks.pop()
                messages, verified = self._read_chunk(ci)
                for log_time, position, cid, message in messages:
                    if cid in ids and lo <= log_time < hi:
                        heapq.heappush(heap, (log_time, ci.chunk_start_offset, position, cid, message, verified))
            if not heap:  # the last chunks held none of the wanted messages
                break
            log_time, _, _, cid, message, verified = heapq.heappop(heap)
            if log_time < last:  # cannot happen with consistent indexes; never pass on a wrong order
                raise CorruptLogError(self.path, f"messages come out of log_time order at {log_time}. "
                                                 f"{_hint(self.path)}")
            last = log_time
            channel = summary.channels[cid]
            yield (summary.schemas.get(channel.schema_id) if channel.schema_id else None), channel, message, verified

    def _chunks_in_time_order(self, ids: set[int], lo: int, hi: int) -> Iterator[ChunkIndex]:
        """The chunks (and runs of messages outside chunks) that may hold a message of ``ids`` with
        ``lo <= log_time < hi``, by ``(message_start_time, offset)``; the chunk indexes are made one at a time."""
        table: ChunkIndexTable = self._summary.chunk_indexes
        chunks = table.indexes_at(table.rows_for_channels(ids, lo, hi))
        loose = sorted((run for run in self._loose
                        if (not run.message_index_offsets or not ids.isdisjoint(run.message_index_offsets))
                        and run.message_end_time >= lo and run.message_start_time < hi),
                       key=lambda run: (run.message_start_time, run.chunk_start_offset))
        return heapq.merge(chunks, loose, key=lambda ci: (ci.message_start_time, ci.chunk_start_offset))

    def _trusted(self, channel: Channel) -> bool:
        """Whether the channel's messages were checked by starlog's writer and the summary saying so is intact."""
        return (self._validate_messages is True and self._summary_verified
                and channel.metadata.get(VALIDATED_METADATA_KEY) == "jsonschema")

    def _checker(self, schema: Schema | None) -> Callable[[Any], str | None] | None:
        if not self._validate_messages or schema is None or schema.encoding != "jsonschema":
            return None
        if schema.id not in self._checkers:
            try:
                schema_value = json.loads(schema.data)
            except ValueError as err:
                raise CorruptLogError(self.path, f"the JSON Schema {schema.name!r} in the log cannot be read "
                                                 f"({err}).") from err
            try:
                self._checkers[schema.id] = compile_json_schema(schema_value)
            except (InvalidInputError, ValueError, TypeError, KeyError) as err:  # keywords of other tools' schemas
                self._checkers[schema.id] = None
                self.add_note(f"messages of schema {schema.name!r} are not checked against it ({err}).")
        return self._checkers[schema.id]

    def messages(
        self, topic: str | Iterable[str], *, start: int | None = None, end: int | None = None, stride: int = 1,
    ) -> Iterator[DecodedMessage]:
        """Decoded messages of one topic (or several, interleaved by ``log_time``), streamed.

        JSON payloads are checked against their channel's schema (see ``validate_messages``).
        With ``stride`` n, only every n-th message (the first, the n+1-th, ...) is decoded and yielded.
        """
        if stride < 1:
            raise InvalidParameterError(f"stride must be >= 1; got {stride}.")
        topics = [topic] if isinstance(topic, str) else list(topic)
        trusted = {c.id: self._trusted(c) for c in self._summary.channels.values()}
        merged = self._merged_messages(topics, start=start, end=end)
        for schema, channel, message, verified in itertools.islice(merged, 0, None, stride):
            check = None if verified and trusted[channel.id] else self._checker(schema)
            yield DecodedMessage(
                channel.topic, message.log_time, message.sequence,
                decode_payload(self.path, schema, channel, message, check),
            )

    def chunk_message_counts(self, topic: str) -> list[tuple[int, int, int]]:
        """``(message_start_time, message_end_time, count)`` of ``topic`` in each chunk holding it, in time order.

        Read from the message index records (a few bytes per chunk; no chunk is decompressed).
        """
        channel_id = next((c.id for c in self._summary.channels.values() if c.topic == topic), None)
        if channel_id is None:
            raise ChannelNotFoundError(self.path, topic, self.topics)
        table: ChunkIndexTable = self._summary.chunk_indexes
        rows, channels, offsets = table.entries()
        mine = channels == channel_id
        out = []
        for ci, offset in zip(table.indexes_at(rows[mine]), offsets[mine].tolist(), strict=True):
            self._file.seek(offset)
            head = self._file.read(_RECORD_HEADER.size + 6)
            try:
                opcode, _ = _RECORD_HEADER.unpack_from(head, 0)
                cid, array_len = struct.unpack_from("<HI", head, _RECORD_HEADER.size)
            except struct.error as err:
                raise self._chunk_error(ci, f"its message index is cut short ({err})") from err
            if opcode != Opcode.MESSAGE_INDEX or cid != channel_id or array_len % 16:
                raise self._chunk_error(ci, f"its message index for channel {channel_id} is damaged")
            out.append((ci.message_start_time, ci.message_end_time, array_len // 16))
        return sorted(out)

    def frames(self, topic: str = "/camera/image", *, start: int | None = None, end: int | None = None,
               first_index: int = 0, on_bad: Callable[[SkippedFrame], None] | None = None,
               ) -> Iterator[tuple[int, int, np.ndarray]]:
        """``(frame_index, log_time, image)`` for every image of ``topic`` (``start <= log_time < end``), in time order.

        Any image type of :mod:`starlog.io.images` is decoded to a 2-D mono array.
        ``first_index`` numbers the first frame returned (for a block read out of a longer log).
        Raises :class:`InvalidMessageError` when a frame is not 2-D, has another size or pixel type
        than the first, or does not come strictly after the previous frame; with ``on_bad``,
        such a frame is handed to it and left out instead.
        """
        for frame in self.frame_records(topic, start=start, end=end, first_index=first_index, on_bad=on_bad):
            yield frame.index, frame.log_time, frame.image

    def frame_records(self, topic: str = "/camera/image", *, start: int | None = None, end: int | None = None,
                      first_index: int = 0, on_bad: Callable[[SkippedFrame], None] | None = None,
                      ) -> Iterator[Frame]:
        """Like :meth:`frames`, as :class:`~starlog.io.frames.Frame` records (with the message's own stamp)."""
        return iter_frames(self, topic, start=start, end=end, first_index=first_index, on_bad=on_bad)

    def metadata(self, name: str | None = None) -> list[tuple[str, dict[str, str]]]:
        """MCAP Metadata records ``(name, map)`` in file order, optionally only those named ``name``."""
        out = []
        for index in sorted(self._summary.metadata_indexes, key=lambda m: m.offset):
            if name is not None and index.name != name:
                continue
            self._file.seek(index.offset)
            raw = self._file.read(index.length)
            try:
                opcode, length = _RECORD_HEADER.unpack_from(raw)
                if opcode != Opcode.METADATA or _RECORD_HEADER.size + length != index.length:
                    raise ValueError(f"no metadata record there (opcode {opcode:#04x})")
                record = Metadata.read(ReadDataStream(io.BytesIO(raw[_RECORD_HEADER.size:])))
                if record.name != index.name:
                    raise ValueError(f"it is named {record.name!r}, its index says {index.name!r}")
            except (struct.error, ValueError, EOFError, McapError) as err:
                raise CorruptLogError(self.path, f"the metadata record {index.name!r} at offset {index.offset} is "
                                                 f"damaged ({err}). {_hint(self.path)}") from err
            out.append((record.name, dict(record.metadata)))
        return out

    def provenance(self) -> list[Provenance]:
        """Every stage recorded in the log, oldest first."""
        out = []
        for _, data in self.metadata(PROVENANCE_METADATA_NAME):
            try:
                record = Provenance.from_metadata(data)
                if not isinstance(record.parameters, dict) or not isinstance(record.channels, list):
                    raise ValueError("parameters must be an object and channels a list")
            except (ValueError, TypeError, RecursionError) as err:
                raise CorruptLogError(self.path, f"a provenance record is damaged ({err}).") from err
            out.append(record)
        return out
