"""Plain helpers shared by the tests (fixtures live in ``conftest.py``)."""

from __future__ import annotations

import re
from pathlib import Path

from starlog.io import LogWriter
from starlog.sim import CameraModel, Jitter, SimulationConfig


def small_config(**overrides: object) -> SimulationConfig:
    """A small, fast simulated dataset (64x48 px, 20 frames, 3 stars)."""
    params: dict[str, object] = dict(width=64, height=48, n_stars=3, n_frames=20, fps=100.0, margin=8.0,
                                     jitter=(Jitter(frequency_hz=7.0, amplitude_px=0.1),), seed=3,
                                     camera=CameraModel(read_noise=3.0, bias=100.0))
    params.update(overrides)
    return SimulationConfig(**params)  # type: ignore[arg-type]


def killed_writer_bytes(writer: LogWriter) -> bytes:
    """What a writer killed now leaves: the header, every chunk and its message indexes flushed, no summary
    and no footer. The writer is then aborted (its temporary file removed)."""
    writer.flush()
    data = writer._tmp_path.read_bytes()
    writer.abort()
    return data


ROOT = Path(__file__).resolve().parent.parent


def doc_pages() -> list[Path]:
    """The documentation in reading order: README.md (its quick start makes the logs later pages use),
    then every page of docs/ by name."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def doc_blocks(language: str, pages: list[Path] | None = None) -> list[tuple[Path, str]]:
    """Every fenced ``language`` block of ``pages`` (default :func:`doc_pages`), in reading order, with its page."""
    return [(page, block) for page in (doc_pages() if pages is None else pages)
            for block in re.findall(rf"```{language}\n(.*?)```", page.read_text(encoding="utf-8"), flags=re.S)]


def doc_section(heading: str) -> str:
    """The text of the one section of the documentation titled ``heading`` (a Markdown heading line), up to the
    next heading of its level or above."""
    found = []
    for page in doc_pages():
        text = page.read_text(encoding="utf-8")
        match = re.search(rf"^{re.escape(heading)}$", text, flags=re.M)
        if match:
            level = len(heading) - len(heading.lstrip("#"))
            end = re.compile(rf"^#{{1,{level}}} ", flags=re.M).search(text, match.end())
            found.append(text[match.start():end.start() if end else len(text)])
    assert len(found) == 1, f"{len(found)} sections of the documentation are titled {heading!r}"
    return found[0]
