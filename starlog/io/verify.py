"""``starlog verify``: read every record of an MCAP file and report every problem found.

Checked: the magic bytes, header and footer; the summary section and its CRC; every chunk's
header, decompression and CRC; the message index records against the chunk contents; the
chunk indexes against the chunks (:mod:`starlog.io.verify_indexes`); the statistics against the
messages counted; schema and channel references; JSON messages against their JSON Schemas;
protobuf, ROS 1 and ROS 2 messages decode; images decode with one size per channel; ``log_time``
order per channel (:mod:`starlog.io.verify_messages`).

Each problem (:mod:`starlog.io.verify_report`) has a ``kind``, a severity (``error``: the file is
damaged, or starlog refuses part of it, such as a topic whose channels' schemas cannot be read as
one series; ``warning``: starlog reads the file in full, but it breaks a rule of the MCAP
specification, such as a summary without the Channel records its chunk indexes name, and
``starlog filter LOG -o OUT`` rewrites it conforming; ``note``: a file every starlog command reads in
full but that is unusual, such as chunks without message indexes, no summary, or channels sharing a
topic; where Foxglove or the ``mcap`` library cannot read it, the note says so and names the command
that rewrites it) and where it lies.

Each file is checked alone (:mod:`starlog.io.verify_walk`: its footer, its summary section, one walk
of its data section); a layer's chain then as a whole (each base the file its layer recorded, ids and
topics unique across the chain).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from starlog.errors import BaseMismatchError, CorruptLogError
from starlog.io.chain import BaseReference, id_collisions, open_base
from starlog.io.provenance import BackgroundDigest
from starlog.io.verify_report import EXIT_STATUS, ChainReport, Problem, VerifyReport
from starlog.io.verify_walk import FileVerifier, verify_one

__all__ = ["EXIT_STATUS", "ChainReport", "Problem", "VerifyReport", "verify_file", "verify_log"]


def verify_file(path: str | os.PathLike[str], *, on_progress: Callable[[int], object] | None = None) -> VerifyReport:
    """Check every record of the MCAP file at ``path`` alone; never raises for a damaged file.

    ``on_progress`` is called with the bytes of the data section checked so far, every few MB
    (for a progress bar).
    """
    return verify_one(Path(path), on_progress)[0]


def verify_log(path: str | os.PathLike[str], *, chain: bool = True,
               on_progress: Callable[[int, int], object] | None = None) -> ChainReport:
    """Check every record of the log at ``path`` and, for a layer, of every file of its chain (``chain=False``:
    the file alone); never raises for a damaged file.

    Besides each file's own checks (:func:`verify_file`): each base is the file its layer recorded (where,
    size, CRCs, SHA-256), the digests of its own chain are those the layer recorded, and schema ids, channel
    ids and topics are unique across the chain. ``on_progress`` is called with the bytes checked so far and
    the bytes of the files found so far.
    """
    report = ChainReport(str(path))
    layer, verified, done = Path(path), [], 0
    total = layer.stat().st_size if layer.is_file() else 0

    def progress(offset: int) -> None:
        if on_progress is not None:
            on_progress(done + offset, total)

    expected: tuple[Path, BaseReference, BackgroundDigest] | None = None
    while True:
        file_report, verifier = verify_one(layer, progress)
        report.files.insert(0, file_report)
        verified.append(verifier)
        done += file_report.size
        reference = _base_record(report, layer, verifier)
        if expected is not None:
            _check_base(report, *expected, reference)
        if reference is None:
            break
        if not chain:
            report.base_checked = False
            break
        base = _followable_base(report, layer, reference, [Path(f.path) for f in report.files])
        if base is None:
            break
        total += base.stat().st_size
        expected = (layer, reference, BackgroundDigest(base))
        layer = base
    _check_ids(report, [v for v in reversed(verified) if v is not None])
    return report


def _followable_base(report: ChainReport, layer: Path, reference: BaseReference, seen: list[Path]) -> Path | None:
    """The base of ``layer`` when it can be checked next; else None, with the problem reported."""
    base = reference.resolve(layer)
    problem = ("is missing" if not base.is_file() else
               "is a file of its own chain" if any(os.path.samefile(base, p) for p in seen if p.is_file()) else None)
    if problem is not None:
        report.chain_problems.append(_base_problem("base_missing" if problem == "is missing" else "base_cycle",
                                                   layer, base, reference, problem))
        report.missing_base = str(base)
        return None
    return base


def _base_problem(kind: str, layer: Path, base: Path, reference: BaseReference, problem: str) -> Problem:
    return Problem(kind, "error", str(BaseMismatchError(layer, base, reference.describe(), problem)))


def _base_record(report: ChainReport, layer: Path, verifier: FileVerifier | None) -> BaseReference | None:
    records = [] if verifier is None else verifier.base_records
    if len(records) > 1:
        report.chain_problems.append(Problem("bad_base_record", "error", f"{layer} has {len(records)} base records"))
    try:
        return BaseReference.from_metadata(records[0], layer) if records else None
    except CorruptLogError as err:
        report.chain_problems.append(Problem("bad_base_record", "error", str(err)))
        return None


def _check_base(report: ChainReport, layer: Path, reference: BaseReference, digest: BackgroundDigest,
                base_reference: BaseReference | None) -> None:
    """Size, CRCs, SHA-256 and chain digests of the base of ``layer`` against what the layer recorded of it."""
    base = reference.resolve(layer)
    try:
        open_base(layer, reference).close()
    except BaseMismatchError as err:
        report.chain_problems.append(_base_problem("base_changed", layer, base, reference, err.problem))
    try:
        sha256 = digest.result()
    except OSError as err:
        sha256 = f"unreadable ({err.strerror or err})"
    if sha256 != reference.sha256:
        report.chain_problems.append(_base_problem("base_digest", layer, base, reference, f"has SHA-256 {sha256}"))
    below = () if base_reference is None else (base_reference.sha256, *base_reference.chain)
    if below != reference.chain:
        report.chain_problems.append(_base_problem("chain_mismatch", layer, base, reference,
                                                   f"stands on files of SHA-256 {list(below)}, not the "
                                                   f"{list(reference.chain)} recorded"))


def _check_ids(report: ChainReport, verifiers: list[FileVerifier]) -> None:
    files = [(v.path, v.schemas, v.channels, [c.topic for c in v.channels.values()]) for v in verifiers]
    for collision in id_collisions(files):
        report.chain_problems.append(Problem("chain_collision", "error", collision))
