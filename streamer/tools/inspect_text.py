"""The text of ``ttl inspect`` (:func:`format_report` of :func:`streamer.tools.inspect.inspect_run`'s dict)."""

from __future__ import annotations

import json
from collections import Counter

from ..bus.keys import to_ranges
from .inspect_model import LOOKBACK_DAYS
from .model_timeline import change_text

#: Errors listed in full by the text report (the rest are counted).
MAX_LISTED = 20


def fmt_ranges(ranges) -> str:
    if not ranges:
        return "-"
    return ",".join(f"{a}" if a == b else f"{a}-{b}" for a, b in ranges)


def refusal_text(r: dict) -> str:
    when = f" at {r['time']}" if r.get("time") else ""
    if r.get("kind") == "forbidden":
        return f"{r.get('subject')} may not {r.get('action')} on {r.get('key')}{when}"
    return f"{r.get('message', json.dumps(r))}{when}"


def topics_text(table: dict) -> str:
    parts = []
    for topic, t in table.items():
        extra = ""
        if t["missing"]:
            extra += f" missing {fmt_ranges(t['missing'])}"
        if t["duplicates"]:
            extra += f" dup {fmt_ranges(to_ranges(t['duplicates']))}"
        parts.append(f"{topic} {t['distinct']} [{fmt_ranges(t['indices'])}]{extra}")
    return "; ".join(parts) or "-"


def _days(t) -> str:
    return f"{round(t / 86400.0, 3) + 0.0:.3f}" if isinstance(t, (int, float)) else "?"


def _num(x) -> str:
    return f"{x:.3f}" if isinstance(x, (int, float)) else "?"


def _span(a, b) -> str:
    return f"segment {a}" if a == b else f"segments {a}-{'' if b is None else b}"


def _hours(t_start, t_stop) -> str:
    if not (isinstance(t_start, (int, float)) and isinstance(t_stop, (int, float))):
        return ""
    return f" ({_days(t_start)}-{_days(t_stop)} d)"


def explained_in_words(recommendation: dict) -> str:
    """The reason of an adoption, in words: the share of the excess the effect explains, or,
    for glitches and gates, the share of their transients' excess they model (the share of
    the whole excess reads 0 % there: a glitch explains its event, not the stationary rest;
    the mission week's model timeline read "explains 0 % of the excess" for every glitch)."""
    actions = [a for a in recommendation.get("actions") or () if a.get("kind") in ("glitch", "gate")]
    shares = [float(a["explained_fraction"]) for a in actions if a.get("explained_fraction") is not None]
    if actions and len(actions) == len(recommendation.get("actions") or ()):
        what = f"models {len(actions)} transient(s)"
        return what + (f", {100 * min(shares):.0f} % or more of each one's excess" if shares else "")
    return f"explains {100 * float(recommendation.get('explained_fraction') or 0):.0f} % of the excess"


def _recommended(rec) -> str:
    """What a model change's ``recommendation`` (the adopted advice) says, in a few words."""
    if not isinstance(rec, dict):
        return ""
    parts = [str(rec.get("spec") or "?")]
    if isinstance(rec.get("explained_fraction"), (int, float)):
        parts.append(explained_in_words(rec))
    if isinstance(rec.get("log_bayes_factor"), (int, float)):
        parts.append(f"log Bayes factor {rec['log_bayes_factor']:.3g}")
    return "recommended " + ", ".join(parts)


def timeline_text(t: dict) -> list[str]:
    """The model timeline of ``ttl inspect`` (:func:`streamer.tools.inspect_timeline.model_timeline`):
    one line per model span, with what changed, by whom and why; then the fitter's gaps and
    the spans it left out of the fit."""
    lines = []
    models = t.get("models") or []
    if models:
        epochs = [s["from_index"] for s in models if s["new_epoch"]]
        lines.append(
            "  Timeline: the model from segment to segment"
            + (
                f" (new couplings from segment(s) {', '.join(map(str, epochs))}: the monitor's trends start "
                "a new series there)"
                if epochs
                else ""
            )
        )
    for s in models:
        fits = f"{s['fits']} fit{'' if s['fits'] == 1 else 's'}"
        lines.append(f"  {_span(s['from_index'], s['to_index']):<16} {','.join(s['effects'])}  ({fits})")
        if s["by"] == "configured":
            lines.append("      as configured")
            continue
        lines.append(
            "      "
            + change_text(
                s["added"],
                s["removed"],
                s["by"],
                diagnosis_index=s.get("diagnosis_index"),
                reason=s.get("reason"),
                new_epoch=s["new_epoch"],
            )
        )
        if _recommended(s.get("recommendation")):
            lines.append(f"      {_recommended(s['recommendation'])}")
    gaps = t.get("gaps") or []
    if gaps:
        lines.append(
            "  Gaps (no TDI segment: NaN pushed, window kept): "
            + "; ".join(f"{_span(g['from_index'], g['to_index'])}{_hours(g['t_start'], g['t_stop'])}" for g in gaps)
        )
    for x in t.get("excluded") or []:
        if x["kind"] == "gap":
            cause = "less than half valid (a gap in the data)"
        elif x["kind"] == "outlier":
            cause = f"outlier{'s' if x['count'] > 1 else ''}" + (
                f", up to {x['z_max']:.0f} sigma above the window" if isinstance(x.get("z_max"), (int, float)) else ""
            )
        else:
            cause = "gated" + (
                f" by the gate {_days(x['gate'][0])}-{_days(x['gate'][1])} d" if isinstance(x.get("gate"), list) else ""
            )
        lines.append(
            f"  Left out of the fit: fit{'s' if x['to_index'] > x['from_index'] else ''} "
            f"{_span(x['from_index'], x['to_index']).split(' ', 1)[1]}, "
            f"{x['count']} FFT segment(s){_hours(x['t_start'], x['t_stop'])}: {cause}"
        )
    return lines


def truth_test_lines(t: dict | None) -> list[str]:
    """The last fit against the truth: errors and the tests of its sigmas
    (:func:`ttlcore.estimate.pulls.pull_summary`)."""
    if not t:
        return []
    lo, hi = t["pull_rms_range"] or (float("nan"), float("nan"))
    return [
        f"  last fit against the truth: max |error| {t['max_abs_error'] * 1e3:.4f} mm/rad, pull RMS "
        f"{t['pull_rms']:.2f} ({lo:.2f}-{hi:.2f} for honest sigmas with this fit's correlations), "
        f"errors' chi2 {t['chi2']:.1f} for {t['n']} (p {t['p_value']:.3g}): sigmas {t['verdict']}"
    ]


def format_report(r: dict) -> str:
    """The text of ``ttl inspect``."""
    lines = _stages_text(r) + _fits_text(r["fits"]) + _model_text(r)
    lines += _alerts_text(r["alerts"]) + _warnings_text(r["warnings"]) + _errors_text(r["errors"])
    lines += _gaps_text(r.get("gaps", []))
    if r.get("security") is not None:
        lines += _security_text(r["security"])
    lines.append("")
    lines.append(f"Interruptions: {len(r['interruptions'])}")
    for i in r["interruptions"]:
        lines.append(f"  {i['stage']}: {i['kind']}: {i['message']}")
    return "\n".join(lines)


def _stages_text(r: dict) -> list[str]:
    """The run's line, then each stage's: its files and state, the topics it published and received."""
    run = r["run"] if isinstance(r["run"], str) else ", ".join(r["run"])
    total = f", {r['segments_total']} segments expected" if r["segments_total"] else ""
    lines = [f"run {run} ({r['directory']}): {len(r['stages'])} stage(s) recorded{total}"]
    if r["stages_missing"]:
        lines.append(f"  no recording of: {', '.join(r['stages_missing'])}")
    lines.append("")
    lines.append("Stages")
    for stage, s in r["stages"].items():
        state = _stage_state(s)
        lines.append(
            f"  {stage:<12} {len(s['files'])} file(s)  errors {s['errors']}  {', '.join(state) or 'running or killed'}"
        )
        lines.append(f"  {'':<12} out: {topics_text(s['outputs'])}")
        if s["inputs"]:
            lines.append(f"  {'':<12} in:  {topics_text(s['inputs'])}")
    return lines


def _stage_state(s: dict) -> list[str]:
    """A stage's state in words: restarts, an unfinished file, complete, how it stopped."""
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
    return state


def _fits_text(f: dict) -> list[str]:
    """The coefficient trends of the fits (with the truth over the last window when known)."""
    if not f["count"]:
        return ["", "Coefficient trends: no fits recorded"]
    last = f["table"][-1]
    lines = [
        "",
        f"Coefficient trends (fitter fit JSON: {f['count']} fits [{fmt_ranges(f['indices'])}], "
        f"last window {_days(last['t_start'])}..{_days(last['t_stop'])} d, "
        f"chi2/dof {_num(last['chi2_dof'])})",
        f"  {'coefficient':<12} {'latest [mm/rad]':>19} {'first':>8} {'min':>8} {'max':>8} "
        f"{'rate [mm/rad/day]':>22}   (rate: GLS line over the last {LOOKBACK_DAYS:g} d of fits)",
    ]
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
        lines += truth_test_lines(f.get("truth_test"))
    return lines


def _model_text(r: dict) -> list[str]:
    """The fitter's model: in force, its timeline, and each live diagnosis with the command
    that applies its advice (live or offline); nothing when no model was recorded."""
    m = r.get("model") or {}
    if not (m.get("model") or m.get("changes") or m.get("diagnoses") or any((r.get("timeline") or {}).values())):
        return []
    current = m.get("model") or {}
    lines = [
        "",
        f"Model (fitter): {','.join(current.get('effects') or ['?'])} at fit {current.get('index')}; "
        f"{len(m['changes'])} change(s), {len(m['diagnoses'])} live diagnos{'i' if len(m['diagnoses']) == 1 else 'e'}s",
    ]
    lines += timeline_text(r.get("timeline") or {})
    run_state = m.get("run_state") or {}
    if any(d.get("advice") or d.get("removal") for d in m["diagnoses"]):
        lines.append(
            f"  the run is live ({run_state.get('why')}): the commands below change the live fitter's model"
            if run_state.get("control")
            else f"  the run is not live here ({run_state.get('why')}): the commands below refit the recordings "
            "offline (ttl refit; ttl control works only while the run goes on)"
        )
    for d in m["diagnoses"]:
        lines += _diagnosis_text(d, bool(run_state.get("control")))
    return lines


def _diagnosis_text(d: dict, live: bool) -> list[str]:
    """One live diagnosis: its window, chi^2/dof and failing bands, what it recommends or
    why not, the evidence gone for an effect, with the commands (``live``: ttl control)."""
    seg = d.get("segments") or ["?", "?"]
    bands = ", ".join(f"{lo:.3g}-{hi:.3g} Hz ({chi:.3f})" for lo, hi, chi in d["failing_bands"]) or "none"
    lines = [
        f"  diagnosis at segment {d['index']} (window {seg[0]}..{seg[1]}, model "
        f"{','.join(d.get('model') or [])}): chi2/dof {_num(d.get('chi2_dof'))}, failing bands {bands}"
    ]
    if d.get("recommendation"):
        adopted = (d.get("adoption") or {}).get("adopted")
        lines.append(f"    recommends {d['recommendation']}{_explains_text(d)}{': adopted' if adopted else ''}")
        if d.get("advice") and not adopted:
            verb = "apply it" if live else "refit with it offline"
            lines.append(f"    {verb}: {d['advice']}")
    elif d.get("message"):
        lines.append(f"    {d['message']}")
    elif not d.get("fails"):
        lines.append("    the model is adequate: nothing to add")
    for x in d.get("removal") or []:
        verb = "remove it" if live else "refit without it offline"
        lines.append(f"    evidence gone: {x.get('spec')} (p = {_num(x.get('p'))}); {verb}: {x.get('advice')}")
    return lines


def _alerts_text(alerts: list[dict]) -> list[str]:
    """The monitor's alerts (with the model epoch they belong to)."""
    lines = ["", f"Alerts (monitor): {len(alerts)}"]
    for a in alerts:
        epoch = (a.get("details") or {}).get("model_epoch") if isinstance(a.get("details"), dict) else None
        lines.append(f"  [{a.get('kind')}] {a.get('message')}" + (f" (model epoch {epoch})" if epoch else ""))
    return lines


def _warnings_text(warnings: list[dict]) -> list[str]:
    """The stages' warnings (the first :data:`MAX_LISTED`)."""
    lines = ["", f"Warnings: {len(warnings)}"]
    for w in warnings[:MAX_LISTED]:
        lines.append(f"  {w.get('stage')} [{w.get('kind')}] {w.get('message')}")
    return lines


def _errors_text(all_errors: list[dict]) -> list[str]:
    """The stages' errors but the gap reports (listed under Gaps): counted by stage and kind,
    the first :data:`MAX_LISTED` in full."""
    # a segment with no data is a gap of the data, reported with an error message so that the
    # stages downstream move on: listed under Gaps, not here
    errors = [e for e in all_errors if e["kind"] != "gap"]
    gap_reports = len(all_errors) - len(errors)
    lines = ["", f"Errors: {len(errors)}" + (f" ({gap_reports} gap report(s): under Gaps)" if gap_reports else "")]
    by = Counter((e["stage"], e["kind"]) for e in errors)
    if by:
        lines.append("  " + ", ".join(f"{stage} {kind} x{n}" for (stage, kind), n in sorted(by.items())))
    for e in errors[:MAX_LISTED]:
        where = f" segment {e['index']}" if e["index"] is not None else ""
        field = f" field {e['field']!r}" if e["field"] else ""
        lines.append(f"  {e['stage']} {e['kind']}{where}{field}: {e['message']}")
    if len(errors) > MAX_LISTED:
        lines.append(f"  ... {len(errors) - MAX_LISTED} more (--json FILE for all)")
    return lines


def _gaps_text(gaps: list[dict]) -> list[str]:
    """The gaps of the run (the first :data:`MAX_LISTED`)."""
    lines = ["", f"Gaps: {len(gaps)}"]
    for g in gaps[:MAX_LISTED]:
        span = f" ({g['seconds'] / 60:.1f} min of NaN)" if g.get("seconds") else ""
        lines.append(f"  {g['stage']} {g['kind']} segment {g['index']}{span}: {g['message']}")
    return lines


def _security_text(sec: dict) -> list[str]:
    """The router's refusals (:func:`streamer.tools.inspect_records.security_report`)."""
    if not sec["present"]:
        return ["", "Security: no security.jsonl (a run with --insecure, or its launcher did not end)"]
    kinds = ", " + ", ".join(f"{k} x{v['count']}" for k, v in sorted(sec["kinds"].items())) if sec["kinds"] else ""
    lines = ["", f"Security (security.jsonl): {sec['count']} refusal(s) by the router{kinds}"]
    for kind, v in sorted(sec["kinds"].items()):
        for rec in v["first"]:
            lines.append(f"  {kind}: {refusal_text(rec)}")
        if v["count"] > len(v["first"]):
            lines.append(f"  {kind}: ... {v['count'] - len(v['first'])} more")
    if sec["unreadable"]:
        lines.append(f"  unreadable line(s) {fmt_ranges(to_ranges(sec['unreadable']))}")
    return lines


def _explains_text(d: dict) -> str:
    """What a live recommendation does for the model: it explains the failing bands' excess,
    it does not, or the model passes and the effect is a significant improvement only."""
    if d.get("fails") is False:
        return " (the model passes; a significant improvement, not a repair)"
    return " (explains the excess)" if d.get("explains") else " (does not explain the excess)"
