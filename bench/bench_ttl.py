"""What the benchmarks share: the ``ttl`` command of this interpreter's ttlcore, and the
simulated data they measure on (``python bench/<name>.py`` finds this module beside it)."""

from __future__ import annotations

import sys
from pathlib import Path

#: ``ttl`` (the science commands) of this interpreter's ttlcore
TTL = [sys.executable, "-m", "ttlcore.cli.main"]


def simulate_command(out: Path, duration: str, *extra: str) -> list[str]:
    """``ttl simulate`` of ``duration`` (``1d``, ``12h`` or seconds) on Keplerian orbits, seed 1,
    ``extra`` options, into the telemetry file ``out`` (its truth file beside it), quietly."""
    options = ["--duration", duration, "--orbit", "keplerian", "--seed", "1", *extra]
    return [*TTL, "simulate", *options, "--out", str(out), "--quiet"]
