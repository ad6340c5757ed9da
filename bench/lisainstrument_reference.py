"""Reference timing: lisainstrument on a configuration comparable to our simulator.

``run_lisainstrument_day(path, duration=86400, orbits="keplerian")`` runs lisainstrument 2.x
in a child process (``python bench/lisainstrument_reference.py --child ...``) and returns its
wall time and the child's own peak resident memory (``os.wait4``), so the numbers do not
depend on what the calling process has already loaded or allocated.

Configuration (the effects our simulator has): laser, OMS, test-mass, backlink noise,
spacecraft and MOSA angular jitter (docs/physics.md levels), DWS noise and TTL (the paper's
2.3 mm/rad for all 24 coefficients) on; clock, modulation and ranging noise off, and the
two lisainstrument effects we do not model (reciprocal backlink noise, longitudinal MOSA
jitter) off.  Everything else is lisainstrument's default (4 Hz output, physics at 16 Hz,
Kaiser anti-alias filter, Lagrange order 31, N1-12 locking).  The measurement file is
written with lisainstrument's own writer (``Instrument.export_hdf5``, core datasets).

Measured on the 2-core development machine (lisainstrument 2.3.0, this configuration):

=========  ======  ========================  ==================  =============
duration   orbits  simulate + write [s]      child wall [s]      peak RSS [GB]
=========  ======  ========================  ==================  =============
1 h        static  3.1                       4.2                 1.3
1 h        Kepler  7.0                       9.6                 1.4
1 day      static  37.6                      38.7                6.6
1 day      Kepler  76.1                      77.5                8.0
=========  ======  ========================  ==================  =============

Usage: ``.venv/bin/python bench/lisainstrument_reference.py OUT.h5 [--duration S] [--orbits static|keplerian|FILE]``
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
TESTS = HERE.parent / "tests"

#: TTL coefficients of the comparison run [m/rad] (the paper's value, all 24).
TTL_COEFF = 2.3e-3


def _simulate(path: str, duration: float, orbits: str) -> dict:
    """Run the simulation in this process (the child)."""
    # load tests/lisainstrument_sim.py by path (tests/ on sys.path would let tests/ttlcore
    # shadow the ttlcore package)
    spec = importlib.util.spec_from_file_location("lisainstrument_sim", TESTS / "lisainstrument_sim.py")
    helper = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(helper)
    simulate_lisainstrument = helper.simulate_lisainstrument

    info = simulate_lisainstrument(
        path,
        duration=duration,
        orbits=orbits,
        ttl=True,
        ttl_coeffs=TTL_COEFF,
        jitter=True,
        dws_noise=True,
        laser=True,
        oms=True,
        testmass=True,
        backlink=True,
        reciprocal_backlink=False,
        longitudinal_jitter=False,
        clock=False,
        modulation=False,
        ranging=False,
        seed=1,
    )
    return {"simulate_wall_time_s": info["wall_time_s"], "settings": info["settings"]}


def run_lisainstrument_day(path, duration: float = 86400, orbits: str = "static") -> dict:
    """Run lisainstrument for ``duration`` seconds and measure it.

    Parameters
    ----------
    path : str or Path
        Output measurement file.
    duration : float
        Simulated seconds (default one day).
    orbits : str
        ``"static"``, ``"keplerian"`` (a lisaorbits file is written beside ``path``) or an
        orbit file path.

    Returns
    -------
    dict
        ``wall_time_s`` (child process, start to exit, including imports and the orbit
        file), ``simulate_wall_time_s`` (the simulation and writing alone),
        ``peak_rss_bytes`` (the child's maximum resident set size), ``duration_s``,
        ``orbits``, ``path`` and the ``settings`` used.
    """
    path = Path(path)
    cmd = [
        sys.executable,
        str(Path(__file__).resolve()),
        str(path),
        "--duration",
        repr(float(duration)),
        "--orbits",
        str(orbits),
        "--child",
    ]
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    # wait4 gives this very child's resource usage (ru_maxrss in KiB on Linux)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    out, err = proc.stdout.read(), proc.stderr.read()
    proc.stdout.close()
    proc.stderr.close()
    if proc.returncode != 0:
        raise RuntimeError(f"lisainstrument run failed (exit {proc.returncode}):\n{err[-4000:]}")
    inner = json.loads(out.strip().splitlines()[-1])
    peak = usage.ru_maxrss * (1 if sys.platform == "darwin" else 1024)
    return {
        "wall_time_s": wall,
        "simulate_wall_time_s": inner["simulate_wall_time_s"],
        "peak_rss_bytes": int(peak),
        "duration_s": float(duration),
        "orbits": str(orbits),
        "path": str(path),
        "settings": inner["settings"],
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="output measurement file")
    ap.add_argument("--duration", type=float, default=86400.0)
    ap.add_argument("--orbits", default="static")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(_simulate(args.out, args.duration, args.orbits)))
        return 0
    print(json.dumps(run_lisainstrument_day(args.out, duration=args.duration, orbits=args.orbits), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
