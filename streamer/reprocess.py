"""``ttl reprocess``: analysis and diagnosis of many days in parallel on Dask distributed.

::

    ttl reprocess DAY.h5... --out DIR [--effects ...] [--scheduler ADDRESS | --workers N]
    ttl reprocess --from-recordings recordings/RUN --out DIR ...

The science (per-day job, summary table, trends) is :mod:`ttlcore.diagnose.reprocess`; this module
adds the days of a recorded run (:func:`recorded_days`: the telemetry segments the replayer
recorded in ``replayer.mcap``, read back with :func:`streamer.recorder.read_recording` and
reassembled into one telemetry file per day) and the command line.  It lives beside the
operations commands because reading MCAP recordings is the plumbing's business
(``ttlcore`` does not import ``streamer``).  See ``docs/reprocessing.md``.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from pathlib import Path

import numpy as np

from ttlcore.cli.diagnose import split_effects
from ttlcore.conventions import DAY, parse_duration
from ttlcore.diagnose.effects import make_effects
from ttlcore.diagnose.reprocess import (
    DEFAULT_MEMORY_LIMIT,
    dask_client,
    jobs_for_files,
    reprocess,
)
from ttlcore.errors import TTLError
from ttlcore.estimate.analyze import check_band
from ttlcore.io.telemetry import Telemetry, write_telemetry

from .refit import recorded_segments

log = logging.getLogger(__name__)


def recorded_days(run_dir, out_dir, *, day_length: float = DAY) -> list[Path]:
    """Reassemble the telemetry segments recorded in ``run_dir`` into one telemetry file per
    day (``out_dir/<run>-day<k>.h5``, written atomically), day ``k`` holding the segments
    that start in ``[t_first + k day_length, t_first + (k + 1) day_length)``.

    Raises
    ------
    TTLError
        No recorded telemetry, or missing or non-contiguous segments (named).
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise TTLError(f"--from-recordings: {run_dir} is not a directory")
    if not (math.isfinite(day_length) and day_length > 0):
        raise TTLError(f"--day-length: must be positive, got {day_length}")
    found = recorded_segments(run_dir, "telemetry")
    if not found:
        raise TTLError(f"--from-recordings: {run_dir} holds no recorded telemetry segments "
                       "(replayer.mcap, or the inputs tdi_builder.mcap recorded)")
    order = sorted(found)
    gaps = [i for i in range(order[0], order[-1] + 1) if i not in found]
    if gaps:  # a missing segment is named, never skipped
        raise TTLError(f"{run_dir}: segments {gaps[:5]}{'...' if len(gaps) > 5 else ''} are missing from the "
                       f"recordings (found {order[0]}-{order[-1]})")
    t_first = found[order[0]][0].t0
    days: dict[int, list[int]] = {}
    for i in order:
        k = int(math.floor((found[i][0].t0 - t_first) / day_length + 1e-9))
        days.setdefault(k, []).append(i)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, idx in sorted(days.items()):
        parts = []
        for i in idx:
            h, a = found[i]
            parts.append(Telemetry(t0=h.t0, fs=h.fs, eta=a["eta"], dws_phi=a["dws_phi"], dws_eta=a["dws_eta"],
                                   ltt=a["ltt"]))
        for a, b in zip(parts[:-1], parts[1:]):
            if abs(b.t0 - (a.t0 + a.size / a.fs)) > 0.5 / a.fs or b.fs != a.fs:
                raise TTLError(f"{run_dir}: recorded segments of day {k} are not contiguous "
                               f"(one ends at {a.t0 + a.size / a.fs:g} s, the next starts at {b.t0:g} s)")
        meta = found[idx[0]][0].meta
        dws = meta.get("dws_asd")
        config = {"source": "recording", "run": run_dir.name, "segments": [idx[0], idx[-1]],
                  "recorded_source": meta.get("source")}
        if dws is not None:  # the fit's errors-in-variables level (ttlcore.estimate.fit.dws_asd_from_config)
            config["jitter"] = {"dws": float(dws)}
            config["noises"] = {"dws": float(dws) > 0}
        tm = Telemetry(t0=parts[0].t0, fs=parts[0].fs, config=config, source=str(run_dir),
                       **{f: np.concatenate([getattr(p, f) for p in parts], axis=1)
                          for f in ("eta", "dws_phi", "dws_eta", "ltt")})
        del parts
        paths.append(write_telemetry(out_dir / f"{run_dir.name}-day{k:03d}.h5", tm))
        log.info("day %d of %s: segments %d-%d, %.3f h -> %s", k, run_dir, idx[0], idx[-1], tm.duration / 3600,
                 paths[-1])
    return paths


# ---------------------------------------------------------------------------- ttl reprocess

def add_parser(sub) -> None:
    """Register ``ttl reprocess``."""
    p = sub.add_parser(
        "reprocess",
        help="analyse and diagnose many days in parallel on Dask (a local cluster or any scheduler)",
        description="Analysis (ttl analyze) and diagnosis (ttl diagnose) of many telemetry files, or of the days "
        "of a recorded run, in parallel on Dask distributed: a LocalCluster on 127.0.0.1 by default, or the "
        "cluster of --scheduler. Writes DIR/<day>/fit.json (+ figures), DIR/<day>/diagnosis.json, "
        "DIR/summary.json and DIR/summary.md (coefficients per day with sigmas, chi2/dof, recommendations, "
        "steps and drifts across days). A failed day is retried, then reported; exit status 1 if any "
        "day failed. See docs/reprocessing.md.",
    )
    p.add_argument("days", nargs="*", metavar="DAY", help="telemetry files (ours or lisainstrument's), one per day")
    p.add_argument("--from-recordings", metavar="RUN", default=None,
                   help="a recorded run (recordings/<run>): its telemetry segments reassembled into days")
    p.add_argument("--day-length", default="1d", help="length of a day cut from --from-recordings (default 1d)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created)")
    p.add_argument("--effects", default="linear-ttl", metavar="EFFECT[:opt=v],...",
                   help="the diagnosis model, as ttl diagnose --effects (default linear-ttl)")
    p.add_argument("--effect-module", action="append", default=[], metavar="PATH",
                   help="Python file (or module) defining user effects; repeatable (must be readable by the workers)")
    p.add_argument("--candidates", default=None, metavar="EFFECT,...", help="effects the diagnosis ranks (default all)")
    p.add_argument("--band", nargs=2, metavar=("FMIN", "FMAX"), default=None, help="fit band in Hz")
    p.add_argument("--segment", default=None, help="FFT segment length, e.g. 6h or 15min (default that of "
                   "ttl analyze, 6 h; give a shorter one for days shorter than 6 h)")
    p.add_argument("--truth-beside", action="store_true",
                   help="compare with the truth file beside each day file when there is one (day.truth.h5)")
    p.add_argument("--no-diagnosis", action="store_true", help="analysis only")
    p.add_argument("--no-witnesses", action="store_true", help="skip the diagnosis' witness search")
    p.add_argument("--no-figures", action="store_true", help="skip the figures of the analysis")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="a running Dask scheduler (tcp://host:8786, or its --scheduler-file); default: a "
                   "LocalCluster on 127.0.0.1")
    p.add_argument("--workers", type=int, default=2, help="worker processes of the LocalCluster (default 2)")
    p.add_argument("--memory-limit", default=DEFAULT_MEMORY_LIMIT,
                   help=f"memory limit per local worker (default {DEFAULT_MEMORY_LIMIT})")
    p.add_argument("--dashboard", action="store_true", help="serve the Dask dashboard on 127.0.0.1 (LocalCluster)")
    p.add_argument("--retries", type=int, default=2, help="retries of a failed day (default 2)")
    p.add_argument("--quiet", action="store_true", help="no progress display")
    p.set_defaults(func=run)


def _job_options(args) -> dict:
    opts = {"effects": tuple(_split_effects(args.effects, args.effect_module)), "effect_modules": tuple(args.effect_module),
            "diagnosis": not args.no_diagnosis, "witnesses": not args.no_witnesses, "figures": not args.no_figures}
    if args.candidates:
        opts["candidates"] = tuple(c.strip() for c in args.candidates.split(",") if c.strip())
    if args.band is not None:
        opts["band"] = check_band(args.band)
    if args.segment is not None:
        opts["segment_duration"] = parse_duration(args.segment, "--segment")
    return opts


def _split_effects(text: str, modules) -> list[str]:
    """``--effects`` as effect specs, validated before any work."""
    specs = split_effects(text)
    try:
        make_effects(specs, list(modules))
    except TTLError as exc:
        raise TTLError(f"--effects: {exc}") from None
    return specs


def run(args) -> int:
    if bool(args.days) == bool(args.from_recordings):
        raise TTLError("give either DAY files or --from-recordings RUN")
    if args.retries < 0:
        raise TTLError(f"--retries: must be >= 0, got {args.retries}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise TTLError(f"--out: {out} exists and is not a directory")
    opts = _job_options(args)
    start = time.monotonic()
    if args.from_recordings:
        day_length = parse_duration(args.day_length, "--day-length")
        if not args.quiet:
            print(f"ttl reprocess: reading the recordings of {args.from_recordings}", file=sys.stderr, flush=True)
        files = recorded_days(args.from_recordings, out / "days", day_length=day_length)
        title = f"recorded run {args.from_recordings}"
    else:
        files = args.days
        title = f"{len(files)} telemetry file(s)"
    jobs = jobs_for_files(files, out, truth_beside=args.truth_beside, **opts)
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), desc="ttl reprocess", unit="day", file=sys.stderr)

    def progress(done, total, row):
        if bar is not None:
            bar.update(1)
            if row["status"] != "ok":
                bar.write(f"ttl reprocess: day {row['day']} FAILED: {row['error']}", file=sys.stderr)

    try:
        with dask_client(args.scheduler, workers=args.workers, memory_limit=args.memory_limit,
                         dashboard=args.dashboard) as client:
            if bar is not None and args.dashboard and client.dashboard_link:
                bar.write(f"ttl reprocess: dashboard {client.dashboard_link}", file=sys.stderr)
            summary = reprocess(jobs, out, client=client, retries=args.retries, progress=progress, title=title)
    finally:
        if bar is not None:
            bar.close()
    for a in summary["trends"]["alerts"]:
        print(f"  {a['kind']}: {a['message']} (day {a['day']})")
    print(f"{summary['n_ok']} of {summary['n_days']} days processed in {time.monotonic() - start:.1f} s on "
          f"{summary['cluster']['workers']} worker(s); wrote {out / 'summary.md'}, {out / 'summary.json'}")
    if summary["failed"]:
        print(f"FAILED days: {', '.join(summary['failed'])} (errors in summary.json)")
        return 1
    return 0
