"""The SHA-256 of a log, kept with the file for the stage that reads it next.

Every stage records its input's SHA-256 in its provenance. Hashing a log of camera frames is
not free (at 1024x1024 about 1 ms a frame, more than tracking a frame costs), and each stage
would hash what the stage before it has just written. The file a stage writes is its input's
data section, then its own records: its SHA-256 continues the state its input's hash reached
at the end of that section (:mod:`starlog.io.resumable_sha256`). So after writing a log, a
stage saves in an extended attribute of the file (:data:`ATTRIBUTE`) the file's digest and the
hash state at the end of its data section, with the file's size and modification time; a
stage reading the log takes the digest from there while size and time still match (writing to
the file changes its time) and continues the state over its own records. Where extended
attributes or the resumable hash are not available, logs are hashed whole, as before.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from starlog.errors import LogError
from starlog.io.layout import locate_data_end
from starlog.io.resumable_sha256 import STATE_SIZE, ResumableSha256, available

__all__ = ["ATTRIBUTE", "CachedDigest", "read_digest_cache", "hash_into", "write_digest_cache"]

#: The extended attribute holding a log's :class:`CachedDigest`.
ATTRIBUTE = "user.starlog.sha256"
_BLOCK = 1024 * 1024


@dataclass(frozen=True)
class CachedDigest:
    """A log's ``"sha256:<hex>"`` digest, and the hash state after its first ``data_end`` bytes (its data section)."""

    digest: str
    data_end: int
    state: bytes


def _supported() -> bool:
    return hasattr(os, "getxattr") and hasattr(os, "setxattr") and available()


def read_digest_cache(path: str | os.PathLike[str]) -> CachedDigest | None:
    """The cached digest of ``path``, or None when there is none or the file changed since it was saved."""
    if not _supported():
        return None
    try:
        raw = os.getxattr(path, ATTRIBUTE)
        stat = os.stat(path)
    except OSError:  # no such attribute, or a file system without them
        return None
    try:
        record = json.loads(raw)
        if record["size"] != stat.st_size or record["mtime_ns"] != stat.st_mtime_ns:
            return None
        state, digest, data_end = bytes.fromhex(record["state"]), str(record["digest"]), int(record["data_end"])
    except (ValueError, KeyError, TypeError):
        return None
    if len(state) != STATE_SIZE or not digest.startswith("sha256:") or not 0 < data_end <= stat.st_size:
        return None
    return CachedDigest(digest, data_end, state)


def hash_into(digest: ResumableSha256, f: BinaryIO, start: int, end: int) -> None:
    """Hash bytes ``start..end`` of the open file ``f``."""
    block = bytearray(_BLOCK)
    view = memoryview(block)
    f.seek(start)
    while start < end:
        count = f.readinto(view[:min(_BLOCK, end - start)])
        if not count:
            raise EOFError(f"the file ends at {start}, before {end}")
        digest.update(view[:count])
        start += count


def write_digest_cache(path: str | os.PathLike[str], *, prefix: tuple[int, bytes] | None = None) -> None:
    """Hash the log ``path`` and save its :class:`CachedDigest` with it (nothing where unsupported).

    ``prefix``: ``(length, state)``, the hash state after the file's first ``length`` bytes (the
    input's data section it starts with); only the rest is read. Without it the whole file is hashed.
    """
    if not _supported():
        return
    path = Path(path)
    start, digest = (0, ResumableSha256()) if prefix is None else (prefix[0], ResumableSha256(prefix[1]))
    try:
        with open(path, "rb", buffering=0) as f:
            data_end = locate_data_end(path, f)
            if data_end < start:
                return
            hash_into(digest, f, start, data_end)
            state = digest.state()
            stat = os.fstat(f.fileno())
            hash_into(digest, f, data_end, stat.st_size)
    except (OSError, EOFError, LogError):  # the file went away or changed: nothing is saved
        return
    record = {"digest": "sha256:" + digest.hexdigest(), "data_end": data_end, "state": state.hex(),
              "size": stat.st_size, "mtime_ns": stat.st_mtime_ns}
    try:
        os.setxattr(path, ATTRIBUTE, json.dumps(record).encode())
    except OSError:  # a file system without user attributes
        return
