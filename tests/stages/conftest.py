"""Fixtures of the stage tests."""

from __future__ import annotations

import pytest
from ttl_testutil import Procs


@pytest.fixture
def procs(tmp_path):
    """Start child processes; all (and their children) killed at the end of the test."""
    p = Procs(tmp_path)
    yield p
    p.close()
