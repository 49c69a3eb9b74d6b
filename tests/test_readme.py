"""The README's Python examples run as written; the docs stand alone (no notes from outside the repository)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from starlog.stages import simulate_log
from tests.helpers import small_config

README = Path(__file__).resolve().parent.parent / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(encoding="utf-8"), flags=re.S)


def test_readme_has_python_examples() -> None:
    assert len(BLOCKS) >= 2


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_python_block_runs(index: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    simulate_log(small_config(), tmp_path / "demo.mcap")  # the quick start's demo log, small
    exec(compile(BLOCKS[index], f"README.md python block {index}", "exec"), {"__name__": "readme"})


# ---------------------------------------------------------------- the repository stands alone
ROOT = README.parent
PAPER = ROOT / "docs" / "PAPER.md"
OUTSIDE_REFERENCES = re.compile(r"DESIGN(\.md| §)|\b[Ii]ssues? [0-9]")


def _text_files() -> list[Path]:
    files = [README, *sorted((ROOT / "docs").glob("*.md"))]
    for folder in ("starlog", "tests", "tools"):
        files += sorted((ROOT / folder).rglob("*.py"))
    return files


def test_no_file_cites_notes_or_tracking_numbers_outside_the_repository() -> None:
    found = [f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
             for path in _text_files()
             for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
             if OUTSIDE_REFERENCES.search(line)]
    assert not found, "\n".join(found)


def test_paper_reading_covers_every_equation_and_names_existing_modules() -> None:
    text = PAPER.read_text(encoding="utf-8")
    assert "docs/PAPER.md" in README.read_text(encoding="utf-8")
    for equation in range(1, 16):
        assert re.search(rf"\*\*eq\. {equation}\*\*", text, re.I), f"eq. {equation} is not read in docs/PAPER.md"
    for module in re.findall(r"`(starlog/[\w/]+\.py)`", text):
        assert (ROOT / module).is_file(), module
    anchors = {re.sub(r"[^\w\- ]", "", h.lower()).replace(" ", "-") for h in re.findall(r"^#+ (.+)$", text, re.M)}
    for path in [README, *ROOT.glob("docs/*.md")]:
        for anchor in re.findall(r"PAPER\.md#([\w-]+)", path.read_text(encoding="utf-8")):
            assert anchor in anchors, f"{path.name} links to a missing section #{anchor}"
        for anchor in re.findall(r"\]\(#([\w-]+)\)", text if path == PAPER else ""):
            assert anchor in anchors, f"docs/PAPER.md links to a missing section #{anchor}"
