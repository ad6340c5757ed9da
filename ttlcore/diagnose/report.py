"""Reports of a diagnosis: the JSON parts (model, adequacy, coefficients), the
recommendation, and the one-minute text report (docs/diagnostics.md, "JSON report")."""

from __future__ import annotations

import shlex

import numpy as np

from ..conventions import COEFFICIENT_NAMES
from ..effects.registry import EFFECTS
from .adequacy import _hz, describe_failures, third_octave_table
from .model_fit import ModelFit
from .noise_model import noise_model_json
from .transients import NOT_AN_EFFECT


def fine_band_table(model: ModelFit):
    """``model``'s adequacy in third-octave bands where the data allow it
    (:func:`ttlcore.diagnose.adequacy.third_octave_table`), its fitted parameters (linear
    and noise) counted as in its band table."""
    data = model.data
    s = data.context.settings
    n_fitted = 6 * data.grid.f.size * len(data.grid.starts) - float(model.bands.dof.sum())
    return third_octave_table(
        model.residual_w, data.grid.f, s.band, n_fitted, data.grid.kappa, s.tolerance, s.alpha, s.min_band_dof
    )


def adequacy_json(model: ModelFit) -> dict:
    """The ``adequacy`` part of the report for ``model``."""
    data = model.data
    s = data.context.settings
    bands = model.bands.to_json()
    summary = describe_failures(model.bands)
    fine = fine_band_table(model)
    summary += [f"localised (third-octave bands): {x}" for x in describe_failures(fine)]
    nm = data.noise.parameters
    if nm is not None and nm.at_bound:
        summary.append(
            f"noise level(s) {', '.join(nm.at_bound)} at the bound of their allowed range: more (or less) "
            "noise of that shape than the instrument is known to have, or an unmodelled effect of that shape"
        )
    time_part = model.time_table or {}
    summary += time_part.get("summary", [])
    return {
        "noise_model": noise_model_json(data.noise.parameters),
        "tolerance": s.tolerance,
        "alpha": s.alpha,
        "variance_factor": data.grid.kappa,
        "band": list(map(float, s.band)),
        "segment_duration": data.grid.seg_duration,
        "segments": len(data.grid.starts),
        "chi2": model.chi2,
        "dof": model.dof,
        "chi2_dof": model.chi2_dof,
        "bands": bands,
        "fine_bands": fine.to_json(),
        "time": time_part,
        "fails": bool(any(b["fails"] for b in bands) or any(r.get("fails") for r in time_part.get("segments", []))),
        "summary": summary or ["no failure: the residual is consistent with the instrument noise model"],
    }


def coefficients_json(model: ModelFit, truth=None) -> dict:
    """The fitted columns (value, robust sigma: :attr:`ModelFit.robust_sigma`) and, with truth, the errors of the 24 linear ones;
    ``offsets``: the fitted offsets of linearised effects (expansion point + ``d1``)."""
    out: dict = {
        "values": {n: float(v) for n, v in zip(model.parameter_names, model.theta)},
        "sigma": {n: float(v) for n, v in zip(model.parameter_names, model.robust_sigma)},
    }
    offsets = {k: {"value": v, "sigma": sg, "unit": "s"} for k, (v, sg) in model.offsets().items()}
    if offsets:
        out["offsets"] = offsets
    if truth is not None:
        C, sig = model.ttl_coefficients(), model.ttl_sigma()
        err = C - np.asarray(truth, dtype=float)
        z = err / sig
        ok = np.isfinite(z)
        out["truth"] = dict(zip(COEFFICIENT_NAMES, map(float, truth)))
        out["error"] = {n: float(e) for n, e, k in zip(COEFFICIENT_NAMES, err, ok) if k}
        out["max_abs_error"] = float(np.nanmax(np.abs(err)))
        out["max_abs_error_over_sigma"] = float(np.nanmax(np.abs(z)))
        out["rms_error"] = float(np.sqrt(np.nanmean(err**2)))
    return out


def model_json(model: ModelFit, truth=None) -> dict:
    """The ``model`` (or ``before``, ``baseline``) part of a report."""
    return {
        "effects": [e.spec() for e in model.effects],
        "n_parameters": len(model.names),
        "cli_effects": ",".join(e.cli_spec() for e in model.effects),
        "searched": dict(model.searches),
        "chi2_dof": model.chi2_dof,
        "adequacy": adequacy_json(model),
        "coefficients": coefficients_json(model, truth),
    }


#: A candidate is recommended only when it explains at least this share of the excess (chi^2
#: beyond the tolerance, over all bands) and of the excess of at least one failing band.
MIN_EXPLAINED = 0.5


def band_explained(report: dict, candidate: dict) -> list[float]:
    """Per failing band of the model, the share of its excess (chi^2 beyond ``(1 + tol)
    dof``, divided by ``kappa``) that ``candidate``'s delta chi^2 in that band explains."""
    ad = report["adequacy"]
    if "bands" not in ad or "bands" not in candidate.get("where", {}):
        return []  # a report without its band table (a partial one built by hand)
    kappa = float(ad.get("variance_factor") or 1.0)
    tol = float(ad.get("tolerance", 0.0))
    out = []
    for b, cb in zip(ad["bands"], candidate["where"]["bands"]):
        if not b["fails"]:
            continue
        excess = (b["chi2"] - (1 + tol) * b["dof"]) / kappa
        out.append(float(max(cb["delta_chi2"], 0.0) / excess) if excess > 0 else 1.0)
    return out


def excess_description(report: dict) -> str:
    """What the excess looks like, in one sentence, from the transient finder's
    classification (:func:`ttlcore.diagnose.excess.transient_report`) and the failing
    bands."""
    tr = report.get("transients") or {}
    verdict = tr.get("classification") or {}
    cls = verdict.get("class")
    failing = [s for s in report["adequacy"].get("summary", []) if s.startswith("fails between")]
    where = failing[0] if failing else "no band fails"
    q = tr.get("quiet") or {}
    if cls == "gravitational-wave" and q.get("fails"):  # in every hour, T nearly empty (a gap's may fail too)
        return (
            f"the excess is a long-lived gravitational-wave-like signal, not a missing effect: in every hour "
            f"(outside any transient chi2/dof {q.get('chi2_dof', float('nan')):.3f}), {where}, T carrying "
            f"{100 * (q.get('t_share') or 0.0):.1f} % of it"
        )
    if verdict.get("signal"):
        ev = tr["events"]
        parts = [
            f"{e['class']} {e['t_start'] / 3600:.2f}-{e['t_stop'] / 3600:.2f} h ({e['f_lo'] * 1e3:.3g}-"
            f"{e['f_hi'] * 1e3:.3g} mHz, {', '.join(e['channels'])}, T share {100 * e['t_share']:.1f} %, "
            f"track {e['track_kind']})"
            for e in ev[:3]
        ]
        parts += [f"missing data {a / 3600:.2f}-{b / 3600:.2f} h" for a, b in (tr.get("gaps") or [])[:3]]
        text = f"the excess is a transient or a gap, not a missing effect: {'; '.join(parts)}"
        q = tr.get("quiet") or {}
        if q.get("chi2_dof") is not None:
            text += f"; outside it the residual reads chi2/dof {q['chi2_dof']:.3f} ({q['hours']:.1f} h)"
        rb = tr.get("robustness")
        if rb:
            text += f"; the TTL fit without those hours moves by at most {rb['max_abs_shift_sigma']:.2f} sigma"
        return text
    if cls == "stationary-excess":
        share = q.get("t_share")
        return (
            f"the excess is stationary (every hour; outside any transient chi2/dof "
            f"{q.get('chi2_dof', float('nan')):.3f}), {where}"
            + (f", T carrying {100 * share:.0f} % of it" if share is not None else "")
            + ": no named effect or witness explains it"
        )
    return f"{where}"


def recommendation(report: dict, effects) -> dict | None:
    """The next step: when the transient finder localised excess in time, the glitches and
    gates that take it, before any effect (the effect candidates are scored again on the
    data without them at the next step), unless the excess reads as a missing coupling
    (``transients.classification.class``) that the best candidate explains: then, and
    otherwise, :func:`effect_recommendation`.  With the
    transients' actions (``report["transients"]["actions"]``,
    :func:`ttlcore.diagnose.transient_advice.transient_actions`) ``option`` adds all of them at once (``--effects
    linear-ttl,glitch:t=9720.4s,tm=12,beta=31.2s,gate:start=15.2h,stop=15.8h``), ``actions`` lists them and ``message``
    reads ``"add glitch at 2.70 h on tm 12 (...); gate 15.20-15.80 h"``."""
    rec = effect_recommendation(report, effects)
    actions = (report.get("transients") or {}).get("actions") or []
    if not actions:
        return rec
    if (
        rec
        and rec.get("option")
        and ((report.get("transients") or {}).get("classification") or {}).get("class") == "missing-coupling"
    ):
        # a coupling that explains the excess comes first: a coupling to jitter whose level
        # changes over the day leaves bursts in the time-frequency map at its resonance, read
        # as events, and gating or "glitches" fitted to them only hid hours of the coupling
        # (two blind lisainstrument days: 15 gates, then 7 glitches advised, the coupling that
        # explained 100 % of the excess never; the bands failed at the end). Real transients
        # are still there at the next diagnosis, on the model with the coupling.
        return rec
    # transients first: a loud signal or glitch pulls the noise levels and the linear fit
    # the effects are scored against (a merger's hours read as a missing second-order term);
    # once they are gated or fitted, the next diagnosis scores the effects on clean data
    rec = dict(rec or {})
    tr = report.get("transients") or {}
    verdict = tr.get("classification") or {}
    specs = [e.cli_spec() for e in effects] + [a["cli_spec"] for a in actions]
    value = ",".join(specs)
    option = "--effects " + shlex.quote(value)
    texts = "; ".join(a["text"] for a in actions)
    description = rec.get("description") or excess_description(report)
    if rec.get("option"):
        rec["effect_after"] = {"cli_spec": rec.get("cli_spec"), "explained_fraction": rec.get("explained_fraction")}
    rec.update(
        {
            "effect": actions[0]["kind"],
            "spec": ",".join(a["spec"] for a in actions),
            "cli_spec": ",".join(a["cli_spec"] for a in actions),
            "option": option,
            "explains": True,
            "actions": actions,
            "excess_class": verdict.get("class"),
            "signal": bool(verdict.get("signal")),
            "description": description,
            "message": f"the excess is localised in time: {texts}" + (f" ({description})" if description else ""),
        }
    )
    rec.setdefault("pointers", [])
    return rec


def with_candidate(specs: list[str], candidate: dict) -> list[str]:
    """The model ``specs`` with a ranking's entry ``candidate`` in it: added at the end, or
    in the place of the effect it ``replaces`` (a shape searched again)."""
    old = candidate.get("replaces")
    if old and old in specs:
        return [candidate["cli_spec"] if s == old else s for s in specs]
    return [*specs, candidate["cli_spec"]]


def _taken_outside(best: dict, quiet: dict) -> float:
    """The delta chi^2 the best candidate takes of the data outside the signals: its score on
    the model with the signals gated - from the ranking there (``delta_chi2_gated``) or, when
    that did not run, the transient report's (``quiet.best_delta_chi2_gated``, the same
    candidate: the first significant) - and its score on the data as they are only when it
    was scored on no gated data.  That score takes the signals too: a live window with 3.6 h
    of a chirp ungated scored a 5.9 mHz resonance at delta chi2 8989 there and 63 gated, was
    classed a stationary excess (63 is under half the quiet excess) and still advised and
    adopted it as explaining 100 % (merger-and-glitches day, segment 9)."""
    same = quiet.get("best_gated_spec", best["spec"]) == best["spec"]
    for taken in (best.get("delta_chi2_gated"), quiet.get("best_delta_chi2_gated") if same else None):
        if taken is not None:
            return float(taken)
    return float(best["delta_chi2"])


def effect_recommendation(report: dict, effects) -> dict | None:
    """The next step: the significant candidate with the largest (marginal) log Bayes
    factor over everything tried (named effects, witness effects, frequency-dependent
    couplings, plugins), its ``--effects`` option runnable as printed (quoted when a shell
    would split or read it otherwise).

    The option is given only when the candidate *explains* the excess: at least
    :data:`MIN_EXPLAINED` of the excess over all bands and of at least one failing band's
    (:func:`band_explained`), and the excess is not a signal or a defect of the data (the
    transient finder's ``classification.signal``: a gravitational wave, glitches, a gap or
    a change of the noise level, for which no effect is recommended).  Otherwise ``option``
    is empty and ``message`` says what the excess looks like (:func:`excess_description`);
    ``pointers`` lists what the top witnesses point at.  None when the model is adequate,
    nothing is significant and no transient was found.

    Keys: ``effect``, ``spec``, ``cli_spec`` (the best candidate, None without one),
    ``option`` (``--effects ...`` or ``""``), ``explains``, ``explained_fraction``,
    ``band_explained`` (per failing band), ``explained_fraction_outside_transients`` (when
    signals share the data with a stationary excess: the share of the excess outside them,
    which then decides), ``excess_class`` (the transient finder's class of the excess),
    ``signal``, ``description``, ``pointers``, ``message``.
    """
    cands = report["candidates"]
    best = next((c for c in cands if c["significant"]), None)
    fails = bool(report["adequacy"]["fails"])
    tr = report.get("transients") or {}
    verdict = tr.get("classification") or {}
    signal = bool(verdict.get("signal"))
    if best is None and not fails and not tr.get("events"):
        return None
    pointers = []
    for w in (report.get("witnesses") or {}).get("overall", [])[:3]:
        pointers.append(
            {"witness": w["name"], "spec": w.get("spec"), "band_hz": w["best_band"], "delta_chi2": w["delta_chi2"]}
        )
    point_text = "; ".join(f"{p['witness']} ({p['band_hz'][0]:.3g}-{p['band_hz'][1]:.3g} Hz)" for p in pointers)
    description = excess_description(report) if (fails or signal) else ""
    common = {"excess_class": verdict.get("class"), "signal": signal, "description": description}
    if best is None:
        msg = "no candidate is significant"
        msg += f"; {description}" if description else ""
        msg += f"; the witnesses point at: {point_text}" if pointers else ""
        return {"effect": None, "option": "", "explains": False, "pointers": pointers, "message": msg, **common}
    specs = with_candidate([e.cli_spec() for e in effects], best)
    value = ",".join(specs)
    option = "--effects " + shlex.quote(value)
    per_band = band_explained(report, best) if fails else []
    explains = not fails or (
        best["explained_fraction"] >= MIN_EXPLAINED and (not per_band or max(per_band) >= MIN_EXPLAINED)
    )
    # with signals in the data (a merger, glitches) their excess is no candidate's to
    # explain: the share is then that of the excess outside them, the quiet tiles' level
    # over the whole span (transients.quiet.excess_chi2_full_span, divided by kappa as the
    # candidates' excess)
    q = tr.get("quiet") or {}
    outside = q.get("excess_chi2_full_span")
    kappa = float(report["adequacy"].get("variance_factor") or 1.0)
    beside = [e for e in tr.get("events", []) if e["class"] in NOT_AN_EFFECT]
    frac_outside = None
    if fails and beside and q.get("fails") and outside:
        frac_outside = float(min(1.0, max(_taken_outside(best, q), 0.0) / (outside / kappa)))
        explains = frac_outside >= MIN_EXPLAINED
    out = {
        "effect": best["effect"],
        "spec": best["spec"],
        "cli_spec": best["cli_spec"],
        "option": option if explains and not signal else "",
        "explains": bool(explains and not signal),
        "explained_fraction": best["explained_fraction"],
        "band_explained": per_band,
        "explained_fraction_outside_transients": frac_outside,
        **({"replaces": best["replaces"]} if best.get("replaces") else {}),
        **common,
    }
    if not fails and not signal:
        out["message"] = (
            f"the model passes the noise test, but {best['cli_spec']} improves it significantly "
            f"(delta chi2 {best['delta_chi2']:.1f} for {best['n_parameters']} parameter"
            f"{'s' if best['n_parameters'] != 1 else ''}, log Bayes factor {best['log_bayes_factor']:.1f}): "
            "an effect too small to fail the test at its tolerance, yet measured"
        )
    if signal:
        out["pointers"] = pointers
        out["message"] = f"no effect recommended: {description} (the best candidate, {best['cli_spec']}, would fit it)"
    elif not explains:
        out["pointers"] = pointers
        out["message"] = (
            f"no candidate explains the excess (the best, {best['cli_spec']}, explains "
            f"{100 * best['explained_fraction']:.0f} %, at most "
            f"{100 * max(per_band or [0.0]):.0f} % of a failing band's; {100 * MIN_EXPLAINED:.0f} % needed)"
            + (f"; {description}" if description else "")
            + (f"; the witnesses point at: {point_text}" if pointers else "")
        )
    return out


def _offset_text(group: str, value: float, intervals: dict) -> str:
    """``"sc1 +0.35025 +- 0.00088 s"``: a candidate's offset [s] with the half-width of its
    searched interval (``offset.<group>``), to the sigma's second digit; without an
    interval, three significant digits."""
    lo_hi = intervals.get(f"offset.{group}")
    if not lo_hi:
        return f"{group} {value:+.3g} s"
    sigma = 0.5 * (lo_hi[1] - lo_hi[0])
    digits = max(0, 1 - int(np.floor(np.log10(sigma)))) if sigma > 0 else 3
    return f"{group} {value:+.{digits}f} +- {sigma:.2g} s"


def _estimate_text(effect: str, option: str, value: float) -> str:
    """``"f0 0.01143 Hz"``: a searched option of a candidate with the unit of the effect's
    option (:attr:`ttlcore.effects.base.Effect.units`; an offset ``offset.<group>`` in s)."""
    cls = EFFECTS.get(effect)
    unit = "s" if option.startswith("offset.") else (cls.units.get(option) if cls is not None else None)
    return f"{option} {value:.4g}" + (f" {unit}" if unit in ("s", "Hz", "rad") else "")


def text_report(report: dict, source: str = "", max_candidates: int = 5) -> str:
    """The one-minute text report."""
    m = report["model"]
    ad = report["adequacy"]
    lines = [
        f"{source}: model {', '.join(m['effects'])} ({m['n_parameters']} parameters), "
        f"chi2/dof {ad['chi2_dof']:.3f} against the instrument noise model"
        f"{' (fitted levels)' if ad['noise_model'].get('kind') == 'fitted' else ''} "
        f"({1e3 * ad['band'][0]:.3g} mHz - {ad['band'][1]:.3g} Hz, tolerance {100 * ad['tolerance']:.0f} %)"
    ]
    if "before" in report:
        lines += _before_after_lines(report)
    elif "max_abs_error" in m["coefficients"]:
        c = m["coefficients"]
        lines.append(
            f"  truth: max |coefficient error| {1e3 * c['max_abs_error']:.4f} mm/rad ({c['max_abs_error_over_sigma']:.1f} sigma)"
        )
    lines.append("  where the model fails:")
    lines += [f"    {x}" for x in ad["summary"]]
    lines += _candidate_lines(report, max_candidates)
    w = report.get("witnesses")
    if w:
        lines.append(
            f"  top witnesses ({w['n_witnesses']} tried): "
            + "; ".join(
                f"{x['name']} (delta chi2 {x['delta_chi2']:.0f}, coherence peaks at {_hz(x['peak_frequency'])})"
                for x in w["overall"][:3]
            )
        )
    tr = report.get("transients")
    if tr:
        lines += transient_lines(tr)
    return "\n".join(lines + _recommendation_lines(report.get("recommendation"), source))


def _before_after_lines(report: dict) -> list[str]:
    """The text report's comparison of the model before and after a change."""
    b, m, ad, ch = report["before"], report["model"], report["adequacy"], report["change"]
    lines = [
        "  before -> after (" + ", ".join(ch["added"]) + "):",
        "    (both columns against the noise levels fitted with the new model; a report of the old model",
        "    alone fits the levels to it, which then absorb part of its excess and read lower)",
        "    band [Hz]            chi2/dof before   after",
    ]
    for bb, ba in zip(b["adequacy"]["bands"], ad["bands"]):
        lines.append(
            f"    {bb['f_lo']:.4f} - {bb['f_hi']:.4f}      {bb['chi2_dof']:8.3f}{' FAIL' if bb['fails'] else '     '}"
            f"  {ba['chi2_dof']:8.3f}{' FAIL' if ba['fails'] else ''}"
        )
    if ch.get("delta_chi2") is not None:
        lines.append(
            f"    evidence for the change: delta chi2 {ch['delta_chi2']:.1f}, log Bayes factor {ch['log_bayes_factor']:.1f}"
        )
    if "max_abs_error" in b["coefficients"] and "max_abs_error" in m["coefficients"]:
        lines.append(
            f"    max |coefficient error|: {1e3 * b['coefficients']['max_abs_error']:.4f} -> "
            f"{1e3 * m['coefficients']['max_abs_error']:.4f} mm/rad "
            f"({b['coefficients']['max_abs_error_over_sigma']:.1f} -> {m['coefficients']['max_abs_error_over_sigma']:.1f} sigma)"
        )
    return lines


def _candidate_lines(report: dict, max_candidates: int) -> list[str]:
    """The text report's candidates (the first ``max_candidates``) and their gated rescoring."""
    cands = report["candidates"]
    fails = report["adequacy"]["fails"]
    lines = ["  candidates (effect: delta chi2 / dof, log Bayes factor, share of the excess, where):"]
    lines += [_candidate_line(c, fails) for c in cands[:max_candidates]]
    if not any(c["significant"] for c in cands):
        lines.append("    no candidate is significant")
    rg = report.get("candidates_gated")
    if rg:
        spans = ", ".join(f"{a / 3600:.2f}-{b / 3600:.2f} h" for a, b in rg["spans"][:4])
        more = f" and {len(rg['spans']) - 4} more" if len(rg["spans"]) > 4 else ""
        lines.append(
            f"    scored again with {spans}{more} gated (the signals' hours): {rg['chosen']} first, {rg['reason']}"
        )
    return lines


def _candidate_line(c: dict, fails: bool) -> str:
    """One candidate's line (``fails``: the model fails, so there is an excess to share out)."""
    where = c["where"]
    bands = ", ".join(f"{lo:.3g}-{hi:.3g} Hz" for lo, hi in where["main_bands"][:3])
    links = ", ".join(x["group"] for x in where["links"][:3])
    extra = f", t_step {where['t_step'] / 3600:.2f} h" if "t_step" in where else ""
    if "offsets" in where:
        top = sorted(where["offsets"].items(), key=lambda kv: -abs(kv[1]))[:3]
        intervals = c.get("searched", {}).get("offset_search", {}).get("intervals", {})
        extra += ", offsets " + ", ".join(_offset_text(k[len(c["effect"]) + 1 :], v, intervals) for k, v in top)
    if "search" in c.get("searched", {}):
        est = c["searched"]["search"]["estimates"]
        extra += ", " + ", ".join(_estimate_text(c["effect"], k, v) for k, v in est.items())
    label = c["effect"] if c["cli_spec"] == c["effect"] else c["cli_spec"]
    if c.get("replaces"):
        extra += f", in the place of {c['replaces']}"
    # a model that passes has no excess to share out: "-", not "0 %"
    share = f"{100 * c['explained_fraction']:5.0f} %" if fails else "    - "
    return (
        f"    {'*' if c['significant'] else ' '} {label:<16} {c['delta_chi2']:10.1f} / {c['n_parameters']:<3d}"
        f" logB {c['log_bayes_factor']:9.1f}  {share}  [{bands}; {links}{extra}]"
    )


def _recommendation_lines(rec: dict | None, source: str) -> list[str]:
    """The text report's best next step and the recommendation's message."""
    lines = []
    if rec and rec.get("option") and rec.get("actions"):
        lines.append(
            f"  best next step: {'; '.join(a['text'].split(' (')[0] for a in rec['actions'])}:  "
            f"ttl diagnose {source or 'DATA'} {rec['option']}"
        )
    elif rec and rec.get("option"):
        verb = (
            f"put {rec['cli_spec']} in the place of {rec['replaces']}"
            if rec.get("replaces")
            else f"add {rec['cli_spec']}"
        )
        lines.append(f"  best next step: {verb}:  ttl diagnose {source or 'DATA'} {rec['option']}")
    if rec and rec.get("message"):
        lines.append(f"  {rec['message']}")
    return lines


def transient_lines(tr: dict) -> list[str]:
    """The text report's lines on transients (:mod:`ttlcore.diagnose.transients`)."""
    lines = _event_lines(tr)
    for a in tr.get("actions") or []:
        lines.append(_transient_action_line(a))
    for a in tr.get("not_advised") or []:  # detectable, but the TTL fit does not move
        lines.append(f"    (not advised: {a['text']}: {a['reason']})")
    verdict = tr.get("classification") or {}
    if verdict.get("class") not in (None, "none"):
        lines.append(
            f"  the excess: {verdict['class']}"
            + ("" if not verdict.get("evidence") else " (" + "; ".join(verdict["evidence"][:4]) + ")")
        )
    rb = tr.get("robustness")
    if rb:
        names, sh = rb["names"], np.abs(rb["shift_sigma"])
        top = np.argsort(-sh)[:3]
        lines.append(
            "  TTL fit with and without those hours: largest shifts "
            + ", ".join(f"{names[i]} {rb['shift_sigma'][i]:+.2f} sigma" for i in top)
        )
    gm = tr.get("gated_model")
    if gm:
        ad = gm["adequacy"]
        hours = [
            r["chi2_dof"]
            for r in (ad.get("time") or {}).get("segments", [])
            if not any(r["t_start"] < b and r["t_stop"] > a for a, b in gm["spans"])
        ]
        lines.append(
            f"  the model with those hours gated: chi2/dof {ad['chi2_dof']:.3f} ({'fails' if ad['fails'] else 'consistent'})"
            + (f", the {len(hours)} hours outside them {np.mean(hours):.3f}" if hours else "")
        )
    return lines


def _event_lines(tr: dict) -> list[str]:
    """The transients' events (the first five), the data gaps and the residual outside them."""
    lines = []
    ev = tr.get("events") or []
    q = tr.get("quiet") or {}
    if ev or tr.get("gaps"):
        lines.append(f"  transients ({tr['tile_duration']:.0f}-s tiles of the whitened residual per channel):")
        for e in ev[:5]:
            lines.append(
                f"    {e['class']:<18} {e['t_start'] / 3600:6.2f}-{e['t_stop'] / 3600:.2f} h  "
                f"{e['f_lo'] * 1e3:.3g}-{e['f_hi'] * 1e3:.3g} mHz  in {', '.join(e['channels']) or '-'}  "
                f"T share {100 * e['t_share']:.1f} %  track {e['track_kind']}  SNR {e['snr']:.0f}  "
                f"witnesses {100 * e['coherence'].get('explained_fraction', 0):.0f} %"
            )
        if len(ev) > 5:
            lines.append(f"    ... {len(ev) - 5} more")
        for a, b in tr.get("gaps") or []:
            lines.append(f"    missing data {a / 3600:.2f}-{b / 3600:.2f} h (gated before the fit)")
    if q.get("chi2_dof") is not None and (ev or tr.get("gaps")):
        lines.append(
            f"    outside them ({q['hours']:.1f} h{', the model refitted with them gated' if q.get('gated') else ''}): "
            f"chi2/dof {q['chi2_dof']:.3f} against the noise model"
            f" ({'fails' if q['fails'] else 'consistent'})"
        )
    return lines


def _transient_action_line(a: dict) -> str:
    """One action on a transient: a glitch with its evidence, or another action with the
    share a glitch would have taken."""
    if a["kind"] == "glitch":
        return (
            f"    -> {a['text']}: delta chi2 {a['delta_chi2']:.0f}, logB {a['log_bayes_factor']:.1f}, "
            f"takes {100 * a['explained_fraction']:.0f} % of the transient's excess"
        )
    tried = a.get("glitch_tried")
    return f"    -> {a['text']}" + (
        f" (a glitch takes only {100 * tried['explained_fraction']:.0f} % of it: {tried['text'].split(' (')[0][4:]})"
        if tried
        else ""
    )
