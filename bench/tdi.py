"""Benchmark: TDI (X2, Y2, Z2) of the data and of the 24 TTL regressors with time-varying
(Keplerian) delays, ours against pytdi on the same simulated data, in the same process.

pytdi is used the natural way: each combination built once (``X2_ETA.build``, its default
delay order 5) and evaluated (its default order 31, ``unit="phase"``, i.e.
``D x(t) = x(t - tau(t))`` as in docs/physics.md) on the data and on each regressor's
witness placed on its link, with the scalar 0 for the five other links; Tx witnesses are
first delayed with ``pytdi.dsp.timeshift`` (order 31), as the simulator forms them
(``tests/pytdi_reference.py``).  Ours is
:func:`ttlcore.tdi.data.compute_tdi` (the block engine :mod:`ttlcore.tdi.engine`).

Accuracy, reported for each duration:

- ``full_band``: largest relative RMS difference over the outputs (data, Rx and Tx
  regressors separately), all frequencies up to Nyquist.
- ``fit_band``: the same after the fit's anti-alias low-pass (0.9-1.1 Hz Kaiser FIR,
  :func:`ttlcore.tdi.data.lowpass_taps`) and decimation to 2 Hz, i.e. what the fit uses.

Prints one JSON object with, per duration, both wall times, the ratio pytdi/ours (target
>= 10, aim 20) and the agreement; and the growth of our time per sample from the shortest
to the longest duration (1 = linear).

Usage: ``.venv/bin/python bench/tdi.py [--durations SECONDS ...]`` (default 7200 86400)
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def _load_reference():
    """``tests/pytdi_reference.py`` loaded by path (the same reference as the tests; putting
    ``tests/`` on ``sys.path`` would shadow the ``ttlcore`` package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "pytdi_reference", Path(__file__).resolve().parents[1] / "tests" / "pytdi_reference.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.pytdi_natural


def relative_rms(a, b, skip):
    """Largest relative RMS difference of ``a`` from ``b`` over outputs (last axis is time;
    outputs identically zero in ``b`` must be zero in ``a``)."""
    a, b = a[..., skip:], b[..., skip:]
    ok = np.isfinite(a) & np.isfinite(b)
    diff = np.sqrt(np.sum(np.where(ok, a - b, 0.0) ** 2, axis=-1))
    scale = np.sqrt(np.sum(np.where(ok, b, 0.0) ** 2, axis=-1))
    used = scale > 0
    if np.any(diff[~used] > 0):
        return float("inf")
    return float(np.max(diff[used] / scale[used]))


def run(duration: float) -> dict:
    from ttlcore.sim.simulator import SimulationConfig, simulate
    from ttlcore.tdi.data import compute_tdi

    tm, _ = simulate(SimulationConfig(duration=duration, orbit="keplerian", seed=1))

    start = time.perf_counter()
    ours = compute_tdi(tm)
    t_ours = time.perf_counter() - start

    start = time.perf_counter()
    ref_data, ref_regs = _load_reference()(tm)
    t_pytdi = time.perf_counter() - start

    skip = int(120 * tm.fs)  # pytdi pads before the data with zeros, we give NaN
    rx = np.array([name.endswith(".rx") for name in ours.names])
    ref = replace(ours, data=ref_data, regressors=ref_regs)
    low_ours, low_ref = ours.decimated(2), ref.decimated(2)
    return {
        "duration_s": duration,
        "samples": tm.size,
        "ours_wall_time_s": round(t_ours, 3),
        "pytdi_wall_time_s": round(t_pytdi, 2),
        "ratio_pytdi_over_ours": round(t_pytdi / t_ours, 1),
        "agreement_full_band": {
            "data": relative_rms(ours.data, ref_data, skip),
            "rx_regressors": relative_rms(ours.regressors[:, rx], ref_regs[:, rx], skip),
            "tx_regressors": relative_rms(ours.regressors[:, ~rx], ref_regs[:, ~rx], skip),
        },
        "agreement_fit_band": {
            "data": relative_rms(low_ours.data, low_ref.data, skip // 2),
            "regressors": relative_rms(low_ours.regressors, low_ref.regressors, skip // 2),
        },
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--durations", type=float, nargs="+", default=[7200.0, 86400.0])
    args = ap.parse_args()
    runs = [run(d) for d in args.durations]
    first, last = runs[0], runs[-1]
    growth = (last["ours_wall_time_s"] / last["samples"]) / (first["ours_wall_time_s"] / first["samples"])
    longest = max(runs, key=lambda r: r["duration_s"])
    result = {
        "benchmark": "tdi",
        "outputs": "X2, Y2, Z2 of data + 24 regressors",
        "runs": runs,
        "time_per_sample_growth_longest_over_shortest": round(growth, 2),
        "target_ratio": 10,
        "aim_ratio": 20,
        "meets_target": longest["ratio_pytdi_over_ours"] >= 10,
    }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
