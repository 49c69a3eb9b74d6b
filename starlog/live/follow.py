"""Following an MCAP file that another program is still writing: its records as they become complete.

A file being written has no summary and no footer yet; its data section grows record by record,
and a reader that reaches the end may be inside a record the writer has not finished. The
:class:`McapFollower` reads the records one after the other from where it stopped, and treats a
short read as *not yet written*, never as the end: it waits for the rest (the caller polls again).
A chunk is handed over whole once its last byte is there, decompressed and CRC-checked; its
messages come with it, in the chunk's order. The file ends when its footer and closing magic are
there; a writer that stops inside a record leaves the follower waiting, and the caller decides how
long to wait (:attr:`McapFollower.stalled_since`).

A chunk that arrives whole but does not decode (CRC, decompression) is reported as damaged and
skipped: its record length says where the next record starts. A record whose header is not one a
writer makes (an unknown opcode, an impossible length) ends the following with :class:`CorruptLogError`:
nothing after it can be trusted.
"""

from __future__ import annotations

import os
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from mcap.opcode import Opcode
from mcap.records import Channel, Message, Metadata, Schema

from starlog.errors import CorruptLogError, NotMcapError
from starlog.io.chunks import decode_chunk
from starlog.io.layout import MAGIC, MESSAGE_HEADER, RECORD_HEADER, chunk_header, parse_record
from starlog.io.record_walk import walk_records

__all__ = ["DamagedChunk", "FollowedChunk", "FollowedMessage", "FollowedMetadata", "McapFollower"]

#: No record a camera log holds comes near this: a longer one is a damaged length field.
_MAX_RECORD = 1 << 36
_KNOWN = {int(o) for o in Opcode}


@dataclass(frozen=True)
class FollowedMessage:
    """A message of the followed file, with its schema (None: schemaless) and channel."""

    schema: Schema | None
    channel: Channel
    message: Message


@dataclass(frozen=True)
class FollowedChunk:
    """A chunk record that arrived whole: where it is, its time range, its messages (in the chunk's order) and
    how many of them each channel has."""

    offset: int
    length: int
    start: int
    end: int
    messages: list[FollowedMessage]
    counts: dict[int, int] = field(default_factory=dict)


@dataclass(frozen=True)
class DamagedChunk:
    """A chunk record that arrived whole but does not decode: where, its time range (from its header) and why."""

    offset: int
    start: int
    end: int
    reason: str


@dataclass(frozen=True)
class FollowedMetadata:
    """A metadata record of the followed file."""

    name: str
    metadata: dict[str, str]


Event = FollowedChunk | FollowedMessage | DamagedChunk | FollowedMetadata


class McapFollower:
    """The records of a growing MCAP file, read as they are completed (module docstring).

    Parameters
    ----------
    path : path-like
        The file; it must exist (its first bytes may not be written yet).
    clock : callable
        Monotonic seconds (``time.monotonic``), for :attr:`stalled_since`.
    """

    def __init__(self, path: str | os.PathLike[str], *, clock: Callable[[], float] = time.monotonic) -> None:
        self.path = Path(path)
        self.file = open(self.path, "rb")  # noqa: SIM115 - closed by close()
        """The file as it was opened (still readable if its name is removed)."""
        self._clock = clock
        self.position = 0
        """Offset of the first byte not yet handed over (the next record's start)."""
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.data_ended = False
        """Whether the DataEnd record was read (the summary and footer follow)."""
        self.finished = False
        """Whether the footer and the closing magic were read: the file is complete."""
        self.stalled_since = clock()
        """When the file last grew (monotonic seconds)."""
        self._size = 0

    def close(self) -> None:
        self.file.close()

    def __enter__(self) -> McapFollower:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def size(self) -> int:
        """The file's size when it was last looked at."""
        return self._size

    def pending(self) -> int:
        """Bytes the file holds beyond the last complete record (a record being written, or what a stalled
        writer left unfinished)."""
        return max(self._size - self.position, 0)

    def poll(self, *, max_events: int = 64) -> list[Event]:
        """The records completed since the last call (at most about ``max_events`` chunks and messages); an
        empty list when nothing new is whole yet."""
        size = os.fstat(self.file.fileno()).st_size
        if size != self._size:
            if size < self._size:
                raise CorruptLogError(self.path, f"it shrank from {self._size} to {size} bytes while being "
                                                 "followed (truncated or replaced by its writer)")
            self._size, self.stalled_since = size, self._clock()
        if self.position == 0 and not self._magic():
            return []
        events: list[Event] = []
        while not self.finished and len(events) < max_events:
            record = self._next_record()
            if record is None:
                break
            offset, opcode, body = record
            events.extend(self._handle(offset, opcode, body))
        return events

    def _magic(self) -> bool:
        if self._size < len(MAGIC):
            return False
        self.file.seek(0)
        head = self.file.read(len(MAGIC))
        if head != MAGIC:
            raise NotMcapError(self.path)
        self.position = len(MAGIC)
        return True

    def _next_record(self) -> tuple[int, int, bytes] | None:
        """The next whole record ``(offset, opcode, body)``, or None while it is not all written."""
        if self._size - self.position < RECORD_HEADER.size:
            return None
        self.file.seek(self.position)
        opcode, length = RECORD_HEADER.unpack(self.file.read(RECORD_HEADER.size))
        if opcode not in _KNOWN or length > _MAX_RECORD:
            raise CorruptLogError(self.path, f"the record at offset {self.position} has opcode {opcode:#04x} and "
                                             f"length {length}, which no MCAP writer makes; the file cannot be "
                                             "followed past it")
        end = self.position + RECORD_HEADER.size + length
        if opcode == Opcode.FOOTER:
            end += len(MAGIC)  # the closing magic ends the file
        if self._size < end:
            return None
        body = self.file.read(length)
        offset, self.position = self.position, self.position + RECORD_HEADER.size + length
        if opcode == Opcode.FOOTER:
            self.finished = True
        return offset, opcode, body

    def _handle(self, offset: int, opcode: int, body: bytes) -> list[Event]:
        if self.data_ended:
            return []  # the summary repeats what the data section said
        try:
            if opcode == Opcode.CHUNK:
                return [self._chunk(offset, body)]
            if opcode == Opcode.SCHEMA:
                self._schema(parse_record(body, Schema))
            elif opcode == Opcode.CHANNEL:
                self._channel(parse_record(body, Channel))
            elif opcode == Opcode.MESSAGE:
                return [self._message(parse_record(body, Message))]
            elif opcode == Opcode.METADATA:
                record = parse_record(body, Metadata)
                return [FollowedMetadata(record.name, dict(record.metadata))]
            elif opcode == Opcode.DATA_END:
                self.data_ended = True
        except (ValueError, struct.error, EOFError, UnicodeDecodeError) as err:
            raise CorruptLogError(self.path, f"the record at offset {offset} (opcode {opcode:#04x}) is damaged "
                                             f"({type(err).__name__}: {err})") from err
        return []

    def _schema(self, schema: Schema) -> None:
        if schema.id != 0:
            self.schemas.setdefault(schema.id, schema)

    def _channel(self, channel: Channel) -> None:
        self.channels.setdefault(channel.id, channel)

    def _message(self, message: Message) -> FollowedMessage:
        channel = self.channels.get(message.channel_id)
        if channel is None:
            raise ValueError(f"its message names channel {message.channel_id}, which no record before it defines")
        return FollowedMessage(self.schemas.get(channel.schema_id), channel, message)

    def _chunk(self, offset: int, body: bytes) -> FollowedChunk | DamagedChunk:
        """A whole chunk, decoded; a damaged one reported with the time range its header gives."""
        start, end = chunk_header(body, whole=False)[:2]
        try:
            contents = decode_chunk(body)
        except Exception as err:  # struct, zstd and lz4 errors, CRC mismatch
            return DamagedChunk(offset, start, end, f"{type(err).__name__}: {err}")
        messages: list[FollowedMessage] = []
        counts: dict[int, int] = {}
        data = contents.data
        for _, opcode, _, record in walk_records(data):
            if record is None:
                continue
            if opcode == Opcode.SCHEMA:
                self._schema(parse_record(record, Schema))
            elif opcode == Opcode.CHANNEL:
                self._channel(parse_record(record, Channel))
            elif opcode == Opcode.MESSAGE:
                cid, seq, log_time, publish_time = MESSAGE_HEADER.unpack_from(record, 0)
                message = Message(cid, log_time, bytes(record[MESSAGE_HEADER.size:]), publish_time, seq)
                messages.append(self._message(message))
                counts[cid] = counts.get(cid, 0) + 1
        return FollowedChunk(offset, RECORD_HEADER.size + len(body), start, end, messages, counts)
