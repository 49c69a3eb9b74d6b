"""Provenance: how each channel of a log was made, stored as MCAP Metadata records."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from starlog.io.stack import StackedLog

__all__ = ["PROVENANCE_METADATA_NAME", "Provenance", "file_digest"]

#: Name of the MCAP Metadata records that hold one stage's provenance each.
PROVENANCE_METADATA_NAME = "starlog.provenance"


def file_digest(path: str | Path | StackedLog) -> str:
    """SHA-256 of a file's bytes (or of the bytes a :class:`StackedLog` stands for), as ``"sha256:<hex>"``."""
    if isinstance(path, StackedLog):
        return path.digest()
    with open(path, "rb") as f:
        return "sha256:" + hashlib.file_digest(f, "sha256").hexdigest()


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
