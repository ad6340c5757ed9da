"""Benchmark: one simulated mission day (all noises, Keplerian arms) against lisainstrument.

Runs, in the same invocation and on the same machine:

1. ``ttl simulate --duration 1d --orbit keplerian`` in a child process (wall time and the
   child's peak resident memory);
2. lisainstrument on a comparable one-day configuration (Keplerian orbit file from
   lisaorbits; laser, OMS, test-mass, backlink, jitter, DWS and TTL on; clock, modulation
   and ranging noise off), also in a child process.

Prints one JSON object: both wall times, the ratio ours/lisainstrument (target <= 0.25)
and our peak memory (target < 4 GB).

Usage: ``.venv/bin/python bench/simulate.py [--duration SECONDS] [--skip-lisainstrument]``
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_ttl import simulate_command

HERE = Path(__file__).resolve().parent


def run_ours(out: Path, duration: float) -> dict:
    cmd = simulate_command(out, str(duration), "--coeffs", "paper")
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    start = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    wall = time.perf_counter() - start
    peak_kib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return {"wall_time_s": wall, "peak_rss_bytes": peak_kib * 1024 if peak_kib > before else None}


def run_lisainstrument(out: Path, duration: float) -> dict:
    code = (
        f"import json, sys; sys.path.insert(0, {str(HERE)!r})\n"
        "from lisainstrument_reference import run_lisainstrument_day\n"
        f"print(json.dumps(run_lisainstrument_day({str(out)!r}, duration={duration!r}, orbits='keplerian')))\n"
    )
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
    wall = time.perf_counter() - start
    inner = json.loads(proc.stdout.strip().splitlines()[-1])
    inner.setdefault("wall_time_s", wall)
    inner["process_wall_time_s"] = wall
    return inner


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=86400.0, help="simulated seconds (default one day)")
    ap.add_argument("--skip-lisainstrument", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ours = run_ours(tmp / "ours.h5", args.duration)
        result = {
            "benchmark": "simulate",
            "duration_s": args.duration,
            "ours_wall_time_s": round(ours["wall_time_s"], 2),
            "ours_peak_memory_gb": round(ours["peak_rss_bytes"] / 1e9, 3) if ours["peak_rss_bytes"] else None,
            "cpu_count": os.cpu_count(),
        }
        if not args.skip_lisainstrument:
            ref = run_lisainstrument(tmp / "lisainstrument.h5", args.duration)
            result["lisainstrument_wall_time_s"] = round(ref["wall_time_s"], 2)
            result["lisainstrument_peak_memory_gb"] = round(ref.get("peak_rss_bytes", 0) / 1e9, 3) or None
            result["ratio_ours_over_lisainstrument"] = round(ours["wall_time_s"] / ref["wall_time_s"], 4)
            result["target_ratio"] = 0.25
            result["meets_target"] = result["ratio_ours_over_lisainstrument"] <= 0.25 and (
                result["ours_peak_memory_gb"] is None or result["ours_peak_memory_gb"] < 4
            )
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
