"""Throughput of ``ttl reprocess`` (days per hour) on Dask: serial, LocalCluster of 1 and 2
workers, and a separately started ``dask scheduler`` with ``dask worker`` processes.

    .venv/bin/python bench/reprocess.py [--days 6] [--hours 2] [--diagnosis] [--witnesses]

Short days (default 6 days of 2 h, cut from one simulation) keep the bench to a few
minutes; the JSON says so (``day_hours``).  The job per day is that of ``ttl reprocess``:
``ttl analyze`` (TDI, GLS fit, subtraction, fit.json; no figures) and, with
``--diagnosis``, ``ttl diagnose`` (no witness search unless ``--witnesses``).  The outside
reference, measured in the same run, is the same per-day job called one day after the other
in this process without Dask (``serial``); each configuration reports its throughput and
its ratio to the serial one.  Cluster start-up is timed apart (``startup_s``) and not in the
throughput.  The machine may be shared: the load average is printed with the numbers.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ttlcore.app.reprocessing import dask_client, jobs_for_files, process_day, reprocess
from ttlcore.io.telemetry import write_telemetry
from ttlcore.sim.simulator import SimulationConfig, simulate

BIN = Path(sys.executable).parent
#: as the LocalCluster of ttl reprocess: no MALLOC_TRIM_THRESHOLD_ in the workers (docs/reprocessing.md)
WORKER_ENV = {"DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON": '{"MALLOC_TRIM_THRESHOLD_": None}'}


def make_days(d: Path, n: int, hours: float) -> list[Path]:
    """``n`` consecutive days of ``hours`` each, cut from one simulation (paper defaults)."""
    tm, _ = simulate(SimulationConfig(duration=n * hours * 3600.0, seed=1))
    m = int(round(hours * 3600 * tm.fs))
    return [write_telemetry(d / f"day{i:02d}.h5", tm.slice(i * m, (i + 1) * m)) for i in range(n)]


def _warm_up() -> None:
    """Import what a day's job imports on first use (as the serial reference's warm-up day)."""
    import ttlcore.app.reprocessing  # noqa: F401
    import ttlcore.diagnose.witnesses  # noqa: F401
    import ttlcore.estimate.subtraction  # noqa: F401
    import ttlcore.io.reader  # noqa: F401
    import ttlcore.tdi.data  # noqa: F401


def run_config(name, jobs_of, n_days, scheduler=None, workers=None) -> dict:
    t0 = time.monotonic()
    with dask_client(scheduler, workers=workers or 1, memory_limit="3GiB") as client:
        if scheduler:
            client.wait_for_workers(workers, timeout=120)
        # the first task imports the analysis' modules on each worker: warm up outside the timing
        client.run(_warm_up)
        startup = time.monotonic() - t0
        out, jobs = jobs_of(name)
        t1 = time.monotonic()
        s = reprocess(jobs, out, client=client, retries=1)
        wall = time.monotonic() - t1
        n_workers = s["cluster"]["workers"]
    assert s["n_ok"] == n_days, s["failed"]
    return {
        "workers": n_workers,
        "startup_s": round(startup, 2),
        "wall_s": round(wall, 2),
        "days_per_hour": round(n_days / wall * 3600, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=int, default=6)
    ap.add_argument("--hours", type=float, default=2.0, help="length of a day [h] (default 2)")
    ap.add_argument("--segment", default=1800.0, type=float, help="FFT segment [s] (default 1800)")
    ap.add_argument("--diagnosis", action="store_true", help="add ttl diagnose to each day's job")
    ap.add_argument("--witnesses", action="store_true", help="with --diagnosis: the witness search too")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-reprocess-"))
    procs = []
    try:
        t = time.monotonic()
        files = make_days(tmp, args.days, args.hours)
        t_sim = time.monotonic() - t
        opts = dict(segment_duration=args.segment, figures=False, diagnosis=args.diagnosis, witnesses=args.witnesses)

        def jobs_of(name):
            out = tmp / name
            return out, jobs_for_files(files, out, **opts)

        results = {}
        # outside reference: the same job, one day after the other, in this process
        _, jobs = jobs_of("serial")
        process_day(jobs[0])  # warm-up (imports, caches), not timed
        t = time.monotonic()
        for j in jobs:
            process_day(j)
        wall = time.monotonic() - t
        results["serial"] = {"workers": 0, "wall_s": round(wall, 2), "days_per_hour": round(args.days / wall * 3600, 1)}
        results["local_1_worker"] = run_config("local1", jobs_of, args.days, workers=1)
        results["local_2_workers"] = run_config("local2", jobs_of, args.days, workers=2)
        # a scheduler and workers started apart, as on a cluster (here on 127.0.0.1)
        sched_file = tmp / "scheduler.json"
        log = open(tmp / "dask.log", "wb")
        _start_cluster(sched_file, log, procs)
        results["dask_scheduler_2_workers"] = run_config(
            "external", jobs_of, args.days, scheduler=str(sched_file), workers=2
        )
        ref = results["serial"]["days_per_hour"]
        for r in results.values():
            r["ratio_to_serial"] = round(r["days_per_hour"] / ref, 3)
        one = results["local_1_worker"]["days_per_hour"]
        print(
            json.dumps(
                {
                    "bench": "reprocess",
                    "day_hours": args.hours,
                    "n_days": args.days,
                    "segment_s": args.segment,
                    "note": f"short days of {args.hours:g} h so the bench runs in minutes; a full day's job takes longer "
                    "(bench/diagnose.py, ttl analyze) and its throughput scales accordingly",
                    "job": "ttl analyze (no figures)"
                    + (" + ttl diagnose" + ("" if args.witnesses else " without witnesses") if args.diagnosis else ""),
                    "simulation_s": round(t_sim, 1),
                    "results": results,
                    "speedup_2_vs_1_local_workers": round(results["local_2_workers"]["days_per_hour"] / one, 3),
                    "speedup_2_vs_1_external_workers": round(
                        results["dask_scheduler_2_workers"]["days_per_hour"] / one, 3
                    ),
                    "machine": {
                        "cpus": os.cpu_count(),
                        "load_average_1min_at_end": round(os.getloadavg()[0], 2),
                        "python": platform.python_version(),
                    },
                },
                indent=2,
            )
        )
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
        shutil.rmtree(tmp, ignore_errors=True)


def _start_cluster(sched_file: Path, log, procs: list) -> None:
    """A Dask scheduler on 127.0.0.1 (its address in ``sched_file``, once written, at most
    60 s) and two single-thread workers apart from it, as on a cluster; their output to
    ``log``, the processes appended to ``procs``."""
    procs.append(
        subprocess.Popen(
            [
                str(BIN / "dask"),
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--no-dashboard",
                "--scheduler-file",
                str(sched_file),
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
    )
    deadline = time.monotonic() + 60
    while not sched_file.exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    procs.append(
        subprocess.Popen(
            [
                str(BIN / "dask"),
                "worker",
                "--scheduler-file",
                str(sched_file),
                "--nworkers",
                "2",
                "--nthreads",
                "1",
                "--host",
                "127.0.0.1",
                "--memory-limit",
                "3GiB",
                "--no-dashboard",
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=dict(os.environ, **WORKER_ENV),
        )
    )


if __name__ == "__main__":
    main()
