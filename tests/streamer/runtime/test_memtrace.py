"""The per-segment memory trace of the stages (TTL_MEMTRACE)."""

import logging
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from streamer.runtime import memtrace
from streamer.runtime.memtrace import ENV, MemoryTrace, every_from_env, rss_mb


def test_env_variable_is_parsed_and_bad_values_named():
    assert every_from_env({}) == 0 and every_from_env({ENV: " 12 "}) == 12 and every_from_env({ENV: "0"}) == 0
    for bad in ("yes", "-1", "1.5"):
        with pytest.raises(ValueError, match=ENV):
            every_from_env({ENV: bad})


def test_off_by_default_logs_nothing(caplog):
    trace = MemoryTrace(0)
    with caplog.at_level(logging.INFO, logger="streamer.runtime.memtrace"):
        assert trace.segment(3) is None
    assert not caplog.records and not trace.on


def test_reports_memory_and_names_the_line_that_grew(caplog, monkeypatch):
    monkeypatch.setattr(memtrace, "PACKAGES", (*memtrace.PACKAGES, str(Path(__file__).parent)))
    was_tracing = tracemalloc.is_tracing()
    if was_tracing:
        tracemalloc.stop()  # started elsewhere with fewer frames
    kept = []
    try:
        trace = MemoryTrace(2)
        with caplog.at_level(logging.INFO, logger="streamer.runtime.memtrace"):
            for i in range(2):
                kept.append(np.ones(2**20))  # 8 MB per segment, held
                out = trace.segment(i)
        assert out["traced_mb"] >= 16 and out["peak_mb"] >= out["traced_mb"]
        assert out["rss_mb"] is None or out["rss_mb"] >= 16
        lines = [r.getMessage() for r in caplog.records]
        assert lines[0].startswith("memory after segment 0: rss ") and 2 < len(lines) <= 2 + memtrace.TOP_LINES
        # charged to the line here that asked numpy for the memory, not to numpy's own
        assert "test_memtrace.py" in lines[2] and "+16.00 MB" in lines[2], lines[2]
    finally:
        tracemalloc.stop()


def test_rss_is_read_where_there_is_proc():
    value = rss_mb()
    assert value is None or 1 < value < 1e6
