"""The summary's chunk indexes as columns of numbers.

An MCAP summary lists one Chunk Index record per chunk. Parsed into ``mcap.records.ChunkIndex``
objects they keep about 0.5 KB each and take 10-16 us to parse: an hour of 1024x1024 frames at
300 Hz has about 1.6 million chunks, i.e. 0.8 GB and tens of seconds in every process that opens
the log (``tools/bench_index.py``).
:class:`ChunkIndexTable` keeps the same fields in arrays (about 80 bytes a chunk) and makes a
``ChunkIndex`` only when one is asked for; it parses runs of Chunk Index records of one layout as
columns at once (:meth:`ChunkIndexTable.append_records`, as :mod:`starlog.io.summary_section` reads
them a block at a time).
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any, overload

import numpy as np
import numpy.typing as npt
from mcap.records import ChunkIndex

from starlog.io.layout import (
    CHUNK_INDEX_HEAD,
    CHUNK_INDEX_PAIR,
    CHUNK_INDEX_SIZES,
    CHUNK_INDEX_TAIL_MIN,
    RECORD_HEADER,
    U32,
    U64,
    chunk_index_dtype,
    chunk_index_record,
    parse_chunk_index,
)

__all__ = ["ROW_BLOCK", "ChunkIndexTable"]

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
        self.append_fields(*parse_chunk_index(memoryview(body)))

    def append_records(self, records: memoryview) -> None:
        """Add the Chunk Index records ``records``: whole records (headers included) of one length, one after
        the other. Those that share the first one's layout (channel count, compression) are parsed together, as
        columns; the rest one at a time. Raises as :meth:`append_record` (the records before the bad one added)."""
        (length,) = U64.unpack_from(records, 1)
        size = RECORD_HEADER.size + length
        count = len(records) // size
        layout = _run_layout(records[RECORD_HEADER.size:size])
        done = 0
        if layout is not None and count > 1:
            rows = np.frombuffer(records, dtype=layout, count=count)
            same = (rows["pairs_bytes"] == rows["pairs_bytes"][0]) & (rows["name_length"] == rows["name_length"][0])
            if "name" in layout.names:  # raw bytes compared (a bytes dtype would drop trailing NULs)
                same &= (rows["name"] == rows["name"][0])
            done = int(np.argmin(same)) if not same.all() else count
            name = rows["name"][0].tobytes() if "name" in layout.names else b""
            self.append_columns(rows[:done], name.decode())
        for k in range(done, count):
            self.append_record(records[k * size + RECORD_HEADER.size:(k + 1) * size])

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
            write(chunk_index_record(
                c["message_start_time"][k], c["message_end_time"][k], c["chunk_start_offset"][k],
                c["chunk_length"][k], c["message_index_length"][k], c["compressed_size"][k],
                c["uncompressed_size"][k], encoded[self._compression[k]],
                b"".join(map(CHUNK_INDEX_PAIR.pack, channels[a:b], offsets[a:b]))))


def _run_layout(body: memoryview) -> np.dtype[Any] | None:
    """The record layout (header included) that a Chunk Index record with ``body`` has, or None when its
    fields do not fit it (left to the one-at-a-time parser, which says why)."""
    if len(body) < CHUNK_INDEX_HEAD.size + CHUNK_INDEX_TAIL_MIN:
        return None
    pairs_bytes = CHUNK_INDEX_HEAD.unpack_from(body)[4]
    n, odd = divmod(pairs_bytes, CHUNK_INDEX_PAIR.size)
    name_at = CHUNK_INDEX_HEAD.size + pairs_bytes + U64.size
    if odd or name_at + U32.size + CHUNK_INDEX_SIZES.size > len(body):
        return None
    name_length = U32.unpack_from(body, name_at)[0]
    if name_at + U32.size + name_length + CHUNK_INDEX_SIZES.size != len(body):
        return None
    return chunk_index_dtype(n, name_length)
