"""The one record walker: the records of a section, from bytes in memory or from a file a block at a time.

Every record is ``opcode (u8), body length (u64), body`` (:data:`~starlog.io.layout.RECORD_HEADER`).
:func:`walk_records` hands each on with its offset and body; the readers of chunks, of the summary
and of the data section (:mod:`starlog.io.data_section`) all walk through it.
"""

from __future__ import annotations

import os
from collections.abc import Container, Generator, Iterator
from typing import BinaryIO

import numpy as np

from starlog.io.layout import RECORD_HEADER

__all__ = ["Record", "RecordOverrun", "walk_records"]

#: ``(offset, opcode, body length, body)`` of a record (``body`` None when it was not read).
Record = tuple[int, int, int, "memoryview | None"]

_HEAD = RECORD_HEADER.size
_IN_MEMORY = (memoryview, bytes, bytearray)


class RecordOverrun(ValueError):
    """A record runs past the end of its section (``cut_header``: not even its nine-byte header fits)."""

    def __init__(self, offset: int, detail: str, *, cut_header: bool = False) -> None:
        self.offset = offset
        self.cut_header = cut_header
        super().__init__(detail)


def _overrun(offset: int, opcode: int, length: int) -> RecordOverrun:
    return RecordOverrun(offset, f"the record at offset {offset} (opcode {opcode:#04x}, {length} bytes) runs past "
                                 "the end of its section")


def _cut_header(offset: int) -> RecordOverrun:
    return RecordOverrun(offset, f"a record header at offset {offset} is cut off", cut_header=True)


def walk_records(source: bytes | bytearray | memoryview | BinaryIO, start: int = 0, end: int | None = None, *,
                 base: int = 0, bodies: Container[int] | None = None, runs: Container[int] = (),
                 block: int = 1 << 20) -> Iterator[Record]:
    """``(offset, opcode, length, body)`` of each record of ``source`` from ``start`` to ``end`` (its end: None).

    ``source`` is bytes in memory (each body a memoryview of them, no copy; offsets from ``base``) or a
    binary file, read a block at a time (a section is never held whole; a body stays valid). ``body``
    is read for the opcodes in ``bodies`` (every record when None) and is None for the others, whose
    bytes are skipped unread when they are large. The records of an opcode in ``runs`` come in runs:
    ``body`` holds one or more whole records (headers included) with the header of the first, one
    after the other, and ``length`` is each one's body length. Raises :class:`RecordOverrun` for a
    record that runs past ``end``.
    """
    if isinstance(source, _IN_MEMORY):
        view = source if type(source) is memoryview else memoryview(source)
        stop = len(view) if end is None else end
        return _in_buffer(view, start, stop, stop, base, bodies, runs, True)
    return _walk_file(source, start, end, bodies, runs, block)


def _in_buffer(view: memoryview, pos: int, stop: int, limit: int, base: int, bodies: Container[int] | None,
               runs: Container[int], whole: bool = False) -> Generator[Record, None, int]:
    """The records from ``view[pos]`` that end by ``limit`` and whose header (and body, when it is wanted) lie
    before ``stop`` (offsets from ``base``); returns where the first of the others starts. ``whole``: ``view``
    holds the whole section up to ``stop``, and a record that does not end by it raises :class:`RecordOverrun`."""
    while pos + _HEAD <= stop:
        opcode, length = RECORD_HEADER.unpack_from(view, pos)
        body = pos + _HEAD
        after = body + length
        if after > limit:
            break
        if runs and opcode in runs:
            if after > stop:
                break
            after = pos + _same_records(view, pos, stop, _HEAD + length) * (_HEAD + length)
            yield base + pos, opcode, length, view[pos:after]
        elif bodies is None or opcode in bodies:
            if after > stop:
                break
            yield base + pos, opcode, length, view[body:after]
        else:
            yield base + pos, opcode, length, None
        pos = after
    if whole and pos < stop:
        raise _cut_header(base + pos) if pos + _HEAD > stop else _overrun(base + pos,
                                                                          *RECORD_HEADER.unpack_from(view, pos))
    return pos


def _same_records(view: memoryview, pos: int, stop: int, size: int) -> int:
    """How many records of ``size`` bytes from ``pos`` start with the same header (opcode and length) as the
    first, within ``view[:stop]`` (at least one)."""
    whole = (stop - pos) // size
    if whole <= 1:
        return 1
    heads = np.frombuffer(view, dtype=np.uint8, count=whole * size, offset=pos).reshape(whole, size)
    differ = np.flatnonzero((heads[:, :_HEAD] != heads[0, :_HEAD]).any(axis=1))
    return int(differ[0]) if differ.size else whole


def _walk_file(f: BinaryIO, start: int, end: int | None, bodies: Container[int] | None, runs: Container[int],
               block: int) -> Iterator[Record]:
    """:func:`walk_records` of a file: a block read and its records walked, the next block read from the first
    record whose body it does not hold; a record larger than a block is read alone."""
    if end is None:
        end = f.seek(0, os.SEEK_END)
    pos = start
    while pos < end:
        f.seek(pos)
        data = memoryview(f.read(min(max(block, _HEAD), end - pos)))
        done = yield from _in_buffer(data, 0, len(data), end - pos, pos, bodies, runs)
        if done:
            pos += done
            continue
        if len(data) < _HEAD:  # the section or the file ends inside a record header
            raise _cut_header(pos)
        opcode, length = RECORD_HEADER.unpack_from(data)
        if pos + _HEAD + length > end:
            raise _overrun(pos, opcode, length)
        f.seek(pos + _HEAD)
        body = f.read(length)
        if len(body) != length:
            raise RecordOverrun(pos, f"the file ends inside the record at offset {pos}")
        yield pos, opcode, length, memoryview(bytes(data[:_HEAD]) + body if opcode in runs else body)
        pos += _HEAD + length
