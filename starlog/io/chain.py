"""Layered logs: a stage's output holds only what it adds and names the log it extends.

A *layer* is a complete, valid MCAP file (header, schemas, channels, chunks, summary, footer)
holding the channels, metadata and provenance a stage added, plus one metadata record
(:data:`BASE_METADATA_NAME`) naming its *base*: the log it was written on, by its path relative
to the layer, its size, the CRCs of its summary and data sections, its SHA-256, and the SHA-256 of
each file below it. A base may itself be a layer; the files from the first log to the newest layer
are a *chain*, read as one log (:class:`~starlog.io.reader.LogReader`), shown file by file by
``starlog info``, merged into one file by ``starlog flatten``.

A layer's schema and channel ids come after every id of its chain and its topics are new to the
chain, so a viewer that merges files opened together (Foxglove) shows exactly what the flattened
log holds. A base that is missing or is another file than the one its layer recorded is never
read: every open compares each base's size and the CRCs its footer and DataEnd record store
(:func:`open_chain`); ``starlog verify`` also compares each SHA-256. (Bytes damaged inside a base's
chunks fail those chunks' own CRCs when they are read.)
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

from starlog.errors import BaseMismatchError, CorruptLogError, LogError
from starlog.io.layout import summary_crc
from starlog.io.mcap_file import McapFile
from starlog.io.provenance import BackgroundDigest

__all__ = ["BASE_METADATA_NAME", "BaseReference", "LayerBase", "base_reference", "id_collisions", "open_base",
           "open_chain"]

#: Name of the metadata record by which a layer names its base.
BASE_METADATA_NAME = "starlog.base"


@dataclass(frozen=True)
class BaseReference:
    """What a layer records of its base.

    Attributes
    ----------
    path : str
        The base's path relative to the layer's folder (``/``-separated), between the files' real paths.
    size : int
        The base's size in bytes.
    summary_crc, data_crc : int
        The CRCs of the base's summary section (as its footer stores it) and of its data section (as its
        DataEnd record stores it; 0: none stored): compared on every open.
    sha256 : str
        ``"sha256:<hex>"`` of the base: compared by ``starlog verify``.
    chain : tuple of str
        The SHA-256 of each file below the base, nearest first (empty when the base is a whole log).
    """

    path: str
    size: int
    summary_crc: int
    data_crc: int
    sha256: str
    chain: tuple[str, ...] = ()

    def to_metadata(self) -> dict[str, str]:
        return {"path": self.path, "size": str(self.size), "summary_crc": f"{self.summary_crc:#010x}",
                "data_crc": f"{self.data_crc:#010x}", "sha256": self.sha256, "chain": json.dumps(list(self.chain))}

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"path": self.path, "size_bytes": self.size, "summary_crc": f"{self.summary_crc:#010x}",
                "data_crc": f"{self.data_crc:#010x}", "sha256": self.sha256, "chain": list(self.chain)}

    @classmethod
    def from_metadata(cls, data: dict[str, str], where: Path) -> BaseReference:
        """Read the record of the layer ``where``; :class:`CorruptLogError` when it is damaged."""
        try:
            chain = json.loads(data.get("chain", "[]"))
            if not isinstance(chain, list) or not all(isinstance(d, str) for d in chain):
                raise ValueError("its chain is not a list of digests")
            reference = cls(str(data["path"]), int(data["size"]), int(data["summary_crc"], 16),
                            int(data.get("data_crc", "0"), 16), str(data["sha256"]), tuple(chain))
            if not reference.path or "\0" in reference.path or reference.size < 0:
                raise ValueError(f"it names no file ({reference.path!r})")
        except (KeyError, ValueError, TypeError) as err:
            raise CorruptLogError(where, f"its base record ({BASE_METADATA_NAME!r}) is damaged ({err}).") from err
        return reference

    def resolve(self, layer: Path) -> Path:
        """Where the base is: its path taken from the layer's real folder (symbolic links followed)."""
        folder = os.path.dirname(os.path.realpath(layer))
        return Path(os.path.realpath(os.path.join(folder, *PurePosixPath(self.path).parts)))

    def describe(self) -> str:
        """What the layer recorded, in words: the relative path, the size, the SHA-256."""
        return f"{self.path!r} relative to its folder, {self.size} bytes, {self.sha256}"


def base_reference(file: McapFile) -> BaseReference | None:
    """The base record of ``file`` (None when it is a whole log). Raises :class:`CorruptLogError` for two."""
    records = file.metadata(BASE_METADATA_NAME)
    if len(records) > 1:
        raise CorruptLogError(file.path, f"it has {len(records)} base records; a layer has one.")
    return BaseReference.from_metadata(records[0][1], file.path) if records else None


def _summary_checksum(file: McapFile) -> int:
    """The CRC of a file's summary section as its footer stores it: the footer's own once the file was opened
    with it checked, else computed (a footer may store none); 0 for a file without a summary section."""
    if file.footer.summary_start == 0:
        return 0
    if file.summary_verified:
        return file.footer.summary_crc
    with open(file.path, "rb") as f:
        return summary_crc(f, file.footer)


def _mismatch(file: McapFile, reference: BaseReference) -> str | None:
    """How ``file`` differs from the base ``reference`` describes, by size and stored CRCs; None when it does not."""
    if file.size != reference.size:
        return f"has changed ({file.size} bytes now)"
    if _summary_checksum(file) != reference.summary_crc:
        return "has changed (its summary is not the one the layer recorded)"
    if reference.data_crc and file.data_section_crc != reference.data_crc:
        return "has changed (its data section is not the one the layer recorded)"
    return None


def open_base(layer: Path, reference: BaseReference, *, validate_crcs: bool = True) -> McapFile:
    """The base of ``layer``, opened once it is the file ``reference`` describes (there, of that size, with
    those CRCs); :class:`BaseMismatchError` otherwise."""
    base = reference.resolve(layer)

    def mismatch(problem: str) -> BaseMismatchError:
        return BaseMismatchError(layer, base, reference.describe(), problem)

    if not base.is_file():
        raise mismatch("is missing")
    try:
        file = McapFile(base, validate_crcs=validate_crcs)
    except LogError as err:
        raise mismatch(f"cannot be read ({err.reason})") from err
    except OSError as err:
        raise mismatch(f"cannot be read ({err.strerror or err})") from err
    problem = _mismatch(file, reference)
    if problem is not None:
        file.close()
        raise mismatch(problem)
    return file


def open_chain(path: str | os.PathLike[str], *, validate_crcs: bool = True, follow: bool = True) -> list[McapFile]:
    """The files of the log at ``path``, from the first log to ``path`` itself, each opened and checked.

    Each base must be the file its layer recorded (:func:`open_base`) and the chain's ids and topics
    must not collide (:class:`CorruptLogError`). With ``follow=False`` only ``path`` is opened.
    """
    files: list[McapFile] = []
    try:
        files.append(McapFile(path, validate_crcs=validate_crcs))
        seen = {os.path.realpath(path)}
        while follow and (reference := base_reference(files[-1])) is not None:
            if str(reference.resolve(files[-1].path)) in seen:
                raise CorruptLogError(files[-1].path, f"its base {reference.resolve(files[-1].path)} is a file of its "
                                                      "own chain (overwritten by a stage's output?): the chain cannot "
                                                      "be read. Run the stages again from the first log.")
            files.append(open_base(files[-1].path, reference, validate_crcs=validate_crcs))
            seen.add(str(files[-1].path))
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
    """What a layer written on a log needs of it: ids and topics to avoid, the files it must not overwrite,
    and what the record naming its base holds.

    Made by :meth:`of` (through :meth:`~starlog.io.reader.LogReader.layer_base`); the SHA-256 of the
    base is computed on a thread from then on (:meth:`digest` waits for it, :meth:`cancel` stops it).
    """

    path: Path
    size: int
    summary_crc: int
    data_crc: int
    chain: tuple[str, ...]
    chain_paths: tuple[str, ...]
    next_schema_id: int
    next_channel_id: int
    topics: frozenset[str]
    _digest: BackgroundDigest = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._digest = BackgroundDigest(self.path)

    @classmethod
    def of(cls, files: list[McapFile]) -> LayerBase:
        """The base of a layer on the chain ``files`` (first log first): the newest file."""
        base = files[-1]
        below = base_reference(base)
        schemas = [i for f in files for i in f.summary.schemas]
        channels = [c for f in files for c in f.summary.channels.values()]
        return cls(base.path, base.size, _summary_checksum(base), base.data_section_crc,
                   () if below is None else (below.sha256, *below.chain),
                   tuple(os.path.realpath(f.path) for f in files),
                   next_schema_id=max(schemas, default=0) + 1,
                   next_channel_id=max((c.id for c in channels), default=0) + 1,
                   topics=frozenset(c.topic for c in channels))

    def digest(self) -> str:
        """``"sha256:<hex>"`` of the base (waits for the thread)."""
        return self._digest.result()

    def cancel(self) -> None:
        """Stop hashing (the layer is not written)."""
        self._digest.cancel()

    def reference(self, layer: Path) -> BaseReference:
        """The base record of a layer written at ``layer``."""
        relative = os.path.relpath(os.path.realpath(self.path), os.path.dirname(os.path.realpath(layer)))
        return BaseReference(PurePosixPath(*Path(relative).parts).as_posix(), self.size, self.summary_crc,
                             self.data_crc, self.digest(), self.chain)
