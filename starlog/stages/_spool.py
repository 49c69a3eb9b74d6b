"""Blocks of numpy arrays spooled to a file and read back, so a stage can pass over a log twice
without holding it in memory or decoding it twice.

A spool is a plain file of consecutive ``.npy`` records (:func:`numpy.save`), written block by
block; each block is a fixed number of arrays. :func:`write_block` returns the block's byte
offset, so a block can be read alone (:func:`read_block`), e.g. by a worker process.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import numpy.typing as npt

__all__ = ["write_block", "read_block", "read_blocks"]


def write_block(file: BinaryIO, *arrays: npt.NDArray[Any]) -> int:
    """Append one block (``arrays``, in order) to ``file``; return the offset it starts at."""
    offset = file.tell()
    for array in arrays:
        np.save(file, array, allow_pickle=False)
    return offset


def _read(file: BinaryIO, arity: int) -> tuple[npt.NDArray[Any], ...]:
    return tuple(np.load(file, allow_pickle=False) for _ in range(arity))


def read_block(path: Path, offset: int, arity: int) -> tuple[npt.NDArray[Any], ...]:
    """The block of ``arity`` arrays starting at ``offset``."""
    with open(path, "rb") as file:
        file.seek(offset)
        return _read(file, arity)


def read_blocks(path: Path, arity: int) -> Iterator[tuple[npt.NDArray[Any], ...]]:
    """Every block of ``arity`` arrays, in the order written."""
    size = path.stat().st_size
    with open(path, "rb") as file:
        while file.tell() < size:
            yield _read(file, arity)
