"""Benchmark: TDI (X2, Y2, Z2) of the data and of the 24 TTL regressors for one day with
time-varying (Keplerian) delays, ours against pytdi on the same data, in the same run.

pytdi gets the same work in its natural form: each combination is built once
(``X2_ETA.build``) and evaluated on the data and on each regressor's witness placed on its
link (zeros elsewhere); Tx witnesses are first delayed with ``pytdi.dsp.timeshift``.
Both use Lagrange order 31 for the data and 5 for nested delays, ``unit="phase"``
(``D x(t) = x(t - tau(t))``, docs/physics.md).

Prints one JSON object: both wall times, the ratio pytdi/ours (target >= 20), and the
agreement (max relative RMS difference over all outputs).

Usage: ``.venv/bin/python bench/tdi.py [--duration SECONDS]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=86400.0)
    args = ap.parse_args()

    from pytdi.dsp import timeshift
    from pytdi.michelson import X2_ETA, Y2_ETA, Z2_ETA

    from ttlcore.conventions import COEFFICIENT_NAMES, LINKS
    from ttlcore.tdi.regressors import ttl_witnesses
    from ttlcore.sim.simulator import SimulationConfig, simulate
    from ttlcore.tdi.data import compute_tdi

    tm, _ = simulate(SimulationConfig(duration=args.duration, orbit="keplerian", seed=1))

    start = time.perf_counter()
    ours = compute_tdi(tm)
    t_ours = time.perf_counter() - start

    start = time.perf_counter()
    delays = {f"d_{l}": tm.ltt[k] for k, l in enumerate(LINKS)}
    built = [c.build(delays, tm.fs, order=5) for c in (X2_ETA, Y2_ETA, Z2_ETA)]
    zeros = np.zeros(tm.size)
    ref_data = np.stack([b({f"eta_{l}": tm.eta[k] for k, l in enumerate(LINKS)}, order=31, unit="phase") for b in built])
    witnesses, index = ttl_witnesses(tm.dws_phi, tm.dws_eta)
    ref_regs = np.zeros_like(ours.regressors)
    for (link, extra), w in witnesses.items():
        for row, k in zip(w, index[(link, extra)]):
            if extra:
                row = timeshift(row, -tm.ltt[LINKS.index(extra[0])] * tm.fs, 31)
            meas = {f"eta_{l}": (row if l == link else zeros) for l in LINKS}
            for c, b in enumerate(built):
                ref_regs[c, k] = b(meas, order=31, unit="phase")
    t_pytdi = time.perf_counter() - start

    skip = int(120 * tm.fs)  # pytdi pads before the data with zeros, we give NaN

    def rel(a, b):
        """Largest relative RMS difference over outputs (outputs that are identically zero
        in pytdi, e.g. regressors on links a combination does not use, must be zero in ours)."""
        a, b = a[..., skip:], b[..., skip:]
        diff = np.sqrt(np.mean((a - b) ** 2, axis=-1))
        scale = np.sqrt(np.mean(b ** 2, axis=-1))
        used = scale > 0
        if np.any(diff[~used] > 0):
            return float("inf")
        return float(np.max(diff[used] / scale[used]))

    result = {
        "benchmark": "tdi",
        "duration_s": args.duration,
        "outputs": f"X2, Y2, Z2 of data + {len(COEFFICIENT_NAMES)} regressors",
        "ours_wall_time_s": round(t_ours, 2),
        "pytdi_wall_time_s": round(t_pytdi, 2),
        "ratio_pytdi_over_ours": round(t_pytdi / t_ours, 1),
        "target_ratio": 20,
        "meets_target": t_pytdi / t_ours >= 20,
        "max_relative_rms_difference_data": rel(ours.data, ref_data),
        "max_relative_rms_difference_regressors": rel(ours.regressors, ref_regs),
    }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
