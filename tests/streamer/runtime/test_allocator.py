"""glibc's allocator settings of a stage process (streamer.runtime.allocator)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from streamer.runtime import allocator

ROOT = Path(__file__).resolve().parents[3]
GLIBC = allocator._glibc() is not None


def test_bad_values_name_the_setting():
    for kw in ({"mmap_threshold": 0}, {"arena_max": -1}, {"mmap_threshold": 1.5}, {"arena_max": True}):
        with pytest.raises(ValueError, match="allocator M_"):
            allocator.configure(**kw, environ={})


def test_the_user_environment_wins():
    env = {allocator.ENV_MMAP_THRESHOLD: "65536", allocator.ENV_ARENA_MAX: "2"}
    assert allocator.configure(arena_max=2, environ=env) == {}
    assert allocator.configure(mmap_threshold=None, environ={}) == {}


@pytest.mark.skipif(not GLIBC, reason="glibc only: elsewhere nothing is set")
def test_freed_large_blocks_go_back_to_the_system():
    """After a burst of large temporaries interleaved with small blocks that stay, the heap
    keeps the large ones (glibc's dynamic threshold has risen) unless the threshold is
    fixed: RSS after freeing, in a fresh process each way."""
    code = f"""
import sys
sys.path.insert(0, {str(ROOT)!r})
from streamer.runtime import allocator
from streamer.runtime.memtrace import rss_mb
if sys.argv[1] == "fixed":
    assert allocator.configure(environ={{}}) == {{"M_MMAP_THRESHOLD": allocator.MMAP_THRESHOLD}}
import numpy as np
a = np.ones(2 << 20); del a          # one 16-MB mmap'd block freed: glibc raises its threshold to 16 MB
base = rss_mb()
pairs = [(np.ones(1 << 19), np.ones(200)) for _ in range(40)]   # 4 MB blocks, each with a small one after it
small = [b for _, b in pairs]       # the small blocks stay: the heap cannot shrink below them
del pairs
print(rss_mb() - base)
"""
    env = {"PATH": "/usr/bin:/bin"}
    kept = {
        how: float(
            subprocess.run(
                [sys.executable, "-c", code, how], capture_output=True, text=True, check=True, env=env
            ).stdout
        )
        for how in ("dynamic", "fixed")
    }
    assert kept["dynamic"] > 100 and kept["fixed"] < 20, kept
