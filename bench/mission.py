"""Benchmark: a mission week of imperfect data through the live loop (``ttl run --adopt auto``).

Seven days (``--days``) are simulated by our simulator (Keplerian arms, all noises, the paper's
coefficients) with what LISA delivers: one glitch a day at a random time on a random test mass
(sizes drawn log-uniformly between LISA Pathfinder's, 1e-12 m/s, and a hundred times larger,
damping 5-300 s), the paper's MBHB1 merger in mid-run, a planned 7-h gap (NaN in eta and the
DWS readouts of the written file) and a coupling outside the 24 - a witness of MOSA 12's DWS on link 23,
one light travel time away - that switches on at day 3 (``witness:...;vary=step``).  The week
is replayed in 1-h segments through the five stage processes at the default cadence with
``--adopt auto``; every stage process is sampled with psutil while it runs.

Prints one JSON object: wall time and real-time factor (target >= 500: a week in under 20
minutes on 2 cores), per-stage CPU seconds and peak memory (target <= 1.5 GB each; the segment
it peaked at: the first fit recorded after the peak) with the
memory at the end of day 1 and at the end (flat or growing), the live model's size over time
(effects per fit), when the coupling was adopted against its onset, the model changes and
alerts, the fits against the segments outside the gap, and the last fit against the truth
(max |C_fit - C_true| [mm/rad], pull RMS).

``--source lisainstrument`` makes the week with outside code only (``tests/mission_week.py``:
lisainstrument's days and its own TTL coefficients, a blind coupling the pipeline does not name
switched on in day 3, lisaglitch's daily glitches, a lisagwresponse merger, a lisa-gap 7-h gap)
and replays lisainstrument's file itself; the issue's blind-week test (``tests/test_mission_week.py``)
runs it and checks the JSON.

Usage: ``.venv/bin/python bench/mission.py [--days 7] [--seed 1] [--source simulator|lisainstrument] [--keep DIR [--reuse]]``
"""

from __future__ import annotations

import argparse
import json
import shutil
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

from streamer.bus.topology import STAGES  # noqa: E402
from streamer.recording.recorder import read_recording  # noqa: E402
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
    return {
        "coupling_on_s": t_on,
        "injections": injections,
        "gap_s": list(GAP) if b <= days * DAY else None,
        "t0": 0.0,
        "duration": days * DAY,
    }


def make_week(data: Path, source: str, days: float, seed: int) -> dict:
    """Write the week at ``data``; returns its setup (what was injected where, see :func:`summarise`)."""
    if source == "simulator":
        return simulate(data, days, seed)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from mission_week import blind_week

    return blind_week(data, days=int(days), seed=seed)


def run_week(
    tmp: Path, source: str = "simulator", days: float = 7.0, seed: int = 1, timeout: float = 14400, reuse: bool = False
) -> dict:
    """Make the week in ``tmp`` (``reuse``: the week an earlier call left there, ``mission.h5``
    and ``mission.setup.json``, when both exist), replay it through ``ttl run --adopt auto`` at
    the default cadence, and return the JSON report (module docstring); the recordings stay in
    ``tmp / "rec" / "mission"`` (an earlier run's are removed)."""
    load_before = psutil.getloadavg()
    tmp.mkdir(parents=True, exist_ok=True)
    data, saved = tmp / "mission.h5", tmp / "mission.setup.json"
    t_sim = time.perf_counter()
    if reuse and data.exists() and saved.exists():
        setup = json.loads(saved.read_text())
    else:
        setup = make_week(data, source, days, seed)
        saved.write_text(json.dumps(setup))
    t_sim = time.perf_counter() - t_sim
    shutil.rmtree(tmp / "rec", ignore_errors=True)
    start, started = time.perf_counter(), time.time()
    cmd = [sys.executable, "-m", "streamer.tools.cli", "run", "--telemetry", str(data), "--run-id", "mission"]
    cmd += ["--recordings", str(tmp / "rec"), "--quiet", "--timeout", str(int(timeout)), "--adopt", "auto"]
    launcher = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    cpu, rss = watch_stages(launcher, start)
    wall = time.perf_counter() - start
    output = launcher.stdout.read() if launcher.stdout else ""
    result = summarise(tmp / "rec" / "mission", data, setup, wall, cpu, rss, started)
    result.update(
        {
            "benchmark": "mission",
            "source": source,
            "run_exit_status": launcher.returncode,
            "simulation_s": round(t_sim, 1),
            "load_average_before": [round(x, 2) for x in load_before],
            "load_average_after": [round(x, 2) for x in psutil.getloadavg()],
        }
    )
    if launcher.returncode != 0:
        result["run_output_tail"] = output[-3000:]
    return result


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=float, default=7.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--source", choices=("simulator", "lisainstrument"), default="simulator")
    ap.add_argument("--keep", type=Path, help="keep the data and recordings in this directory")
    ap.add_argument("--reuse", action="store_true", help="with --keep: replay the week kept there, if any")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmpdir:
        result = run_week(args.keep or Path(tmpdir), args.source, args.days, args.seed, reuse=args.reuse)
    print(json.dumps(result, indent=2))
    return 0 if result["run_exit_status"] == 0 else 1


def _transient(effect: str) -> bool:
    return effect.startswith(("glitch", "gate")) or effect == "linear-ttl"


def _truth(data: Path, setup: dict, fit) -> np.ndarray:
    """The true coefficients [m/rad] over the fit's window: lisainstrument's constant ones, or
    our simulator's truth file's mean."""
    if setup.get("truth") is not None:
        return np.asarray(setup["truth"], dtype=float)
    return FileTruth(data.with_name(data.stem + ".truth.h5")).mean(
        fit.header.meta["t_start"], fit.header.meta["t_stop"]
    )


def _peak_segments(rss: dict, fits: dict, started: float | None) -> dict:
    """Per stage, the index of the first fit the fitter recorded after the stage's memory
    peaked (from the fits' wall-clock ``publish_time``): the segment whose handling peaked."""
    if started is None:
        return {}
    recorded = sorted((m.publish_time / 1e9 - started, i) for i, m in fits.items() if m.publish_time)
    out = {}
    for stage, samples in rss.items():
        if samples:
            t_peak = max(samples, key=lambda s: s[1])[0]
            out[stage] = next((i for t, i in recorded if t >= t_peak), None)
    return out


def summarise(
    run_dir: Path, data: Path, setup: dict, wall: float, cpu: dict, rss: dict, started: float | None = None
) -> dict:
    """The JSON report of a finished run (see the module docstring); ``started``: the run's
    start [s since the epoch], to name the segment each stage's memory peaked at (the first
    fit recorded after the peak)."""
    fits = {}
    events, alerts = [], []
    for path in sorted(run_dir.glob("fitter*.mcap")):
        rec = read_recording(path)
        for m in rec.segments("fit"):
            fits.setdefault(m.header.index, m)
        events += [e for e in rec.json("events") if e.get("kind") in ("model", "excess")]
    if (run_dir / "monitor.mcap").exists():
        alerts = read_recording(run_dir / "monitor.mcap").json("alerts")
    t0, days = setup["t0"], setup["duration"] / DAY
    segments = int(np.ceil(setup["duration"] / HOUR - 1e-9))
    gap = setup["gap_s"]
    in_gap = set()
    if gap:  # wholly inside the gap (a segment partly in it is fitted on what it holds)
        in_gap = {i for i in range(segments) if gap[0] <= t0 + i * HOUR and t0 + (i + 1) * HOUR <= gap[1]}
    last = fits[max(fits)] if fits else None
    error = pull = None
    if last is not None:
        err = last.arrays["coefficients"] - _truth(data, setup, last)
        error = float(np.max(np.abs(err)) * 1e3)
        pull = float(np.sqrt(np.mean((err / last.arrays["sigma"]) ** 2)))
    adopted = [e for e in events if e.get("kind") == "model" and (e.get("details") or {}).get("by") == "adopt auto"]
    on_segment = int((setup["coupling_on_s"] - t0) // HOUR)
    # a coupling (not a glitch or gate) adopted: before the onset it is spurious
    couplings = [
        (e["details"]["from_index"], [str(x) for x in e["details"]["effects"] if not _transient(str(x))])
        for e in adopted
    ]
    couplings = [(i, c) for i, c in couplings if c]
    coupling_at = next((i for i, _ in couplings if i >= on_segment), None)
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
        "per_stage_peak_memory_segment": _peak_segments(rss, fits, started),
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
        "coupling_on_segment": on_segment,
        "coupling_adopted_from_segment": coupling_at,
        "couplings_adopted_before_the_onset": [c for i, c in couplings if i < on_segment],
        "couplings_in_the_model_at_end": [
            str(x) for x in (last.header.meta.get("model") or []) if not _transient(str(x))
        ]
        if last is not None
        else None,
        "glitches_in_the_model_at_end_older_than_a_day": [
            str(x)
            for x in (last.header.meta.get("model") or [])
            if str(x).startswith("glitch") and _glitch_time(str(x)) < last.header.meta["t_stop"] - DAY
        ]
        if last is not None
        else None,
        "alerts": [a.get("message") for a in alerts],
        "last_fit_max_error_mm_per_rad": error,
        "last_fit_pull_rms": pull,
    }


def _glitch_time(spec: str) -> float:
    """The ``t=`` of a glitch spec [s] (``glitch:t=...,``)."""
    return float(spec.split("t=", 1)[1].split(",", 1)[0].rstrip("s"))


if __name__ == "__main__":
    sys.exit(main())
