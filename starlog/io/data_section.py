"""One pass over a data section, each record handed to its kind's callback.

:func:`walk_data_section` walks the records of a data section (:func:`~starlog.io.record_walk.walk_records`)
and dispatches each by opcode to a :class:`DataVisitor`'s callbacks, schema and channel records parsed;
:func:`walk_chunk` does the same for the records inside a decompressed chunk. The summary rebuilding
and the search for loose messages (:mod:`starlog.io.scan`), ``starlog recover`` and ``starlog verify``
are visitors of their own: what differs between them is what they do with a record, and with a damaged one.
"""

from __future__ import annotations

from collections.abc import Container
from typing import BinaryIO

from mcap.opcode import Opcode
from mcap.records import Channel, Schema

from starlog.io.layout import MESSAGE_HEADER, RECORD_HEADER, parse_record
from starlog.io.record_walk import walk_records

__all__ = ["DataVisitor", "MessageHead", "walk_chunk", "walk_data_section"]

#: A message's fixed fields: channel id, sequence, log_time, publish_time.
MessageHead = tuple[int, int, int, int]


class DataVisitor:
    """The callbacks of a pass over a data section; each does nothing here (:meth:`damaged` re-raises).

    ``bodies``: the opcodes whose bodies the pass reads (None: every one); a callback gets None for the
    others, but a message's fixed fields are read in any case, and schema and channel records are handed
    on (parsed) only when their bodies are read. A callback sets ``done`` to end the pass after its
    record; the DataEnd record's does.
    """

    bodies: Container[int] | None = None
    done = False

    def record(self, offset: int, opcode: int, length: int) -> None:
        """Called for every record before its own callback."""

    def schema(self, offset: int, schema: Schema) -> None:
        """A Schema record (``offset``: its own, or its chunk's)."""

    def channel(self, offset: int, channel: Channel) -> None:
        """A Channel record (``offset``: its own, or its chunk's)."""

    def message(self, offset: int, length: int, head: MessageHead, payload: memoryview | None) -> None:
        """A Message record outside chunks (``length``: its body's)."""

    def chunk_message(self, position: int, head: MessageHead, payload: memoryview) -> None:
        """A Message record inside the chunk :func:`walk_chunk` walks (``position``: its offset in the chunk)."""

    def chunk(self, offset: int, length: int, body: memoryview | None) -> None:
        """A Chunk record."""

    def message_index(self, offset: int, length: int, body: memoryview | None) -> None:
        """A Message Index record."""

    def metadata(self, offset: int, length: int, body: memoryview | None) -> None:
        """A Metadata record."""

    def attachment(self, offset: int, length: int, body: memoryview | None) -> None:
        """An Attachment record."""

    def data_end(self, offset: int, length: int) -> None:
        """The DataEnd record: the end of the data section."""
        self.done = True

    def other(self, offset: int, opcode: int, length: int) -> None:
        """Any other record: the header, records of the summary section, opcodes the format does not define."""

    def damaged(self, offset: int, opcode: int, error: Exception) -> None:
        """A callback raised ``error`` (a record that does not parse, or that it refuses)."""
        raise error


def walk_data_section(f: BinaryIO, start: int, end: int, visitor: DataVisitor) -> None:
    """Hand each record of ``f`` from ``start`` to ``end`` to ``visitor``, until it is ``done``.

    Raises :class:`~starlog.io.record_walk.RecordOverrun` for a record that runs past ``end``.
    """
    for offset, opcode, length, body in walk_records(f, start, end, bodies=visitor.bodies):
        visitor.record(offset, opcode, length)
        try:
            _dispatch(f, visitor, offset, opcode, length, body)
        except Exception as err:  # struct.error, ValueError, EOFError, the callback's own ...
            visitor.damaged(offset, opcode, err)
        if visitor.done:
            return


def _dispatch(f: BinaryIO, visitor: DataVisitor, offset: int, opcode: int, length: int,
              body: memoryview | None) -> None:
    if opcode == Opcode.MESSAGE:
        if body is None:
            f.seek(offset + RECORD_HEADER.size)
            head = MESSAGE_HEADER.unpack(f.read(MESSAGE_HEADER.size))
        else:
            head = MESSAGE_HEADER.unpack_from(body)
        visitor.message(offset, length, head, None if body is None else body[MESSAGE_HEADER.size:])
    elif opcode == Opcode.CHUNK:
        visitor.chunk(offset, length, body)
    elif opcode == Opcode.MESSAGE_INDEX:
        visitor.message_index(offset, length, body)
    elif opcode == Opcode.SCHEMA and body is not None:
        visitor.schema(offset, parse_record(body, Schema))
    elif opcode == Opcode.CHANNEL and body is not None:
        visitor.channel(offset, parse_record(body, Channel))
    elif opcode == Opcode.METADATA:
        visitor.metadata(offset, length, body)
    elif opcode == Opcode.ATTACHMENT:
        visitor.attachment(offset, length, body)
    elif opcode == Opcode.DATA_END:
        visitor.data_end(offset, length)
    elif opcode not in (Opcode.SCHEMA, Opcode.CHANNEL):
        visitor.other(offset, opcode, length)


def walk_chunk(data: bytes | memoryview, visitor: DataVisitor, offset: int) -> None:
    """Hand the records of a decompressed chunk (``data``; the chunk record at ``offset``) to ``visitor``: its
    messages to :meth:`~DataVisitor.chunk_message`, its schemas and channels to their callbacks.

    Raises :class:`~starlog.io.record_walk.RecordOverrun` and the parsers' errors for damaged records.
    """
    for position, opcode, _, body in walk_records(data):
        if body is None:  # never: this walk reads every body
            continue
        if opcode == Opcode.MESSAGE:
            visitor.chunk_message(position, MESSAGE_HEADER.unpack_from(body), body[MESSAGE_HEADER.size:])
        elif opcode == Opcode.SCHEMA:
            visitor.schema(offset, parse_record(body, Schema))
        elif opcode == Opcode.CHANNEL:
            visitor.channel(offset, parse_record(body, Channel))
