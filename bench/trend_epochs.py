"""Benchmark: false step alerts of the monitor's trends at model changes, with and without the
fits' models (ttlcore.diagnose.trends.TrendMonitor, "Model epochs"; issue 31).

Synthetic: 124 h of hourly one-day rolling fits (sigma 0.01 mm/rad per window) whose model
changes seven times - two couplings adopted, glitches added and dropped when they leave the
window - and whose 24 estimates jump at each change by a normal draw of ``--jump`` sigma each
(the fitter rebuilding its window under another model).  Prints the step and drift alerts
over ``--runs`` runs when the trends are given each fit's model and when they are not, and
how often a real 0.3 mm/rad step in one coefficient 20-34 h into the first coupling's epoch
is alerted within 3 h of its time.

``--run DIR``: the fits of a recorded run instead (``DIR/fitter*.mcap``, ``fit/summary``):
its alerts both ways, and the model epochs.

Usage: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/trend_epochs.py [--jump 1] [--runs 20] [--run DIR]``
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ttlcore.conventions import COEFFICIENT_NAMES  # noqa: E402
from ttlcore.diagnose.trends import TrendMonitor  # noqa: E402

HOUR, N, SIGMA, HOURS = 3600.0, 24, 0.01e-3, 124
LINEAR = ["linear-ttl"]
W1, W2 = "witness:source=12.eta,link=23,delay=2", "witness:source=23.phi,link=13,delay=2"


def glitch(t: int) -> str:
    return f"glitch:t={t}h,tm=12,beta=100s"


#: (first fit under the model, model)
MODELS = [
    (0, LINEAR),
    (20, LINEAR + [W1]),
    (33, LINEAR + [W1, glitch(30)]),
    (54, LINEAR + [W1]),
    (60, LINEAR + [W1, W2]),
    (75, LINEAR + [W1, W2, glitch(70)]),
    (96, LINEAR + [W1, W2]),
    (100, LINEAR + [W1, W2, glitch(98)]),
]


def model_at(k: int) -> list[str]:
    return next(m for start, m in reversed(MODELS) if k >= start)


def alerts_both_ways(fits) -> dict[bool, tuple[list, TrendMonitor]]:
    """``fits``: (index, t_start, t_stop, C, S, model) -> {given the models: (alerts, monitor)}."""
    out = {}
    for use in (False, True):
        mon, alerts = TrendMonitor(), []
        for i, ts, te, c, s, model in fits:
            alerts += mon.add(i, ts, te, c, s, model if use else None)
        out[use] = (alerts, mon)
    return out


def synthetic(seed: int, jump: float, step=None):
    rng = np.random.default_rng(seed)
    nseg = HOURS + N - 1
    seg_start = (np.arange(nseg) - (N - 1)) * HOUR
    truth = np.tile(rng.normal(0.0, 2e-3, 24), (nseg, 1))
    if step:
        p, t, size = step
        truth[:, p] += size * (seg_start >= t)
    seg = truth + rng.normal(0.0, SIGMA * math.sqrt(N), truth.shape)
    C = np.array([seg[k - N + 1 : k + 1].mean(axis=0) for k in range(N - 1, nseg)])
    t_stop = seg_start[N - 1 :] + HOUR
    offset = np.zeros(24)
    starts = {start for start, _ in MODELS if start}
    fits = []
    for k in range(HOURS):
        if k in starts:
            offset = offset + rng.normal(0.0, jump * SIGMA, 24)
        fits.append((k, t_stop[k] - N * HOUR, t_stop[k], C[k] + offset, np.full(24, SIGMA), model_at(k)))
    return fits


def recorded(run_dir: Path):
    from streamer.recording.recorder import read_recording

    summaries = {}
    for path in sorted(run_dir.glob("fitter*.mcap")):
        for d in read_recording(path).json("fit/summary"):
            summaries[d["index"]] = d
    return [
        (i, d["t_start"], d["t_end"], d["coefficients"], d["sigma"], d.get("model"))
        for i, d in sorted(summaries.items())
    ]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--jump", type=float, default=1.0, help="jump per coefficient at a model change [sigma]")
    p.add_argument("--runs", type=int, default=20)
    p.add_argument("--run", type=Path, help="a recorded run's directory instead of the synthetic runs")
    args = p.parse_args()
    if args.run:
        for use, (alerts, mon) in alerts_both_ways(recorded(args.run)).items():
            epochs = [(e.number, e.index, e.breaks) for e in mon.epochs]
            print(f"{'with' if use else 'without'} the fits' models: {len(alerts)} alert(s), epochs {epochs}")
            for a in alerts:
                print(f"    {a.message}")
        return 0
    counts = {use: {"step": 0, "drift": 0} for use in (False, True)}
    found = {False: 0, True: 0}
    for seed in range(args.runs):
        for use, (alerts, _) in alerts_both_ways(synthetic(seed, args.jump)).items():
            for a in alerts:
                counts[use][a.kind] += 1
        t = (40 + seed % 15) * HOUR
        for use, (alerts, _) in alerts_both_ways(synthetic(1000 + seed, args.jump, (5, t, 0.3e-3))).items():
            found[use] += any(
                a.kind == "step" and a.coefficient == COEFFICIENT_NAMES[5] and abs(a.t - t) <= 3 * HOUR for a in alerts
            )
    print(
        f"jumps of N(0, {args.jump:g} sigma) per coefficient at {len(MODELS) - 1} model changes, "
        f"{args.runs} runs of {HOURS} h"
    )
    for use in (False, True):
        c = counts[use]
        print(
            f"  {'with' if use else 'without'} the models: {c['step']} step alerts ({c['step'] / args.runs:.1f} "
            f"per run), {c['drift']} drift alerts; a real 0.3 mm/rad step found {found[use]}/{args.runs}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
