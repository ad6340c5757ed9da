"""The end of ``ttl run``: what happened to the plan's segments, and the exit status.

The launcher's final report (:func:`report`) reads its board (what it believed of every
stage, :class:`streamer.runtime.progress.Progress`), the error reports it received and the exit
statuses of its stage processes:

* **1**: a stage or the router died beyond ``--restart``, a stage gave up a segment for
  another reason than a gap in the data or did not handle every segment, a stage reported
  conflicting copies, or the run timed out;
* **3**: none of those, but segments were **lost**: a segment of the plan outside the gaps
  in the data got no fit or no residual (:func:`lost_segments`);
* **130 / 143**: interrupted (SIGINT / SIGTERM).

A gap in the data is not a loss: a segment with no data (``gaps`` in some stage's progress,
the replayer's ``gap`` error) needs neither; a NaN stretch inside a segment still gets its
fit (the window's fit before it, flagged ``excluded.gap``) and its residual.  A segment the
fitter had no data to fit yet (its ``no-fit`` warning: "the window holds no FFT segment with
data yet", the first segments gapped, gated or left out) needs no fit either
(:func:`no_data_yet`, read from the fitter's recordings only when some segment lacks a fit).
The final summary line names the lost segments and what each lacked.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from ttlcore.conventions import parse_duration

from ..bus.keys import to_ranges
from ..recording.recording_reader import RecordingError, read_recording
from ..runtime.progress import Progress
from ..runtime.rangeset import RangeSet

__all__ = ["EXIT_LOST", "conflicts", "fit_span", "lost_segments", "no_data_yet", "report", "spans"]

#: Exit status of a run that ended with every segment handled but some lost (no fit, no residual).
EXIT_LOST = 3
#: What the fitter's ``no-fit`` warning says of a segment it had no data to fit yet
#: (``stages.fitter.fitter.Fitter.no_fit``): not a loss.
NO_DATA_YET = "no FFT segment with data yet"


def no_data_yet(run_dir: Path, indices: Iterable[int]) -> set[int]:
    """Of ``indices``, the segments whose ``no-fit`` warning (in ``<run_dir>/fitter*.mcap``)
    says the fitter had no data to fit yet (:data:`NO_DATA_YET`); unreadable files give none."""
    wanted, out = set(indices), set()
    for path in sorted(Path(run_dir).glob("fitter*.mcap")):
        try:
            warnings = read_recording(path).json("warnings")
        except (RecordingError, OSError, ValueError):
            continue
        for w in warnings:
            if w.get("kind") == "no-fit" and w.get("index") in wanted and NO_DATA_YET in str(w.get("message")):
                out.add(w["index"])
    return out


def spans(indices: Iterable[int], limit: int = 10) -> str:
    """``{0, 1, 2, 5}`` -> ``"0..2, 5"`` (the first ``limit`` ranges, then ``...``)."""
    ranges = to_ranges(indices)
    text = ", ".join(f"{a}" if a == b else f"{a}..{b}" for a, b in ranges[:limit])
    return text + (", ..." if len(ranges) > limit else "")


def conflicts(errors: Iterable) -> list[str]:
    """The segments (``topic/index``, by first report) of which a stage reported
    conflicting copies (error ``kind: conflict`` on the errors topic)."""
    seen: dict[str, None] = {}
    for err in errors:
        if isinstance(err, dict) and err.get("kind") == "conflict":
            key = str(err.get("key") or "")
            seen.setdefault("/".join(key.split("/")[2:]) or f"segment {err.get('index')}", None)
    return list(seen)


def fit_span(fitter_options: Mapping, plan: Mapping | None) -> int:
    """Run segments per FFT segment of the fitter (``fit_segment`` over the plan's segment
    length, at least 1): with a longer FFT segment only the segment that completes one is
    refitted, and the segments before it are covered by that fit."""
    fit_segment = fitter_options.get("fit_segment")
    if not fit_segment or not plan or not plan.get("samples") or not plan.get("fs"):
        return 1
    try:
        seconds = parse_duration(fit_segment, "--fit-segment")
    except ValueError:
        return 1
    segment = plan["samples"] / plan["fs"]
    return max(1, math.ceil(seconds / segment - 1e-9))


def lost_segments(
    total: int | None,
    expected: Iterable[str],
    progress: Mapping[str, Progress],
    errors: Iterable = (),
    span: int = 1,
    no_data: Iterable[int] = (),
) -> dict[str, list[int]]:
    """The plan's segments outside the gaps in the data that got no fit or no residual.

    Parameters
    ----------
    total : int or None
        Segments of the plan (None: unknown, nothing is counted lost).
    expected : list of str
        The run's stages: a fit is required when the fitter is one of them, a residual when
        the subtractor is.
    progress : dict
        The launcher's board: ``gaps`` of every stage, the fitter's ``fits`` extra, the
        subtractor's ``done``.
    errors : list of dict
        Error reports: a subtractor's ``missing-fit`` (an announced fit that never came: the
        segment got an older one) counts its segment as without a fit.
    span : int
        Segments per FFT segment of the fitter (:func:`fit_span`): segment ``i`` has a fit
        when some fit ``j`` has ``i <= j < i + span``.
    no_data : list of int
        Segments the fitter had no data to fit yet (:func:`no_data_yet`): no fit needed.

    Returns
    -------
    dict
        ``"gaps"``, ``"no_fit"``, ``"no_residual"``, ``"lost"`` (the union of the two before):
        sorted lists of indices.
    """
    expected = list(expected)
    if not total:
        return {"gaps": [], "no_fit": [], "no_residual": [], "lost": []}
    gaps: set[int] = set()
    for p in progress.values():
        gaps |= set(p.gaps)
    wanted = [i for i in range(total) if i not in gaps]
    no_fit: list[int] = []
    if "fitter" in expected:
        fitter = progress.get("fitter")
        fits = sorted(fitter.extra.get("fits", ())) if fitter is not None else []
        missing = {
            e.get("index")
            for e in errors
            if isinstance(e, dict) and e.get("kind") == "missing-fit" and e.get("stage") == "subtractor"
        }
        fitted: set[int] = set()
        for j in fits:
            fitted.update(range(max(0, j - span + 1), j + 1))
        excused = set(no_data)
        no_fit = [i for i in wanted if (i not in fitted and i not in excused) or i in missing]
    no_residual: list[int] = []
    if "subtractor" in expected:
        sub = progress.get("subtractor")
        done = sub.done if sub is not None else RangeSet()
        no_residual = [i for i in wanted if i not in done]
    lost = sorted(set(no_fit) | set(no_residual))
    return {"gaps": sorted(gaps), "no_fit": no_fit, "no_residual": no_residual, "lost": lost}


def stage_failures(la: Any, abort: str | None) -> int:
    """Say, one line each, which stages exited badly, gave up segments or left segments
    unhandled, and which reported gaps; 1 when anything went wrong, else 0."""
    total = la.total
    status = 0
    for name, child in la.children.items():  # after a Ctrl-C: no news (a stage starting dies of it)
        bad = [c for c in child.exit_codes[-1:] if c != 0 and abort != "interrupted"]
        if bad:
            la.say(f"stage {name} exited with status {bad[0]} (log {child.log})")
            status = 1
    for s in la.expected:
        p = la.progress.get(s) or Progress(s)
        gaps = sorted(p.gaps)
        failed = sorted(p.failed - p.gaps)
        if gaps:
            la.say(f"stage {s}: gap(s) in the data at segment(s) {to_ranges(gaps)} (no data; reported)")
        if failed:
            la.say(f"stage {s} gave up segment(s) {failed}")
            status = 1
        if total is not None and s in la.progress and not la.handled(s).issuperset(range(total)):
            missing = sorted(set(range(total)) - la.handled(s))
            la.say(f"stage {s} did not handle segment(s) {missing[:20]}{' ...' if len(missing) > 20 else ''}")
            status = 1
    return status


def report(la: Any, abort: str | None) -> int:
    """The final report of launcher ``la`` (:class:`streamer.launch.launcher.Launcher`): what went
    wrong, one line each, then the summary line; returns the exit status (module docstring)."""
    la.end_status_line()
    total = la.total
    status = stage_failures(la, abort)
    found = conflicts(la.errors)
    if found:
        # two different copies of a segment were published: one of them was not the
        # producer's (docs/operations.md, "Conflicting copies"), whatever was used
        la.say(
            f"conflicting copies of {len(found)} segment(s) received: "
            + ", ".join(found[:10])
            + (" ..." if len(found) > 10 else "")
        )
        status = 1
    span = fit_span(la.opts.stage_options.get("fitter") or {}, la.run_plan)
    lost = lost_segments(total, la.expected, la.progress, la.errors, span)
    if lost["no_fit"]:  # those the fitter had no data for yet are not lost (its recordings say)
        no_data = no_data_yet(la.run_dir, lost["no_fit"])
        if no_data:
            lost = lost_segments(total, la.expected, la.progress, la.errors, span, no_data)
    lost_text = ""
    if lost["lost"]:
        parts = [f"no fit: {spans(lost['no_fit'])}"] if lost["no_fit"] else []
        parts += [f"no residual: {spans(lost['no_residual'])}"] if lost["no_residual"] else []
        lost_text = f", {len(lost['lost'])} lost outside the gaps ({'; '.join(parts)})"
        if status == 0:
            status = EXIT_LOST
    if abort:
        # what was lost, but after a Ctrl-C or SIGTERM (the run was stopped on purpose: the
        # line stays "run stopped: interrupted")
        stopped = abort in ("interrupted", "terminated")
        la.say(f"run stopped: {abort}" + (f"; {lost_text[2:]}" if lost_text and not stopped else ""))
        return {"interrupted": 130, "terminated": 143}.get(abort, 1)
    files = sorted(p.name for p in la.run_dir.glob("*.mcap")) + sorted(p.name for p in la.run_dir.glob("*.rrd"))
    refused = f", {len(la.refused)} refusal(s) by the router (security.jsonl)" if la.refused else ""
    # the counts also when the run failed: what went wrong is above, how much here
    la.say(
        f"{'done' if status == 0 else f'ended (exit status {status})'}: {total} segments{lost_text}, "
        f"{len(la.errors)} error report(s){refused}, {len(la.refused_progress)} progress message(s) "
        f"refused; files in {la.run_dir}: {', '.join(files)}",
        status=status == 0,
    )
    return status
