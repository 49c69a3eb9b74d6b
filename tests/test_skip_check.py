"""CI's check on skips (tests/skip_check.py): with CI set, a test skipped for a missing import fails the run,
naming it; a skip for another reason does not; without CI, both are plain skips."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

TESTS = {
    "test_skips.py": "import pytest\n\n"
                     "def test_needs_a_package():\n    pytest.importorskip('starlog_no_such_module')\n\n"
                     "def test_needs_a_program():\n    pytest.skip('chromium is not installed')\n\n"
                     "def test_runs():\n    pass\n",
    "test_module_skip.py": "import pytest\n\npytest.importorskip('starlog_no_such_module_either')\n\n"
                           "def test_never_runs():\n    pass\n",
}


def _pytest(folder: Path, *, ci: bool) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "CI"} | ({"CI": "true"} if ci else {})
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "tests.skip_check", "-p", "no:cacheprovider",
                           "-c", str(folder / "pytest.ini"), "--rootdir", str(folder), "-q", str(folder)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=120, check=False)


def test_ci_fails_on_a_skip_for_a_missing_import_and_names_it(tmp_path: Path) -> None:
    (tmp_path / "pytest.ini").write_text("[pytest]\n", encoding="utf-8")
    for name, text in TESTS.items():
        (tmp_path / name).write_text(text, encoding="utf-8")
    in_ci = _pytest(tmp_path, ci=True)
    assert in_ci.returncode == 1, in_ci.stdout + in_ci.stderr
    assert "2 skipped for a missing import" in in_ci.stdout
    assert "test_skips.py::test_needs_a_package: could not import 'starlog_no_such_module'" in in_ci.stdout
    assert "test_module_skip.py: could not import 'starlog_no_such_module_either'" in in_ci.stdout
    assert "test_needs_a_program" not in in_ci.stdout.split("skipped for a missing import")[1]
    elsewhere = _pytest(tmp_path, ci=False)
    assert elsewhere.returncode == 0, elsewhere.stdout + elsewhere.stderr
    assert "1 passed, 3 skipped" in elsewhere.stdout and "missing import" not in elsewhere.stdout
