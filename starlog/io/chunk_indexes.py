"""The summary's chunk indexes as columns of numbers, and a summary reader that streams them in.

An MCAP summary lists one Chunk Index record per chunk. Parsed into ``mcap.records.ChunkIndex``
objects they keep about 0.5 KB each and take 10-16 us to parse: an hour of 1024x1024 frames at
300 Hz has about 1.6 million chunks, i.e. 0.8 GB and tens of seconds in every process that opens
the log (``tools/bench_index.py``).
:class:`ChunkIndexTable` keeps the same fields in arrays (about 80 bytes a chunk) and makes a
``ChunkIndex`` only when one is asked for; :func:`read_summary` fills it from the file a block
at a time, so the summary section is never held whole either.
"""

from __future__ import annotations

import io
import math
import struct
from array import array
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any, BinaryIO, overload

import numpy as np
import numpy.typing as npt
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import AttachmentIndex, Channel, ChunkIndex, MetadataIndex, Schema, Statistics
from mcap.summary import Summary

from starlog.io.layout import FOOTER, MAGIC, RECORD_HEADER

__all__ = ["ChunkIndexTable", "read_file_summary", "read_summary"]

_CHUNK_INDEX_HEAD = struct.Struct("<QQQQI")  # start time, end time, chunk offset, chunk length, offsets' bytes
_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")
_SIZES = struct.Struct("<QQ")  # compressed, uncompressed
_PAIR = struct.Struct("<HQ")  # channel id, message index offset
_TAIL_MIN = 8 + 4 + 16  # message index length, compression name length, sizes
_READ_BLOCK = 1 << 20
#: Chunks in a block of :meth:`ChunkIndexTable.row_blocks` (a few MB of temporary arrays for a check).
ROW_BLOCK = 1 << 16

#: The numeric columns, in the order :meth:`ChunkIndexTable.append_fields` takes them.
_COLUMNS = ("message_start_time", "message_end_time", "chunk_start_offset", "chunk_length",
            "message_index_length", "compressed_size", "uncompressed_size")


class ChunkIndexTable(Sequence[ChunkIndex]):
    """Chunk indexes in file order, stored by column; reads as a sequence of ``ChunkIndex``.

    Iterating or indexing makes the ``ChunkIndex`` objects one at a time; the vectorised
    queries (:meth:`column`, :meth:`rows_for_channels`, :meth:`channel_time_ranges`, ...) make
    none. Each channel's message index offset keeps the order of its record.
    """

    def __init__(self, indexes: Iterable[ChunkIndex] = ()) -> None:
        self._columns = {name: array("Q") for name in _COLUMNS}
        self._compression = array("H")
        self._names: list[str] = []
        self._codes: dict[str, int] = {}
        self._entry_start = array("Q", [0])
        self._entry_channel = array("H")
        self._entry_offset = array("Q")
        self._cache: dict[str, npt.NDArray[Any]] = {}
        for ci in indexes:
            self.append(ci)

    # ------------------------------------------------------------------ building
    def append(self, ci: ChunkIndex) -> None:
        """Add one chunk index at the end."""
        self.append_fields(ci.message_start_time, ci.message_end_time, ci.chunk_start_offset, ci.chunk_length,
                           ci.message_index_length, ci.compressed_size, ci.uncompressed_size, ci.compression,
                           ci.message_index_offsets.keys(), ci.message_index_offsets.values())

    def append_fields(self, start_time: int, end_time: int, chunk_offset: int, chunk_length: int,
                      index_length: int, compressed_size: int, uncompressed_size: int, compression: str,
                      channel_ids: Iterable[int], index_offsets: Iterable[int]) -> None:
        """Add one chunk index from its fields (``channel_ids`` and ``index_offsets`` pair up, in order).

        Raises ``ValueError`` or ``OverflowError`` (the table unchanged) for a value out of range.
        """
        numbers = array("Q", (start_time, end_time, chunk_offset, chunk_length, index_length, compressed_size,
                              uncompressed_size))
        channels, offsets = array("H", channel_ids), array("Q", index_offsets)
        if len(channels) != len(offsets):
            raise ValueError("a chunk index needs one message index offset per channel")
        code = self._code_for(compression)
        if self._cache:
            self._unshare()
        for column, value in zip(self._columns.values(), numbers, strict=True):
            column.append(value)
        self._compression.append(code)
        self._entry_channel.extend(channels)
        self._entry_offset.extend(offsets)
        self._entry_start.append(len(self._entry_channel))

    def append_record(self, body: bytes | memoryview) -> None:
        """Add one chunk index from its record's body (the bytes after the opcode and length).

        Raises ``ValueError`` or ``struct.error`` (the table unchanged) for a body that does not parse.
        """
        _append_chunk_index(self, memoryview(body))

    def append_columns(self, rows: npt.NDArray[np.void], compression: str) -> None:
        """Add chunk indexes of one compression from a record array with the numeric fields' names and a
        ``pairs`` field of ``(channel, offset)`` subarrays (every row listing as many channels)."""
        if not rows.size:
            return
        code = self._code_for(compression)
        if self._cache:
            self._unshare()
        for name, column in self._columns.items():
            column.frombytes(np.ascontiguousarray(rows[name], dtype="=u8").tobytes())
        self._compression.frombytes(np.full(rows.size, code, dtype="=u2").tobytes())
        pairs = rows["pairs"].reshape(-1)
        self._entry_channel.frombytes(np.ascontiguousarray(pairs["channel"], dtype="=u2").tobytes())
        self._entry_offset.frombytes(np.ascontiguousarray(pairs["offset"], dtype="=u8").tobytes())
        per_row = rows["pairs"].shape[1] if rows["pairs"].ndim > 1 else 0
        ends = self._entry_start[-1] + per_row * np.arange(1, rows.size + 1, dtype=np.uint64)
        self._entry_start.frombytes(ends.astype("=u8").tobytes())

    def _code_for(self, compression: str) -> int:
        """The code of a compression name (a new one for a name not seen yet)."""
        code = self._codes.get(compression)
        if code is None:
            code = self._codes[compression] = len(self._names)
            self._names.append(compression)
        return code

    def _unshare(self) -> None:
        """Forget the array views handed out, and copy the columns they may still share (an array
        cannot grow while a view of it lives)."""
        self._cache.clear()
        self._columns = {name: array("Q", column) for name, column in self._columns.items()}
        self._compression = array("H", self._compression)
        self._entry_start = array("Q", self._entry_start)
        self._entry_channel = array("H", self._entry_channel)
        self._entry_offset = array("Q", self._entry_offset)

    def extend(self, indexes: Iterable[ChunkIndex]) -> None:
        for ci in indexes:
            self.append(ci)

    # ------------------------------------------------------------------ the sequence
    def __len__(self) -> int:
        return len(self._compression)

    def __bool__(self) -> bool:
        return len(self) > 0

    @overload
    def __getitem__(self, i: int) -> ChunkIndex: ...

    @overload
    def __getitem__(self, i: slice) -> list[ChunkIndex]: ...

    def __getitem__(self, i: int | slice) -> ChunkIndex | list[ChunkIndex]:
        if isinstance(i, slice):
            return [self._make(k) for k in range(*i.indices(len(self)))]
        n = len(self)
        if not -n <= i < n:
            raise IndexError("chunk index out of range")
        return self._make(i % n)

    def __iter__(self) -> Iterator[ChunkIndex]:
        return (self._make(k) for k in range(len(self)))

    def indexes_at(self, rows: Iterable[int]) -> Iterator[ChunkIndex]:
        """The chunk indexes at ``rows`` (positions in file order), made one at a time."""
        return (self._make(int(k)) for k in rows)

    def __eq__(self, other: object) -> bool:
        """Equal to a table or list of the same chunk indexes, in the same order."""
        if not isinstance(other, ChunkIndexTable | list | tuple):
            return NotImplemented
        return len(self) == len(other) and all(a == b for a, b in zip(self, other, strict=True))

    __hash__ = None  # type: ignore[assignment]  # mutable

    def _make(self, k: int) -> ChunkIndex:
        c = self._columns
        a, b = self._entry_start[k], self._entry_start[k + 1]
        return ChunkIndex(
            chunk_length=c["chunk_length"][k], chunk_start_offset=c["chunk_start_offset"][k],
            compression=self._names[self._compression[k]], compressed_size=c["compressed_size"][k],
            message_end_time=c["message_end_time"][k], message_index_length=c["message_index_length"][k],
            message_index_offsets=dict(zip(self._entry_channel[a:b], self._entry_offset[a:b], strict=True)),
            message_start_time=c["message_start_time"][k], uncompressed_size=c["uncompressed_size"][k],
        )

    # ------------------------------------------------------------------ vectorised queries
    def column(self, name: str) -> npt.NDArray[np.uint64]:
        """One numeric field of every chunk (``"chunk_start_offset"``, ``"message_start_time"``, ...)."""
        if name not in self._columns:
            raise KeyError(name)
        return self._array(name, lambda: np.frombuffer(self._columns[name], dtype=np.uint64))

    def compressions(self) -> set[str]:
        """The compressions the chunks use."""
        return set(self._names)  # a name is added with the first chunk that uses it

    def row_blocks(self, size: int | None = None) -> Iterator[tuple[int, int, int, int]]:
        """``(first row, end row, first entry, end entry)`` of consecutive blocks of at most ``size`` chunks
        (:data:`ROW_BLOCK` by default): a query made block by block keeps its temporary arrays to the
        block's size, whatever the log's length."""
        size = ROW_BLOCK if size is None else size
        if size <= 0:
            raise ValueError(f"a block holds at least one chunk; got {size}")
        bounds = self._entry_arrays()[0]
        for a in range(0, len(self), size):
            b = min(len(self), a + size)
            yield a, b, int(bounds[a]), int(bounds[b])

    def entry_counts(self, start: int = 0, stop: int | None = None) -> npt.NDArray[np.int64]:
        """How many channels each chunk's message indexes list (0: the chunk has none), for the rows
        ``start:stop`` (all by default; ``0 <= start <= stop <= len(self)``)."""
        stop = len(self) if stop is None else stop
        if not 0 <= start <= stop <= len(self):
            raise IndexError(f"rows {start}:{stop} of a table of {len(self)} chunks")
        return np.diff(self._entry_arrays()[0][start:stop + 1]).astype(np.int64)

    def entries(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.uint16], npt.NDArray[np.uint64]]:
        """Every (chunk row, channel id, message index offset) listed, as three arrays in file order."""
        _, channel, offset = self._entry_arrays()
        return self._array("entry_row", lambda: np.repeat(np.arange(len(self), dtype=np.int64),
                                                          self.entry_counts())), channel, offset

    def rows_for_channels(self, channel_ids: Iterable[int], lo: int = 0, hi: int = 2**64
                          ) -> npt.NDArray[np.int64]:
        """Rows of the chunks that may hold a message of ``channel_ids`` with ``lo <= log_time < hi``
        (their message indexes list one of the channels, or they have none), in order of
        ``(message_start_time, chunk_start_offset)``."""
        lo, hi = math.ceil(lo), math.ceil(hi)  # integer log times: t >= lo and t < hi as for the bounds given
        row, channel, _ = self.entries()
        wanted = np.zeros(len(self), dtype=bool)
        wanted[row[np.isin(channel, np.fromiter(channel_ids, dtype=np.int64))]] = True
        wanted |= self.entry_counts() == 0
        start, end = self.column("message_start_time"), self.column("message_end_time")
        if hi <= 0:
            wanted[:] = False
        elif hi < 2**64:
            wanted &= start < np.uint64(hi)
        if lo >= 2**64:
            wanted[:] = False
        elif lo > 0:
            wanted &= end >= np.uint64(lo)
        rows = np.flatnonzero(wanted)
        order = np.lexsort((self.column("chunk_start_offset")[rows], start[rows]))
        return rows[order]

    def first_index_offsets(self) -> npt.NDArray[np.uint64]:
        """Each chunk's lowest message index offset (the largest uint64 for a chunk without message indexes):
        its message indexes span ``message_index_length`` bytes from there."""
        def make() -> npt.NDArray[np.uint64]:
            row, _, offset = self.entries()
            first = np.full(len(self), np.iinfo(np.uint64).max, dtype=np.uint64)
            np.minimum.at(first, row, offset)
            return first

        return self._array("first_index_offset", make)

    def channel_time_ranges(self) -> dict[int, tuple[int, int]]:
        """Per channel id, the earliest ``message_start_time`` and latest ``message_end_time`` of the
        chunks whose message indexes list it."""
        row, channel, _ = self.entries()
        start, end = self.column("message_start_time"), self.column("message_end_time")
        out = {}
        for cid in np.unique(channel).tolist():
            mine = row[channel == cid]
            out[int(cid)] = (int(start[mine].min()), int(end[mine].max()))
        return out

    def channel_ids(self) -> set[int]:
        """Every channel id the chunks' message indexes list."""
        channel = self._entry_arrays()[1]
        listed = self._array("channel_ids", lambda: np.flatnonzero(np.bincount(channel, minlength=1)))
        return set(listed.tolist())

    def first_rows(self, channel_ids: Iterable[int]) -> dict[int, int]:
        """Per channel id of ``channel_ids`` that the message indexes list, the row of the first chunk in the
        file (lowest ``chunk_start_offset``; of two at one offset, the first row) that lists it."""
        row, channel, _ = self.entries()
        wanted = np.isin(channel, np.fromiter(channel_ids, dtype=np.int64))
        row, channel = row[wanted], channel[wanted]
        offsets = self.column("chunk_start_offset")[row]
        lowest = np.full(1 << 16, np.iinfo(np.uint64).max, dtype=np.uint64)
        np.minimum.at(lowest, channel, offsets)
        at_lowest = offsets == lowest[channel]
        found, first = np.unique(channel[at_lowest], return_index=True)  # rows ascend: the first is the lowest
        return dict(zip(found.tolist(), row[at_lowest][first].tolist(), strict=True))

    def _entry_arrays(self) -> tuple[npt.NDArray[np.uint64], npt.NDArray[np.uint16], npt.NDArray[np.uint64]]:
        return (self._array("entry_start", lambda: np.frombuffer(self._entry_start, dtype=np.uint64)),
                self._array("entry_channel", lambda: np.frombuffer(self._entry_channel, dtype=np.uint16)),
                self._array("entry_offset", lambda: np.frombuffer(self._entry_offset, dtype=np.uint64)))

    def _array(self, key: str, make: Callable[[], npt.NDArray[Any]]) -> npt.NDArray[Any]:
        """A read-only array of the table, made once (until the next append); the columns' are views."""
        value = self._cache.get(key)
        if value is None:
            value = self._cache[key] = make()
            value.flags.writeable = False
        return value

    # ------------------------------------------------------------------ writing
    def write_records(self, write: Callable[[bytes], object]) -> None:
        """Give ``write`` the Chunk Index record of each chunk, the bytes ``ChunkIndex.write`` makes."""
        c = self._columns
        starts, channels, offsets = self._entry_start, self._entry_channel, self._entry_offset
        encoded = [name.encode() for name in self._names]
        for k in range(len(self)):
            a, b = starts[k], starts[k + 1]
            name = encoded[self._compression[k]]
            pairs = b"".join(map(_PAIR.pack, channels[a:b], offsets[a:b]))
            body = b"".join((
                _CHUNK_INDEX_HEAD.pack(c["message_start_time"][k], c["message_end_time"][k],
                                       c["chunk_start_offset"][k], c["chunk_length"][k], len(pairs)),
                pairs, _U64.pack(c["message_index_length"][k]), _U32.pack(len(name)), name,
                _SIZES.pack(c["compressed_size"][k], c["uncompressed_size"][k]),
            ))
            write(RECORD_HEADER.pack(Opcode.CHUNK_INDEX, len(body)) + body)


# ---------------------------------------------------------------------- reading a summary
def read_summary(f: BinaryIO, summary_start: int) -> Summary:
    """The summary section that starts at ``summary_start`` in ``f``, read up to the footer.

    As ``mcap``'s own summary reader, with the chunk indexes in a :class:`ChunkIndexTable` and
    the section read a block at a time. Raises ``ValueError`` or ``struct.error`` for a damaged or
    cut section (``mcap``'s errors for a damaged record of another kind).
    """
    summary = Summary()
    table = ChunkIndexTable()
    summary.chunk_indexes = table  # type: ignore[assignment]  # a sequence of ChunkIndex, stored by column
    for opcode, body in _records(f, summary_start):
        if opcode == Opcode.FOOTER:
            break
        if opcode == Opcode.CHUNK_INDEX:
            _append_chunk_indexes(table, body)
            continue
        record = _read_other(opcode, body)
        if isinstance(record, Statistics):
            summary.statistics = record
        elif isinstance(record, Schema):
            summary.schemas[record.id] = record
        elif isinstance(record, Channel):
            summary.channels[record.id] = record
        elif isinstance(record, AttachmentIndex):
            summary.attachment_indexes.append(record)
        elif isinstance(record, MetadataIndex):
            summary.metadata_indexes.append(record)
    else:
        raise ValueError("the summary section ends without a footer")
    return summary


def read_file_summary(f: BinaryIO) -> Summary | None:
    """The summary of the MCAP file ``f`` (found through its footer); None when it has none."""
    size = f.seek(0, io.SEEK_END)
    if size < FOOTER.size + len(MAGIC):
        raise ValueError("the file is too short to end with a footer")
    f.seek(size - len(MAGIC) - FOOTER.size)
    opcode, _, summary_start, _, _ = FOOTER.unpack(f.read(FOOTER.size))
    if opcode != Opcode.FOOTER:
        raise ValueError(f"the file does not end with a footer record (opcode {opcode:#04x})")
    return None if summary_start == 0 else read_summary(f, summary_start)


def _records(f: BinaryIO, start: int) -> Iterator[tuple[int, memoryview]]:
    """``(opcode, body)`` of each record from ``start`` on; a body is valid until the next one is asked for.

    Chunk indexes come as runs instead: ``(CHUNK_INDEX, records)``, one or more whole records (headers
    included) of the same length, one after the other.
    """
    left = f.seek(0, io.SEEK_END) - start  # bytes not yet read: no record can claim more
    f.seek(start)
    buffer = b""
    pos = 0
    while True:
        if len(buffer) - pos < RECORD_HEADER.size:
            block = f.read(min(_READ_BLOCK, max(left, 0)))
            left -= len(block)
            buffer, pos = buffer[pos:] + block, 0
            if len(buffer) < RECORD_HEADER.size:
                if buffer:
                    raise ValueError("the summary section ends inside a record header")
                return
        opcode, length = RECORD_HEADER.unpack_from(buffer, pos)
        end = pos + RECORD_HEADER.size + length
        if end > len(buffer):
            if end - len(buffer) > left:
                raise ValueError(f"the summary section ends inside a record (opcode {opcode:#04x}, length {length})")
            block = f.read(max(min(_READ_BLOCK, left), end - len(buffer)))
            left -= len(block)
            buffer, end, pos = buffer[pos:] + block, end - pos, 0
            if end > len(buffer):
                raise ValueError(f"the summary section ends inside a record (opcode {opcode:#04x}, length {length})")
        if opcode == Opcode.CHUNK_INDEX:  # the records of the same length that follow, in one piece
            end = pos + _same_records(buffer, pos, RECORD_HEADER.size + length) * (RECORD_HEADER.size + length)
            yield opcode, memoryview(buffer)[pos:end]
        else:
            yield opcode, memoryview(buffer)[pos + RECORD_HEADER.size:end]
        pos = end


def _same_records(buffer: bytes, pos: int, size: int) -> int:
    """How many records of ``size`` bytes from ``pos`` start with the same header (opcode and length)
    as the first, within ``buffer`` (at least one)."""
    whole = (len(buffer) - pos) // size
    if whole <= 1:
        return 1
    heads = np.frombuffer(buffer, dtype=np.uint8, count=whole * size, offset=pos).reshape(whole, size)
    differ = np.flatnonzero((heads[:, :RECORD_HEADER.size] != heads[0, :RECORD_HEADER.size]).any(axis=1))
    return int(differ[0]) if differ.size else whole


def _append_chunk_indexes(table: ChunkIndexTable, records: memoryview) -> None:
    """Chunk Index records of one length, one after the other: those that share the first one's layout
    (channel count, compression) are parsed together, as columns; the rest one at a time."""
    (length,) = _U64.unpack_from(records, 1)
    size = RECORD_HEADER.size + length
    count = len(records) // size
    first = records[RECORD_HEADER.size:size]
    layout = _run_layout(first)
    done = 0
    if layout is not None and count > 1:
        rows = np.frombuffer(records, dtype=layout, count=count)
        same = (rows["pairs_bytes"] == rows["pairs_bytes"][0]) & (rows["name_length"] == rows["name_length"][0])
        if "name" in layout.names:  # raw bytes compared (a bytes dtype would drop trailing NULs)
            same &= (rows["name"] == rows["name"][0])
        done = int(np.argmin(same)) if not same.all() else count
        name = rows["name"][0].tobytes() if "name" in layout.names else b""
        table.append_columns(rows[:done], name.decode())
    for k in range(done, count):
        _append_chunk_index(table, records[k * size + RECORD_HEADER.size:(k + 1) * size])


def _run_layout(body: memoryview) -> np.dtype[Any] | None:
    """The record layout (header included) that a Chunk Index record with ``body`` has, or None when its
    fields do not fit it (left to the one-at-a-time parser, which says why)."""
    if len(body) < _CHUNK_INDEX_HEAD.size + _TAIL_MIN:
        return None
    pairs_bytes = _CHUNK_INDEX_HEAD.unpack_from(body)[4]
    n, odd = divmod(pairs_bytes, _PAIR.size)
    name_at = _CHUNK_INDEX_HEAD.size + pairs_bytes + 8
    if odd or name_at + 4 + _SIZES.size > len(body):
        return None
    name_length = _U32.unpack_from(body, name_at)[0]
    if name_at + 4 + name_length + _SIZES.size != len(body):
        return None
    return np.dtype([
        ("opcode", "u1"), ("length", "<u8"), ("message_start_time", "<u8"), ("message_end_time", "<u8"),
        ("chunk_start_offset", "<u8"), ("chunk_length", "<u8"), ("pairs_bytes", "<u4"),
        ("pairs", [("channel", "<u2"), ("offset", "<u8")], (n,)), ("message_index_length", "<u8"),
        ("name_length", "<u4"), *([("name", f"V{name_length}")] if name_length else []),
        ("compressed_size", "<u8"), ("uncompressed_size", "<u8"),
    ])


def _append_chunk_index(table: ChunkIndexTable, body: memoryview) -> None:
    start, end, offset, length, pairs_bytes = _CHUNK_INDEX_HEAD.unpack_from(body)
    q = _CHUNK_INDEX_HEAD.size
    if pairs_bytes % _PAIR.size:
        raise ValueError(f"a chunk index's message index offsets take {pairs_bytes} bytes, not a multiple of "
                         f"{_PAIR.size} (a channel id and an offset each)")
    if q + pairs_bytes + _TAIL_MIN > len(body):
        raise ValueError(f"a chunk index's message index offsets take {pairs_bytes} bytes, which do not fit "
                         f"its record of {len(body)}")
    pairs = list(_PAIR.iter_unpack(body[q:q + pairs_bytes]))
    q += pairs_bytes
    (index_length,) = _U64.unpack_from(body, q)
    (name_length,) = _U32.unpack_from(body, q + 8)
    q += 12
    if q + name_length + _SIZES.size > len(body):
        raise ValueError(f"a chunk index's compression name of {name_length} bytes does not fit its record")
    name = bytes(body[q:q + name_length])
    compressed, uncompressed = _SIZES.unpack_from(body, q + name_length)
    table.append_fields(start, end, offset, length, index_length, compressed, uncompressed, name.decode(),
                        [cid for cid, _ in pairs], [at for _, at in pairs])


class _StrictBytes(io.BytesIO):
    """A record's bytes whose ``read`` refuses to come back short (``mcap``'s parsers do not check)."""

    def read(self, size: int | None = -1) -> bytes:
        data = super().read(size)
        if size is not None and size >= 0 and len(data) != size:
            raise ValueError(f"a summary record is cut short ({len(data)} of {size} bytes)")
        return data


#: The other records a summary keeps, by opcode (the rest, e.g. summary offsets, are skipped).
_OTHER_RECORDS: dict[int, Any] = {Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel, Opcode.STATISTICS: Statistics,
                                  Opcode.ATTACHMENT_INDEX: AttachmentIndex, Opcode.METADATA_INDEX: MetadataIndex}


def _read_other(opcode: int, body: memoryview) -> object | None:
    """A summary record other than a chunk index, parsed by ``mcap`` (None for unknown or skipped kinds)."""
    kind = _OTHER_RECORDS.get(opcode)
    if kind is None:
        return None
    return kind.read(ReadDataStream(_StrictBytes(bytes(body))))
