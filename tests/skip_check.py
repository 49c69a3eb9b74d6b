"""A pytest plugin (loaded by ``conftest.py``): with ``CI`` set in the environment, the run fails when a test
was skipped because a module could not be imported (``pytest.importorskip``), and names each such test.

CI installs every package a test imports (``.ci/run``): a test skipping there for want of one would let a
change that breaks what it tests land green. Skips for other reasons (a program such as Chromium missing, a
documentation block another test runs) stay skips, each with its reason (``-ra``).
"""

from __future__ import annotations

import os
from typing import Any

import pytest


def raised_by_importorskip(excinfo: Any) -> bool:
    """Whether ``excinfo`` (a test's or a module's outcome) is a skip raised by ``pytest.importorskip``."""
    if excinfo is None or not isinstance(excinfo.value, pytest.skip.Exception):
        return False
    tb = excinfo.tb
    while tb is not None:
        code = tb.tb_frame.f_code
        if code.co_name == "importorskip" and "_pytest" in code.co_filename:
            return True
        tb = tb.tb_next
    return False


class ImportSkips:
    """The tests and modules skipped for a missing import; the session fails on any when ``CI`` is set."""

    def __init__(self) -> None:
        self.found: list[str] = []

    def _note(self, where: str, excinfo: Any) -> None:
        if raised_by_importorskip(excinfo):
            self.found.append(f"{where}: {excinfo.value.msg}")

    def pytest_runtest_makereport(self, item: pytest.Item, call: pytest.CallInfo[None]) -> None:
        self._note(item.nodeid, call.excinfo)

    @pytest.hookimpl(wrapper=True)
    def pytest_make_collect_report(self, collector: pytest.Collector) -> Any:
        report = yield
        call = getattr(report, "call", None)  # pytest keeps the collection's CallInfo on its report, for a while
        if report.skipped and call is not None:
            self._note(report.nodeid, call.excinfo)
        return report

    def pytest_sessionfinish(self, session: pytest.Session) -> None:
        if not self.found or not os.environ.get("CI"):
            return
        reporter = session.config.pluginmanager.get_plugin("terminalreporter")
        if reporter is not None:
            reporter.ensure_newline()
            reporter.write_sep("=", f"{len(self.found)} skipped for a missing import (CI installs every package "
                                    "the tests use: see .ci/run)", red=True)
            for line in self.found:
                reporter.write_line(line)
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_configure(config: pytest.Config) -> None:
    config.pluginmanager.register(ImportSkips(), "starlog-import-skips")
