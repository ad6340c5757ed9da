"""Offline inspection of a run from its recordings: ``ttl inspect`` and ``ttl view``.

``ttl inspect recordings/NAME [--json FILE]``
    From the MCAP files alone (``<stage>.mcap``, and ``<stage>.<n>.mcap`` kept by restarts,
    oldest ``.1``): which stages ran; the segments each produced and received per topic,
    with missing and duplicate indices; the coefficients and their trends with
    uncertainties (the fitter's fit JSON, ``fit/summary``, schema ``ttl.Fit``); the model
    timeline (what the fitter's model held from which segment to which and why, the
    segments it had no data for and those it left out of its fit); the monitor's alerts; the errors of every stage; the router's refusals (``security.jsonl``:
    unauthenticated peers and forbidden publications, counted per kind with the first few);
    and interruptions: files without footer
    (the process was killed; the reader salvages them), segments whose payload never made
    it to disk, a stage's restarts, a recording that ends without a ``stop`` event, a
    closed file damaged afterwards (flipped bytes: read past the damage, what was skipped
    listed), a file that is not MCAP at all (``unreadable``: exit status 1).
    Works on a run whose stages were killed.  ``--json FILE``: the same as one JSON object
    (:func:`inspect_run`) written to FILE (``-``: standard output).
``ttl view recordings/NAME [--web [--port P]] [--print]``
    ``--web`` serves ``monitor.rrd`` in Rerun's web viewer on 127.0.0.1 and prints the URL
    (a machine without a display, :mod:`streamer.tools.webview`; Ctrl-C: exit status 130);
    otherwise opens it in the ``rerun`` viewer binary with ``--bind 127.0.0.1`` (its gRPC
    server listens on loopback only; no web server is started), refused in one line naming
    ``--web`` when there is no display, and a viewer that fails is one line too (its Rust
    log kept from the terminal); ``--print`` only prints the command.

Errors (no such directory, no recordings, no ``monitor.rrd``, no ``rerun`` binary) are one
line naming the file or directory at fault (``ttl`` exits with status 2).
"""

from __future__ import annotations

import json
import logging
import math
import re
import shlex
import signal
import sys
from collections import Counter, defaultdict
from pathlib import Path

from ttlcore.io.atomic import write_json

from ..bus.keys import to_ranges
from ..bus.message_schema import to_jsonable
from ..bus.segment_record import segments_total_of
from ..bus.topology import STAGES
from ..recording.recorder import Recording, RecordingError, read_recording, read_stop_note
from .inspect_advice import advise
from .inspect_interruptions import interruptions
from .inspect_model import (
    LOOKBACK_DAYS,
    coefficient_trends,
    model_report,
    recorded_fits,
    truth_over_window,
    truth_test,
)
from .inspect_records import MAX_REFUSALS, InspectError, launcher_journal, read_plan, run_gaps, security_report
from .inspect_text import MAX_LISTED, format_report
from .inspect_timeline import model_timeline
from .viewer import no_display, rerun_binary, run_native_viewer
from .webview import WebView

_FILE = re.compile(r"^(?P<stage>.+?)(?:\.(?P<n>\d+))?\.mcap$")

__all__ = [
    "InspectError",
    "LOOKBACK_DAYS",
    "MAX_LISTED",
    "MAX_REFUSALS",
    "format_report",
    "inspect_run",
    "launcher_journal",
    "model_report",
    "recording_files",
    "recording_to_view",
    "security_report",
    "truth_over_window",
    "view_command",
]

# ---------------------------------------------------------------------------- reading


def recording_files(run_dir) -> dict[str, list[Path]]:
    """Stage -> its MCAP files, oldest first (``<stage>.1.mcap``, ``.2``, ..., ``<stage>.mcap``).

    Raises
    ------
    InspectError
        If ``run_dir`` is not a directory or holds no ``.mcap`` file.
    """
    run_dir = Path(run_dir)
    if not run_dir.exists():
        raise InspectError(f"{run_dir}: no such run directory")
    if not run_dir.is_dir():
        raise InspectError(f"{run_dir}: not a directory (give recordings/<run>)")
    by_stage: dict[str, list[tuple[float, Path]]] = defaultdict(list)  # (n, or inf for the current file)
    for path in run_dir.iterdir():
        m = _FILE.match(path.name)
        if m and path.is_file():
            n = int(m.group("n")) if m.group("n") else math.inf  # the current file is the newest
            by_stage[m.group("stage")].append((n, path))
    if not by_stage:
        raise InspectError(f"{run_dir}: no MCAP recordings (*.mcap) in this directory")
    order = {s: i for i, s in enumerate(STAGES)}
    return {
        stage: [p for _, p in sorted(files, key=lambda x: x[0])]
        for stage, files in sorted(by_stage.items(), key=lambda kv: (order.get(kv[0], 99), kv[0]))
    }


def _file_summary(path: Path, stage: str) -> tuple[dict, Recording | None]:
    try:
        rec = read_recording(path)
    except RecordingError as exc:
        return {"file": path.name, "readable": False, "complete": False, "problem": str(exc), "records": 0}, None
    events = rec.json("events")
    kinds = Counter(e.get("kind") for e in events if isinstance(e, dict))
    times = [t for e in events if isinstance(e, dict) and isinstance(t := e.get("time"), (int, float))]
    ttl_metadata = rec.metadata.get("ttl", {})  # the recording's metadata record, not a message's meta
    info = {
        "file": path.name,
        "readable": True,
        "complete": rec.complete,
        "problem": rec.problem,
        "records": rec.records,
        "run": ttl_metadata.get("run"),
        "stage": ttl_metadata.get("stage", stage),
        "started": min(times) if times else None,
        "last_event": max(times) if times else None,
        "stopped": "stop" in kinds,
        "completed": "complete" in kinds,
        "events": dict(kinds),
        "incomplete_segments": [
            {"topic": m.topic, "index": (m.data or {}).get("index")} for m in rec.messages if m.kind == "incomplete"
        ],
        "invalid_messages": [{"topic": m.topic, "error": m.error} for m in rec.messages if m.kind == "invalid"],
        "stop_event": next((e for e in reversed(events) if isinstance(e, dict) and e.get("kind") == "stop"), None),
        "stop_note": read_stop_note(path),
    }
    return info, rec


def _segment_table(per_file: list[dict[str, list[int]]]) -> dict:
    """Topic -> count, indices, duplicates (within and across files), from per-file index lists."""
    out = {}
    for topic in sorted({t for f in per_file for t in f}):
        all_idx = [i for f in per_file for i in f.get(topic, [])]
        counts = Counter(all_idx)
        out[topic] = {
            "count": len(all_idx),
            "distinct": len(counts),
            "indices": to_ranges(counts),
            "duplicates": sorted(i for i, c in counts.items() if c > 1),
        }
    return out


def _stage_report(stage: str, files: list[Path]) -> tuple[dict, list[Recording]]:
    infos, recs = [], []
    outputs: list[dict[str, list[int]]] = []
    inputs: list[dict[str, list[int]]] = []
    totals = set()
    for path in files:
        info, rec = _file_summary(path, stage)
        infos.append(info)
        if rec is None:
            continue
        recs.append(rec)
        name = info["stage"] or stage
        out_f: dict[str, list[int]] = defaultdict(list)
        in_f: dict[str, list[int]] = defaultdict(list)
        for m in rec.messages:
            if m.kind == "segment":
                (out_f if m.header.producer == name else in_f)[m.topic].append(m.header.index)
                t = segments_total_of(m.header.meta)
                if t is not None:
                    totals.add(t)
            elif (
                m.kind == "json"
                and m.topic.endswith("/input")
                and isinstance(m.data, dict)
                and isinstance(m.data.get("index"), int)
            ):  # input headers recorded as JSON
                in_f[m.topic[: -len("/input")]].append(m.data["index"])
        outputs.append(out_f)
        # inputs recorded both as segments and as header JSON count once per file
        inputs.append({t: sorted(set(v)) for t, v in in_f.items()})
    report = {
        "files": infos,
        "restarts": max(0, len(files) - 1),
        "outputs": _segment_table(outputs),
        "inputs": _segment_table(inputs),
        "errors": sum(len(r.json("errors")) for r in recs),
        "segments_total": max(totals) if totals else None,
    }
    return report, recs


def inspect_run(run_dir, truth=None) -> dict:
    """Everything ``ttl inspect`` reports, as a JSON-ready dict.

    Keys: ``run``, ``directory``, ``stages`` (stage -> files, restarts, outputs and inputs
    per topic with counts, index ranges, missing and duplicate indices, error count),
    ``stages_missing`` (pipeline stages without a recording), ``segments_total``,
    ``fits`` (count, index range, the table of fits in m/rad and ``trends`` per
    coefficient in mm/rad and mm/rad/day), ``alerts`` (the monitor's), ``warnings`` (all stages: a fit that did not converge...), ``errors`` (all
    stages'), ``interruptions``, ``gaps``, ``security`` (:func:`security_report`),
    ``timeline`` (the fitter's model from which segment to which and why, its gaps and the
    spans it left out of the fit: :func:`streamer.tools.inspect_timeline.model_timeline`).

    Raises
    ------
    InspectError
        If ``run_dir`` is not a run directory.
    """
    run_dir = Path(run_dir)
    files = recording_files(run_dir)
    stages, recs_of = {}, {}
    for stage, paths in files.items():
        stages[stage], recs_of[stage] = _stage_report(stage, paths)
    totals = [s["segments_total"] for s in stages.values() if s["segments_total"]]
    total = max(totals) if totals else None
    _mark_missing(stages, total)
    runs = sorted({f.get("run") for s in stages.values() for f in s["files"] if f.get("run")})
    errors = _recorded_errors(recs_of)
    plan = read_plan(run_dir)
    if plan is not None:
        total = plan["segments_total"]
    fitter = recs_of.get("fitter", [])
    model = model_report(fitter)
    # the command each recommendation is applied with: ttl control while the run is live, else ttl refit
    model["run_state"] = advise(model, run_dir, runs[0] if len(runs) == 1 else run_dir.name)
    return {
        "run": runs[0] if len(runs) == 1 else (runs or [run_dir.name]),
        "directory": str(run_dir),
        "stages": stages,
        "stages_missing": [s for s in STAGES if s not in stages],
        "segments_total": total,
        "fits": _fit_report(recorded_fits(fitter), truth),
        "model": model,
        "alerts": _recorded(recs_of, "alerts"),
        "warnings": _recorded(recs_of, "warnings"),
        "errors": errors,
        "interruptions": interruptions(run_dir, stages, recs_of, errors, plan),
        "gaps": run_gaps(recs_of, errors, plan),
        "timeline": model_timeline(fitter, plan),
        "security": security_report(run_dir),
    }


def _mark_missing(stages: dict[str, dict], total: int | None) -> None:
    """Give every topic table of every stage its ``missing`` index ranges: those below the
    run's ``total`` (else the highest index seen) it has not seen."""
    for s in stages.values():
        for table in (s["outputs"], s["inputs"]):
            for t in table.values():
                seen = {i for a, b in t["indices"] for i in range(a, b + 1)}
                top = (total - 1) if total else (max(seen) if seen else -1)
                t["missing"] = to_ranges(set(range(top + 1)) - seen)


def _recorded_errors(recs_of: dict[str, list[Recording]]) -> list[dict]:
    """The errors every stage recorded, each with the file it is in."""
    errors = []
    for stage, recs in recs_of.items():
        for rec in recs:
            for e in rec.json("errors"):
                if isinstance(e, dict):
                    errors.append(
                        {
                            "stage": e.get("stage", stage),
                            "file": rec.path.name,
                            "kind": e.get("kind"),
                            "index": e.get("index"),
                            "field": e.get("field"),
                            "key": e.get("key"),
                            "message": e.get("message"),
                            "time": e.get("time"),
                        }
                    )
    return errors


def _recorded(recs_of: dict[str, list[Recording]], topic: str) -> list[dict]:
    """The JSON records of ``topic`` (``alerts``, ``warnings``) of every stage, each with its file."""
    return [
        {**r, "file": rec.path.name}
        for recs in recs_of.values()
        for rec in recs
        for r in rec.json(topic)
        if isinstance(r, dict)
    ]


def _fit_report(fits: list[dict], truth) -> dict:
    """The fitter's fits: count, indices, the table in m/rad, the coefficient trends in
    mm/rad (:func:`streamer.tools.inspect_model.coefficient_trends`) and, with a ``truth`` file,
    the truth over the last fit's window and the error in sigmas."""
    report = {
        "count": len(fits),
        "indices": to_ranges(f["index"] for f in fits),
        "names": fits[-1]["names"] if fits else [],
        "units": "m/rad",
        "table": [
            {k: f[k] for k in ("index", "t_start", "t_stop", "chi2_dof", "converged", "coefficients", "sigma")}
            for f in fits
        ],
        "trends": coefficient_trends(fits),
        "trend_units": {"values": "mm/rad", "rate": "mm/rad/day"},
    }
    if truth is not None and fits:
        last = fits[-1]
        true = truth_over_window(truth, last["t_start"], last["t_stop"], report["trends"])
        for name, t in report["trends"].items():
            if name in true:
                t["truth_latest_window"] = true[name]
                t["error_over_sigma"] = (t["latest"] - true[name]) / t["sigma"] if t["sigma"] > 0 else None
        report["truth_file"] = str(truth)
        report["truth_test"] = truth_test(last, truth)
    return report


# ---------------------------------------------------------------------------- view


def view_command(target, binary: str | None = None) -> list[str]:
    """The ``rerun`` command that opens a run's ``monitor.rrd`` bound to 127.0.0.1.

    ``target`` is a run directory (its ``monitor.rrd``) or an ``.rrd`` file.

    Raises
    ------
    InspectError
        If there is no recording to open; FileNotFoundError if there is no viewer binary.
    """
    rrd = recording_to_view(target)
    binary = binary or rerun_binary()
    # --bind: the viewer's own gRPC server listens on loopback only; --new: a new viewer on a free port
    return [binary, "--bind", "127.0.0.1", "--new", str(rrd)]


def recording_to_view(target) -> Path:
    """The ``.rrd`` file of ``target``: a run directory's ``monitor.rrd`` (else its newest
    ``monitor.<n>.rrd``) or the ``.rrd`` file itself (:class:`InspectError` otherwise)."""
    target = Path(target)
    if target.is_dir():
        rrd = target / "monitor.rrd"
        if not rrd.exists():
            older = sorted(target.glob("monitor*.rrd"))
            if not older:
                raise InspectError(f"{target}: no monitor.rrd in this run directory (did the monitor run?)")
            rrd = older[-1]
    elif target.exists():
        if target.suffix != ".rrd":
            raise InspectError(f"{target}: not a Rerun recording (.rrd) nor a run directory")
        rrd = target
    else:
        raise InspectError(f"{target}: no such run directory or .rrd file")
    return rrd


# ---------------------------------------------------------------------------- command line


def _cmd_inspect(args) -> int:

    # the reader's "salvaged ..." warnings are part of the report (interruptions)
    reader_log = logging.getLogger("streamer.recording.recorder")
    level = reader_log.level
    if not getattr(args, "verbose", 0):
        reader_log.setLevel(logging.ERROR)
    try:
        report = inspect_run(args.run_dir, truth=args.truth)
    finally:
        reader_log.setLevel(level)
    # a recording that is not an MCAP file at all is reported, and the exit status says so
    unreadable = [f"{f['file']}" for s in report["stages"].values() for f in s["files"] if not f.get("readable", True)]
    status = 1 if unreadable else 0
    if args.json == "-":
        print(json.dumps(to_jsonable(report), indent=1, allow_nan=False))
        return status
    if args.json:
        write_json(args.json, to_jsonable(report))
    print(format_report(report))
    if unreadable:
        print(f"ttl inspect: not readable as MCAP: {', '.join(unreadable)} (exit status 1)", file=sys.stderr)
    return status


def _cmd_view(args) -> int:
    if args.web:
        view = WebView(recording_to_view(args.run_dir), rerun_binary(), args.port)
        print(f"Rerun web viewer of {view.rrd}: {view.url}  (Ctrl-C to stop)", flush=True)
        for sig in (signal.SIGINT, signal.SIGTERM):  # stop the servers (SIGINT too when started in the background)
            signal.signal(sig, signal.default_int_handler)
        try:  # Ctrl-C: the KeyboardInterrupt goes on to ttl's "interrupted", exit status 130
            return view.wait()
        finally:
            view.close()
    cmd = view_command(args.run_dir)
    if args.print:
        print(shlex.join(cmd))
        return 0
    web = f"'ttl view {shlex.quote(str(args.run_dir))} --web' serves the web viewer on 127.0.0.1 for a browser"
    why = no_display()
    if why:
        raise InspectError(f"no display ({why}): the native Rerun viewer cannot open a window; {web}")
    code, last = run_native_viewer(cmd)
    if code != 0:
        raise InspectError(f"the Rerun viewer failed (exit status {code}{': ' + last if last else ''}); {web}")
    return 0
