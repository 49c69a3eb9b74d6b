"""Every shell block of the README and of docs/ runs as written, on small inputs, so that the docs cannot drift
from the code.

The blocks run in order in one folder, as a reader would type them: the README's quick start makes the log
(made small: 32x32 px, 1 star) the pages of docs/ use. A block this file does not run names the test that does,
or why no test can; every block is named here with its page, so that one moved or dropped fails the test.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import ROOT, doc_blocks, doc_pages

#: docs/BENCHMARKS.md's blocks run the benchmarks of tools/: speed measured on a quiet machine, not tests.
PAGES = [page for page in doc_pages() if page.name != "BENCHMARKS.md"]
BLOCKS = [(page.relative_to(ROOT).as_posix(), block) for page, block in doc_blocks("bash", PAGES)]
INSTALL = "python3 -m venv .venv && .venv/bin/pip install -q . && "

#: Blocks run here, by their first words, and their page.
RUN = {
    INSTALL: "README.md",
    "starlog centroid demo.mcap -o demo-cen.mcap": "docs/SLICES.md",
    "starlog filter demo-result.mcap -o demo-tracks.mcap": "docs/SLICES.md",
}

#: Blocks run elsewhere or not at all, by their first words: their page, and why.
NOT_RUN = {
    "python3 -m venv .venv && .venv/bin/pip install -q -e '.[test]'": (
        "README.md", "it runs this test suite"),
    "starlog run demo.mcap -o fwhm.mcap --config flux_fwhm.toml": (
        "docs/STAGES.md", "tests/test_custom_stages.py runs it, with the page's module and config"),
    "starlog flux_fwhm demo.mcap": (
        "docs/STAGES.md", "tests/test_custom_stages.py runs it, with the stage installed"),
    "starlog experiment -o results/": (
        "docs/EXPERIMENT.md", "minutes of work; tests/test_experiment.py runs the --quick experiment"),
    "dask scheduler": (
        "docs/CLUSTERS.md", "it needs a Dask cluster on a network; tests/test_batch.py runs a local one"),
    "starlog simulate -o camera.mcap --size 512x512": (
        "docs/LIVE.md", "a minute of frames at 300 Hz; tests/test_live.py runs live on a smaller log written at its "
                        "camera's rate"),
    "starlog run camera.mcap -o replay.mcap": (
        "docs/LIVE.md", "it needs the live run above; tests/test_live.py compares run with live"),
    "starlog simulate -o sky.mcap --size 384x384 --sky-attitude": (
        "docs/PROCESSING.md", "tests/test_solve.py runs it as written"),
    "starlog simulate -o sky.mcap --size 256x256 --sky-attitude": (
        "docs/PROCESSING.md", "tests/test_compensated_attitude.py runs it (smaller)"),
}


def _not_run(block: str) -> str | None:
    return next((why for start, (_, why) in NOT_RUN.items() if block.startswith(start)), None)


def _runnable(block: str) -> str:
    """The block as this environment runs it: the quick start's install done already (the suite runs in an
    installed starlog), its log small; a line needing a program that is not installed is left out."""
    if block.startswith(INSTALL):
        block = block.removeprefix(INSTALL).replace(".venv/bin/starlog", "starlog")
        block = block.replace("--frames 1200 ", "--frames 1200 --size 32x32 --stars 1 ")
    lines = [line for line in block.splitlines() if "| jq" not in line or shutil.which("jq")]
    return "\n".join(lines)


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("readme")


def test_every_shell_block_is_run_here_or_named() -> None:
    pages = {**RUN, **{start: page for start, (page, _) in NOT_RUN.items()}}
    found = {start: [p for p, b in BLOCKS if b.startswith(start)] for start in pages}
    assert found == {start: [page] for start, page in pages.items()}, "a block listed here left its page, or moved"
    assert BLOCKS[0][1].startswith(INSTALL), "the quick start's first command installs and runs the demo"


@pytest.mark.slow
@pytest.mark.parametrize("index", range(len(BLOCKS)), ids=[f"{page}-{i}" for i, (page, _) in enumerate(BLOCKS)])
def test_readme_shell_block_runs(index: int, folder: Path) -> None:
    page, block = BLOCKS[index]
    why = _not_run(block)
    if why is not None:
        pytest.skip(f"{page} shell block {index}: {why}")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    done = subprocess.run(["bash", "-eo", "pipefail", "-c", _runnable(block)], cwd=folder, env=env,
                          capture_output=True, text=True, timeout=900, check=False)
    assert done.returncode == 0, f"{page} shell block {index} failed:\n{block}\n{done.stdout}\n{done.stderr}"
