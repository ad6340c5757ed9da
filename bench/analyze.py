"""Benchmark: ``ttl analyze`` of one simulated day (Keplerian orbits, all noises, paper
coefficients, with its truth file): wall time and peak memory of the process.

The day is simulated once into a temporary directory (or ``--data FILE`` is used); then
``ttl analyze FILE --truth FILE.truth.h5 --out DIR`` runs in a fresh process, whose wall
time, CPU time (user + system: on a shared machine the wall time also measures the
other processes) and peak resident memory (``ru_maxrss`` of the child) are measured.  Targets: <= 10 s
and <= 1.5 GB.  The step timings written by analyze to ``fit.json`` are included.

Prints one JSON object.

Usage: ``.venv/bin/python bench/analyze.py [--data FILE] [--duration SECONDS] [--keep DIR]``
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_ttl import TTL, simulate_command


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, help="telemetry file to analyse (default: simulate one day)")
    ap.add_argument("--duration", default="1d", help="length of the simulated data (default 1d)")
    ap.add_argument("--keep", type=Path, help="directory for the simulated day and the outputs (kept)")
    args = ap.parse_args()

    tmp = tempfile.TemporaryDirectory(prefix="bench-analyze-") if args.keep is None else None
    work = Path(tmp.name) if tmp else args.keep
    work.mkdir(parents=True, exist_ok=True)
    data = args.data
    if data is None:
        data = work / "day.h5"
        if not data.exists():
            subprocess.run(simulate_command(data, args.duration), check=True)
    truth = data.with_name(data.name.replace(".h5", ".truth.h5"))
    cmd = [*TTL, "analyze", str(data), "--out", str(work / "analysis")]
    if truth.exists():
        cmd += ["--truth", str(truth)]
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, env=dict(os.environ))
    # the rusage of this one child (RUSAGE_CHILDREN would also hold the simulation's peak)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"ttl analyze failed with exit code {proc.returncode}: {' '.join(cmd)}")
    peak_bytes = usage.ru_maxrss * 1024  # Linux: kB
    fit = json.loads((work / "analysis" / "fit.json").read_text())
    result = {
        "benchmark": "analyze",
        "data": str(data),
        "samples": fit["data"]["size"],
        "wall_time_s": round(wall, 2),
        "cpu_time_s": round(usage.ru_utime + usage.ru_stime, 2),
        "peak_rss_gb": round(peak_bytes / 1e9, 3),
        "target_wall_time_s": 10,
        "target_peak_rss_gb": 1.5,
        "meets_targets": wall <= 10 and peak_bytes <= 1.5e9,
        "steps_s": fit.get("timings_s"),
        "chi2_dof": fit.get("chi2_dof"),
    }
    print(json.dumps(result, indent=2))
    if tmp:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
