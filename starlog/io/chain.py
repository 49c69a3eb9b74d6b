"""Layered logs: a stage's output holds only what it adds and names the log it extends.

A *layer* is a complete, valid MCAP file (header, schemas, channels, chunks, summary, footer)
holding the channels, metadata and provenance a stage added, plus one metadata record
(:data:`BASE_METADATA_NAME`) naming its *base*: the log it was written on, by its path relative
to the layer, its size, the CRC of its summary section, its SHA-256, and the SHA-256 of each file
below it. A base may itself be a layer; the files from the first log to the newest layer are a
*chain*, read as one log (:class:`~starlog.io.reader.LogReader`), shown file by file by
``starlog info``, merged into one file by ``starlog flatten``.

A layer's schema and channel ids come after every id of its chain and its topics are new to the
chain, so a viewer that merges files opened together (Foxglove) shows exactly what the flattened
log holds. A base that is missing or has changed is never read: every open checks each base's
size and summary CRC (:func:`open_chain`); ``starlog verify`` also checks each SHA-256.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

from starlog.errors import BaseMismatchError, CorruptLogError, LogError
from starlog.io.layout import read_footer, summary_crc
from starlog.io.mcap_file import McapFile
from starlog.io.provenance import BackgroundDigest

__all__ = ["BASE_METADATA_NAME", "BaseReference", "LayerBase", "base_problem", "base_reference",
           "file_summary_checksum", "id_collisions", "open_chain", "summary_checksum"]

#: Name of the metadata record by which a layer names its base.
BASE_METADATA_NAME = "starlog.base"


@dataclass(frozen=True)
class BaseReference:
    """What a layer records of its base.

    Attributes
    ----------
    path : str
        The base's path relative to the layer's folder (``/``-separated).
    size : int
        The base's size in bytes.
    summary_crc : int
        :func:`summary_checksum` of the base: checked on every open.
    sha256 : str
        ``"sha256:<hex>"`` of the base: checked by ``starlog verify``.
    chain : tuple of str
        The SHA-256 of each file below the base, nearest first (empty when the base is a whole log).
    """

    path: str
    size: int
    summary_crc: int
    sha256: str
    chain: tuple[str, ...] = ()

    def to_metadata(self) -> dict[str, str]:
        return {"path": self.path, "size": str(self.size), "summary_crc": f"{self.summary_crc:#010x}",
                "sha256": self.sha256, "chain": json.dumps(list(self.chain))}

    @classmethod
    def from_metadata(cls, data: dict[str, str], where: Path) -> BaseReference:
        """Read the record of the layer ``where``; :class:`CorruptLogError` when it is damaged."""
        try:
            chain = json.loads(data.get("chain", "[]"))
            if not isinstance(chain, list) or not all(isinstance(d, str) for d in chain):
                raise ValueError("its chain is not a list of digests")
            reference = cls(str(data["path"]), int(data["size"]), int(data["summary_crc"], 16), str(data["sha256"]),
                            tuple(chain))
            if not reference.path or reference.size < 0:
                raise ValueError("it names no file")
        except (KeyError, ValueError, TypeError) as err:
            raise CorruptLogError(where, f"its base record ({BASE_METADATA_NAME!r}) is damaged ({err}).") from err
        return reference

    def resolve(self, layer: Path) -> Path:
        """Where the base is: its path taken relative to the layer's folder."""
        return Path(os.path.normpath(layer.parent / Path(*PurePosixPath(self.path).parts)))

    def describe(self) -> str:
        return f"{self.path} ({self.size} bytes, {self.sha256})"


def summary_checksum(file: McapFile) -> int:
    """The CRC-32 of a file's summary section and footer fields, as a footer stores it.

    The footer's own when the file was opened with it checked; else computed (a footer may store
    none); 0 for a file without a summary section.
    """
    if file.summary_verified or file.footer.summary_start == 0:
        return file.footer.summary_start and file.footer.summary_crc
    with open(file.path, "rb") as f:
        return summary_crc(f, file.footer)


def file_summary_checksum(path: Path) -> int:
    """:func:`summary_checksum` of the file at ``path``, computed from its bytes (:class:`LogError` when it has
    no footer)."""
    with open(path, "rb") as f:
        footer = read_footer(path, f)
        return summary_crc(f, footer) if footer.summary_start else 0


def base_reference(file: McapFile) -> BaseReference | None:
    """The base record of ``file`` (None when it is a whole log). Raises :class:`CorruptLogError` for two."""
    records = file.metadata(BASE_METADATA_NAME)
    if len(records) > 1:
        raise CorruptLogError(file.path, f"it has {len(records)} base records; a layer has one.")
    return BaseReference.from_metadata(records[0][1], file.path) if records else None


def open_chain(path: str | os.PathLike[str], *, validate_crcs: bool = True, follow: bool = True) -> list[McapFile]:
    """The files of the log at ``path``, from the first log to ``path`` itself, each opened and checked.

    Each base must be where its layer says, of the size and summary CRC it recorded
    (:class:`BaseMismatchError` otherwise), and the chain's ids and topics must not collide
    (:class:`CorruptLogError`). With ``follow=False`` only ``path`` is opened.
    """
    files: list[McapFile] = []
    try:
        files.append(McapFile(path, validate_crcs=validate_crcs))
        seen = {os.path.realpath(files[0].path)}
        while follow and (reference := base_reference(files[-1])) is not None:
            base_path = reference.resolve(files[-1].path)
            if os.path.realpath(base_path) in seen:
                raise CorruptLogError(files[-1].path, f"its base {base_path} is a file of its own chain.")
            seen.add(os.path.realpath(base_path))
            files.append(_open_base(files[-1].path, base_path, reference, validate_crcs=validate_crcs))
        files.reverse()
        collisions = id_collisions([(f.path, f.summary.schemas, f.summary.channels,
                                     [c.topic for c in f.summary.channels.values()]) for f in files])
        if collisions:
            raise CorruptLogError(files[-1].path, f"its chain's files cannot be read as one log: {collisions[0]}.")
    except BaseException:
        for file in files:
            file.close()
        raise
    return files


def _open_base(layer: Path, base: Path, reference: BaseReference, *, validate_crcs: bool) -> McapFile:
    """The base of ``layer``, opened once it is the file ``reference`` describes (:func:`base_problem`)."""
    problem = base_problem(base, reference)
    if problem is not None:
        raise BaseMismatchError(layer, base, reference.describe(), problem)
    try:
        return McapFile(base, validate_crcs=validate_crcs)
    except LogError as err:
        raise BaseMismatchError(layer, base, reference.describe(), f"cannot be read ({err.reason})") from err


def base_problem(base: Path, reference: BaseReference) -> str | None:
    """How ``base`` differs from the file a layer recorded, by the checks made on every open (it is there,
    of that size, with that summary CRC); None when it passes them."""
    if not base.is_file():
        return "is missing"
    size = base.stat().st_size
    if size != reference.size:
        return f"has changed ({size} bytes now)"
    try:
        crc = file_summary_checksum(base)
    except LogError as err:
        return f"cannot be read ({err.reason})"
    if crc != reference.summary_crc:
        return "has changed (its summary is not the one the layer recorded)"
    return None


def id_collisions(files: list[tuple[Path, Iterable[int], Iterable[int], Iterable[str]]]) -> list[str]:
    """The schema ids, channel ids and topics found in two files of a chain, given each file's path, schema
    ids, channel ids and topics (first log first); none when the files read as one log."""
    owner: dict[tuple[str, Any], Path] = {}
    found = []
    for path, schema_ids, channel_ids, topics in files:
        keys = [("schema id", i) for i in schema_ids] + [("channel id", i) for i in channel_ids]
        for key in keys + [("topic", t) for t in topics]:
            if key in owner and owner[key] != path:
                found.append(f"the {key[0]} {key[1]!r} of {path} is also in {owner[key]}")
            owner.setdefault(key, path)
    return found


@dataclass
class LayerBase:
    """What a layer written on a log needs of it: ids and topics to avoid, and the record naming it.

    Made by :meth:`~starlog.io.reader.LogReader.layer_base`; the SHA-256 of the base file is
    computed on a thread from then on (:meth:`digest` waits for it).
    """

    path: Path
    size: int
    summary_crc: int
    chain: tuple[str, ...]
    next_schema_id: int
    next_channel_id: int
    topics: frozenset[str]
    _digest: BackgroundDigest | None = None

    def __post_init__(self) -> None:
        if self._digest is None:
            self._digest = BackgroundDigest(self.path)

    def digest(self) -> str:
        """``"sha256:<hex>"`` of the base file (waits for the thread)."""
        assert self._digest is not None
        return self._digest.result()

    def cancel(self) -> None:
        """Stop hashing (the layer is not written)."""
        if self._digest is not None:
            self._digest.cancel()

    def reference(self, layer: Path) -> BaseReference:
        """The base record of a layer written at ``layer``."""
        relative = os.path.relpath(os.path.abspath(self.path), os.path.dirname(os.path.abspath(layer)))
        return BaseReference(PurePosixPath(*Path(relative).parts).as_posix(), self.size, self.summary_crc,
                             self.digest(), self.chain)

