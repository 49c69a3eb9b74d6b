"""Output files that appear only once complete: written beside their destination and renamed over it.

Every output of starlog (logs, tables, figures, reports) goes to a temporary file beside its
destination and is renamed over it only when it is complete, so a killed command leaves either
no output or the previous file, never a half-written one under the final name. Two commands
writing one path at once: the first to finish wins (:func:`commit_output`). A log read while it is
written is the one output written under its final name from the start (:func:`open_in_place`).
:class:`ChecksummedFile` keeps the CRC-32 of what is written to an output.
"""

from __future__ import annotations

import errno
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import BinaryIO

from starlog.errors import FileAccessError, OutputChangedError, OutputExistsError, OutputFolderError, file_errors
from starlog.io.checksum import crc32

__all__ = ["ChecksummedFile", "Identity", "atomic_output", "commit_output", "open_in_place", "output_identity",
           "temporary_folder", "temporary_output"]


def temporary_output(output: Path) -> tuple[int, Path]:
    """A new file beside ``output`` to write it in, renamed over it when complete: its descriptor and path.

    Its permissions are those of a file the user creates (``mkstemp``'s 0600 would survive the rename
    and make every log private). An OS error (read-only or full file system, no permission) is a
    :class:`~starlog.errors.FileAccessError` naming ``output``.
    """
    with file_errors(output):
        fd, tmp = tempfile.mkstemp(prefix=f".{output.name}.", suffix=".partial", dir=output.parent or ".")
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
    except BaseException:
        os.close(fd)
        Path(tmp).unlink(missing_ok=True)
        raise
    return fd, Path(tmp)


Identity = tuple[int, int, int, int]


def output_identity(path: Path) -> Identity | None:
    """Which file is at ``path`` (device, inode, size, modification time), or None when there is none."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return None
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


def commit_output(tmp: Path, output: Path, *, seen: Identity | None) -> None:
    """Put the finished file ``tmp`` in place as ``output``, which held ``seen`` when the output was opened.

    When another command has written ``output`` meanwhile (two commands writing the same path at once),
    its file is kept and :class:`~starlog.errors.OutputChangedError` raised: the first to finish wins. The
    check and the rename are one step for starlog commands (a lock on the folder), and an output that did
    not exist is never written over, whoever created it (a hard link, which fails on an existing name).
    """
    with _folder_lock(output.parent):
        now = output_identity(output)
        if now is not None and now != seen:
            raise OutputChangedError(output)
        if seen is None and _link(tmp, output):
            tmp.unlink()
        else:
            os.replace(tmp, output)


def _link(tmp: Path, output: Path) -> bool:
    """Hard-link ``tmp`` as ``output`` (False where the file system has no hard links)."""
    try:
        os.link(tmp, output)
    except FileExistsError:
        raise OutputChangedError(output) from None
    except OSError as err:
        if err.errno in _NO_HARD_LINKS:
            return False
        raise
    return True


_NO_HARD_LINKS = {errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK}


@contextmanager
def _folder_lock(folder: Path) -> Iterator[None]:
    """An exclusive lock on ``folder`` among starlog commands (``flock`` of its descriptor); none where the
    platform or the file system has none, or the folder is gone (the rename then says so)."""
    fd = None
    with suppress(ImportError, OSError):
        import fcntl

        fd = os.open(folder, os.O_RDONLY)
        with suppress(OSError):
            fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        yield
    finally:
        if fd is not None:
            os.close(fd)


@contextmanager
def atomic_output(output: Path, *, force: bool = True) -> Iterator[Path]:
    """A temporary file beside ``output`` for the block to write: put in place as ``output`` when the block
    succeeds (:func:`commit_output`), removed whatever else happens. Refuses an existing ``output`` without
    ``force``; an OS error is a :class:`~starlog.errors.FileAccessError` naming ``output``."""
    output = Path(output)
    if output.exists() and not force:
        raise OutputExistsError(output)
    OutputFolderError.check(output)
    seen = output_identity(output)
    fd, tmp = temporary_output(output)
    os.close(fd)
    try:
        with file_errors(output):
            yield tmp
            _fsync(tmp)
            commit_output(tmp, output, seen=seen)
    finally:
        with suppress(OSError):
            tmp.unlink(missing_ok=True)


def _fsync(path: Path) -> None:
    """Make the bytes written to ``path`` durable before it is renamed into place (as the log writer does)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def temporary_folder(beside: Path) -> Iterator[Path]:
    """A new hidden folder beside ``beside`` (e.g. for the layers of a chain that is then flattened into
    ``beside``), removed at the end whatever happens. A failure to write in it names ``beside``, the output
    the user asked for."""
    OutputFolderError.check(beside)
    with file_errors(beside):
        folder = tempfile.TemporaryDirectory(prefix=f".{beside.name}.", suffix=".layers", dir=beside.parent or ".",
                                             ignore_cleanup_errors=True)
    with folder as name:
        try:
            yield Path(name)
        except FileAccessError as err:
            if Path(name) not in err.path.parents:
                raise
            raise FileAccessError(beside, err.action, err.errno, err.detail) from err


def open_in_place(output: Path) -> tuple[int, Path]:
    """``output`` itself, created or emptied (the caller refused an existing one without ``force``); an OS error
    is a :class:`~starlog.errors.FileAccessError` naming it."""
    with file_errors(output):
        return os.open(output, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o666), output


class ChecksummedFile:
    """An output file keeping the CRC-32 of every byte written to it (a log's writer: until the summary, that of
    the data section, which the DataEnd record stores). A failed write is a
    :class:`~starlog.errors.FileAccessError` naming the output (``path``), not its temporary file."""

    def __init__(self, file: BinaryIO, path: Path) -> None:
        self._file = file
        self._path = path
        self.crc = 0

    def write(self, data: bytes | memoryview) -> int:
        self.crc = crc32(data, self.crc)
        with file_errors(self._path):
            return self._file.write(data)

    def tell(self) -> int:
        return self._file.tell()

    def flush(self) -> None:
        with file_errors(self._path):
            self._file.flush()

    def fileno(self) -> int:
        return self._file.fileno()

    def close(self) -> None:
        self._file.close()
