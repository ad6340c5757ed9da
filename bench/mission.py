"""Benchmark: a mission week of imperfect data through the live loop (``ttl run --adopt auto``).

Seven days (``--days``) are simulated by our simulator (Keplerian arms, all noises, the paper's
coefficients) with what LISA delivers: one glitch a day at a random time on a random test mass
(sizes drawn log-uniformly between LISA Pathfinder's, 1e-12 m/s, and a hundred times larger,
damping 5-300 s), the paper's MBHB1 merger in mid-run, a planned 7-h gap (NaN in every series
of the written file) and a coupling outside the 24 - a witness of MOSA 12's DWS on link 23,
one light travel time away - that switches on at day 3 (``witness:...;vary=step``).  The week
is replayed in 1-h segments through the five stage processes at the default cadence with
``--adopt auto``; every stage process is sampled with psutil while it runs.

Prints one JSON object: wall time and real-time factor (target >= 500: a week in under 20
minutes on 2 cores), per-stage CPU seconds and peak memory (target <= 1.5 GB each) with the
memory at the end of day 1 and at the end (flat or growing), the live model's size over time
(effects per fit), when the coupling was adopted against its onset, the model changes and
alerts, the fits against the segments outside the gap, and the last fit against the truth
(max |C_fit - C_true| [mm/rad], pull RMS).

Usage: ``.venv/bin/python bench/mission.py [--days 7] [--seed 1] [--keep DIR]``
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
import psutil

sys.path.insert(0, str(Path(__file__).parent))
from pipeline import watch_stages  # noqa: E402

from streamer.recorder import read_recording  # noqa: E402
from streamer.topology import STAGES  # noqa: E402
from ttlcore.conventions import DAY  # noqa: E402
from ttlcore.estimate.monitoring import FileTruth  # noqa: E402

HOUR = 3600.0

#: The coupling that switches on at day 3: a witness of 12.eta one light travel time away on
#: link 23 (the simulator injects one delay per part), its gain as the live-loop tests' (5e-3: the linear fit is
#: ~0.5 mm/rad off without it).
COUPLING = "witness:source=12.eta,link=23,delay=1,vary=step,t_step={t_on},all=5e-3"
#: The planned gap: 7 h from day 5.3 (NaN in eta and the DWS readouts).
GAP = (5.3 * DAY, 5.3 * DAY + 7 * HOUR)


def glitches(days: float, rng: np.random.Generator) -> list[str]:
    """One ``--inject`` glitch a day: random time (away from the day's edges), test mass,
    damping 5-300 s (the Pathfinder catalogue's range) and size 1e-12 .. 1e-10 m/s."""
    out = []
    for d in range(int(days)):
        t = (d + rng.uniform(0.1, 0.9)) * DAY
        tm = str(rng.choice(["12", "23", "31", "13", "32", "21"]))
        beta = float(np.exp(rng.uniform(np.log(5), np.log(300))))
        dv = float(10 ** rng.uniform(-12, -10)) * rng.choice([-1, 1])
        out.append(f"glitch:t={t:.1f},tm={tm},beta={beta:.1f},all={dv:.3g}")
    return out


def simulate(path: Path, days: float, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    t_on = 3 * DAY
    injections = [COUPLING.format(t_on=t_on), *glitches(days, rng)]
    cmd = [sys.executable, "-m", "ttlcore.cli.main", "simulate", "--duration", f"{days}d", "--orbit", "keplerian"]
    cmd += ["--coeffs", "paper", "--seed", str(seed), "--gw", "mbhb1", "--telemetry", str(path), "--quiet"]
    for spec in injections:
        cmd += ["--inject", spec]
    subprocess.run(cmd, check=True)
    a, b = GAP
    if b <= days * DAY:
        with h5py.File(path, "r+") as f:
            fs, t0 = float(f.attrs["fs"]), float(f.attrs["t0"])
            i, j = int((a - t0) * fs), int((b - t0) * fs)
            for name in ("eta", "dws/phi", "dws/eta"):
                ds = f[name]
                block = ds[:, i:j]
                block[...] = np.nan
                ds[:, i:j] = block
    return {"coupling_on_s": t_on, "injections": injections, "gap_s": list(GAP) if b <= days * DAY else None}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=float, default=7.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--keep", type=Path, help="keep the data and recordings in this directory")
    args = ap.parse_args()
    load_before = psutil.getloadavg()
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = args.keep or Path(tmpdir)
        tmp.mkdir(parents=True, exist_ok=True)
        data = tmp / "mission.h5"
        t_sim = time.perf_counter()
        setup = simulate(data, args.days, args.seed)
        t_sim = time.perf_counter() - t_sim
        start = time.perf_counter()
        cmd = [sys.executable, "-m", "streamer.cli", "run", "--telemetry", str(data), "--run-id", "mission"]
        cmd += ["--recordings", str(tmp / "rec"), "--quiet", "--timeout", "14400", "--adopt", "auto"]
        launcher = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        cpu, rss = watch_stages(launcher, start)
        wall = time.perf_counter() - start
        output = launcher.stdout.read() if launcher.stdout else ""
        run_dir = tmp / "rec" / "mission"
        result = summarise(run_dir, data, setup, args.days, wall, cpu, rss)
        result.update(
            {
                "benchmark": "mission",
                "run_exit_status": launcher.returncode,
                "simulation_s": round(t_sim, 1),
                "load_average_before": [round(x, 2) for x in load_before],
                "load_average_after": [round(x, 2) for x in psutil.getloadavg()],
            }
        )
        if launcher.returncode != 0:
            result["run_output_tail"] = output[-3000:]
    print(json.dumps(result, indent=2))
    return 0 if launcher.returncode == 0 else 1


def summarise(run_dir: Path, data: Path, setup: dict, days: float, wall: float, cpu: dict, rss: dict) -> dict:
    """The JSON report of a finished run (see the module docstring)."""
    fits = {}
    events, alerts = [], []
    for path in sorted(run_dir.glob("fitter*.mcap")):
        rec = read_recording(path)
        for m in rec.segments("fit"):
            fits.setdefault(m.header.index, m)
        events += [e for e in rec.json("events") if e.get("kind") in ("model", "excess")]
    if (run_dir / "monitor.mcap").exists():
        alerts = read_recording(run_dir / "monitor.mcap").json("alerts")
    segments = int(round(days * 24))
    gap = setup["gap_s"]
    in_gap = set()
    if gap:
        in_gap = {i for i in range(segments) if gap[0] <= i * HOUR and (i + 1) * HOUR <= gap[1]}
    truth = data.with_name(data.stem + ".truth.h5")
    last = fits[max(fits)] if fits else None
    error = pull = None
    if last is not None:
        c_true = FileTruth(truth).mean(last.header.meta["t_start"], last.header.meta["t_stop"])
        err = last.arrays["coefficients"] - c_true
        error = float(np.max(np.abs(err)) * 1e3)
        pull = float(np.sqrt(np.mean((err / last.arrays["sigma"]) ** 2)))
    adopted = [e for e in events if e.get("kind") == "model" and (e.get("details") or {}).get("by") == "adopt auto"]
    coupling_at = next(
        (
            e["details"]["from_index"]
            for e in adopted
            if any(str(s).startswith("witness:source=12.eta,link=23") for s in e["details"]["effects"])
        ),
        None,
    )
    per_stage_cpu = {s: round(sum(v for (n, _), v in cpu.items() if n == s), 1) for s in STAGES}
    day1 = wall / days  # the samples' wall clock at the end of the first day's worth of run time

    def at(samples, t):
        before = [r for s, r in samples if s <= t]
        return round(max(before) / 1e9, 3) if before else None

    return {
        "days": days,
        "segments": segments,
        "setup": setup,
        "wall_time_s": round(wall, 1),
        "real_time_factor": round(days * DAY / wall, 0),
        "target_real_time_factor": 500,
        "per_stage_cpu_s": per_stage_cpu,
        "per_stage_peak_memory_gb": {s: round(max((r for _, r in rss[s]), default=0) / 1e9, 3) for s in STAGES},
        "per_stage_memory_gb_after_day_1_and_at_end": {s: [at(rss[s], day1), at(rss[s], wall)] for s in STAGES},
        "target_peak_memory_gb": 1.5,
        "fits": len(fits),
        "segments_outside_gap": segments - len(in_gap),
        "segments_outside_gap_without_fit": sorted(set(range(segments)) - in_gap - set(fits)),
        "model_size_per_fit": {i: len(fits[i].header.meta.get("model") or []) for i in sorted(fits)},
        "model_at_end": last.header.meta.get("model") if last is not None else None,
        "model_changes": [
            {k: (e.get("details") or {}).get(k) for k in ("from_index", "by", "effects", "removed")}
            for e in events
            if e.get("kind") == "model"
        ],
        "excess_events": [e.get("index") for e in events if e.get("kind") == "excess"],
        "coupling_on_segment": int(setup["coupling_on_s"] // HOUR),
        "coupling_adopted_from_segment": coupling_at,
        "alerts": [a.get("message") for a in alerts],
        "last_fit_max_error_mm_per_rad": error,
        "last_fit_pull_rms": pull,
    }


if __name__ == "__main__":
    sys.exit(main())
