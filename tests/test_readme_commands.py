"""Every shell block of the README runs as written, on small inputs, so that the README cannot drift from the code.

The blocks run in order in one folder, as a reader would type them: the quick start's log (made
small: 32x32 px, 1 star) feeds the blocks after it. A block this file does not run names the test
that does, or why no test can.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parent.parent / "README.md"
BLOCKS = re.findall(r"```bash\n(.*?)```", README.read_text(encoding="utf-8"), flags=re.S)
INSTALL = "python3 -m venv .venv && .venv/bin/pip install -q . && "

#: Blocks run elsewhere or not at all, by their first words, and why.
NOT_RUN = {
    "python3 -m venv .venv && .venv/bin/pip install -q -e '.[test]'": "it runs this test suite",
    "starlog run demo.mcap -o fwhm.mcap --config flux_fwhm.toml": "tests/test_custom_stages.py runs it, with the "
                                                                  "README's module and config",
    "starlog flux_fwhm demo.mcap": "tests/test_custom_stages.py runs it, with the stage installed",
    "starlog experiment -o results/": "minutes of work; tests/test_experiment.py runs the --quick experiment",
    "dask scheduler": "it needs a Dask cluster on a network; tests/test_batch.py runs a local one",
    "starlog simulate -o camera.mcap --size 512x512": "a minute of frames at 300 Hz; tests/test_live.py runs live on "
                                                     "a smaller log written at its camera's rate",
    "starlog run camera.mcap -o replay.mcap": "it needs the live run above; tests/test_live.py compares run with live",
    "starlog simulate -o sky.mcap --size 384x384 --sky-attitude": "tests/test_solve.py runs it as written",
    "starlog simulate -o sky.mcap --size 256x256 --sky-attitude": "tests/test_compensated_attitude.py runs it "
                                                                  "(smaller)",
}


def _not_run(block: str) -> str | None:
    return next((why for start, why in NOT_RUN.items() if block.startswith(start)), None)


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
    assert all(any(b.startswith(start) for b in BLOCKS) for start in NOT_RUN), "a block listed here left the README"
    assert BLOCKS[0].startswith(INSTALL), "the quick start's first command installs and runs the demo"


@pytest.mark.slow
@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_shell_block_runs(index: int, folder: Path) -> None:
    block = BLOCKS[index]
    why = _not_run(block)
    if why is not None:
        pytest.skip(f"README shell block {index}: {why}")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    done = subprocess.run(["bash", "-eo", "pipefail", "-c", _runnable(block)], cwd=folder, env=env,
                          capture_output=True, text=True, timeout=900, check=False)
    assert done.returncode == 0, f"README shell block {index} failed:\n{block}\n{done.stdout}\n{done.stderr}"
