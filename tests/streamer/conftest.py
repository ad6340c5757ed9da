"""Fixtures of the streamer tests."""

from __future__ import annotations

import pytest
from streamer_testutil import Children


@pytest.fixture
def children(tmp_path):
    """Start child processes (tests/streamer/procs.py); all killed at the end of the test."""
    c = Children(tmp_path)
    yield c
    c.close()
