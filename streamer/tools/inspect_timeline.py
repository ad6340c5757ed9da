"""The fitter's model over a run as a timeline, for ``ttl inspect`` (key ``timeline`` of
:func:`streamer.tools.inspect.inspect_run`): what was in the model from which segment to which and
why, and the segments the fitter had no data for or left out of its fit.

Read from the fitter's recordings (``fitter.mcap`` and the files of earlier processes):

* ``model`` events (:meth:`stages.fitter.fitter.Fitter.change_model`): ``details`` ``effects`` (the
  new model), ``before``, ``from_index`` (the first segment fitted under it), ``by``
  (``control``, ``adopt auto``, ``window`` when a transient leaves the one-day window),
  ``reason``, ``recommendation`` (the diagnosis' advice that was adopted),
  ``diagnosis_index``, ``removed`` (the specs a ``window`` change takes out).  The model
  before the first change is the first fit's (``fit/summary`` ``model``), else that
  change's ``before``: the model the run was started with.
* ``gap`` events: a TDI segment that did not come (NaN pushed over its span, window kept).
* ``segment-excluded`` warnings (an FFT segment left out of the rolling fit as an outlier:
  ``t_start``, ``t_stop``, ``chi2_dof``, ``z``) and ``segment-gated`` events (one overlapping a
  gate of the model: ``t_start``, ``t_stop``, ``gate``).

Each model span says whether it starts a new *model epoch* of the monitor's trends (its
couplings differ from the span before: the step and drift tests start a new series there;
a change of the transients ``glitch`` and ``gate`` only does not,
:func:`ttlcore.diagnose.trends.model_key`).
"""

from __future__ import annotations

from ..bus.fit_record import FitMessage
from ..bus.keys import to_ranges
from ..recording.recorder import Recording
from .inspect_model import fit_summaries
from .inspect_records import json_object
from .model_timeline import SpanMerger, model_delta


def _fit_models(recs: list[Recording]) -> dict[int, list]:
    """Segment -> the model its fit was estimated under (``fit/summary``, else the fit
    segments' meta), a later file's fit winning."""
    models: dict[int, list] = {}
    for rec in recs:
        summaries = fit_summaries(rec)
        for s in summaries:
            if s.meta.model is not None:
                models[s.index] = list(s.meta.model)
        if not summaries:
            for m in rec.segments("fit"):
                model = FitMessage.from_header(m.header.meta, f"fit {m.header.index}").model
                if model is not None:
                    models[m.header.index] = list(model)
    return models


def _changes(recs: list[Recording]) -> list[dict]:
    """The ``model`` events, by segment (a change recorded twice - by a process and again by
    its restarted successor - once)."""
    out, seen = [], set()
    for rec in recs:
        for e in rec.json("events"):
            if not (isinstance(e, dict) and e.get("kind") == "model"):
                continue
            d = json_object(e.get("details"))
            start = d.get("from_index", e.get("index"))
            effects = d.get("effects")
            if not isinstance(start, int) or not isinstance(effects, list):
                continue
            key = (start, tuple(map(str, effects)), d.get("by"))
            if key in seen:
                continue
            seen.add(key)
            out.append({"from_index": start, "effects": list(effects), "event": d, "file": rec.path.name})
    return sorted(out, key=lambda c: c["from_index"])  # stable: two changes before one segment keep their order


def _segment_times(plan: dict | None, first: int, last: int) -> tuple[float | None, float | None]:
    """Mission time [s] from the start of segment ``first`` to the end of ``last`` (the
    run's plan, ``plan.json``; None without one)."""
    if plan is None:
        return None, None
    try:
        table = plan.get("table")
        if table:
            return float(table[first][0]), float(table[last][0]) + table[last][1] / float(plan["fs"])
        t0, n, fs = float(plan["t0"]), int(plan["samples"]), float(plan["fs"])
        return t0 + first * n / fs, t0 + (last + 1) * n / fs
    except (TypeError, KeyError, IndexError, ValueError):
        return None, None


def model_spans(recs: list[Recording]) -> list[dict]:
    """The model in force from which segment to which, and why (module docstring).

    Each span: ``from_index``, ``to_index`` (the last fit recorded for the last span; None
    when no fit is), ``effects``, ``added``, ``removed`` (against the span before), ``by``
    (``configured`` for the model the run started with), ``reason``, ``recommendation``,
    ``diagnosis_index``, ``new_epoch`` (new couplings: a new series of the monitor's trends),
    ``fits`` (fits recorded in the span), ``file``."""
    models = _fit_models(recs)
    changes = _changes(recs)
    last = max(models) if models else None
    first_fit = min(models) if models else None
    spans: list[dict] = []
    if first_fit is not None and (not changes or first_fit < changes[0]["from_index"]):
        initial, start = models[first_fit], first_fit
    elif changes and isinstance(changes[0]["event"].get("before"), list):
        initial, start = list(changes[0]["event"]["before"]), 0
    else:
        initial, start = None, None
    if initial is not None:
        spans.append({"from_index": start, "effects": initial, "by": "configured", "file": None, "event": {}})
    spans += [{**c, "by": c["event"].get("by") or "control"} for c in changes]
    out: list[dict] = []
    for k, span in enumerate(spans):
        nxt = spans[k + 1]["from_index"] if k + 1 < len(spans) else None
        to = nxt - 1 if nxt is not None else last
        if to is not None and to < span["from_index"]:
            continue  # superseded before a segment was fitted under it
        prev = out[-1]["effects"] if out else None
        event = span["event"]
        added, removed, new_epoch = model_delta(prev, span["effects"])
        out.append(
            {
                "from_index": span["from_index"],
                "to_index": to,
                "effects": span["effects"],
                "added": added,
                "removed": event.get("removed") or removed,
                "by": span["by"],
                "reason": event.get("reason"),
                "recommendation": event.get("recommendation"),
                "diagnosis_index": event.get("diagnosis_index"),
                "new_epoch": bool(new_epoch),
                "fits": sum(1 for i in models if span["from_index"] <= i and (to is None or i <= to)),
                "file": span["file"],
            }
        )
    return out


def fitter_gaps(recs: list[Recording], plan: dict | None) -> list[dict]:
    """The fitter's ``gap`` events as spans of consecutive segments (``from_index``,
    ``to_index``, ``segments``, ``t_start``, ``t_stop`` from the plan)."""
    indices = {
        e["index"]
        for rec in recs
        for e in rec.json("events")
        if isinstance(e, dict) and e.get("kind") == "gap" and isinstance(e.get("index"), int)
    }
    out = []
    for a, b in to_ranges(indices):
        t_start, t_stop = _segment_times(plan, a, b)
        out.append({"from_index": a, "to_index": b, "segments": b - a + 1, "t_start": t_start, "t_stop": t_stop})
    return out


def excluded_spans(recs: list[Recording]) -> list[dict]:
    """The FFT segments the rolling fit left out, as spans: consecutive fits that left out
    segments for the same cause (``kind`` ``outlier``: a ``segment-excluded`` warning, with
    the largest excess ``z_max`` in sigma; ``gated``: a ``segment-gated`` event, with its
    ``gate`` [s]; ``gap``: a ``segment-gap`` event, less than half of the FFT segment valid), with ``from_index``, ``to_index`` (the fits), ``t_start``, ``t_stop``
    (mission time [s] left out), ``count``."""
    wanted = {
        "segment-excluded": ("warnings", "outlier"),
        "segment-gated": ("events", "gated"),
        "segment-gap": ("events", "gap"),
    }
    items = {}
    for rec in recs:
        for kind, (topic, cause) in wanted.items():
            for r in rec.json(topic):
                if not isinstance(r, dict) or r.get("kind") != kind or not isinstance(r.get("index"), int):
                    continue
                d = json_object(r.get("details"))
                if not all(isinstance(d.get(k), (int, float)) for k in ("t_start", "t_stop")):
                    continue
                # the same FFT segment recorded again (a restarted fitter) counts once
                items[(float(d["t_start"]), cause)] = (r["index"], float(d["t_stop"]), d.get("gate"), d.get("z"))
    merger = SpanMerger()
    for (t_start, cause), (index, t_stop, gate, z) in sorted(items.items(), key=lambda kv: (kv[0][0], kv[1][0])):
        merger.add(cause, index, t_start, t_stop, gate=gate, z=z)
    return merger.spans


def model_timeline(recs: list[Recording], plan: dict | None) -> dict:
    """``{"models": model_spans, "gaps": fitter_gaps, "excluded": excluded_spans}`` of the
    fitter's recordings ``recs`` (oldest first) and the run's plan."""
    return {"models": model_spans(recs), "gaps": fitter_gaps(recs, plan), "excluded": excluded_spans(recs)}
