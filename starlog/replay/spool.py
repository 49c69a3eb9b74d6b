"""Blocks of numpy arrays spooled to a file and read back, so a stage can pass over a log twice
without holding it in memory or decoding it twice.

A spool is a plain file of consecutive ``.npy`` records (:func:`numpy.save`), written block by
block; each block is a fixed number of arrays. :func:`write_block` returns the block's byte
offset, so a block can be read alone (:func:`read_block`). A spool is an open file (an anonymous
temporary file, which vanishes with the process however it ends) or, to be shared with worker
processes, a path.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import numpy.typing as npt

__all__ = ["Spool", "opened", "write_block", "read_block", "read_blocks"]

Spool = BinaryIO | Path


def opened(spool: Spool, mode: str = "rb") -> AbstractContextManager[BinaryIO]:
    """The spool as an open file: a path is opened (and closed after), a file is used as is."""
    if isinstance(spool, Path):
        return open(spool, mode)  # noqa: SIM115 - the caller's with-statement closes it
    return nullcontext(spool)


def write_block(file: BinaryIO, *arrays: npt.NDArray[Any]) -> int:
    """Append one block (``arrays``, in order) to ``file``; return the offset it starts at."""
    offset = file.tell()
    for array in arrays:
        np.save(file, array, allow_pickle=False)
    return offset


def _read(file: BinaryIO, arity: int) -> tuple[npt.NDArray[Any], ...]:
    return tuple(np.load(file, allow_pickle=False) for _ in range(arity))


def read_block(spool: Spool, offset: int, arity: int) -> tuple[npt.NDArray[Any], ...]:
    """The block of ``arity`` arrays starting at ``offset``."""
    with opened(spool) as file:
        file.seek(offset)
        return _read(file, arity)


def read_blocks(spool: Spool, arity: int) -> Iterator[tuple[npt.NDArray[Any], ...]]:
    """Every block of ``arity`` arrays, in the order written."""
    with opened(spool) as file:
        file.flush()
        size = os.fstat(file.fileno()).st_size
        file.seek(0)
        while file.tell() < size:
            yield _read(file, arity)
