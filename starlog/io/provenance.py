"""Provenance: how each channel of a log was made, stored as MCAP Metadata records."""

from __future__ import annotations

import hashlib
import json
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from starlog.errors import LogError
from starlog.io.digest_cache import read_digest_cache
from starlog.io.layout import locate_data_end
from starlog.io.resumable_sha256 import ResumableSha256
from starlog.io.resumable_sha256 import available as resumable_available
from starlog.io.stack import StackedLog

__all__ = ["PROVENANCE_METADATA_NAME", "BackgroundDigest", "Provenance", "file_digest"]

#: Name of the MCAP Metadata records that hold one stage's provenance each.
PROVENANCE_METADATA_NAME = "starlog.provenance"


def file_digest(path: str | Path | StackedLog) -> str:
    """SHA-256 of a file's bytes (or of the bytes a :class:`StackedLog` stands for), as ``"sha256:<hex>"``."""
    if isinstance(path, StackedLog):
        return path.digest()
    with open(path, "rb") as f:
        return "sha256:" + hashlib.file_digest(f, "sha256").hexdigest()


class BackgroundDigest:
    """:func:`file_digest` of a log, computed on a thread while the caller works.

    A stage needs its input's SHA-256 only for the provenance it writes last; hashing hundreds
    of MB (``hashlib`` and file reads release the GIL) then overlaps the stage's own work
    instead of preceding it. :meth:`result` waits for the digest, :meth:`cancel` stops it.
    A log whose digest a stage saved with it (:mod:`starlog.io.digest_cache`) is not read at all.
    :meth:`prefix` gives the hash state at the end of the log's data section, from which the
    digest of a stage's output (which starts with those bytes) continues.
    """

    _BLOCK = 1024 * 1024

    def __init__(self, path: str | Path | StackedLog) -> None:
        self._digest: str | None = None
        self._prefix: tuple[int, bytes] | None = None
        self._error: BaseException | None = None
        self._stop = threading.Event()
        cached = None if isinstance(path, StackedLog) else read_digest_cache(path)
        if isinstance(path, StackedLog):  # hashes only its newest layer's tail: no thread needed
            self._digest = path.digest()
            self._thread = None
        elif cached is not None:
            self._digest, self._prefix = cached.digest, (cached.data_end, cached.state)
            self._thread = None
        else:
            self._thread = threading.Thread(target=self._hash, args=(Path(path),), name="starlog-digest",
                                            daemon=True)
            self._thread.start()

    def _hash(self, path: Path) -> None:
        try:
            block = bytearray(self._BLOCK)
            view = memoryview(block)
            with open(path, "rb", buffering=0) as f:
                digest, data_end = self._start(path, f)
                done = 0
                while not self._stop.is_set():
                    count = f.readinto(block if data_end is None or done >= data_end
                                       else view[:min(self._BLOCK, data_end - done)])
                    if not count:
                        self._digest = "sha256:" + digest.hexdigest()
                        return
                    digest.update(view[:count])
                    done += count
                    if done == data_end:
                        self._prefix = (data_end, digest.state())
        except BaseException as err:  # handed to the caller by result()
            self._error = err

    @staticmethod
    def _start(path: Path, f: BinaryIO) -> tuple[Any, int | None]:
        """A fresh hash, and where to save its state (the data section's end) when it can be saved."""
        if not resumable_available():
            return hashlib.sha256(), None
        try:
            data_end = locate_data_end(path, f)
        except (LogError, OSError, ValueError):  # not a complete log: its digest alone is wanted
            data_end = None
        f.seek(0)
        return ResumableSha256(), data_end

    def result(self) -> str:
        """``"sha256:<hex>"`` of the file (waits for the thread; re-raises its error)."""
        if self._thread is not None:
            self._thread.join()
        if self._error is not None:
            raise self._error
        if self._digest is None:
            raise RuntimeError("the digest was cancelled")
        return self._digest

    def prefix(self) -> tuple[int, bytes] | None:
        """``(data_end, state)``: the hash state after the log's data section (waits for the thread), or None
        when it cannot be saved here."""
        self.result()
        return self._prefix

    def cancel(self) -> None:
        """Stop hashing (within one block) and wait for the thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()


@dataclass(frozen=True)
class Provenance:
    """One stage's record: what ran, with which parameters, on which input, making which channels.

    Attributes
    ----------
    stage : str
        Stage name (``simulate``, ``ingest``, ``centroid``, ...).
    version : str
        starlog version that ran it.
    parameters : dict
        The stage's parameters, JSON-serialisable.
    input_digest : str
        ``"sha256:<hex>"`` of the input log (empty for stages that start a log).
    channels : list of str
        Topics the stage added.
    """

    stage: str
    version: str
    parameters: dict[str, Any] = field(default_factory=dict)
    input_digest: str = ""
    channels: list[str] = field(default_factory=list)

    def to_metadata(self) -> dict[str, str]:
        """The MCAP Metadata map (string to string)."""
        return {
            "stage": self.stage,
            "starlog_version": self.version,
            "parameters": json.dumps(self.parameters, sort_keys=True, allow_nan=False),
            "input_digest": self.input_digest,
            "channels": json.dumps(list(self.channels)),
        }

    @classmethod
    def from_metadata(cls, data: dict[str, str]) -> Provenance:
        """Rebuild from an MCAP Metadata map written by :meth:`to_metadata`."""
        return cls(
            stage=data.get("stage", ""),
            version=data.get("starlog_version", ""),
            parameters=json.loads(data.get("parameters", "{}")),
            input_digest=data.get("input_digest", ""),
            channels=json.loads(data.get("channels", "[]")),
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "stage": self.stage,
            "version": self.version,
            "parameters": self.parameters,
            "input_digest": self.input_digest,
            "channels": list(self.channels),
        }
