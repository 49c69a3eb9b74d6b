"""Provenance: how each channel of a log was made, stored as MCAP Metadata records."""

from __future__ import annotations

import hashlib
import json
import os
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["PROVENANCE_METADATA_NAME", "BackgroundDigest", "Provenance", "file_digest"]

#: Name of the MCAP Metadata records that hold one stage's provenance each.
PROVENANCE_METADATA_NAME = "starlog.provenance"


def file_digest(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes, as ``"sha256:<hex>"``."""
    with open(path, "rb") as f:
        return "sha256:" + hashlib.file_digest(f, "sha256").hexdigest()


class BackgroundDigest:
    """:func:`file_digest` of a file, computed on a thread while the caller works.

    A stage needs its input's SHA-256 only for the records it writes last; hashing a log of
    images (``hashlib`` and file reads release the GIL) then overlaps the stage's own work
    instead of preceding it. :meth:`result` waits for the digest, :meth:`cancel` stops it.
    """

    _BLOCK = 1024 * 1024

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self._digest: str | None = None
        self._error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._hash, args=(Path(path),), name="starlog-digest", daemon=True)
        self._thread.start()

    def _hash(self, path: Path) -> None:
        try:
            digest = hashlib.sha256()
            block = bytearray(self._BLOCK)
            view = memoryview(block)
            with open(path, "rb", buffering=0) as f:
                while not self._stop.is_set():
                    count = f.readinto(block)
                    if not count:
                        self._digest = "sha256:" + digest.hexdigest()
                        return
                    digest.update(view[:count])
        except BaseException as err:  # handed to the caller by result()
            self._error = err

    def result(self) -> str:
        """``"sha256:<hex>"`` of the file (waits for the thread; re-raises its error)."""
        self._thread.join()
        if self._error is not None:
            raise self._error
        if self._digest is None:
            raise RuntimeError("the digest was cancelled")
        return self._digest

    def cancel(self) -> None:
        """Stop hashing (within one block) and wait for the thread."""
        self._stop.set()
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
