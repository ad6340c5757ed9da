"""``ttl reprocess``: analysis and diagnosis of many days in parallel on Dask distributed.

::

    ttl reprocess DAY.h5... --out DIR [--effects ...] [--band FMIN FMAX] [--diagnose-band FMIN FMAX]
                  [--scheduler ADDRESS | --workers N] [--json FILE|-] [--quiet]
    ttl reprocess --from-recordings recordings/RUN --out DIR ...

Every file is checked before the cluster starts (:func:`day_inputs`): a file that is not
telemetry is refused with one line (exit status 2, nothing written), the truth files
``ttl simulate`` writes beside the days are skipped with one logged line.  Progress follows
the other commands (:func:`ttlcore.cli.progress.progress_bar`: a bar in place on a
terminal, a line per tenth otherwise), Dask's own INFO lines are not shown
(:func:`ttlcore.app.cluster.dask_log_level`), and a day that fails is one line on standard
error, its traceback logged at DEBUG (``-vv``) and kept in ``summary.json``.

The science (per-day job, summary table, trends) is :mod:`ttlcore.app.reprocessing`; this module
adds the days of a recorded run (:func:`recorded_days`: the telemetry segments the replayer
recorded in ``replayer.mcap``, read back with :func:`streamer.recording.recorder.read_recording` and
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
from tqdm import tqdm

from ttlcore.app.analysis import check_band
from ttlcore.app.cluster import dask_client, dask_log_level
from ttlcore.app.reprocessing import day_files, jobs_for_files, reprocess
from ttlcore.cli.progress import progress_bar
from ttlcore.cli.report import to_stdout, write_report
from ttlcore.conventions import DAY, parse_duration
from ttlcore.diagnose.diagnoser import DiagnoseSettings
from ttlcore.effects import make_effects, split_effects
from ttlcore.errors import TTLError
from ttlcore.estimate.fit import DEFAULT_BAND, FitSettings
from ttlcore.io.telemetry import Telemetry, write_telemetry

from ..bus.segment_record import segment_meta
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
        raise TTLError(
            f"--from-recordings: {run_dir} holds no recorded telemetry segments "
            "(replayer.mcap, or the inputs tdi_builder.mcap recorded)"
        )
    order = sorted(found)
    gaps = [i for i in range(order[0], order[-1] + 1) if i not in found]
    if gaps:  # a missing segment is named, never skipped
        raise TTLError(
            f"{run_dir}: segments {gaps[:5]}{'...' if len(gaps) > 5 else ''} are missing from the "
            f"recordings (found {order[0]}-{order[-1]})"
        )
    t_first = found[order[0]][0].t0
    days: dict[int, list[int]] = {}
    for i in order:
        k = int(math.floor((found[i][0].t0 - t_first) / day_length + 1e-9))
        days.setdefault(k, []).append(i)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, idx in sorted(days.items()):
        tm = _day_telemetry(run_dir, k, [found[i] for i in idx], [idx[0], idx[-1]])
        paths.append(write_telemetry(out_dir / f"{run_dir.name}-day{k:03d}.h5", tm))
        log.info(
            "day %d of %s: segments %d-%d, %.3f h -> %s", k, run_dir, idx[0], idx[-1], tm.duration / 3600, paths[-1]
        )
    return paths


def _job_options(args) -> dict:
    opts = {
        "effects": tuple(_split_effects(args.effects, args.effect_module)),
        "effect_modules": tuple(args.effect_module),
        "diagnosis": not args.no_diagnosis,
        "witnesses": not args.no_witnesses,
        "figures": not args.no_figures,
        # both bands stated in every job (and so in summary.json), defaults included
        "band": tuple(DEFAULT_BAND) if args.band is None else check_band(args.band),
        "diagnose_band": (
            tuple(DiagnoseSettings().band)
            if args.diagnose_band is None
            else check_band(args.diagnose_band, option="--diagnose-band")
        ),
    }
    if args.candidates:
        opts["candidates"] = tuple(c.strip() for c in args.candidates.split(",") if c.strip())
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


def _names(paths, shown: int = 3) -> str:
    names = [str(p) for p in paths]
    return ", ".join(names[:shown]) + (f" and {len(names) - shown} more" if len(names) > shown else "")


def day_inputs(paths, opts: dict, quiet: bool = False) -> list[Path]:
    """The days among ``paths``, every file checked before any work
    (:func:`ttlcore.app.reprocessing.day_files`): a file that is not telemetry is refused
    (:class:`TTLError`, one line); truth files are skipped with one logged line (a warning;
    at INFO, so unseen, with ``--quiet``), or refused when nothing else is left."""
    segment = opts.get("segment_duration", FitSettings().segment_duration)
    days, truths = day_files(paths, segment_duration=segment)
    if truths and not days:
        raise TTLError(
            f"{_names(truths)}: truth file(s), not telemetry (ttl simulate writes day.truth.h5 beside each "
            f"day.h5); give the telemetry files"
        )
    if truths:
        log.log(
            logging.INFO if quiet else logging.WARNING,
            "skipping %d truth file(s), not telemetry (ttl simulate writes one beside each day; "
            "--truth-beside compares each day with its own): %s",
            len(truths),
            _names(truths),
        )
    return days


def _say(text: str) -> None:
    """A line on standard error that leaves a progress bar on the terminal whole."""
    tqdm.write(text, file=sys.stderr)


def _day_telemetry(run_dir: Path, k: int, segments: list[tuple], span: list[int]) -> Telemetry:
    """Day ``k``'s telemetry: its recorded ``segments`` ``(header, arrays)`` (indices
    ``span`` = first, last) joined; a TTLError when two do not follow each other."""
    parts = [
        Telemetry(t0=h.t0, fs=h.fs, eta=a["eta"], dws_phi=a["dws_phi"], dws_eta=a["dws_eta"], ltt=a["ltt"])
        for h, a in segments
    ]
    for a, b in zip(parts[:-1], parts[1:]):
        if abs(b.t0 - (a.t0 + a.size / a.fs)) > 0.5 / a.fs or b.fs != a.fs:
            raise TTLError(
                f"{run_dir}: recorded segments of day {k} are not contiguous "
                f"(one ends at {a.t0 + a.size / a.fs:g} s, the next starts at {b.t0:g} s)"
            )
    meta = segment_meta(segments[0][0])
    dws = meta.dws_asd
    config: dict = {"source": "recording", "run": run_dir.name, "segments": span, "recorded_source": meta.source}
    if dws is not None:  # the fit's errors-in-variables level (ttlcore.estimate.fit.dws_asd_from_config)
        config["jitter"] = {"dws": float(dws)}
        config["noises"] = {"dws": float(dws) > 0}
    return Telemetry(
        t0=parts[0].t0,
        fs=parts[0].fs,
        config=config,
        source=str(run_dir),
        **{f: np.concatenate([getattr(p, f) for p in parts], axis=1) for f in ("eta", "dws_phi", "dws_eta", "ltt")},
    )


def _checked_out(args) -> Path:
    """The output directory of ``ttl reprocess``, its arguments checked (TTLError naming the one at fault)."""
    if bool(args.days) == bool(args.from_recordings):
        raise TTLError("give either DAY files or --from-recordings RUN")
    if args.retries < 0:
        raise TTLError(f"--retries: must be >= 0, got {args.retries}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise TTLError(f"--out: {out} exists and is not a directory")
    return out


def _inputs(args, opts: dict, out: Path) -> tuple[list[Path], str]:
    """The day files to process (the recorded run's reassembled under ``out/days``) and a title."""
    if args.from_recordings:
        day_length = parse_duration(args.day_length, "--day-length")
        if not args.quiet:
            print(f"ttl reprocess: reading the recordings of {args.from_recordings}", file=sys.stderr, flush=True)
        files = recorded_days(args.from_recordings, out / "days", day_length=day_length)
        return files, f"recorded run {args.from_recordings}"
    files = day_inputs(args.days, opts, quiet=args.quiet)
    return files, f"{len(files)} telemetry file(s)"


def _print_summary(summary: dict, opts: dict, out: Path, seconds: float) -> None:
    """The run's outcome on stdout: alerts, days processed, the model's verdicts, failures, files."""
    for a in summary["trends"]["alerts"]:
        print(f"  {a['kind']}: {a['message']} (day {a['day']})")
    print(
        f"{summary['n_ok']} of {summary['n_days']} days processed in {seconds:.1f} s on "
        f"{summary['cluster']['workers']} worker(s)"
    )
    verdicts = [r["diagnosis"]["fails"] for r in summary["days"] if r["status"] == "ok" and r.get("diagnosis")]
    if verdicts:
        f0, f1 = summary["settings"]["bands_hz"]["diagnosis"]
        print(
            f"  the model ({', '.join(opts['effects'])}) fails on {sum(verdicts)} of {len(verdicts)} day(s) "
            f"against the instrument noise model in {f0:g}-{f1:g} Hz"
        )
    if summary["failed"]:
        print(f"FAILED days: {', '.join(summary['failed'])} (errors in summary.json)")
    print(f"  wrote {out / 'summary.md'}, {out / 'summary.json'}")


def run(args) -> int:
    out = _checked_out(args)
    opts = _job_options(args)
    start = time.monotonic()
    files, title = _inputs(args, opts, out)
    jobs = jobs_for_files(files, out, truth_beside=args.truth_beside, **opts)
    level = dask_log_level(args.verbose)
    with progress_bar("ttl reprocess", quiet=args.quiet) as shown:  # in place on a terminal only

        def progress(done, total, row):
            shown(done, total)
            if row["status"] != "ok":  # an error: said even with --quiet
                _say(f"ttl reprocess: day {row['day']} failed: {row['error']}")

        with dask_client(
            args.scheduler,
            workers=args.workers,
            memory_limit=args.memory_limit,
            dashboard=args.dashboard,
            log_level=level,
        ) as client:
            if args.dashboard and client.dashboard_link and not args.quiet:
                _say(f"ttl reprocess: dashboard {client.dashboard_link}")
            summary = reprocess(jobs, out, client=client, retries=args.retries, progress=progress, title=title)
    status = 1 if summary["failed"] else 0
    write_report(args.json, summary)
    if args.quiet or to_stdout(args.json):  # the files (and the exit status) are the result
        return status
    _print_summary(summary, opts, out, time.monotonic() - start)
    return status
