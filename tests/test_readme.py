"""The Python examples of the README and docs/ run as written; the docs stand alone (no notes from outside the
repository)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from starlog.stages import simulate_log
from tests.helpers import ROOT, doc_blocks, doc_pages, small_config

README = ROOT / "README.md"
BLOCKS = [(page.relative_to(ROOT).as_posix(), block) for page, block in doc_blocks("python")]

#: The Python examples by a line each holds, and their page: one moved or dropped fails the test.
EXAMPLES = {'with LogReader("demo.mcap") as log:': "docs/PYTHON.md",
            'tracker = StarTracker(model="STATIC", sigma_floor=0.02)': "docs/PYTHON.md",
            '@stage(name="flux_fwhm"': "docs/STAGES.md"}


def test_the_docs_hold_their_python_examples() -> None:
    assert {line: [page for page, block in BLOCKS if line in block] for line in EXAMPLES} == {
        line: [page] for line, page in EXAMPLES.items()}


#: Frames an example simulates at most here (the examples work frame by frame: fewer frames, the same calls).
MAX_FRAMES = 100


def _runnable(block: str) -> str:
    """The example as this test runs it: a simulation it writes out as ``n_frames=N`` made at most
    :data:`MAX_FRAMES` long."""
    return re.sub(r"\bn_frames=(\d+)", lambda m: f"n_frames={min(int(m[1]), MAX_FRAMES)}", block)


@pytest.mark.parametrize("index", range(len(BLOCKS)), ids=[f"{page}-{i}" for i, (page, _) in enumerate(BLOCKS)])
def test_readme_python_block_runs(index: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    simulate_log(small_config(), tmp_path / "demo.mcap")  # the quick start's demo log, small
    page, block = BLOCKS[index]
    exec(compile(_runnable(block), f"{page} python block {index}", "exec"), {"__name__": "readme"})


# ---------------------------------------------------------------- the repository stands alone
PAPER = ROOT / "docs" / "PAPER.md"
OUTSIDE_REFERENCES = re.compile(r"DESIGN(\.md| §)|\b[Ii]ssues? [0-9]")


def _text_files() -> list[Path]:
    files = doc_pages()
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
    for path in doc_pages():
        for anchor in re.findall(r"PAPER\.md#([\w-]+)", path.read_text(encoding="utf-8")):
            assert anchor in anchors, f"{path.name} links to a missing section #{anchor}"
        for anchor in re.findall(r"\]\(#([\w-]+)\)", text if path == PAPER else ""):
            assert anchor in anchors, f"docs/PAPER.md links to a missing section #{anchor}"
