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
from pathlib import Path
from typing import BinaryIO

from starlog.errors import TruncatedLogError

__all__ = ["BackgroundCopy", "copy_range", "copy_range_at"]

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


class BackgroundCopy:
    """A log's data section (its first ``length`` bytes) copied to the start of an output, then ``fdatasync``-ed,
    on a thread: the copy (hundreds of MB for a long log) and its disk writes overlap the work that writes the
    rest of the output, and the final ``fsync`` has only those bytes left to write.

    The copy is positional (:func:`copy_range_at`), so the rest of the output is written after the data section
    meanwhile. The thread works on duplicates of the descriptors it is given, which it closes: the caller's may
    be closed, and their numbers reused, before the copy ends. An error is kept and raised by :meth:`wait`:
    Linux reports a failed write-back once per file, so it must not be lost on this thread.
    """

    def __init__(self, src_fd: int, dst_fd: int, source: Path, length: int) -> None:
        self._error: BaseException | None = None
        self._stop = threading.Event()
        owned: list[int] = []
        try:
            owned.append(os.dup(src_fd))
            owned.append(os.dup(dst_fd))
            self._thread = threading.Thread(target=self._copy_and_sync, args=(*owned, source, length),
                                            name="starlog-writeback", daemon=True)
            self._thread.start()
        except BaseException:
            for fd in owned:
                os.close(fd)
            raise

    def _copy_and_sync(self, src_fd: int, dst_fd: int, source: Path, length: int) -> None:
        try:
            copied = copy_range_at(src_fd, dst_fd, 0, length, 0, stop=self._stop)
            if self._stop.is_set():
                return
            if copied < length:
                raise TruncatedLogError(source, "it ended while its data section was being copied")
            getattr(os, "fdatasync", os.fsync)(dst_fd)  # macOS has no fdatasync
        except BaseException as err:  # raised by wait(), in the thread that finishes the output
            self._error = err
        finally:
            os.close(src_fd)
            os.close(dst_fd)

    def cancel(self) -> None:
        """Stop the copy (between blocks) and wait for the thread; its error, if any, is dropped (the output
        is being discarded). A sync already under way is waited for: it cannot be interrupted."""
        self._stop.set()
        self._thread.join()

    def wait(self) -> None:
        """Wait for the copy and its write-back, and raise their error."""
        self._thread.join()
        if self._error is not None:
            raise self._error
