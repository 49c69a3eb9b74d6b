"""What ``starlog verify`` reports: each problem found, each file's status and verdict, and a chain's.

A problem has a ``kind`` (a stable name), a severity (``error``: the file is damaged, or starlog refuses
part of it; ``warning``: starlog reads the file in full, but it breaks a rule of the MCAP
specification, quoted in :attr:`Problem.rule`; ``note``: a file every starlog command reads in full
but that is unusual), the file ``offset`` of the record, and the ``channel`` and ``log_time`` where
they apply. A report's :attr:`~VerifyReport.status` follows: ``damaged`` or ``refused`` (an error;
exit status 1), ``nonconformant`` (warnings only; exit status 3), ``valid`` (notes at most; 0).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

__all__ = ["EXIT_STATUS", "REFUSALS", "ChainReport", "Problem", "VerifyReport", "status_of"]

#: ``starlog verify``'s exit status for each :attr:`VerifyReport.status`.
EXIT_STATUS = {"valid": 0, "nonconformant": 3, "refused": 1, "damaged": 1}
#: Errors of valid MCAP files that starlog refuses (its frames, tables, stages), as opposed to damage.
REFUSALS = frozenset({"topic_schemas_differ", "image_size", "image_size_changed", "duplicate_frame_time"})


@dataclass(frozen=True)
class Problem:
    """One problem: ``kind`` (stable name), ``severity`` (error / warning / note), where, and what; a warning's
    ``rule`` quotes the rules of the MCAP specification the file breaks (each in double quotes)."""

    kind: str
    severity: str
    detail: str
    offset: int | None = None
    channel: str | None = None
    log_time: int | None = None
    rule: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "severity": self.severity, "offset": self.offset, "channel": self.channel,
                "log_time": self.log_time, "detail": self.detail, "rule": self.rule or None}

    def line(self) -> str:
        where = [f"offset {self.offset}" if self.offset is not None else "",
                 f"channel {self.channel}" if self.channel else "",
                 f"log_time {self.log_time}" if self.log_time is not None else ""]
        place = ", ".join(w for w in where if w)
        return f"{self.severity} {self.kind}{f' ({place})' if place else ''}: {self.detail}"


@dataclass
class VerifyReport:
    """What :func:`verify_log` found."""

    path: str
    size: int = 0
    messages: int = 0
    chunks: int = 0
    channels: int = 0
    problems: list[Problem] = field(default_factory=list)

    @property
    def errors(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == "error"]

    @property
    def warnings(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == "warning"]

    @property
    def ok(self) -> bool:
        """No error: every starlog command reads the file in full (it may still break the specification)."""
        return not self.errors

    @property
    def status(self) -> str:
        """:func:`status_of` the file's problems."""
        return status_of(self.problems)

    @property
    def exit_status(self) -> int:
        """``starlog verify``'s exit status: 0 valid, 3 nonconformant, 1 refused or damaged."""
        return EXIT_STATUS[self.status]

    def verdict(self) -> str:
        """One line: valid, nonconformant, refused or damaged, with counts."""
        notes = len(self.problems) - len(self.errors) - len(self.warnings)
        what = f"{self.messages} messages, {self.channels} channels, {self.chunks} chunks"
        also = f", {notes} notes" if notes else ""
        status = self.status
        if status == "valid":
            return f"OK: {self.path} is a valid MCAP file ({what}{also})."
        if status == "nonconformant":
            rules = "; ".join(dict.fromkeys(p.rule for p in self.warnings))
            return (f"NONCONFORMANT: starlog reads {self.path} in full ({what}{also}), but it does not conform to the "
                    f"MCAP specification: {rules}. Rewrite it conforming with: starlog filter {self.path} -o OUT.mcap")
        kinds = ", ".join(sorted({p.kind for p in self.errors}))
        if status == "refused":
            return (f"REFUSED: {self.path} is valid MCAP ({what}{also}), but starlog refuses part of it: "
                    f"{len(self.errors)} errors ({kinds}; see above).")
        return (f"DAMAGED: {self.path} has {len(self.errors)} errors ({kinds}){also}"
                f"; read {what}. Keep what is intact with: starlog recover {self.path} -o RECOVERED.mcap")

    def to_dict(self) -> dict[str, Any]:
        return {"path": self.path, "ok": self.ok, "status": self.status, "size_bytes": self.size,
                "messages": self.messages, "chunks": self.chunks, "channels": self.channels,
                "verdict": self.verdict(), "problems": [p.to_dict() for p in self.problems]}


def status_of(problems: list[Problem]) -> str:
    """``damaged`` (an error other than a refusal), ``refused`` (valid MCAP, part of which starlog refuses:
    :data:`REFUSALS`), ``nonconformant`` (read in full, but it breaks a rule of the MCAP specification) or
    ``valid``."""
    errors = {p.kind for p in problems if p.severity == "error"}
    if errors:
        return "refused" if errors <= REFUSALS else "damaged"
    return "nonconformant" if any(p.severity == "warning" for p in problems) else "valid"




@dataclass
class ChainReport:
    """What :func:`verify_log` found: each file of the chain (first log first) and the chain's own problems.

    ``problems``, ``errors`` and the counts cover every file, so a report of a whole log (one file)
    reads as that file's :class:`VerifyReport`.
    """

    path: str
    files: list[VerifyReport] = field(default_factory=list)
    chain_problems: list[Problem] = field(default_factory=list)
    base_checked: bool = True  # False when the newest file is a layer checked alone
    missing_base: str = ""  # the base that is missing (or a file of its own chain), when one is

    @property
    def problems(self) -> list[Problem]:
        return [p for f in self.files for p in f.problems] + self.chain_problems

    @property
    def errors(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == "error"]

    @property
    def ok(self) -> bool:
        """No error: every starlog command reads the log in full."""
        return not self.errors

    @property
    def status(self) -> str:
        """The log's status, as :attr:`VerifyReport.status` says it of a file (a chain's own errors are damage)."""
        return status_of(self.problems)

    @property
    def exit_status(self) -> int:
        """``starlog verify``'s exit status (:data:`EXIT_STATUS`)."""
        return EXIT_STATUS[self.status]

    @property
    def size(self) -> int:
        return sum(f.size for f in self.files)

    @property
    def messages(self) -> int:
        return sum(f.messages for f in self.files)

    @property
    def chunks(self) -> int:
        return sum(f.chunks for f in self.files)

    @property
    def channels(self) -> int:
        return sum(f.channels for f in self.files)

    def verdict(self) -> str:
        """One line for the whole log."""
        if len(self.files) == 1 and self.base_checked and not self.chain_problems:
            return self.files[0].verdict()
        what = (f"a layer checked alone (its base was not checked: verify {self.path} without --file-only)"
                if not self.base_checked else
                f"a chain of {len(self.files)} files whose base {self.missing_base} could not be checked"
                if self.missing_base else f"a chain of {len(self.files)} files")
        status = self.status
        checked = "" if not self.base_checked else ", every base the file its layer was written on"
        if status == "valid":
            return f"OK: {self.path} is {what}: every file valid{checked}."
        if status == "nonconformant":
            files = ", ".join(f.path for f in self.files if f.status == "nonconformant")
            return (f"NONCONFORMANT: {self.path} is {what}, read in full by starlog{checked}; {files} does not "
                    "conform to the MCAP specification (see above). Write the log as one conforming file with: "
                    f"starlog filter {self.path} -o OUT.mcap")
        parts = [f"{kind} files: {', '.join(f.path for f in self.files if f.status == kind)}{why}"
                 for kind, why in (("damaged", " (keep what is intact with starlog recover)"),
                                   ("refused", " (valid MCAP, part of which starlog refuses: see above)"))
                 if any(f.status == kind for f in self.files)]
        errors = sorted({p.kind for p in self.chain_problems if p.severity == "error"})
        parts += [f"chain errors: {', '.join(errors)} (see above)"] if errors else []
        return f"{status.upper()}: {self.path} is {what}; {'; '.join(parts)}."

    def to_dict(self) -> dict[str, Any]:
        problems = [{**p.to_dict(), "file": f.path} for f in self.files for p in f.problems]
        problems += [{**p.to_dict(), "file": self.path} for p in self.chain_problems]
        return {"path": self.path, "ok": self.ok, "status": self.status, "verdict": self.verdict(),
                "size_bytes": self.size,
                "messages": self.messages, "chunks": self.chunks, "channels": self.channels,
                "problems": problems, "files": [f.to_dict() for f in self.files]}

    def lines(self, per_kind: int = 20) -> list[str]:
        """Every problem, at most ``per_kind`` of a kind per file (and of the chain), each file's verdict when
        there are several, and the verdict."""
        several = len(self.files) > 1
        lines = []
        for file in self.files:
            lines += [f"{file.path}:"] if several else []
            lines += _problem_lines(file.problems, per_kind)
            lines += [f"  {file.verdict()}"] if several else []
        return lines + _problem_lines(self.chain_problems, per_kind) + [self.verdict()]


def _problem_lines(problems: list[Problem], per_kind: int) -> list[str]:
    """One line per problem, at most ``per_kind`` of a kind, then how many more of each kind (all with --json)."""
    shown: dict[str, int] = {}
    lines = []
    for problem in problems:
        shown[problem.kind] = shown.get(problem.kind, 0) + 1
        if shown[problem.kind] <= per_kind:
            lines.append(problem.line())
    for kind, count in shown.items():
        if count > per_kind:
            lines.append(f"... {count - per_kind} more {kind} problems (all of them with --json)")
    return lines
