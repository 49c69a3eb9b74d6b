"""The targets of a benchmark run: each one judged, and the run's exit status.

A target is PASS or FAIL; ``n/a`` when this run cannot judge it (e.g. ``--quick`` inputs too small
for a target set for the full run); ``MISS`` when it is informational (its miss is printed but does
not fail the run, e.g. a wall-clock figure that other jobs on a shared machine decide). Each
``n/a`` or informational target carries one line saying why; each distinct reason is printed once.
The exit status is 1 when a judged target failed, else 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["Targets"]


@dataclass(frozen=True)
class _Target:
    text: str
    ok: bool
    not_judged: str = ""  # why this run cannot judge it
    informational: str = ""  # why a miss does not fail the run

    @property
    def verdict(self) -> str:
        if self.not_judged:
            return "n/a"
        if self.ok:
            return "PASS"
        return "MISS" if self.informational else "FAIL"


@dataclass
class Targets:
    """The targets of one run, in the order they were checked."""

    items: list[_Target] = field(default_factory=list)

    def check(self, text: str, ok: bool, *, not_judged: str = "", informational: str = "") -> bool:
        """Record a target (``text`` states figure and limit); ``ok`` is returned for the caller's own use."""
        self.items.append(_Target(text, bool(ok), not_judged, informational))
        return bool(ok)

    def count(self, verdict: str) -> int:
        return sum(t.verdict == verdict for t in self.items)

    def report(self) -> int:
        """Print every target's verdict, each reason once, a summary line; return the exit status."""
        print("\n# targets")
        for target in self.items:
            print(f"{target.verdict:<5} {target.text}")
        for reason in dict.fromkeys(t.not_judged for t in self.items if t.not_judged):
            print(f"# n/a: {reason}")
        for reason in dict.fromkeys(t.informational for t in self.items if t.informational and not t.not_judged):
            print(f"# informational (a miss does not fail the run): {reason}")
        passed, failed, judged = self.count("PASS"), self.count("FAIL"), len(self.items) - self.count("n/a")
        met = f"{passed}/{judged} targets met" if judged else "no target judged"
        print(f"# {met}, {failed} failed, {self.count('MISS')} informational missed, "
              f"{self.count('n/a')} not judged in this run")
        return 1 if failed else 0
