"""Benchmark: incremental against full updates of the rolling fit (ttlcore.estimate.rolling.RollingFit).

Simulates a day and a half (Keplerian arms, all noises, paper coefficients), streams it hour
by hour through TDIStream into two RollingFits with a one-day window and 1-h FFT segments:
the default (incremental updates between full refits every 6 h of data) and one that
refits fully at every segment.  Prints one JSON object: the CPU time per update of each
kind (single-threaded BLAS for a fair comparison), and the largest distance of the
incremental estimates from the full refit of the same window, in sigma, while the window
fills (fewer than 12 segments) and after, with the largest relative sigma difference.

Usage: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/rolling.py``
"""

from __future__ import annotations

import json
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from ttlcore.conventions import DAY  # noqa: E402
from ttlcore.estimate.fit import FitSettings  # noqa: E402
from ttlcore.estimate.rolling import RollingFit  # noqa: E402
from ttlcore.sim.simulator import SimulationConfig, simulate  # noqa: E402
from ttlcore.tdi.data import TDIStream  # noqa: E402


def main() -> int:
    tm, _ = simulate(SimulationConfig(duration=1.5 * DAY, orbit="keplerian", seed=3))
    settings = FitSettings(segment_duration=3600.0)
    sa, sb = TDIStream(), TDIStream()
    inc, full = RollingFit(settings, window_duration=DAY), RollingFit(settings, window_duration=DAY, full_every=None)
    cpu = {"incremental": [], "full": [], "full_every_segment": []}
    dist = {"filling": 0.0, "after": 0.0}
    sigma_rel = 0.0
    per_hour = int(round(3600 * tm.fs))
    for k in range(tm.size // per_hour):
        piece = tm.slice(k * per_hour, (k + 1) * per_hour)
        ta, tb = sa.push(piece), sb.push(piece)
        c = time.process_time()
        r_inc = inc.push(ta)
        cpu[r_inc.extra["update"]].append(time.process_time() - c)
        c = time.process_time()
        r_full = full.push(tb)
        cpu["full_every_segment"].append(time.process_time() - c)
        if r_inc.extra["update"] == "incremental":
            d = float(np.max(np.abs(r_inc.coefficients - r_full.coefficients) / r_full.sigma))
            key = "filling" if r_full.n_segments < 12 else "after"
            dist[key] = max(dist[key], d)
            sigma_rel = max(sigma_rel, float(np.max(np.abs(r_inc.sigma / r_full.sigma - 1))))
    result = {
        "benchmark": "rolling",
        "updates": {k: len(v) for k, v in cpu.items()},
        "cpu_s_median": {k: round(float(np.median(v)), 3) for k, v in cpu.items() if v},
        "max_distance_sigma": {k: round(v, 3) for k, v in dist.items()},
        "max_sigma_relative_difference": round(sigma_rel, 4),
        "target_update_s": 0.2,
    }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
