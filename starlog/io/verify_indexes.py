"""``starlog verify``'s check of the summary's chunk indexes against the chunks the walk of the data section meets.

Each chunk index is compared with the chunk it points at when the walk finishes that chunk
(:meth:`ChunkIndexCheck.compare`): neither the indexes nor the chunks are kept as objects.
"""

from __future__ import annotations

from array import array
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from mcap.records import ChunkIndex

from starlog.io.chunk_indexes import ChunkIndexTable

__all__ = ["ChunkIndexCheck", "Seen", "disagreement"]


@dataclass
class Seen:
    """A chunk as found in the data section."""

    offset: int
    length: int
    start: int
    end: int
    compression: str
    compressed_size: int
    uncompressed_size: int
    positions: dict[int, list[tuple[int, int]]]
    index_offsets: dict[int, int] = field(default_factory=dict)
    index_end: int = 0


def disagreement(ci: ChunkIndex, seen: Seen) -> list[str]:
    """The fields in which a chunk index disagrees with the chunk it points at."""
    index_length = seen.index_end - min(seen.index_offsets.values()) if seen.index_offsets else 0
    return [name for name, got, want in [
        ("chunk_length", ci.chunk_length, seen.length), ("message_start_time", ci.message_start_time, seen.start),
        ("message_end_time", ci.message_end_time, seen.end), ("compression", ci.compression, seen.compression),
        ("compressed_size", ci.compressed_size, seen.compressed_size),
        ("uncompressed_size", ci.uncompressed_size, seen.uncompressed_size),
        ("message_index_offsets", dict(ci.message_index_offsets), seen.index_offsets),
        ("message_index_length", ci.message_index_length, index_length)] if got != want]


class ChunkIndexCheck:
    """The summary's chunk indexes, each compared with the chunk it points at when the walk of the
    data section finishes that chunk: neither the indexes nor the chunks are kept as objects."""

    def __init__(self, table: ChunkIndexTable | None = None, record_offsets: array | None = None) -> None:
        self.table = ChunkIndexTable() if table is None else table
        self.record_offsets = array("Q") if record_offsets is None else record_offsets  # of each index record
        self._by_chunk: tuple[np.ndarray, np.ndarray] | None = None  # rows sorted by chunk offset, and the offsets
        self._matched = np.zeros(0, dtype=bool)
        self._next = 0  # in the sorted offsets: where the next chunk of the walk is expected
        self._disagreements: dict[int, list[str]] = {}

    def compare(self, seen: Seen) -> bool:
        """Compare the chunk with every index that points at it; False when none does."""
        if self._by_chunk is None:
            starts = self.table.column("chunk_start_offset")
            order = np.argsort(starts, kind="stable")
            self._by_chunk = order, starts[order]
            self._matched = np.zeros(len(self.table), dtype=bool)
        order, starts = self._by_chunk
        # the walk meets the chunks in file order: usually the index after the last one matched
        lo = self._next
        if not (lo < starts.size and starts[lo] == seen.offset):
            lo = int(np.searchsorted(starts, np.uint64(seen.offset)))
        hi = lo
        while hi < starts.size and starts[hi] == seen.offset:
            hi += 1
        self._next = hi
        for row in order[lo:hi].tolist():
            self._matched[row] = True
            wrong = disagreement(self.table[row], seen)
            if wrong:
                self._disagreements[row] = wrong
        return hi > lo

    def problems(self) -> Iterator[tuple[int, str]]:
        """``(record offset, detail)`` of each index that points where no chunk starts, or that disagrees
        with its chunk, in the summary's order."""
        matched = self._matched if self._matched.size else np.zeros(len(self.table), dtype=bool)
        for row in sorted({*np.flatnonzero(~matched).tolist(), *self._disagreements}):
            start = int(self.table.column("chunk_start_offset")[row])
            if row in self._disagreements:
                detail = f"the chunk index disagrees with the chunk at {start} in {', '.join(self._disagreements[row])}"
            else:
                detail = f"a chunk index points at {start}, where no chunk starts"
            yield self.record_offsets[row], detail
