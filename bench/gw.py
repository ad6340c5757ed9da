"""Benchmark: GW link responses of one mission day at 4 Hz, per source.

For each source of ``--gw`` (hmcnc, ztfj1539, galaxy, sgwb, mbhb1, mbhb2) the time the
simulator's injection hook takes to make its six link responses over the day (Keplerian
orbit, 3-h chunks as ``ttl simulate``), and the daily RMS of the responses (the galaxy's is
the paper's "strain RMS", 4.8e-22 / 5.9e-22). Prints one JSON object.

Usage: ``.venv/bin/python bench/gw.py [--duration SECONDS] [--sources a,b]``
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def main() -> None:
    from ttlcore.gw.injection import parse_gw_spec
    from ttlcore.sim.simulator import NoiseSwitches, SimulationConfig, Simulator

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=86400.0)
    ap.add_argument("--sources", default="hmcnc,ztfj1539,galaxy,sgwb,mbhb1,mbhb2")
    args = ap.parse_args()
    out = {"duration_s": args.duration, "fs_hz": 4.0, "orbit": "keplerian", "sources": {}}
    for name in args.sources.split(","):
        inj = parse_gw_spec(name, duration=args.duration, seed=1)
        cfg = SimulationConfig(
            duration=args.duration, orbit="keplerian", seed=1, noises=NoiseSwitches.parse("none"), injections=inj
        )
        start = time.perf_counter()
        sq, n = 0.0, 0
        for _, truth in Simulator(cfg).chunks():
            y = truth[f"injections/{inj[0].name}"]
            sq += float(np.sum(y**2))
            n += y.size
        out["sources"][name] = {"wall_time_s": round(time.perf_counter() - start, 2), "rms_links": (sq / n) ** 0.5}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
