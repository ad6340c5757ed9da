"""The interruptions of a run that ``ttl inspect`` lists (:func:`streamer.tools.inspect.inspect_run`):
what each stage's recordings say went wrong (restarts, files unreadable, not closed, damaged,
closed without their ``stop`` event, segments cut off while written, a stage stopped by a full
disk or by itself, a window rebuilt after a restart), the stages that did not finish the
run's plan, and the launcher's journal."""

from __future__ import annotations

from pathlib import Path

from ..recording.recorder import Recording
from .inspect_records import launcher_journal
from .inspect_text import fmt_ranges


def interruptions(
    run_dir: Path, stages: dict[str, dict], recs_of: dict[str, list[Recording]], errors: list[dict], plan: dict | None
) -> list[dict]:
    """Every interruption of the run, stage by stage (:func:`stage_interruptions`), then the
    windows shortened after a restart (``errors``), the stages that did not handle every
    segment of the ``plan``, and the launcher's journal; each ``{"stage", "kind", "file" (or
    "files"), "message"}``."""
    out: list[dict] = []
    for stage, s in stages.items():
        out += stage_interruptions(stage, s, recs_of.get(stage, []))
    for e in errors:
        if e["kind"] == "window-shortened":
            out.append({"stage": e["stage"], "kind": "window-shortened", "file": e["file"], "message": e["message"]})
    if plan is not None:
        out += _unfinished(stages, plan["segments_total"])
    out.extend(launcher_journal(run_dir))
    return out


def stage_interruptions(stage: str, s: dict, recs: list[Recording]) -> list[dict]:
    """The interruptions of one stage (its report ``s``, its recordings ``recs``): its
    restarts, each file's problems (:func:`_file_problems`), the files it stopped by itself
    (orphaned) and the windows it rebuilt after a restart (``restored`` events)."""
    out: list[dict] = []
    names = [f["file"] for f in s["files"]]
    if s["restarts"]:
        out.append(
            {
                "stage": stage,
                "kind": "restart",
                "files": names,
                "message": f"{stage} ran {len(names)} times (recordings {', '.join(names)})",
            }
        )
    for f in s["files"]:
        out += _file_problems(stage, f)
    for f in s["files"]:
        stop = f.get("stop_event") or {}
        if (stop.get("details") or {}).get("orphaned"):
            out.append(
                {
                    "stage": stage,
                    "kind": "orphaned",
                    "file": f["file"],
                    "message": f"{f['file']}: stopped by itself: {stop.get('message')}",
                }
            )
    for rec in recs:
        for e in rec.json("events"):
            if isinstance(e, dict) and e.get("kind") == "restored":
                out.append({"stage": stage, "kind": "restored", "file": rec.path.name, "message": e.get("message")})
    return out


def _file_problems(stage: str, f: dict) -> list[dict]:
    """What one recording file ``f`` (its summary) of ``stage`` says went wrong: unreadable;
    stopped on a full disk, not closed (killed) or damaged after it was closed; closed with
    no ``stop`` event; segments with a header and no payload."""
    if not f["readable"]:
        return [{"stage": stage, "kind": "unreadable", "file": f["file"], "message": f["problem"]}]
    out = []
    note = f.get("stop_note") or {}
    if note.get("reason") == "disk-full":  # the stage said why it stopped (Recorder.note_stop)
        closed = "closed" if f["complete"] else f"not closed: salvaged {f['records']} records; {f['problem']}"
        message = f"{f['file']}: stopped: {note.get('message')} ({closed})"
        out.append({"stage": stage, "kind": "disk-full", "file": f["file"], "message": message})
    elif not f["complete"]:
        message = f"{f['file']} was not closed (process killed?): salvaged {f['records']} records; {f['problem']}"
        out.append({"stage": stage, "kind": "unfinished", "file": f["file"], "message": message})
    elif f["problem"]:  # closed, then damaged (flipped bytes): read past the damage
        message = f"{f['file']} is damaged: salvaged {f['records']} records; {f['problem']}"
        out.append({"stage": stage, "kind": "damaged", "file": f["file"], "message": message})
    if f["complete"] and not f["stopped"]:
        message = f"{f['file']} is closed but has no 'stop' event"
        out.append({"stage": stage, "kind": "no-stop", "file": f["file"], "message": message})
    for seg in f["incomplete_segments"]:
        message = (
            f"{f['file']}: {seg['topic']} segment {seg['index']} has a header but no payload (cut off while writing)"
        )
        out.append({"stage": stage, "kind": "incomplete-segment", "file": f["file"], "message": message})
    return out


def _unfinished(stages: dict[str, dict], total: int) -> list[dict]:
    """The stages whose first output misses segments of the plan's ``total`` and whose last
    file has no ``complete`` event."""
    out = []
    for stage, s in stages.items():
        first = next(iter(s["outputs"].values()), None) if s["outputs"] else None
        last = s["files"][-1] if s["files"] else {}
        if first is not None and first["missing"] and not last.get("completed"):
            out.append(
                {
                    "stage": stage,
                    "kind": "unfinished",
                    "file": last.get("file"),
                    "message": f"{stage} did not finish: segment(s) {fmt_ranges(first['missing'])} "
                    f"of {total} not handled",
                }
            )
    return out
