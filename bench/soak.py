"""Soak run: a long ``ttl run`` (7 simulated days in 1-h segments by default), the memory
(RSS) and the per-segment latency of every stage against the segment index, with a verdict
per stage: flat or growing.

    python bench/soak.py                      # 7 days, 1-h segments (168 segments)
    python bench/soak.py --days 3 --segment 10min
    python bench/soak.py --days 0.5           # a quick look (too short for a verdict)
    TTL_MEMTRACE=24 python bench/soak.py --keep DIR   # what grows: see streamer/runtime/memtrace.py

What is measured
----------------
* **RSS per segment.**  Every stage process, and the run's Zenoh router (``ttl router``,
  against the replayer's segments: every message goes through it), is sampled with psutil
  every ``--interval`` seconds; a sample belongs to the segment the stage handled last (its own progress, as the
  launcher verified it on ``ttl/<run>/control/board/<stage>``), and a segment's RSS is the
  median of its samples.  Samples before the first segment (imports, set-up) and after the
  last one (waiting for the stop, closing the files) are left out.
* **Latency per segment.**  For a stage, the time between its upstream's report of segment
  ``i`` and its own; for the replayer, the time between two consecutive segments.
* **Load.**  The 1-minute load average of the machine, sampled with the RSS (mean and max):
  the machine is shared, and latencies scale with it.

Slopes, warm-up, noise and the verdict
--------------------------------------
For each series ``y_i`` (RSS [MB] or latency [s] of segment ``i``) the bench fits a straight
line by least squares twice: over the **whole run**, start-up included, and **after the
warm-up**, segments ``i >= W`` with ``W`` the segments of ``--warmup`` (one day by default:
the fitter's one-day window is then full; the other stages reach their working set within
the first few segments).  After the warm-up it reports the slope ``b``, its standard error
``se_b`` (ordinary least squares), and the spread ``s`` of the series about the line (the
standard deviation of the residuals: allocator churn, the fitter's periodic adequacy refit,
GC, the machine's load).

The **growth over the run** is the post-warm-up slope extrapolated over the whole run,
``G = b * N`` (``N`` segments), and the **noise** is ``2 s`` (at least 0.1 MB for the RSS:
:data:`MIN_NOISE`).  The verdict:

* ``"flat"`` when ``G <= 2 s``: over a run as long as this one the series would not climb
  out of its own scatter (a series that falls is flat);
* ``"growing"`` when ``G > 2 s`` and the slope is significant, ``b > 2 se_b``;
* ``"unresolved"`` when ``G > 2 s`` but ``b <= 2 se_b``: the slope is not distinguishable
  from zero with so few segments after the warm-up (a longer run decides);
* null when fewer than three segments follow the warm-up.

``se_b`` assumes independent residuals; allocator steps make them correlated, so a
``"growing"`` verdict is confirmed with ``TTL_MEMTRACE`` (what grows, and whether Python
holds it) before it is called a leak.  ``docs/operations.md`` (Measuring) has the measured
numbers.

Prints one JSON object; exit status 1 when the run failed.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from streamer.bus.keys import from_ranges  # noqa: E402
from streamer.bus.session import Bus, SessionSettings, free_port  # noqa: E402
from streamer.runtime.memtrace import ENV as MEMTRACE_ENV  # noqa: E402
from ttlcore.conventions import DAY, parse_duration  # noqa: E402

UPSTREAM = {"tdi_builder": "replayer", "fitter": "tdi_builder", "subtractor": "fitter", "monitor": "subtractor"}
#: Processes that are not stages, sampled against the progress of a stage: the router's RSS
#: against the segments the replayer has published.
CLOCK = {"router": "replayer"}
#: Noise of a series: this many standard deviations of its residuals about the fitted line.
NOISE_SIGMAS = 2.0
#: Smallest noise of an RSS series [MB]: a process whose RSS hardly moves (the router: 10 kB
#: over the 3-day run) has a spread of a few kB, and a growth of a few pages over the whole
#: run would otherwise count as "growing".  0.1 MB over a run is 0.2 kB per segment of the
#: 3-day, 10-min run (11 MB over a year of 10-min segments).
MIN_NOISE = {"mb": 0.1, "s": 0.0}


def line_fit(x, y) -> dict | None:
    """Least-squares line through ``(x, y)``: slope, its standard error and the residuals'
    standard deviation (None with fewer than three finite points)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < 3 or np.ptp(x) == 0:
        return None
    b, a = np.polyfit(x, y, 1)
    resid = y - (a + b * x)
    s = float(np.sqrt(np.sum(resid**2) / (x.size - 2)))
    se = s / float(np.sqrt(np.sum((x - x.mean()) ** 2)))
    return {"slope": float(b), "slope_stderr": se, "spread": s, "points": int(x.size)}


def assess(series: dict[int, float], warmup: int, total: int, unit: str, digits: int) -> dict:
    """Whole-run and post-warm-up slopes of ``series`` (segment -> value in ``unit``) [unit per
    segment], the growth over the run extrapolated from the post-warm-up slope and the noise
    [unit], and the verdict (module docstring)."""
    ks = sorted(series)
    whole = line_fit(ks, [series[k] for k in ks])
    late = [k for k in ks if k >= warmup]
    after = line_fit(late, [series[k] for k in late])
    out = {
        f"slope_whole_run_{unit}_per_segment": whole["slope"] if whole else None,
        f"slope_after_warmup_{unit}_per_segment": after["slope"] if after else None,
        f"slope_after_warmup_stderr_{unit}_per_segment": after["slope_stderr"] if after else None,
        f"spread_after_warmup_{unit}": after["spread"] if after else None,
        f"growth_over_run_{unit}": after["slope"] * total if after else None,
        f"noise_{unit}": max(NOISE_SIGMAS * after["spread"], MIN_NOISE[unit]) if after else None,
        "verdict": None,
    }
    if after:
        if out[f"growth_over_run_{unit}"] <= out[f"noise_{unit}"]:
            out["verdict"] = "flat"
        elif after["slope"] > NOISE_SIGMAS * after["slope_stderr"]:
            out["verdict"] = "growing"
        else:
            out["verdict"] = "unresolved"
    return {k: (round(v, digits) if isinstance(v, float) else v) for k, v in out.items()}


def per_segment_rss(samples: list[tuple[int, float]], last: int) -> dict[int, float]:
    """Median RSS per segment index; samples before the first segment (index < 0) and from the
    last one on (waiting for the stop, closing) are left out."""
    by: dict[int, list[float]] = {}
    for index, mb in samples:
        if 0 <= index < last:
            by.setdefault(index, []).append(mb)
    return {k: float(np.median(v)) for k, v in by.items()}


def latencies(stage: str, done_at: dict[str, dict[int, float]]) -> dict[int, float]:
    mine = done_at.get(stage, {})
    if stage == "replayer":
        return {k: mine[k] - mine[k - 1] for k in mine if k - 1 in mine}
    up = done_at.get(UPSTREAM.get(stage, ""), {})
    return {k: mine[k] - up[k] for k in mine if k in up}


def main(argv=None) -> int:
    p = _parser()
    args = p.parse_args(argv)
    segment_s = parse_duration(args.segment, "--segment")
    total = math.ceil(round(args.days * DAY / segment_s, 6))
    warmup = math.ceil(round(parse_duration(args.warmup, "--warmup") / segment_s, 6))

    rec = args.keep or Path(tempfile.mkdtemp(prefix="ttl-soak-"))
    port = free_port()
    run = "soak"
    cmd = _run_command(args, run, rec, port)
    env = dict(os.environ)
    if args.memtrace is not None:
        env[MEMTRACE_ENV] = str(args.memtrace)
    t_start = time.monotonic()
    load_start = os.getloadavg()
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)
    out_chunks: list[bytes] = []
    reader = threading.Thread(target=lambda: out_chunks.extend(iter(lambda: proc.stdout.read(4096), b"")), daemon=True)
    reader.start()
    done_at: dict[str, dict[int, float]] = {}
    lock = threading.Lock()

    def on_board(sample):
        msg = json.loads(sample.payload.to_bytes())
        now = time.monotonic()
        with lock:
            seen = done_at.setdefault(msg["stage"], {})
            for i in from_ranges(msg.get("done")) | from_ranges(msg.get("failed")):
                seen.setdefault(i, now)

    rss: dict[str, list[tuple[int, float]]] = {}
    loads: list[float] = []
    bus = _open_bus(proc, port)
    if bus is None:
        proc.wait()
        reader.join(5)
        print(
            json.dumps(
                {"exit_status": proc.returncode, "output_tail": b"".join(out_chunks).decode(errors="replace")[-2000:]}
            )
        )
        return 1
    with bus:
        bus.segment_subscriber(f"ttl/{run}/control/board/*", on_board, history=1)
        _sample_rss(proc, done_at, lock, (rss, loads), args.interval)
    reader.join(10)
    out = b"".join(out_chunks).decode(errors="replace")
    result = {
        "days": args.days,
        "segment": args.segment,
        "segments": total,
        "warmup_segments": warmup,
        "exit_status": proc.returncode,
        "seconds": round(time.monotonic() - t_start, 1),
        "load_average_1min": {
            "start": round(load_start[0], 2),
            "mean": round(float(np.mean(loads)), 2) if loads else None,
            "max": round(float(np.max(loads)), 2) if loads else None,
        },
        "recordings": str(rec),
        "stages": {},
    }
    series = {}
    for stage, samples in sorted(rss.items()):
        result["stages"][stage], series[stage] = _stage_result(stage, samples, done_at, total, warmup)
    if args.series:
        args.series.write_text(json.dumps(series))
    if proc.returncode != 0:
        result["output_tail"] = out[-2000:]
    print(json.dumps(result, indent=2))
    return 0 if proc.returncode == 0 else 1


def _parser() -> argparse.ArgumentParser:
    """The command line of the soak bench."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--days", type=float, default=7.0)
    p.add_argument("--segment", default="1h")
    p.add_argument(
        "--warmup", default="1d", help="left out of the post-warm-up fits (default 1d: the fitter's window is full)"
    )
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--interval", type=float, default=1.0, help="RSS sampling period [s]")
    p.add_argument("--keep", type=Path, help="keep the recordings (and the stage logs) in this directory")
    p.add_argument(
        "--series",
        type=Path,
        help="write the per-segment RSS [MB] and latency [s] of every stage "
        "here (JSON: stage -> {rss_mb, latency_s}: segment -> value)",
    )
    p.add_argument(
        "--memtrace",
        type=int,
        default=None,
        help=f"set {MEMTRACE_ENV}=N for the stages: memory lines in their logs (with --keep)",
    )
    return p


def _run_command(args, run: str, rec: Path, port: int) -> list[str]:
    """The ``ttl run`` of the soak: ``args.days`` simulated days in ``args.segment`` segments,
    recorded in ``rec``, its router on loopback ``port`` (plain TCP: the bench's own client
    only reads)."""
    return [
        str(Path(sys.executable).with_name("ttl")),
        "run",
        "--simulate",
        f"--duration {args.days * 24:g}h --orbit unequal --seed {args.seed}",
        "--segment",
        args.segment,
        "--run-id",
        run,
        "--recordings",
        str(rec),
        "--listen",
        f"tcp/127.0.0.1:{port}",
        "--quiet",
        "--insecure",
    ]


def _open_bus(proc, port: int):
    """A client session on the run's router once it is up (None if the run ended first)."""
    bus = None
    while bus is None and proc.poll() is None:
        try:
            bus = Bus.open(SessionSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",)))
        except Exception:  # noqa: BLE001 - the router is not up yet
            time.sleep(1.0)
    return bus


def _stage_name(k) -> str | None:
    """The stage (or ``router``) a child process of the run is, from its command line."""
    cmdline = k.cmdline()
    name = next((w.split(".", 1)[1] for w in cmdline if w.startswith("stages.")), None)
    if name is None and cmdline[3:4] == ["router"]:  # python -c "..." router ...
        name = "router"  # the run's Zenoh router (ttl router): every segment goes through it
    return name


def _sample_rss(proc, done_at: dict, lock, into: tuple, interval: float) -> None:
    """Every ``interval`` [s] until the run ends: each stage's resident memory [MB] with the
    last segment its clock stage has handled, and the load average (``into``: ``(rss,
    loads)``)."""
    rss, loads = into
    while proc.poll() is None:
        try:
            kids = psutil.Process(proc.pid).children(recursive=True)
        except psutil.NoSuchProcess:
            break
        loads.append(os.getloadavg()[0])
        for k in kids:
            try:
                name = _stage_name(k)
                if name:
                    mb = k.memory_info().rss / 2**20
                    with lock:
                        index = max(done_at.get(CLOCK.get(name, name), {}), default=-1)
                    rss.setdefault(name, []).append((index, mb))
            except psutil.Error:
                continue
        time.sleep(interval)


def _stage_result(stage: str, samples: list, done_at: dict, total: int, warmup: int) -> tuple[dict, dict]:
    """One stage's summary (segments, RSS [MB] at the first, warm-up and last segment and its
    maximum, latency [s], each assessed after the warm-up) and its per-segment curves."""
    mem = per_segment_rss(samples, total - 1)
    lat = latencies(stage, done_at)
    ks = sorted(mem)
    entry = {
        "segments": len(done_at.get(CLOCK.get(stage, stage), {})),
        "rss_mb": {
            "first_segment": round(mem[ks[0]], 1) if ks else None,
            "at_warmup": round(mem[min(ks, key=lambda k: abs(k - warmup))], 1) if ks else None,
            "last_segment": round(mem[ks[-1]], 1) if ks else None,
            "max": round(max(m for _, m in samples), 1) if samples else None,
        },
        "rss": assess(mem, warmup, total, "mb", 4),
        "latency_s": {"median": round(float(np.median(list(lat.values()))), 3) if lat else None},
        "latency": assess(lat, warmup, total, "s", 5),
    }
    curves = {
        "rss_mb": {k: round(v, 2) for k, v in sorted(mem.items())},
        "latency_s": {k: round(v, 4) for k, v in sorted(lat.items())},
    }
    return entry, curves


if __name__ == "__main__":
    sys.exit(main())
