"""What ``ttl inspect`` reads besides the MCAP files: the launcher's journal
(``launcher.jsonl``), the router's refusals (``security.jsonl``), the run's plan
(``plan.json``), and the gaps the stages recorded; and :class:`InspectError`, the error of
every ``ttl inspect`` / ``ttl view`` module (re-exported by :mod:`streamer.tools.inspect`)."""

from __future__ import annotations

import json
from pathlib import Path

#: Refusals of each kind kept in the report (``security.jsonl``; the rest are counted).
MAX_REFUSALS = 5


class InspectError(ValueError):
    """The run cannot be inspected (message names the file or directory)."""


def json_object(value: object) -> dict:
    """``value`` when it is a JSON object (a dict), else an empty one: a recorded field that
    is missing or of another type reads as empty."""
    return value if isinstance(value, dict) else {}


def launcher_journal(run_dir: Path) -> list[dict]:
    """The interruptions ``ttl run`` recorded in ``launcher.jsonl`` (:mod:`streamer.launch.launcher`,
    "Journal and resuming"): every stage or router that died and was restarted, every
    launcher that ended without its ``end`` record (killed), every Ctrl-C and every ``--resume``."""
    path = Path(run_dir) / "launcher.jsonl"
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return []
    out: list[dict] = []
    open_start: dict | None = None
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
                out.append(_launcher_killed(open_start, path, "ended without its end record (killed)"))
            open_start = rec
        elif kind == "end":
            open_start = None
        elif kind in ("stage-died", "stage-restarted", "router-died", "router-restarted", "resume", "interrupted"):
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
        out.append(_launcher_killed(open_start, path, "has no end record (killed, or still running)"))
    return out


def _launcher_killed(start: dict, path: Path, what: str) -> dict:
    """The interruption of a ``ttl run`` whose journal ``path`` has its ``start`` record and no end."""
    return {
        "stage": "launcher",
        "kind": "launcher-killed",
        "file": path.name,
        "time": start.get("time"),
        "message": f"ttl run (pid {start.get('launcher_pid')}) {what}",
    }


def security_report(run_dir: Path) -> dict:
    """The router's refusals of a run (``security.jsonl``, written by ``ttl run`` with
    credentials when the run ends; :func:`streamer.bus.security.refusals`).

    Returns ``{"file", "present", "count", "kinds": {kind: {"count", "first": [the first
    MAX_REFUSALS records]}}, "unreadable": [line numbers]}``; ``present`` is False when the
    file is absent (a run with ``--insecure``, or whose launcher did not end).  A line that is
    not a JSON object with a ``kind`` is counted in ``unreadable``, not fatal (the file of a
    damaged run is still reported).
    """
    path = Path(run_dir) / "security.jsonl"
    kinds: dict[str, dict] = {}  # kind -> {"count", "first": the first MAX_REFUSALS records}
    unreadable: list[int] = []  # line numbers
    out = {"file": str(path), "present": path.exists(), "count": 0, "kinds": kinds, "unreadable": unreadable}
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
            unreadable.append(n)
            continue
        kind = kinds.setdefault(record["kind"], {"count": 0, "first": []})
        kind["count"] += 1
        if len(kind["first"]) < MAX_REFUSALS:
            kind["first"].append(record)
    out["count"] = sum(k["count"] for k in kinds.values())
    return out


def read_plan(run_dir: Path) -> dict | None:
    """The run's plan (``plan.json`` written by ``ttl run``), or None."""
    try:
        return json.loads((run_dir / "plan.json").read_text())
    except (OSError, ValueError):
        return None


def run_gaps(recs_of: dict, errors: list[dict], plan: dict | None) -> list[dict]:
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
