"""Reprocessing of many mission days in parallel on Dask distributed (``ttl reprocess``).

::

    from ttlcore.app.reprocessing import DayJob, dask_client, reprocess
    jobs = [DayJob(name=p.stem, data=str(p), out_dir=f"out/{p.stem}") for p in days]
    with dask_client(workers=2) as client:
        summary = reprocess(jobs, "out", client=client)
    summary["days"][0]["coefficients"], summary["trends"]["alerts"]

Each day is one task (:func:`process_day`): the batch analysis of ``ttl analyze``
(:func:`ttlcore.app.analysis.analyze`: TDI, GLS fit of the 24 coefficients, subtraction,
``fit.json`` and figures) and the diagnosis of ``ttl diagnose``
(:func:`ttlcore.diagnose.diagnoser.diagnose`: the model's chi^2/dof against the fixed instrument noise
model per band and per time slice, the ranking of missing effects, the recommendation),
written to the day's directory with atomic writes (:mod:`ttlcore.io.atomic`: a file is there
whole or not at all).  The tasks run on any Dask cluster (a
:class:`distributed.LocalCluster` by default, see :func:`dask_client`); the files are read
by the workers, so on several machines they must sit on a shared file system.

Inputs are checked before any work (:func:`day_files`, with the readers' own checks,
``file_kind`` and ``read_header``): a file that is not telemetry is refused, and the truth
files ``ttl simulate`` writes beside each day (``day.truth.h5``, told by their content) are
set aside, so that ``data/day*.h5`` names the days.

Failures: the task (:func:`run_day`) does not raise: a day that fails is returned as a
failed row with its error (one line) and traceback.  An error of the data or of the
options (:class:`~ttlcore.errors.TTLError`, ``ValueError``, any error but those below) fails
again whenever it is run, so it is not retried; an ``OSError`` or ``MemoryError`` (a shared
file system that hiccups, a full machine) is run again ``retries`` times.  A day whose worker
dies is rescheduled on another worker by the scheduler (up to its
``distributed.scheduler.allowed-failures``).  A day that still fails is kept in the summary
with ``status: "failed"`` and the error; it is never silently dropped.

Bands: the fit runs in :attr:`DayJob.band` (default that of ``ttl analyze``, 3 mHz-0.9 Hz),
the diagnosis in :attr:`DayJob.diagnose_band` (default that of ``ttl diagnose``,
3 mHz-0.8 Hz: the instrument noise model it tests against lacks TDI's residual laser noise
above 0.8 Hz, so a clean day would fail there).

Outputs in ``out_dir``: ``<day>/fit.json`` (+ figures), ``<day>/diagnosis.json``,
``summary.json`` (one row per day: coefficients and sigmas [m/rad], chi^2/dof of the fit
and against the noise model, the recommendation; the trends), ``summary.md`` (the same as
tables).

Trends across days: the days' fits go, in time order, through
:class:`ttlcore.diagnose.trends.TrendMonitor`, the step (CUSUM on consecutive differences) and
drift (GLS line with the window covariance) detection of the live monitor.  Day windows do
not overlap, so the correlation of consecutive estimates is zero; the drift look-back of
the live monitor (3 days of hourly fits) would hold three day fits, fewer than the line
needs, so reprocessing uses :data:`DAY_TRENDS` (30 days, at least 5 fits) unless told
otherwise.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..conventions import COEFFICIENT_NAMES, DAY
from ..diagnose.diagnoser import DiagnoseSettings, diagnose
from ..diagnose.diagnosis import Diagnosis
from ..diagnose.trends import TrendMonitor, TrendSettings
from ..errors import TelemetryError, TTLError
from ..estimate.fit import DEFAULT_BAND, FitSettings
from ..io.atomic import write_json, write_text
from ..io.reader import file_kind, read_telemetry
from ..io.telemetry import read_header
from ..io.truth import truth_path
from .analysis import _check_segment, analyze
from .cluster import DEFAULT_MEMORY_LIMIT, SPAWN_ENV, dask_client

log = logging.getLogger(__name__)

#: Trend thresholds for one fit per day (see the module docstring): the live monitor's
#: step test, a drift line over the last 30 days of fits (at least 5).
DAY_TRENDS = TrendSettings(drift_lookback=30 * DAY, drift_min_windows=5)
#: Errors that may not recur when a day is run again (a shared file system, a full machine):
#: the only ones retried.  Any other error fails the same way every time.
TRANSIENT_ERRORS = (OSError, MemoryError)


@dataclass(frozen=True)
class DayJob:
    """One day to reprocess (plain values only: it travels to the workers).

    Attributes
    ----------
    name : str
        Name of the day in the summary (and of its output directory).
    data : str
        Telemetry file (ours or lisainstrument's).
    out_dir : str
        Directory of the day's outputs (created).
    truth : str or None
        Truth file (comparisons only, as ``ttl analyze --truth``).
    band : (float, float) or None
        Fit band [Hz] (default that of ``ttl analyze``, 3 mHz-0.9 Hz).
    diagnose_band : (float, float) or None
        Band of the diagnosis [Hz] (default that of ``ttl diagnose``,
        ``DiagnoseSettings().band``, 3 mHz-0.8 Hz).
    segment_duration : float or None
        FFT segment length [s] of the fit and the diagnosis (default: ``ttl analyze``'s
        6 h, and the diagnosis' own default).
    effects : tuple of str
        The diagnosis model (``ttl diagnose --effects``, one spec per effect).
    effect_modules : tuple of str
        User effect modules.
    candidates : tuple of str or None
        Effects the diagnosis ranks (``ttl diagnose --candidates``; default all).
    diagnosis : bool
        Run the diagnosis (default True).
    witnesses : bool
        Search the witness library in the diagnosis.
    figures : bool
        Draw the figures of ``ttl analyze``.
    """

    name: str
    data: str
    out_dir: str
    truth: str | None = None
    band: tuple | None = None
    diagnose_band: tuple | None = None
    segment_duration: float | None = None
    effects: tuple = ("linear-ttl",)
    effect_modules: tuple = ()
    candidates: tuple | None = None
    diagnosis: bool = True
    witnesses: bool = True
    figures: bool = True


def fit_settings(job: DayJob):
    """The :class:`~ttlcore.estimate.fit.FitSettings` of ``ttl analyze`` for ``job``."""
    s = FitSettings(band=tuple(job.band or DEFAULT_BAND))
    if job.segment_duration is None:
        return s
    return replace(s, segment_duration=float(job.segment_duration))


def diagnose_settings(job: DayJob) -> DiagnoseSettings:
    """The :class:`~ttlcore.diagnose.diagnoser.DiagnoseSettings` of ``ttl diagnose`` for ``job``
    (one candidate thread: the cluster's workers already run days side by side)."""
    s = DiagnoseSettings(workers=1)
    if job.diagnose_band is not None:
        s = replace(s, band=tuple(float(b) for b in job.diagnose_band))
    if job.segment_duration is not None:
        s = replace(s, segment_duration=float(job.segment_duration))
    return s


def process_day(job: DayJob) -> dict:
    """Analysis and diagnosis of one day (the task run on a worker).

    Writes ``fit.json`` (and figures) exactly as ``ttl analyze DATA --out DIR`` with the same
    band and segment, and ``diagnosis.json`` as ``ttl diagnose DATA --effects ... --json``
    with the same diagnosis band and segment.  Raises on failure (:func:`run_day` does not).

    Returns
    -------
    dict
        The day's row of the summary (:func:`day_row`).
    """
    start = time.monotonic()
    out = Path(job.out_dir)
    s = fit_settings(job)
    res = analyze(job.data, truth_path=job.truth, band=s.band, out_dir=out, settings=s, figures=job.figures)
    fit_json = res["fit_json"]
    t_analysis = time.monotonic() - start
    del res  # the TDI of a day is hundreds of MB: free it before the diagnosis
    diagnosis = None
    if job.diagnosis:
        tm = read_telemetry(job.data)
        diagnosis = diagnose(
            tm,
            list(job.effects),
            settings=diagnose_settings(job),
            effect_modules=tuple(job.effect_modules),
            candidates=None if job.candidates is None else list(job.candidates),
            witnesses=job.witnesses,
        )
        del tm
        report = diagnosis.to_json()
        report["file"] = str(job.data)
        write_json(out / "diagnosis.json", report)
    timings = {"analysis": round(t_analysis, 3), "total": round(time.monotonic() - start, 3)}
    return day_row(job, fit_json, diagnosis, timings)


def day_row(job: DayJob, fit_json: dict, diagnosis: Diagnosis | None, timings: dict) -> dict:
    """The summary row of a processed day from its ``fit.json`` and diagnosis."""
    row = {
        "day": job.name,
        "file": str(job.data),
        "status": "ok",
        "out_dir": str(job.out_dir),
        "t_start": float(fit_json["window"]["t_start"]),
        "t_stop": float(fit_json["window"]["t_stop"]),
        "coefficients": dict(fit_json["coefficients"]),
        "sigma": dict(fit_json["sigma"]),
        "chi2_dof_fit": fit_json["chi2_dof"],
        "units": "m/rad",
        "worker": {"host": socket.gethostname(), "pid": os.getpid()},
        "timings_s": timings,
        "outputs": {"fit_json": str(Path(job.out_dir) / "fit.json")},
    }
    if "error" in fit_json:
        row["max_abs_error"] = float(np.max(np.abs(list(fit_json["error"].values()))))
    if diagnosis is not None:
        ad, rec = diagnosis.adequacy, diagnosis.recommendation
        row["diagnosis"] = {
            "effects": list(diagnosis.model.effects),
            "chi2_dof": ad.chi2_dof,
            "fails": ad.fails,
            "bands_chi2_dof": [b.chi2_dof for b in ad.bands],
            "summary": list(ad.summary),
            "recommendation": None if rec is None else rec.to_json(),
        }
        row["outputs"]["diagnosis_json"] = str(Path(job.out_dir) / "diagnosis.json")
    return row


# ---------------------------------------------------------------------------- the run


def error_text(exc: BaseException) -> str:
    """One line for an error: our errors say what is at fault themselves, others are named."""
    text = str(exc) if isinstance(exc, TTLError) else f"{type(exc).__name__}: {exc}"
    return " ".join(text.split()) or type(exc).__name__


def failed_row(job: DayJob, exc: BaseException) -> dict:
    """The summary row of a day that failed with ``exc`` (``transient``: worth running again)."""
    return {
        "day": job.name,
        "file": str(job.data),
        "status": "failed",
        "out_dir": str(job.out_dir),
        "error": error_text(exc),
        "transient": isinstance(exc, TRANSIENT_ERRORS),
        "traceback": "".join(traceback.format_exception(type(exc), exc, exc.__traceback__)),
    }


def run_day(job: DayJob) -> dict:
    """The task run on a worker: :func:`process_day`, whose failure is returned as a failed
    row (:func:`failed_row`) instead of raised, so that Dask neither retries it nor logs it:
    :func:`reprocess` decides what is run again."""
    try:
        return process_day(job)
    except Exception as exc:  # noqa: BLE001 - every failure is reported, none is lost
        return failed_row(job, exc)


def _check_jobs(jobs: list[DayJob], retries: int) -> None:
    """TTLError, naming what is wrong, unless the days' names are unique, there is a day,
    and ``retries`` is not negative."""
    names = [j.name for j in jobs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise TTLError(f"days: names must be unique, {', '.join(dup)} repeated")
    if not jobs:
        raise TTLError("no day to reprocess")
    if retries < 0:
        raise TTLError(f"--retries: must be >= 0, got {retries}")


def _task_key(job: DayJob, i: int, attempt: int = 0) -> str:
    return f"day-{i:05d}-{job.name}" + (f"-retry{attempt}" if attempt else "")


def reprocess(
    jobs: Sequence[DayJob],
    out_dir,
    *,
    client,
    retries: int = 2,
    trend_settings: TrendSettings | None = None,
    progress: Callable[[int, int, dict], None] | None = None,
    title: str = "",
) -> dict:
    """Run every job on ``client``'s cluster (:func:`run_day`) and write the summary.

    Parameters
    ----------
    jobs : sequence of DayJob
        Day names must be unique.
    out_dir : path-like
        Where ``summary.json`` and ``summary.md`` go (the days' directories are the jobs').
    client : distributed.Client
    retries : int
        Times a day that failed with a transient error (:data:`TRANSIENT_ERRORS`) is run
        again; other errors are not retried (they would fail the same way), and a day whose
        worker died is rescheduled by the scheduler itself.
    trend_settings : TrendSettings, optional
        Default :data:`DAY_TRENDS`.
    progress : callable(done, total, row), optional
        Called as each day finishes (or fails for good).

    Returns
    -------
    dict
        The ``summary.json`` content: ``days`` (rows in time order, failed days included
        with ``status: "failed"``, ``error`` (one line) and ``traceback``), ``trends``,
        ``failed`` (names), ``settings``, ``wall_s``.
    """
    from distributed import as_completed

    jobs = list(jobs)
    _check_jobs(jobs, retries)
    out_dir = Path(out_dir)
    start = time.monotonic()
    running: dict[str, tuple[int, int]] = {}  # task key -> (job index, attempt)
    pending = as_completed()

    def submit(i: int, attempt: int) -> None:
        fut = client.submit(run_day, jobs[i], key=_task_key(jobs[i], i, attempt), pure=False)
        running[fut.key] = (i, attempt)
        pending.add(fut)

    for i in range(len(jobs)):
        submit(i, 0)
    rows: dict[str, dict] = {}
    for fut in pending:
        i, attempt = running.pop(fut.key)
        job = jobs[i]
        try:
            row = fut.result()
        except Exception as exc:  # noqa: BLE001 - its worker died too often, or the cluster is gone
            row = failed_row(job, exc)
            row["transient"] = False  # the scheduler has rescheduled it already
        fut.release()
        if row["status"] != "ok":
            if row["transient"] and attempt < retries:
                log.info("day %s: %s; running it again (%d of %d)", job.name, row["error"], attempt + 1, retries)
                submit(i, attempt + 1)
                continue
            row["retries"] = attempt
            log.debug("day %s failed:\n%s", job.name, row["traceback"])
        rows[job.name] = row
        if progress is not None:
            progress(len(rows), len(jobs), row)
    ordered = [rows[j.name] for j in jobs]
    ok = sorted((r for r in ordered if r["status"] == "ok"), key=lambda r: r["t_stop"])
    failed = [r for r in ordered if r["status"] != "ok"]
    trends = day_trends(ok, trend_settings or DAY_TRENDS)
    summary = {
        "title": title,
        "days": ok + failed,
        "failed": [r["day"] for r in failed],
        "n_days": len(jobs),
        "n_ok": len(ok),
        "trends": trends,
        "settings": {
            "retries": int(retries),
            "bands_hz": {"fit": list(fit_settings(jobs[0]).band), "diagnosis": list(diagnose_settings(jobs[0]).band)},
            "jobs": asdict(jobs[0]) | {"name": None, "data": None, "out_dir": None, "truth": None},
        },
        "cluster": {"scheduler": client.scheduler.address, "workers": len(client.scheduler_info().get("workers", {}))},
        "wall_s": round(time.monotonic() - start, 3),
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "summary.json", summary)
    write_text(out_dir / "summary.md", summary_markdown(summary))
    return summary


# ---------------------------------------------------------------------------- trends and tables


def day_trends(rows: Sequence[dict], settings: TrendSettings | None = None) -> dict:
    """Steps and drifts across days: the rows' fits fed in time order to the live monitor's
    :class:`~ttlcore.diagnose.trends.TrendMonitor` (window = the fit window of each day).

    Returns ``{"alerts": [Alert.to_json()...], "rates_mm_per_rad_per_day": {...},
    "rate_significance": {...}, "settings": {...}}`` (rates only once a line can be fitted).
    """
    s = settings or DAY_TRENDS
    mon = TrendMonitor(COEFFICIENT_NAMES, s, units="m/rad", max_history=math.inf)
    alerts = []
    for i, r in enumerate(sorted(rows, key=lambda r: r["t_stop"])):
        C = [r["coefficients"][n] for n in COEFFICIENT_NAMES]
        S = [r["sigma"][n] for n in COEFFICIENT_NAMES]
        for a in mon.add(i, r["t_start"], r["t_stop"], C, S):
            d = a.to_json()
            d["day"] = r["day"]
            alerts.append(d)
    out: dict = {"alerts": alerts, "settings": asdict(s), "days": len(rows)}
    est = mon.estimates
    if est is not None:
        out["rates_mm_per_rad_per_day"] = {n: _finite(v) for n, v in zip(est.names, est.rate)}
        out["rate_significance"] = {n: _finite(v) for n, v in zip(est.names, est.significance)}
    return out


def _finite(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def _num(v, spec: str = ".3f") -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def _bands_text(bands: dict | None) -> str:
    if not bands:
        return ""
    (f0, f1), (d0, d1) = bands["fit"], bands["diagnosis"]
    return f"; fit band {f0:g}-{f1:g} Hz, diagnosis band {d0:g}-{d1:g} Hz"


def summary_markdown(summary: dict) -> str:
    """``summary.md``: days (chi^2/dof, adequacy, recommendation), coefficients, trends."""
    days = summary["days"]
    lines = [
        f"# Reprocessing summary{': ' + summary['title'] if summary.get('title') else ''}\n",
        f"{summary['n_ok']} of {summary['n_days']} days processed"
        + (f"; **failed: {', '.join(summary['failed'])}**" if summary["failed"] else "")
        + f" in {summary['wall_s']:.1f} s on {summary['cluster']['workers']} worker(s). "
        "chi2/dof fit: the GLS fit against its re-estimated noise; chi2/dof model: the diagnosis' "
        "residual against the fixed instrument noise model (1 when adequate)"
        + _bands_text(summary.get("settings", {}).get("bands_hz"))
        + ".\n",
        "\n## Days\n\n| day | status | t start [d] | t stop [d] | chi2/dof fit | chi2/dof model | model fails "
        "| recommendation |\n|---|---|---|---|---|---|---|---|",
    ]
    for r in days:
        if r["status"] != "ok":
            err = r["error"].replace("|", "/").replace("\n", " ")
            lines.append(f"| {r['day']} | FAILED | - | - | - | - | - | {err} |")
            continue
        dg = r.get("diagnosis") or {}
        rec = (dg.get("recommendation") or {}).get("option", "none") if dg else "-"
        lines.append(
            f"| {r['day']} | ok | {r['t_start'] / DAY:.4f} | {r['t_stop'] / DAY:.4f} | "
            f"{_num(r['chi2_dof_fit'])} | {_num(dg.get('chi2_dof'))} | "
            f"{'-' if not dg else ('yes' if dg['fails'] else 'no')} | {rec} |"
        )
    ok = [r for r in days if r["status"] == "ok"]
    if ok:
        lines.append("\n## Coefficients [mm/rad], value (sigma)\n")
        lines.append("| day | " + " | ".join(COEFFICIENT_NAMES) + " |")
        lines.append("|---" * (len(COEFFICIENT_NAMES) + 1) + "|")
        for r in ok:
            cells = [f"{1e3 * r['coefficients'][n]:.4f} ({1e3 * r['sigma'][n]:.4f})" for n in COEFFICIENT_NAMES]
            lines.append(f"| {r['day']} | " + " | ".join(cells) + " |")
    tr = summary["trends"]
    lines.append("\n## Trends across days\n")
    if tr["alerts"]:
        for a in tr["alerts"]:
            lines.append(f"- {a['kind']} in {a['coefficient']} (day {a['day']}): {a['message']}")
    else:
        lines.append(
            f"No step or drift flagged over {tr['days']} day(s) (steps need "
            f"{tr['settings']['min_history']} days of history, drifts "
            f"{tr['settings']['drift_min_windows']} fits)."
        )
    return "\n".join(lines) + "\n"


def day_files(paths: Sequence, segment_duration: float | None = None) -> tuple[list[Path], list[Path]]:
    """The input files of a reprocessing, checked before any work: ``(days, truths)``.

    Each file goes through the check every command makes of its input
    (:func:`ttlcore.io.reader.file_kind`, and :func:`ttlcore.io.telemetry.read_header` for
    ours: an HDF5 file of a known layout, its root attributes consistent).  Telemetry
    files (ours or lisainstrument's) are the days; our truth files (root attribute
    ``format='ttl-truth'``, the ``day.truth.h5`` that ``ttl simulate`` writes beside each
    day, whatever their name) are returned apart, for the caller to skip.  With
    ``segment_duration`` [s], a day of ours shorter than one segment is refused (the
    analysis would refuse it on its worker).

    Raises
    ------
    TelemetryError
        Naming the first file that is neither (missing, not HDF5, truncated, another layout),
        with the count of the others.
    """
    days: list[Path] = []
    truths: list[Path] = []
    refused: list[TTLError] = []
    for p in map(Path, paths):
        try:
            kind = file_kind(p)
            if kind == "ttl":
                head = read_header(p)
                if segment_duration is not None:
                    _check_segment(segment_duration, head["duration"], p)
        except TTLError as exc:
            refused.append(exc)
            continue
        (truths if kind == "truth" else days).append(p)
    if refused:
        more = f" (and {len(refused) - 1} more file(s) refused)" if len(refused) > 1 else ""
        first = refused[0]
        if isinstance(first, TelemetryError):
            raise TelemetryError(first.path, first.what + more, first.dataset)
        raise TTLError(f"{first}{more}")
    return days, truths


def jobs_for_files(paths: Sequence, out_dir, *, truth_beside: bool = False, **options) -> list[DayJob]:
    """One :class:`DayJob` per telemetry file: name = the file's stem (made unique with its
    position when two stems coincide), outputs in ``out_dir/<name>``; ``truth_beside``: use
    the truth file beside a file when there is one.  ``options``: other DayJob fields."""
    out_dir = Path(out_dir)
    paths = [Path(p) for p in paths]
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise TTLError(f"{missing[0]}: no such file" + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
    stems = [p.stem for p in paths]
    jobs = []
    for i, p in enumerate(paths):
        name = p.stem if stems.count(p.stem) == 1 else f"{i:04d}-{p.stem}"
        truth = None
        if truth_beside and truth_path(p).is_file():
            truth = str(truth_path(p))
        jobs.append(DayJob(name=name, data=str(p), out_dir=str(out_dir / name), truth=truth, **options))
    return jobs


__all__ = [
    "DAY_TRENDS",
    "DayJob",
    "process_day",
    "day_row",
    "dask_client",
    "reprocess",
    "day_trends",
    "summary_markdown",
    "jobs_for_files",
    "fit_settings",
    "diagnose_settings",
    "day_files",
    "run_day",
    "failed_row",
    "DEFAULT_MEMORY_LIMIT",
    "SPAWN_ENV",
]
