"""Offline inspection of a run from its recordings: ``ttl inspect`` and ``ttl view``.

``ttl inspect recordings/NAME [--json FILE]``
    From the MCAP files alone (``<stage>.mcap``, and ``<stage>.<n>.mcap`` kept by restarts,
    oldest ``.1``): which stages ran; the segments each produced and received per topic,
    with missing and duplicate indices; the coefficients and their trends with
    uncertainties (the fitter's fit JSON, ``fit/summary``, schema ``ttl.Fit``); the
    monitor's alerts; the errors of every stage; the router's refusals (``security.jsonl``:
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
    (a machine without a display, :mod:`streamer.webview`); otherwise opens it in the ``rerun`` viewer binary with
    ``--bind 127.0.0.1`` (its
    gRPC server listens on loopback only; no web server is started); ``--print`` only
    prints the command.

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
import subprocess
import sys
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.diagnose.trends import TrendSettings, trend_estimates
from ttlcore.estimate.monitoring import FileTruth
from ttlcore.io.atomic import write_json

from .keys import to_ranges
from .recorder import Recording, RecordingError, read_recording, read_stop_note, to_jsonable
from .topology import STAGES
from .viewer import rerun_binary
from .webview import WebView

_FILE = re.compile(r"^(?P<stage>.+?)(?:\.(?P<n>\d+))?\.mcap$")
#: Span of the drift rate in the report [days] (ttlcore.diagnose.trends.TrendSettings.drift_lookback).
LOOKBACK_DAYS = 3.0
#: Errors listed in full by the text report (the rest are counted).
MAX_LISTED = 20
#: Refusals of each kind kept in the report (``security.jsonl``; the rest are counted).
MAX_REFUSALS = 5


class InspectError(ValueError):
    """The run cannot be inspected (message names the file or directory)."""


# ---------------------------------------------------------------------------- reading


def _fmt_ranges(ranges) -> str:
    if not ranges:
        return "-"
    return ",".join(f"{a}" if a == b else f"{a}-{b}" for a, b in ranges)


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
    by_stage: dict[str, list[tuple[int, Path]]] = defaultdict(list)
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
    times = [e.get("time") for e in events if isinstance(e, dict) and isinstance(e.get("time"), (int, float))]
    meta = rec.metadata.get("ttl", {})
    info = {
        "file": path.name,
        "readable": True,
        "complete": rec.complete,
        "problem": rec.problem,
        "records": rec.records,
        "run": meta.get("run"),
        "stage": meta.get("stage", stage),
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
                t = m.header.meta.get("segments_total") if isinstance(m.header.meta, dict) else None
                if isinstance(t, int) and t > 0:
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


def _fits(recs: list[Recording]) -> list[dict]:
    """The fits of the fitter's recordings, one per index (a later file's fit wins)."""
    fits: dict[int, dict] = {}
    for rec in recs:
        summaries = [d for d in rec.json("fit/summary") if isinstance(d, dict) and isinstance(d.get("index"), int)]
        if summaries:
            for d in summaries:
                fit = d.get("fit") if isinstance(d.get("fit"), dict) else {}
                names = d.get("names") or fit.get("names")
                coeffs, sigma = d.get("coefficients"), d.get("sigma")
                if isinstance(coeffs, dict):  # FitResult.to_json layout
                    coeffs = [coeffs[n] for n in names]
                if isinstance(sigma, dict):
                    sigma = [sigma[n] for n in names]
                window = fit.get("window", {}) if isinstance(fit.get("window"), dict) else {}
                fits[d["index"]] = {
                    "index": d["index"],
                    "names": list(names or []),
                    "t_start": d.get("t_start", window.get("t_start")),
                    "t_stop": d.get("t_end", d.get("t_stop", window.get("t_stop"))),
                    "chi2_dof": d.get("chi2_dof", fit.get("chi2_dof")),
                    "converged": fit.get("converged", d.get("converged")),
                    "coefficients": coeffs,
                    "sigma": sigma,
                }
        else:  # no summaries: the fit segments themselves
            for m in rec.segments("fit"):
                a, meta = m.arrays, m.header.meta
                if "coefficients" not in a:
                    continue
                fits[m.header.index] = {
                    "index": m.header.index,
                    "names": list(meta.get("names") or []),
                    "t_start": meta.get("t_start"),
                    "t_stop": meta.get("t_stop"),
                    "chi2_dof": meta.get("chi2_dof"),
                    "converged": meta.get("converged"),
                    "coefficients": a["coefficients"].tolist(),
                    "sigma": a["sigma"].tolist() if "sigma" in a else None,
                }
    good = []
    for f in sorted(fits.values(), key=lambda f: f["index"]):
        try:
            c = np.asarray(f["coefficients"], dtype=float)
            s = np.asarray(f["sigma"], dtype=float) if f["sigma"] is not None else np.full(c.shape, np.nan)
        except (TypeError, ValueError):
            continue
        if c.ndim == 1 and c.shape == s.shape and c.size:
            good.append(f)
    return good


def _trends(fits: list[dict]) -> dict:
    """Per coefficient: latest value and sigma, range, and the GLS drift rate of ttlcore.diagnose.trends [mm/rad]."""
    if not fits:
        return {}
    names = fits[-1]["names"] or [f"c{i}" for i in range(len(fits[-1]["coefficients"]))]
    same = [f for f in fits if len(f["coefficients"]) == len(names)]
    C = np.array([f["coefficients"] for f in same], dtype=float) * 1e3
    S = np.array([f["sigma"] for f in same], dtype=float) * 1e3
    out = {
        n: {
            "latest": float(C[-1, p]),
            "sigma": float(S[-1, p]),
            "first": float(C[0, p]),
            "min": float(np.nanmin(C[:, p])),
            "max": float(np.nanmax(C[:, p])),
            "rate": None,
            "rate_se": None,
            "significance": None,
        }
        for p, n in enumerate(names)
    }
    windows = [(f["t_start"], f["t_stop"]) for f in same]
    ok = all(isinstance(a, (int, float)) and isinstance(b, (int, float)) and b > a for a, b in windows)
    if ok and len(same) >= 3 and np.all(np.isfinite(S)):
        try:
            te = np.array([b for _, b in windows])
            order = np.argsort(te, kind="stable")
            keep = order[np.concatenate([[True], np.diff(te[order]) > 0])]
            est = trend_estimates(
                te[keep],
                C[keep],
                S[keep],
                t_start=np.array([a for a, _ in windows])[keep],
                names=names,
                units="mm/rad",
                settings=TrendSettings(drift_min_windows=3, drift_lookback=LOOKBACK_DAYS * 86400.0),
            )
            for p, n in enumerate(names):
                if np.isfinite(est.rate[p]):
                    out[n].update(
                        rate=float(est.rate[p]), rate_se=float(est.se[p]), significance=float(est.significance[p])
                    )
        except ValueError:
            pass
    return out


def truth_over_window(truth_path, t_start: float, t_stop: float, names) -> dict:
    """True coefficients [mm/rad] averaged over ``[t_start, t_stop)`` from a truth file
    (:class:`ttlcore.estimate.monitoring.FileTruth`, as the monitor draws them); empty when
    the window is outside the file."""
    mean = FileTruth(truth_path).mean(t_start, t_stop)
    if mean is None:
        return {}
    mean = dict(zip(COEFFICIENT_NAMES, mean * 1e3))
    return {n: float(mean[n]) for n in names if n in mean}


def model_report(recs: list[Recording]) -> dict:
    """The fitter's model over the run: its changes (``model`` events: from which segment,
    by whom - a control message or ``--adopt auto`` - and why) and the live diagnoses (the
    ``diagnosis`` of the fit summaries: window, chi^2/dof, failing bands, recommendation and
    the ``ttl control`` command applying it, adoption)."""
    changes, diagnoses, last_model = [], {}, None
    for rec in recs:
        for e in rec.json("events"):
            if isinstance(e, dict) and e.get("kind") == "model":
                d = e.get("details") or {}
                changes.append(
                    {
                        "from_index": d.get("from_index"),
                        "effects": d.get("effects"),
                        "before": d.get("before"),
                        "by": d.get("by"),
                        "reason": d.get("reason"),
                        "file": rec.path.name,
                    }
                )
        for d in rec.json("fit/summary"):
            if not isinstance(d, dict) or not isinstance(d.get("index"), int):
                continue
            if isinstance(d.get("model"), list):
                last_model = (d["index"], d["model"])
            diag = d.get("diagnosis")
            if isinstance(diag, dict):
                rec_ = diag.get("recommendation") if isinstance(diag.get("recommendation"), dict) else {}
                diagnoses[d["index"]] = {
                    "index": d["index"],
                    "segments": diag.get("segments"),
                    "model": diag.get("model"),
                    "chi2_dof": diag.get("chi2_dof"),
                    "fails": diag.get("fails"),
                    "failing_bands": [
                        [b.get("f_lo"), b.get("f_hi"), b.get("chi2_dof")]
                        for b in diag.get("bands") or []
                        if isinstance(b, dict) and b.get("fails")
                    ],
                    "failing_hours": diag.get("failing_hours"),
                    "summary": diag.get("summary"),
                    "recommendation": rec_.get("spec"),
                    "explains": rec_.get("explains"),
                    "command": rec_.get("command"),
                    "message": rec_.get("message"),
                    "adoption": diag.get("adoption"),
                    "text": diag.get("text"),
                }
    return {
        "model": None if last_model is None else {"index": last_model[0], "effects": last_model[1]},
        "changes": changes,
        "diagnoses": [diagnoses[i] for i in sorted(diagnoses)],
    }


def inspect_run(run_dir, truth=None) -> dict:
    """Everything ``ttl inspect`` reports, as a JSON-ready dict.

    Keys: ``run``, ``directory``, ``stages`` (stage -> files, restarts, outputs and inputs
    per topic with counts, index ranges, missing and duplicate indices, error count),
    ``stages_missing`` (pipeline stages without a recording), ``segments_total``,
    ``fits`` (count, index range, the table of fits in m/rad and ``trends`` per
    coefficient in mm/rad and mm/rad/day), ``alerts`` (the monitor's), ``warnings`` (all stages: a fit that did not converge...), ``errors`` (all
    stages'), ``interruptions``, ``gaps``, ``security`` (:func:`security_report`).

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
    for s in stages.values():
        for table in (s["outputs"], s["inputs"]):
            for t in table.values():
                seen = {i for a, b in t["indices"] for i in range(a, b + 1)}
                top = (total - 1) if total else (max(seen) if seen else -1)
                t["missing"] = to_ranges(set(range(top + 1)) - seen)
    runs = sorted({f.get("run") for s in stages.values() for f in s["files"] if f.get("run")})

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
    alerts = [
        {**a, "file": rec.path.name}
        for stage, recs in recs_of.items()
        for rec in recs
        for a in rec.json("alerts")
        if isinstance(a, dict)
    ]
    warnings = [
        {**w, "file": rec.path.name}
        for stage, recs in recs_of.items()
        for rec in recs
        for w in rec.json("warnings")
        if isinstance(w, dict)
    ]

    interruptions = []
    for stage, s in stages.items():
        names = [f["file"] for f in s["files"]]
        if s["restarts"]:
            interruptions.append(
                {
                    "stage": stage,
                    "kind": "restart",
                    "files": names,
                    "message": f"{stage} ran {len(names)} times (recordings {', '.join(names)})",
                }
            )
        for f in s["files"]:
            if not f["readable"]:
                interruptions.append({"stage": stage, "kind": "unreadable", "file": f["file"], "message": f["problem"]})
                continue
            note = f.get("stop_note") or {}
            if note.get("reason") == "disk-full":  # the stage said why it stopped (Recorder.note_stop)
                closed = "closed" if f["complete"] else f"not closed: salvaged {f['records']} records; {f['problem']}"
                interruptions.append(
                    {
                        "stage": stage,
                        "kind": "disk-full",
                        "file": f["file"],
                        "message": f"{f['file']}: stopped: {note.get('message')} ({closed})",
                    }
                )
            elif not f["complete"]:
                interruptions.append(
                    {
                        "stage": stage,
                        "kind": "unfinished",
                        "file": f["file"],
                        "message": f"{f['file']} was not closed (process killed?): salvaged "
                        f"{f['records']} records; {f['problem']}",
                    }
                )
            elif f["problem"]:  # closed, then damaged (flipped bytes): read past the damage
                interruptions.append(
                    {
                        "stage": stage,
                        "kind": "damaged",
                        "file": f["file"],
                        "message": f"{f['file']} is damaged: salvaged {f['records']} records; {f['problem']}",
                    }
                )
            if f["complete"] and not f["stopped"]:
                interruptions.append(
                    {
                        "stage": stage,
                        "kind": "no-stop",
                        "file": f["file"],
                        "message": f"{f['file']} is closed but has no 'stop' event",
                    }
                )
            for seg in f["incomplete_segments"]:
                interruptions.append(
                    {
                        "stage": stage,
                        "kind": "incomplete-segment",
                        "file": f["file"],
                        "message": f"{f['file']}: {seg['topic']} segment {seg['index']} has a header "
                        "but no payload (cut off while writing)",
                    }
                )

        for f in s["files"]:
            stop = f.get("stop_event") or {}
            if (stop.get("details") or {}).get("orphaned"):
                interruptions.append(
                    {
                        "stage": stage,
                        "kind": "orphaned",
                        "file": f["file"],
                        "message": f"{f['file']}: stopped by itself: {stop.get('message')}",
                    }
                )
        for rec in recs_of.get(stage, []):
            for e in rec.json("events"):
                if isinstance(e, dict) and e.get("kind") == "restored":
                    interruptions.append(
                        {"stage": stage, "kind": "restored", "file": rec.path.name, "message": e.get("message")}
                    )
    for e in errors:
        if e["kind"] == "window-shortened":
            interruptions.append(
                {"stage": e["stage"], "kind": "window-shortened", "file": e["file"], "message": e["message"]}
            )
    plan = _plan(run_dir)
    if plan is not None:
        total = plan["segments_total"]
        for stage, s in stages.items():
            out = next(iter(s["outputs"].values()), None) if s["outputs"] else None
            last = s["files"][-1] if s["files"] else {}
            if out is not None and out["missing"] and not last.get("completed"):
                interruptions.append(
                    {
                        "stage": stage,
                        "kind": "unfinished",
                        "file": last.get("file"),
                        "message": f"{stage} did not finish: segment(s) {_fmt_ranges(out['missing'])} "
                        f"of {total} not handled",
                    }
                )
    interruptions.extend(launcher_journal(run_dir))
    gaps = _gaps(recs_of, errors, plan)

    fits = _fits(recs_of.get("fitter", []))
    model = model_report(recs_of.get("fitter", []))
    fit_report = {
        "count": len(fits),
        "indices": to_ranges(f["index"] for f in fits),
        "names": fits[-1]["names"] if fits else [],
        "units": "m/rad",
        "table": [
            {k: f[k] for k in ("index", "t_start", "t_stop", "chi2_dof", "converged", "coefficients", "sigma")}
            for f in fits
        ],
        "trends": _trends(fits),
        "trend_units": {"values": "mm/rad", "rate": "mm/rad/day"},
    }
    if truth is not None and fits:
        last = fits[-1]
        true = truth_over_window(truth, last["t_start"], last["t_stop"], fit_report["trends"])
        for name, t in fit_report["trends"].items():
            if name in true:
                t["truth_latest_window"] = true[name]
                t["error_over_sigma"] = (t["latest"] - true[name]) / t["sigma"] if t["sigma"] > 0 else None
        fit_report["truth_file"] = str(truth)
    return {
        "run": runs[0] if len(runs) == 1 else (runs or [run_dir.name]),
        "directory": str(run_dir),
        "stages": stages,
        "stages_missing": [s for s in STAGES if s not in stages],
        "segments_total": total,
        "fits": fit_report,
        "model": model,
        "alerts": alerts,
        "warnings": warnings,
        "errors": errors,
        "interruptions": interruptions,
        "gaps": gaps,
        "security": security_report(run_dir),
    }


def launcher_journal(run_dir: Path) -> list[dict]:
    """The interruptions ``ttl run`` recorded in ``launcher.jsonl`` (:mod:`streamer.launcher`,
    "Journal and resuming"): every stage or router that died and was restarted, every
    launcher that ended without its ``end`` record (killed) and every ``--resume``."""
    path = Path(run_dir) / "launcher.jsonl"
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return []
    out, open_start = [], None
    for n, line in enumerate(lines, 1):
        try:
            rec = json.loads(line)
        except ValueError:
            out.append(
                {
                    "stage": "launcher",
                    "kind": "journal-unreadable",
                    "file": path.name,
                    "message": f"launcher.jsonl line {n} is not JSON (cut off when the launcher died?)",
                }
            )
            continue
        if not isinstance(rec, dict):
            continue
        kind, when = rec.get("kind"), rec.get("time")
        if kind == "start":
            if open_start is not None:
                out.append(
                    {
                        "stage": "launcher",
                        "kind": "launcher-killed",
                        "file": path.name,
                        "time": open_start.get("time"),
                        "message": f"ttl run (pid {open_start.get('launcher_pid')}) ended without its end record "
                        "(killed)",
                    }
                )
            open_start = rec
        elif kind == "end":
            open_start = None
        elif kind in ("stage-died", "stage-restarted", "router-died", "router-restarted", "resume"):
            out.append(
                {
                    "stage": rec.get("stage") or "launcher",
                    "kind": kind,
                    "file": path.name,
                    "time": when,
                    "message": rec.get("message"),
                }
            )
    if open_start is not None:
        out.append(
            {
                "stage": "launcher",
                "kind": "launcher-killed",
                "file": path.name,
                "time": open_start.get("time"),
                "message": f"ttl run (pid {open_start.get('launcher_pid')}) has no end record (killed, or still "
                "running)",
            }
        )
    return out


def security_report(run_dir: Path) -> dict:
    """The router's refusals of a run (``security.jsonl``, written by ``ttl run`` with
    credentials when the run ends; :func:`streamer.security.refusals`).

    Returns ``{"file", "present", "count", "kinds": {kind: {"count", "first": [the first
    MAX_REFUSALS records]}}, "unreadable": [line numbers]}``; ``present`` is False when the
    file is absent (a run with ``--insecure``, or whose launcher did not end).  A line that is
    not a JSON object with a ``kind`` is counted in ``unreadable``, not fatal (the file of a
    damaged run is still reported).
    """
    path = Path(run_dir) / "security.jsonl"
    out = {"file": str(path), "present": path.exists(), "count": 0, "kinds": {}, "unreadable": []}
    if not out["present"]:
        return out
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise InspectError(f"{path}: cannot read: {exc}") from None
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except ValueError:
            record = None
        if not isinstance(record, dict) or not isinstance(record.get("kind"), str):
            out["unreadable"].append(n)
            continue
        kind = out["kinds"].setdefault(record["kind"], {"count": 0, "first": []})
        kind["count"] += 1
        out["count"] += 1
        if len(kind["first"]) < MAX_REFUSALS:
            kind["first"].append(record)
    return out


def _refusal_text(r: dict) -> str:
    when = f" at {r['time']}" if r.get("time") else ""
    if r.get("kind") == "forbidden":
        return f"{r.get('subject')} may not {r.get('action')} on {r.get('key')}{when}"
    return f"{r.get('message', json.dumps(r))}{when}"


def _plan(run_dir: Path) -> dict | None:
    """The run's plan (``plan.json`` written by ``ttl run``), or None."""
    try:
        return json.loads((run_dir / "plan.json").read_text())
    except (OSError, ValueError):
        return None


def _gaps(recs_of: dict, errors: list[dict], plan: dict | None) -> list[dict]:
    """Every gap of the run: NaN stretches the replayer published flagged (``gap`` events,
    sample ranges in the segment) and segments with no data or skipped (``gap`` errors)."""
    fs = plan["fs"] if plan else None
    out = []
    for rec in recs_of.get("replayer", []):
        for e in rec.json("events"):
            if isinstance(e, dict) and e.get("kind") == "gap":
                stretches = (e.get("details") or {}).get("stretches") or []
                samples = sum(b - a for a, b in stretches)
                out.append(
                    {
                        "stage": "replayer",
                        "kind": "nan-stretch",
                        "index": e.get("index"),
                        "stretches": stretches,
                        "seconds": samples / fs if fs else None,
                        "message": e.get("message"),
                    }
                )
    for e in errors:
        if e["kind"] == "gap":
            out.append({"stage": e["stage"], "kind": "missing", "index": e["index"], "message": e["message"]})
    return out


# ---------------------------------------------------------------------------- text


def _topics_text(table: dict) -> str:
    parts = []
    for topic, t in table.items():
        extra = ""
        if t["missing"]:
            extra += f" missing {_fmt_ranges(t['missing'])}"
        if t["duplicates"]:
            extra += f" dup {_fmt_ranges(to_ranges(t['duplicates']))}"
        parts.append(f"{topic} {t['distinct']} [{_fmt_ranges(t['indices'])}]{extra}")
    return "; ".join(parts) or "-"


def _days(t) -> str:
    return f"{round(t / 86400.0, 3) + 0.0:.3f}" if isinstance(t, (int, float)) else "?"


def _num(x) -> str:
    return f"{x:.3f}" if isinstance(x, (int, float)) else "?"


def format_report(r: dict) -> str:
    """The text of ``ttl inspect``."""
    lines = []
    run = r["run"] if isinstance(r["run"], str) else ", ".join(r["run"])
    total = f", {r['segments_total']} segments expected" if r["segments_total"] else ""
    lines.append(f"run {run} ({r['directory']}): {len(r['stages'])} stage(s) recorded{total}")
    if r["stages_missing"]:
        lines.append(f"  no recording of: {', '.join(r['stages_missing'])}")
    lines.append("")
    lines.append("Stages")
    for stage, s in r["stages"].items():
        state = []
        files = s["files"]
        if s["restarts"]:
            state.append(f"restarted {s['restarts']}x")
        if any(not f["complete"] for f in files):
            state.append("unfinished file")
        if files and files[-1].get("completed"):
            state.append("complete")
        if files and files[-1].get("stopped"):
            stop = files[-1].get("stop_event") or {}
            details = stop.get("details") or {}
            state.append(
                "stopped: disk full"
                if details.get("disk_full")
                else "stopped: orphaned (launcher gone)"
                if details.get("orphaned")
                else "stopped"
            )
        lines.append(
            f"  {stage:<12} {len(files)} file(s)  errors {s['errors']}  {', '.join(state) or 'running or killed'}"
        )
        lines.append(f"  {'':<12} out: {_topics_text(s['outputs'])}")
        if s["inputs"]:
            lines.append(f"  {'':<12} in:  {_topics_text(s['inputs'])}")

    f = r["fits"]
    lines.append("")
    if f["count"]:
        last = f["table"][-1]
        lines.append(
            f"Coefficient trends (fitter fit JSON: {f['count']} fits [{_fmt_ranges(f['indices'])}], "
            f"last window {_days(last['t_start'])}..{_days(last['t_stop'])} d, "
            f"chi2/dof {_num(last['chi2_dof'])})"
        )
        lines.append(
            f"  {'coefficient':<12} {'latest [mm/rad]':>19} {'first':>8} {'min':>8} {'max':>8} "
            f"{'rate [mm/rad/day]':>22}   (rate: GLS line over the last {LOOKBACK_DAYS:g} d of fits)"
        )
        with_truth = "truth_file" in f
        if with_truth:
            lines[-1] += "   truth(last window)  (latest-truth)/sigma"
        for name, t in f["trends"].items():
            rate = (
                f"{t['rate']:+8.4f} ± {t['rate_se']:.4f}" + (" *" if abs(t["significance"]) >= 5 else "  ")
                if t["rate"] is not None
                else f"{'-':>20}"
            )
            line = (
                f"  {name:<12} {t['latest']:+9.4f} ± {t['sigma']:.4f} {t['first']:+8.4f} "
                f"{t['min']:+8.4f} {t['max']:+8.4f} {rate:>22}"
            )
            if with_truth and "truth_latest_window" in t:
                line += f"   {t['truth_latest_window']:+9.4f}   {t['error_over_sigma']:+6.2f}"
            lines.append(line)
        lines.append("  (* rate significant at 5 sigma with the overlap covariance of the rolling windows)")
        if with_truth:
            lines.append(f"  truth: {f['truth_file']}, averaged over the last fit window")
    else:
        lines.append("Coefficient trends: no fits recorded")

    m = r.get("model") or {}
    if m.get("model") or m.get("changes") or m.get("diagnoses"):
        lines.append("")
        current = m.get("model") or {}
        lines.append(
            f"Model (fitter): {','.join(current.get('effects') or ['?'])} at fit {current.get('index')}; "
            f"{len(m['changes'])} change(s), {len(m['diagnoses'])} live diagnos{'i' if len(m['diagnoses']) == 1 else 'e'}s"
        )
        for c in m["changes"]:
            lines.append(
                f"  from segment {c['from_index']}: {','.join(c['before'] or [])} -> {','.join(c['effects'] or [])}"
                f" ({c.get('by') or 'control'}{': ' + c['reason'] if c.get('reason') else ''})"
            )
        for d in m["diagnoses"]:
            seg = d.get("segments") or ["?", "?"]
            bands = ", ".join(f"{lo:.3g}-{hi:.3g} Hz ({chi:.3f})" for lo, hi, chi in d["failing_bands"]) or "none"
            lines.append(
                f"  diagnosis at segment {d['index']} (window {seg[0]}..{seg[1]}, model "
                f"{','.join(d.get('model') or [])}): chi2/dof {_num(d.get('chi2_dof'))}, failing bands {bands}"
            )
            if d.get("recommendation"):
                adopted = (d.get("adoption") or {}).get("adopted")
                lines.append(
                    f"    recommends {d['recommendation']}"
                    f"{' (explains the excess)' if d.get('explains') else ' (does not explain the excess)'}"
                    f"{': adopted' if adopted else ''}"
                )
                if d.get("command") and not adopted:
                    lines.append(f"    apply it: {d['command']}")
            elif d.get("message"):
                lines.append(f"    {d['message']}")
            elif not d.get("fails"):
                lines.append("    the model is adequate: nothing to add")

    lines.append("")
    lines.append(f"Alerts (monitor): {len(r['alerts'])}")
    for a in r["alerts"]:
        lines.append(f"  [{a.get('kind')}] {a.get('message')}")

    lines.append("")
    lines.append(f"Warnings: {len(r['warnings'])}")
    for w in r["warnings"][:MAX_LISTED]:
        lines.append(f"  {w.get('stage')} [{w.get('kind')}] {w.get('message')}")

    lines.append("")
    lines.append(f"Errors: {len(r['errors'])}")
    by = Counter((e["stage"], e["kind"]) for e in r["errors"])
    if by:
        lines.append("  " + ", ".join(f"{stage} {kind} x{n}" for (stage, kind), n in sorted(by.items())))
    for e in r["errors"][:MAX_LISTED]:
        where = f" segment {e['index']}" if e["index"] is not None else ""
        field = f" field {e['field']!r}" if e["field"] else ""
        lines.append(f"  {e['stage']} {e['kind']}{where}{field}: {e['message']}")
    if len(r["errors"]) > MAX_LISTED:
        lines.append(f"  ... {len(r['errors']) - MAX_LISTED} more (--json FILE for all)")

    lines.append("")
    lines.append(f"Gaps: {len(r.get('gaps', []))}")
    for g in r.get("gaps", [])[:MAX_LISTED]:
        span = f" ({g['seconds'] / 60:.1f} min of NaN)" if g.get("seconds") else ""
        lines.append(f"  {g['stage']} {g['kind']} segment {g['index']}{span}: {g['message']}")

    sec = r.get("security")
    if sec is not None:
        lines.append("")
        if not sec["present"]:
            lines.append("Security: no security.jsonl (a run with --insecure, or its launcher did not end)")
        else:
            lines.append(
                f"Security (security.jsonl): {sec['count']} refusal(s) by the router"
                + (
                    ", " + ", ".join(f"{k} x{v['count']}" for k, v in sorted(sec["kinds"].items()))
                    if sec["kinds"]
                    else ""
                )
            )
            for kind, v in sorted(sec["kinds"].items()):
                for rec in v["first"]:
                    lines.append(f"  {kind}: {_refusal_text(rec)}")
                if v["count"] > len(v["first"]):
                    lines.append(f"  {kind}: ... {v['count'] - len(v['first'])} more")
            if sec["unreadable"]:
                lines.append(f"  unreadable line(s) {_fmt_ranges(to_ranges(sec['unreadable']))}")

    lines.append("")
    lines.append(f"Interruptions: {len(r['interruptions'])}")
    for i in r["interruptions"]:
        lines.append(f"  {i['stage']}: {i['kind']}: {i['message']}")
    return "\n".join(lines)


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
    reader_log = logging.getLogger("streamer.recorder")
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
        try:
            return view.wait()
        except KeyboardInterrupt:
            return 0
        finally:
            view.close()
    cmd = view_command(args.run_dir)
    if args.print:
        print(shlex.join(cmd))
        return 0
    return subprocess.call(cmd)
