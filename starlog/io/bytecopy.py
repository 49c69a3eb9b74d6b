"""Copying a byte range of one file into another inside the kernel.

A stage's output starts with its input's data section (hundreds of MB of images). Copied with
``os.copy_file_range`` the bytes never pass through Python buffers (and a file system that
can share blocks, e.g. Btrfs or XFS, shares them instead); where the kernel call is missing
or refused (another file system, an old kernel) the copy falls back to reading and writing
blocks. The bytes written are the same either way.
"""

from __future__ import annotations

import os
import threading
from typing import BinaryIO

__all__ = ["copy_range", "copy_range_at"]

_BLOCK = 64 * 1024 * 1024  # per kernel call: a copy that is asked to stop does so within one block
_FALLBACK_BLOCK = 4 * 1024 * 1024


def copy_range(src: BinaryIO, dst: BinaryIO, offset: int, length: int) -> int:
    """Write ``length`` bytes of ``src`` from ``offset`` at the current position of ``dst``.

    ``dst`` is left positioned after them. Returns the number of bytes copied: fewer than
    ``length`` only when ``src`` ends first (the caller says what that means).
    """
    dst.flush()
    start = dst.tell()
    done = copy_range_at(src.fileno(), dst.fileno(), offset, length, start)
    dst.seek(start + done)  # the copy does not move dst's position (nor its buffer's idea of it)
    return done


def copy_range_at(src_fd: int, dst_fd: int, offset: int, length: int, dst_offset: int, *,
                  stop: threading.Event | None = None) -> int:
    """Copy ``length`` bytes of ``src_fd`` from ``offset`` to ``dst_offset`` of ``dst_fd``.

    Positional: neither file's position moves, so another thread may write elsewhere in
    ``dst_fd`` meanwhile. Returns the number of bytes copied: fewer than ``length`` when
    ``src_fd`` ends first, or when ``stop`` is set (checked between blocks).
    """
    done = 0
    kernel = hasattr(os, "copy_file_range")
    while done < length and not (stop is not None and stop.is_set()):
        sent = -1
        if kernel:
            try:
                sent = os.copy_file_range(src_fd, dst_fd, min(length - done, _BLOCK), offset + done, dst_offset + done)
            except OSError:  # EXDEV, ENOSYS, EOPNOTSUPP, EINVAL...: copy by hand from here on
                kernel = False
        if sent < 0:
            block = os.pread(src_fd, min(length - done, _FALLBACK_BLOCK), offset + done)
            written = 0
            while written < len(block):
                written += os.pwrite(dst_fd, block[written:], dst_offset + done + written)
            sent = len(block)
        if sent == 0:
            break
        done += sent
    return done
