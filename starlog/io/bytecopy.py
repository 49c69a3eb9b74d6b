"""Copying a byte range of one file to the end of another inside the kernel.

A stage's output starts with its input's data section (hundreds of MB of images). Copied with
``os.copy_file_range`` the bytes never pass through Python buffers (and a file system that
can share blocks, e.g. Btrfs or XFS, shares them instead); where the kernel call is missing
or refused (another file system, an old kernel) the copy falls back to reading and writing
blocks. The bytes written are the same either way.
"""

from __future__ import annotations

import os
from typing import BinaryIO

__all__ = ["copy_range"]

_KERNEL_BLOCK = 1 << 30  # copy_file_range copies at most ~2 GB a call
_FALLBACK_BLOCK = 4 * 1024 * 1024


def copy_range(src: BinaryIO, dst: BinaryIO, offset: int, length: int) -> int:
    """Write ``length`` bytes of ``src`` from ``offset`` at the current position of ``dst``.

    ``dst`` is left positioned after them. Returns the number of bytes copied: fewer than
    ``length`` only when ``src`` ends first (the caller says what that means).
    """
    dst.flush()
    start = dst.tell()
    done = 0
    kernel = hasattr(os, "copy_file_range")
    while done < length:
        sent = -1
        if kernel:
            try:
                sent = os.copy_file_range(src.fileno(), dst.fileno(), min(length - done, _KERNEL_BLOCK),
                                          offset + done, start + done)
            except OSError:  # EXDEV, ENOSYS, EOPNOTSUPP, EINVAL...: copy by hand from here on
                kernel = False
        if sent < 0:
            src.seek(offset + done)
            block = src.read(min(length - done, _FALLBACK_BLOCK))
            dst.seek(start + done)
            dst.write(block)
            dst.flush()
            sent = len(block)
        if sent == 0:
            break
        done += sent
    dst.seek(start + done)  # the kernel copy does not move dst's position (nor its buffer's idea of it)
    return done
