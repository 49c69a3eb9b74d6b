"""The one error hierarchy of starlog.

Every error starlog raises on purpose derives from :class:`StarlogError`; the command line
turns these into a one-line message and a non-zero exit status, anything else is a bug.
Messages are full sentences that say what went wrong, where, and how to fix it.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = [
    "StarlogError",
    "InvalidInputError",
    "InvalidParameterError",
    "LogError",
    "LogNotFoundError",
    "TruncatedLogError",
    "CorruptLogError",
    "BaseMismatchError",
    "ChannelNotFoundError",
    "MessageDecodeError",
    "OutputExistsError",
    "OutputChangedError",
    "ImageFolderError",
    "FitError",
    "StageFunctionError",
]


def _restore(cls: type, args: tuple, state: dict) -> StarlogError:
    error = cls.__new__(cls)
    Exception.__init__(error, *args)
    error.__dict__.update(state)
    return error


class StarlogError(Exception):
    """Base class of every error starlog raises on purpose."""

    def __reduce__(self) -> tuple:
        """Picklable whatever the subclass's constructor takes (errors cross from worker processes)."""
        return (_restore, (type(self), self.args, dict(self.__dict__)))


class InvalidInputError(StarlogError, ValueError):
    """An array, image or table handed to a starlog function cannot be used as given."""


class InvalidParameterError(StarlogError, ValueError):
    """A parameter (keyword argument, command-line option, config entry) is out of range."""


class LogError(StarlogError):
    """A problem with an MCAP log file."""

    def __init__(self, path: str | Path, reason: str) -> None:
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class LogNotFoundError(LogError, FileNotFoundError):
    """The log file does not exist."""

    def __init__(self, path: str | Path) -> None:
        super().__init__(path, "no such file.")


class TruncatedLogError(LogError):
    """The log ends early (cut off, or never finished): run ``starlog recover`` on it."""

    def __init__(self, path: str | Path, detail: str) -> None:
        super().__init__(
            path,
            f"the log is truncated or unfinished ({detail}). "
            f"Rebuild a readable copy with: starlog recover {path} -o RECOVERED.mcap",
        )


class CorruptLogError(LogError):
    """The log's bytes are damaged (CRC mismatch, invalid record)."""


class NotMcapError(CorruptLogError):
    """The file is not an MCAP log at all (it does not start with the MCAP magic bytes)."""

    def __init__(self, path: str | Path) -> None:
        super().__init__(path, "is not an MCAP file (it does not start with the MCAP magic bytes).")


class BaseMismatchError(LogError):
    """A layer's base (the log it extends) is missing or is not the file the layer was written on.

    Names the layer, where its base should be, what the layer recorded of it (``expected``: its
    relative path, size and SHA-256), what is wrong (``problem``) and how to fix it.
    """

    def __init__(self, layer: str | Path, base: str | Path, expected: str, problem: str) -> None:
        self.base = Path(base)
        self.expected = expected
        self.problem = problem
        super().__init__(
            layer,
            f"its base {self.base} {problem} (the layer recorded {expected}). Put that file back there (a layer "
            "and its base move together: the base is found relative to the layer), or run the stage again on "
            "the log you have.")


class OutputFolderError(StarlogError, FileNotFoundError):
    """The folder an output should be written to does not exist."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        super().__init__(f"cannot write {self.path}: the folder {self.path.parent} does not exist.")

    @classmethod
    def check(cls, path: str | Path) -> None:
        """Raise this error when the folder ``path`` is to be written into does not exist."""
        if not Path(path).parent.is_dir():
            raise cls(path)


class ChannelNotFoundError(LogError, KeyError):
    """A channel (topic) asked for is not in the log."""

    def __init__(self, path: str | Path, topic: str, available: list[str]) -> None:
        self.topic = topic
        self.available = available
        listing = ", ".join(sorted(available)) or "none"
        super().__init__(path, f"no channel {topic!r} in the log (channels: {listing}).")

    def __str__(self) -> str:  # KeyError would otherwise quote the message
        return f"{self.path}: {self.reason}"


class MessageDecodeError(LogError):
    """A message's bytes do not decode to what its schema says."""

    def __init__(self, path: str | Path, topic: str, log_time: int, detail: str) -> None:
        self.topic = topic
        self.log_time = log_time
        super().__init__(
            path, f"message on {topic!r} at log_time {log_time} cannot be decoded: {detail}"
        )


class OutputExistsError(StarlogError, FileExistsError):
    """The output path exists and overwriting was not asked for."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        super().__init__(f"{self.path} exists already; pass --force to overwrite it.")


class OutputChangedError(OutputExistsError):
    """Another command wrote the output path while this one wrote it: that file is kept, this output discarded."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        StarlogError.__init__(
            self, f"{self.path} was written by another command while this one ran; that file is kept and this "
                  "command's output discarded. Run it again (with --force to replace that file).")


class ImageFolderError(StarlogError):
    """A folder of images cannot be ingested as given."""

    def __init__(self, path: str | Path, reason: str) -> None:
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class FitError(StarlogError):
    """A model fit (centroid fit, filter initialisation, error model) failed."""


# ---------------------------------------------------------------- reliability
__all__ += ["CorruptChunkError", "InvalidMessageError"]


class CorruptChunkError(CorruptLogError):
    """A chunk of the log is damaged (CRC mismatch, undecompressable, or it disagrees with its indexes).

    The error names the chunk: its file ``offset``, the ``topics`` of the channels it holds and
    its ``log_time`` range, so a user knows what is lost; ``starlog recover`` keeps every other chunk.
    """

    def __init__(self, path: str | Path, offset: int, topics: list[str], start: int, end: int, detail: str) -> None:
        self.offset = offset
        self.topics = list(topics)
        self.start = start
        self.end = end
        listing = ", ".join(self.topics) or "no known channel"
        super().__init__(
            path,
            f"the chunk at offset {offset} (channels {listing}; log_time {start}..{end}) is damaged: {detail}. "
            f"Keep every intact chunk with: starlog recover {path} -o RECOVERED.mcap",
        )


class InvalidMessageError(LogError):
    """A message decodes, but its value cannot be used (out of order, wrong frame size, schema violation)."""

    def __init__(self, path: str | Path, topic: str, log_time: int, detail: str) -> None:
        self.topic = topic
        self.log_time = log_time
        super().__init__(path, f"message on {topic!r} at log_time {log_time} is invalid: {detail}")


class StageFunctionError(StarlogError):
    """A declared stage's own function failed, or returned what its channels cannot take."""


# ---------------------------------------------------------------- topics of several channels
__all__ += ["MixedTopicError"]


class MixedTopicError(LogError):
    """The channels of one topic carry messages of schemas that cannot be read as one series (an image
    channel and a JSON channel, say); the message names the topic and the schemas
    (:func:`starlog.io.shared_topics.topic_conflict`)."""

    def __init__(self, path: str | Path, topic: str, detail: str) -> None:
        self.topic = topic
        super().__init__(path, f"{detail}.")


# ---------------------------------------------------------------- the file system
__all__ += ["FileAccessError", "WRITE_ERRNOS", "file_errors"]

#: What a failed read or write means and what to do, by ``errno``.
_ADVICE = {
    errno.ENOSPC: ("there is no space left on the device", "free some space there, or choose another folder"),
    errno.EDQUOT: ("the disk quota is exhausted", "free some space there, or choose another folder"),
    errno.EROFS: ("the file system is read-only", "choose a folder on a writable file system"),
    errno.EACCES: ("permission denied", "choose a folder you may write to, or change its permissions"),
    errno.EPERM: ("the operation is not permitted", "choose a folder you may write to, or change its permissions"),
    errno.EFBIG: ("the file would exceed the size limit (ulimit -f, or the file system's largest file)",
                  "raise the limit, or write less (--start/--end, fewer frames)"),
    errno.ENOENT: ("the file or its folder was removed meanwhile", "put it back, then run the command again"),
    errno.EIO: ("an input/output error occurred (a failing disk or lost network mount)",
                "check the device, then run the command again"),
}


#: The errors only a write can meet: whichever file an OSError without a name met them on, it was an output.
WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS})


class WorkerProcessError(StarlogError):
    """A worker process ended before its work was done."""

    def __init__(self) -> None:
        super().__init__(
            "a worker process ended before its work was done (it was killed, or ran out of memory). From a Python "
            "script, put the calls to starlog under `if __name__ == \"__main__\":` (the workers import the script "
            "again, as Python's multiprocessing does), or pass workers=1.")


class FileAccessError(StarlogError, OSError):
    """Reading or writing a file failed in the operating system (disk full, read-only file system, permission
    denied, file-size limit, a file or folder removed meanwhile).

    ``path`` is the user's file (an output's final name, not its temporary file), ``action`` what starlog was
    doing (``"write"``, ``"read"``), ``errno`` the OS error number. The message says which file, what
    happened and what to do; nothing partial was left under an output's name.
    """

    def __init__(self, path: str | os.PathLike[str], action: str, code: int | None, detail: str) -> None:
        what, todo = _ADVICE.get(code or 0, (detail, "check the file and its folder, then run the command again"))
        self.path = Path(path)
        self.action = action
        self.detail = detail
        self.message = f"cannot {action} {self.path}: {what}; {todo}."
        super().__init__(code, self.message)

    def __str__(self) -> str:
        return self.message

    def __reduce__(self) -> tuple:
        return (type(self), (self.path, self.action, self.errno, self.detail))

    @classmethod
    def of(cls, err: OSError, path: str | os.PathLike[str], action: str) -> FileAccessError:
        """``err`` as met while ``action``-ing ``path`` (kept as it is when it already is one)."""
        if isinstance(err, FileAccessError):
            return err
        return cls(path, action, err.errno, err.strerror or str(err))


@contextmanager
def file_errors(path: str | os.PathLike[str], action: str = "write", *,
                only_writes: bool = False) -> Iterator[None]:
    """Turn an :class:`OSError` raised in the block into a :class:`FileAccessError` naming ``path``.

    With ``only_writes``, only the errors a write alone can meet (:data:`WRITE_ERRNOS`), or any on the hidden
    files written beside ``path`` for it (``.NAME.*``: its temporary file, a stage's scratch files): a block
    that also reads its inputs leaves the others to whoever knows the file.
    """
    try:
        yield
    except StarlogError:
        raise
    except OSError as err:
        if only_writes and not _met_writing(err, Path(path)):
            raise
        raise FileAccessError.of(err, path, action) from err


def _met_writing(err: OSError, path: Path) -> bool:
    if err.errno in WRITE_ERRNOS:
        return True
    if err.filename is None:
        return False
    where = Path(os.fsdecode(err.filename)).absolute()
    folder = path.absolute().parent
    return where.is_relative_to(folder) and where.relative_to(folder).parts[0].startswith(f".{path.name}.")
