"""A log and the sidecars of the stages run on it, read as the one log that appending them would give.

A stage that extends a log writes a file that starts with a byte-for-byte copy of its input's
data section (see :class:`~starlog.io.LogWriter`). Several stages in a row would copy that data
once per stage. A :class:`StackedLog` avoids it: a stage given a stacked log as its input writes
only what it adds — its chunks, message indexes and metadata, then the summary of the whole
(a *sidecar*) — with every offset counted as if the data before it were there. The stack reads
as the concatenation ``base data section + each sidecar's data + last sidecar's summary``, which
is exactly the file the stage would have written; its SHA-256 is hashed from those same bytes,
and :meth:`StackedLog.write_to` writes it once at the end. Most of those bytes are the base's data
section, which no stage changes: :meth:`StackedLog.begin_output` starts copying it into the output
(and syncing it to disk) on a thread before the stages run, and :meth:`PendingOutput.finish` adds
the rest once the last sidecar is written.
"""

from __future__ import annotations

import hashlib
import io
import os
import struct
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from starlog.errors import CorruptLogError, InvalidParameterError, LogNotFoundError, OutputExistsError, OutputFolderError
from starlog.io.bytecopy import BackgroundCopy, copy_range_at
from starlog.io.digest_cache import read_digest_cache, write_digest_cache
from starlog.io.layout import DATA_END_RECORD_LEN, FOOTER_RECORD_LEN, MCAP_MAGIC, locate_data_end
from starlog.io.resumable_sha256 import ResumableSha256
from starlog.io.resumable_sha256 import available as resumable_available

__all__ = ["PendingOutput", "StackedLog"]

_COPY_BLOCK = 4 * 1024 * 1024


@dataclass(frozen=True)
class _Segment:
    """``length`` bytes of ``path`` from ``offset``."""

    path: Path
    offset: int
    length: int


def _summary_start(path: Path) -> int:
    """The (virtual) offset of the summary named in the footer of ``path``."""
    with open(path, "rb") as f:
        size = f.seek(0, os.SEEK_END)
        if size < FOOTER_RECORD_LEN + len(MCAP_MAGIC):
            raise CorruptLogError(path, "a sidecar too short to end with a footer")
        f.seek(size - len(MCAP_MAGIC) - FOOTER_RECORD_LEN)
        tail = f.read()
    if tail[-len(MCAP_MAGIC):] != MCAP_MAGIC:
        raise CorruptLogError(path, "a sidecar that does not end with the MCAP magic")
    (summary_start,) = struct.unpack_from("<Q", tail, 9)
    return int(summary_start)


def _hash_range(digest: Any, path: Path, offset: int, length: int) -> None:
    with open(path, "rb") as f:
        f.seek(offset)
        while length:
            block = f.read(min(length, _COPY_BLOCK))
            if not block:
                raise CorruptLogError(path, "it ended while it was being read")
            digest.update(block)
            length -= len(block)


#: What :class:`StackedLog`'s constructor sets (the rest of an instance's attributes is extra state).
_CONSTRUCTED = frozenset({"base", "_base_data_end", "_segments", "_tail", "_prefix_hash", "_full_digest"})


class StackedLog:
    """A complete log (``base``) plus the sidecars written on it, viewed as one log.

    Build it with :meth:`of`, add each stage's sidecar with :meth:`extend`. :class:`LogReader`
    reads it, :class:`LogWriter` given it as ``base`` writes a sidecar, and
    :func:`~starlog.io.file_digest` gives the SHA-256 of the bytes it stands for.
    """

    def __init__(self, base: Path, base_data_end: int, segments: tuple[_Segment, ...], tail: _Segment,
                 prefix_hash: Any, full_digest: str | None = None) -> None:
        self.base = base
        self._base_data_end = base_data_end
        self._segments = segments  # the data section: base's, then each sidecar's new records
        self._tail = tail  # DataEnd, summary, footer, magic of the newest layer
        self._prefix_hash = prefix_hash
        self._full_digest = full_digest

    @classmethod
    def of(cls, path: str | os.PathLike[str]) -> StackedLog:
        """A stack of one complete log and no sidecar (reads the log once, for its digest, unless the
        digest was saved with it: :mod:`starlog.io.digest_cache`)."""
        base = Path(path)
        if not base.is_file():
            raise LogNotFoundError(base)
        with open(base, "rb") as f:
            data_end = locate_data_end(base, f)
            size = f.seek(0, os.SEEK_END)
        segments, tail = (_Segment(base, 0, data_end),), _Segment(base, data_end, size - data_end)
        cached = read_digest_cache(base)
        if cached is not None and cached.data_end == data_end:  # the stage that wrote it saved its digest
            return cls(base, data_end, segments, tail, ResumableSha256(cached.state), cached.digest)
        prefix = ResumableSha256() if resumable_available() else hashlib.sha256()
        _hash_range(prefix, base, 0, data_end)
        full = prefix.copy()
        _hash_range(full, base, data_end, size - data_end)
        return cls(base, data_end, segments, tail, prefix, "sha256:" + full.hexdigest())

    @property
    def layers(self) -> int:
        """Number of sidecars on the base."""
        return len(self._segments) - 1

    @property
    def path(self) -> Path:
        """The file that names this stack in messages: the newest sidecar, or the base."""
        return self._tail.path

    @property
    def data_end(self) -> int:
        """Offset of the DataEnd record in the log this stack stands for."""
        return sum(s.length for s in self._segments)

    @property
    def size(self) -> int:
        """Size in bytes of the log this stack stands for."""
        return self.data_end + self._tail.length

    def files(self) -> tuple[Path, ...]:
        """The files this stack reads: the base, then each sidecar."""
        return tuple(dict.fromkeys(s.path for s in (*self._segments, self._tail)))

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled (for a worker process to read it) without the digest's running state, which
        cannot be pickled: a copy that is asked for a digest hashes its data section again.
        Attributes set after construction (a subclass's) travel with it."""
        extra = {k: v for k, v in vars(self).items() if k not in _CONSTRUCTED}
        return (type(self), (self.base, self._base_data_end, self._segments, self._tail, None, self._full_digest),
                extra or None)

    def _prefix(self) -> Any:
        """The running SHA-256 of the data section (hashed here if this stack came from a pickle)."""
        if self._prefix_hash is None:
            prefix = ResumableSha256() if resumable_available() else hashlib.sha256()
            for segment in self._segments:
                _hash_range(prefix, segment.path, segment.offset, segment.length)
            self._prefix_hash = prefix
        return self._prefix_hash

    def extend(self, sidecar: str | os.PathLike[str]) -> StackedLog:
        """This stack with ``sidecar`` (written by a :class:`LogWriter` whose base was this stack) on top."""
        path = Path(sidecar)
        new_data_end = _summary_start(path) - DATA_END_RECORD_LEN
        added = new_data_end - self.data_end
        size = path.stat().st_size
        if not 0 <= added <= size:
            raise CorruptLogError(path, f"this sidecar does not continue a log whose data ends at {self.data_end}")
        prefix = self._prefix().copy()
        _hash_range(prefix, path, 0, added)
        return StackedLog(self.base, self._base_data_end, (*self._segments, _Segment(path, 0, added)),
                          _Segment(path, added, size - added), prefix)

    def digest(self) -> str:
        """``"sha256:<hex>"`` of the bytes this stack stands for."""
        if self._full_digest is not None:
            return self._full_digest
        full = self._prefix().copy()
        _hash_range(full, self._tail.path, self._tail.offset, self._tail.length)
        return "sha256:" + full.hexdigest()

    def open(self) -> BinaryIO:
        """A read-only, seekable file of the bytes this stack stands for."""
        return io.BufferedReader(_ConcatenatedFile((*self._segments, self._tail)), buffer_size=64 * 1024)

    def write_to(self, output: str | os.PathLike[str], *, force: bool = False) -> Path:
        """Write the log this stack stands for to ``output`` (temporary file, fsync, rename)."""
        return self.begin_output(output, force=force).finish(self)

    def begin_output(self, output: str | os.PathLike[str], *, force: bool = False) -> PendingOutput:
        """Start writing ``output`` now: the base's data section is copied (and synced) on a thread.

        Finish it with :meth:`PendingOutput.finish` given this stack or any stack extended from it;
        :meth:`PendingOutput.discard` removes it.
        """
        out = Path(output)
        if out.exists() and not force:
            raise OutputExistsError(out)
        OutputFolderError.check(out)
        return PendingOutput(out, self._segments[0])

    def __fspath__(self) -> str:
        if self.layers:
            raise InvalidParameterError(f"{self} is not one file; read it with LogReader or write it out first.")
        return str(self.base)

    def __str__(self) -> str:
        return str(self.base) if not self.layers else f"{self.base} + {self.layers} sidecar(s)"

    def __repr__(self) -> str:
        return f"StackedLog({str(self)!r})"


def temporary_output(output: Path) -> tuple[int, Path]:
    """A new file beside ``output`` to write it in, renamed over it when complete: its descriptor and path.

    Its permissions are those of a file the user creates (``mkstemp``'s 0600 would survive the rename
    and make every log private).
    """
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


class PendingOutput:
    """A stack's output begun before the stack is complete (:meth:`StackedLog.begin_output`).

    It goes to a temporary file beside the destination. The base's data section (most of the
    bytes: the images) is copied there and synced on a thread while the stages write their sidecars;
    :meth:`finish` copies the sidecars' records and the newest summary after it, waits for the
    thread, syncs and renames the file into place.
    """

    def __init__(self, output: Path, base: _Segment) -> None:
        if base.offset != 0:
            raise InvalidParameterError(f"{base.path}: a stack's base data section starts at offset 0.")
        self.output = output
        self._base = base
        self._done = False
        self._fd, self._tmp = temporary_output(output)
        self._copy: BackgroundCopy | None = None
        try:
            with open(base.path, "rb") as src:  # the thread copies from this very file
                self._copy = BackgroundCopy(src.fileno(), self._fd, base.path, base.length)
        except BaseException:
            self.discard()
            raise

    def finish(self, stack: StackedLog) -> Path:
        """Write the rest of ``stack`` (the stack this output was begun for, or one extended from it)."""
        if self._done:
            raise InvalidParameterError(f"{self.output}: this output is already finished or discarded.")
        if stack._segments[0] != self._base:
            raise InvalidParameterError(f"{self.output} was begun for another base than {stack.base}.")
        try:
            position = self._base.length
            for segment in (*stack._segments[1:], stack._tail):
                with open(segment.path, "rb") as src:
                    if copy_range_at(src.fileno(), self._fd, segment.offset, segment.length, position) < segment.length:
                        raise CorruptLogError(segment.path, "it ended while it was being copied")
                position += segment.length
            assert self._copy is not None
            self._copy.wait()
            os.fsync(self._fd)
            fd, self._fd = self._fd, -1
            os.close(fd)
            os.replace(self._tmp, self.output)
            self._done = True
        except BaseException:
            self.discard()
            raise
        if isinstance(stack._prefix_hash, ResumableSha256):  # for the provenance of the next stage
            write_digest_cache(self.output, prefix=(stack.data_end, stack._prefix_hash.state()))
        return self.output

    def discard(self) -> None:
        """Remove the temporary file and stop the copy (nothing once :meth:`finish` has succeeded).

        The file goes first: the copy thread may be in a sync that cannot be interrupted, and an
        interruption while it is waited for must not leave the file behind.
        """
        if self._done:
            return
        self._done = True
        try:
            if self._fd >= 0:
                fd, self._fd = self._fd, -1
                os.close(fd)
        finally:
            try:
                self._tmp.unlink(missing_ok=True)
            finally:
                if self._copy is not None:
                    self._copy.cancel()


class _ConcatenatedFile(io.RawIOBase):
    """Byte ranges of several files read as one seekable file."""

    def __init__(self, segments: tuple[_Segment, ...]) -> None:
        super().__init__()
        self._segments = [s for s in segments if s.length]
        self._starts: list[int] = []
        position = 0
        for s in self._segments:
            self._starts.append(position)
            position += s.length
        self._size = position
        self._position = 0
        self._files: dict[Path, BinaryIO] = {}

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._position

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self._position, os.SEEK_END: self._size}[whence]
        if base + offset < 0:
            raise OSError(22, "negative seek position")
        self._position = base + offset
        return self._position

    def readinto(self, buffer: Any) -> int:
        view = memoryview(buffer).cast("B")
        done = 0
        while done < len(view) and self._position < self._size:
            index = max(i for i, start in enumerate(self._starts) if start <= self._position)
            segment, start = self._segments[index], self._starts[index]
            within = self._position - start
            count = min(len(view) - done, segment.length - within)
            f = self._files.get(segment.path)
            if f is None:
                f = self._files[segment.path] = open(segment.path, "rb", buffering=0)
            f.seek(segment.offset + within)
            got = f.readinto(view[done: done + count])
            if not got:
                raise CorruptLogError(segment.path, "it is shorter than when it was written")
            done += got
            self._position += got
        return done

    def close(self) -> None:
        for f in self._files.values():
            f.close()
        self._files.clear()
        super().close()
