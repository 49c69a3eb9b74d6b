"""Shared fixtures: tiny simulated logs built with starlog's own writer.

Plain helpers that tests import (such as ``small_config``) live in ``tests/helpers.py``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from starlog.stages import simulate_log
from tests.helpers import small_config

pytest_plugins = ["tests.skip_check"]


@pytest.fixture(scope="session")
def sim_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small simulated log, shared read-only by tests (never modify it)."""
    path = tmp_path_factory.mktemp("sim") / "small.mcap"
    simulate_log(small_config(), path)
    return path
