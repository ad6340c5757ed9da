"""What to add to a model for the transients the finder reported: glitches, gates, or nothing.

docs/diagnostics.md, "Glitches and gates: what to add for a transient".  Each event that is
not a missing coupling is tried with a glitch template where one could explain it (an event
classified ``glitch`` or ``unclassified``; a short ``gravitational-wave`` too, which a glitch
with a long damping imitates: its power lies at the lowest frequencies, where T's share of
any instrumental signal is smallest), else gated; and a glitch or gate is advised only when
it moves the TTL fit (:func:`moves_the_fit`): a transient that is detectable but does not
change the 24 coefficients beyond their sigmas is left in the data, and the report says so
(``not_advised``).
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
from scipy import stats

from ..effects.base import Effect
from ..effects.gate import Gate
from ..effects.glitch import Glitch
from .adequacy import p_value
from .columns import concat
from .excess import gated_ttl_fit
from .gating import in_gates
from .glitches import glitch_columns, glitch_search, glitch_series
from .model_fit import ModelFit, solve
from .transients import NOISE_CHANGE_HOURS, event_excess, residual_map

log = logging.getLogger(__name__)

#: A glitch is advised for a transient when it takes at least this share of the transient's
#: excess in the time-frequency map (:func:`transient_actions`); otherwise the span is gated.
GLITCH_EXPLAINED = 0.5
#: Glitches searched at most in one event (:func:`transient_actions`).
MAX_GLITCHES_PER_EVENT = 3
#: Passes over an event's glitches searched again each with the others in the model, on
#: its placement and within ``REFINE_SPAN`` seconds of its time.
REFINE_PASSES = 2
REFINE_SPAN = 300.0
#: The search of an event's glitches stops once they take this share of its excess.
GLITCH_DONE = 0.9
#: A further glitch in one event is kept only when it takes at least this share of the
#: event's excess more than the glitches before it: a loud glitch inside the hours of a
#: chirp made one event of both, and two glitches of 1/200 of its step (significant: the
#: chirp is loud) took the chirp's power, not a glitch's (live merger day, issue 24).
GLITCH_MORE = 0.1
#: Events longer than this share of the analysed span (an inspiral in band for most of
#: it, a noise change over half a day) are not gated: the report shows the fit's
#: robustness to them instead.  A merger in band for hours is gated: it pulls the TTL fit
#: (a 2.4-h chirp on a 12-h day with a witness coupling: 6.7 sigma, 0.083 mm/rad after the
#: coupling was found; a 2-h limit left it in the data).
MAX_GATE_FRACTION = 1.0 / 3.0
#: Event classes for which glitches are searched before gating.
GLITCH_CLASSES = ("glitch", "unclassified")
#: Short events of these classes are tried with one glitch, advised only when it takes
#: :data:`GLITCH_DONE` of the event's excess (then the event is a glitch): a glitch with a
#: 300-s damping puts its power at 3-10 mHz, where T's share of a test-mass signal is below
#: the threshold computed for a velocity step's spectrum, and it read as a
#: gravitational wave and was gated (issue 32, ``bench/diagnose.py --glitches``).
GLITCH_ALSO = ("gravitational-wave",)
#: A glitch or gate is advised only when it moves some TTL coefficient by at least this
#: many of its sigmas (:func:`moves_the_fit`).  A bias below half a sigma on every
#: coefficient keeps the pulls' RMS within ~1.1 of their own; glitches of the LISA
#: Pathfinder size (1e-12 to 5e-12 m/s) move the coefficients by hundredths of a sigma,
#: those a hundred times louder by several sigma.
MIN_SHIFT_SIGMA = 0.5
#: ... and a gate only when that shift is also this many times what leaving out the span's
#: noise alone would give (``sqrt(sigma_gated^2 - sigma^2)`` per coefficient): gating half
#: an hour of noise moves the coefficients of a 12-h day by ~0.25 sigma RMS, 0.6 at most.
GATE_Z = 4.0


def ttl_shift(before: ModelFit, after: ModelFit) -> np.ndarray:
    """``(C_after - C_before) / sigma_before`` of the linear TTL coefficients in both."""
    c0, c1, s0 = before.ttl_coefficients(), after.ttl_coefficients(), before.ttl_sigma()
    ok = np.isfinite(c0) & np.isfinite(c1) & (s0 > 0)
    return (c1[ok] - c0[ok]) / s0[ok]


def gate_shift(model: ModelFit, span) -> dict:
    """The TTL fit's change when ``span`` [s] is gated (:func:`~ttlcore.diagnose.excess.gated_ttl_fit`,
    on the data less the model's fitted glitches: a glitch the model holds inside the span
    is not the span's pull): ``max_shift_sigma`` (in sigma of the fit of all data) and
    ``max_z``, the shift over what leaving out the span's noise alone gives,
    ``sqrt(sigma_gated^2 - sigma^2)``."""
    data = model.data
    y = np.array(data.tdi.data_series, dtype=float)
    for e in model.effects:
        if isinstance(e, Glitch) and e.column_name() in model.names:
            dv = float(model.theta[list(model.names).index(e.column_name())])
            y -= dv * glitch_series(data, e.where, float(e.options["t"]), float(e.options["beta"]))
    data = replace(data, tdi=replace(data.tdi, data_series=y))
    rb = gated_ttl_fit(data, [span], data.tdi.ttl_names or None)
    sf, sg = np.asarray(rb["sigma_full"]), np.asarray(rb["sigma_gated"])
    shift = np.asarray(rb["gated"]) - np.asarray(rb["full"])
    noise = np.sqrt(np.maximum(sg**2 - sf**2, 1e-6 * sf**2))
    return {"max_shift_sigma": float(np.max(np.abs(shift / sf))), "max_z": float(np.max(np.abs(shift / noise)))}


def fails_a_band(delta_band, bands) -> bool:
    """Whether the chi^2 a transient puts in the bands (``delta_band`` (G,)) would by itself
    fail one of the fit's adequacy bands (``bands``, :class:`~ttlcore.diagnose.adequacy.BandTable`:
    ``dof + delta`` at p < alpha with its tolerance and ``kappa``)."""
    p = p_value(np.asarray(bands.dof) + np.maximum(delta_band, 0.0), bands.dof, bands.kappa, bands.tolerance)
    return bool(np.any(p < bands.alpha))


def moves_the_fit(kind: str, shift: dict) -> bool:
    """Whether a glitch or a gate matters for the TTL fit enough to be advised: the chi^2 it
    removes would alone fail a band of the fit (``shift["fails_a_band"]``: left in, the
    model fails for it), or it moves a coefficient by :data:`MIN_SHIFT_SIGMA` of its sigma
    (``max_shift_sigma``) and, a gate, by :data:`GATE_Z` times what gating the span's noise
    would (``max_z``)."""
    if shift.get("fails_a_band"):
        return True
    if shift["max_shift_sigma"] < MIN_SHIFT_SIGMA:
        return False
    return kind != "gate" or shift["max_z"] >= GATE_Z


def transient_actions(model: ModelFit, report: dict, residual: np.ndarray, checkpoint=None) -> dict:
    """What to add to the model for the transients and gaps the finder reported
    (``report["transients"]``, :func:`ttlcore.diagnose.excess.transient_report`):

    - an event classified ``glitch`` (or ``unclassified``): :class:`~ttlcore.effects.glitch.Glitch`\\ es
      searched over the event's span widened by a hop (time, damping, test mass or link,
      :func:`~ttlcore.diagnose.glitches.glitch_search`; :func:`_event_glitches`), kept when
      significant (p < alpha for ``delta chi2`` on 1 + 3 degrees of freedom - the velocity
      step, and the time, damping and placement searched - and log Bayes factor above the
      threshold) and advised when together they take at least :data:`GLITCH_EXPLAINED` of
      the event's excess in the time-frequency map (``1 - X_after / X_before``, ``X`` the
      excess chi^2 of the event's tiles, :func:`~ttlcore.diagnose.transients.event_excess`,
      of the residual before and after the fitted glitches are subtracted, against the same
      background); an event of :data:`GLITCH_ALSO` shorter than two hours: one glitch,
      advised when it takes :data:`GLITCH_DONE` of it (the event is then re-classed
      ``glitch`` in the report);
    - any other event that is not a missing coupling and lasts at most
      :data:`MAX_GATE_FRACTION` of the analysed span, and every run of missing data not
      gated yet: a :class:`~ttlcore.effects.gate.Gate` over its span (the event's widened
      by a hop), overlapping spans merged;
    - a glitch or gate for an event is advised only when it moves the TTL fit
      (:func:`moves_the_fit`: the glitches' fit against the model without them, the gated
      fit against the fit of all data); the others are listed under ``not_advised``.  A
      gate over missing data is always advised.

    Returns
    -------
    dict
        ``actions``: list of dict, ``kind`` (``"glitch"`` or ``"gate"``), ``spec``,
        ``cli_spec``, ``text`` (``"glitch at 2.70 h on tm 12"``, ``"gate 15.20-15.80 h"``),
        ``events`` (indices), ``shift`` (``max_shift_sigma``, for a gate ``max_z``); a
        glitch also ``dv``, ``sigma_dv`` [m/s], ``beta`` [s], ``delta_chi2``,
        ``log_bayes_factor``, ``explained_fraction``, ``search``; a gate, the glitch tried
        for its events (if any) under ``glitch_tried``.  ``not_advised``: the same for
        those that do not move the fit, with ``reason``.
    """
    tr = report.get("transients") or {}
    events = tr.get("events") or []
    gaps = tr.get("gaps") or []
    if not events and not gaps:
        return {"actions": [], "not_advised": []}
    actions, spans, skipped = _event_actions(model, tr, residual, checkpoint or (lambda step: None))
    spans += [[float(a), float(b), [], None] for a, b in gaps]
    for act in _gates(model.data, spans):
        gap = any(x < act["stop"] and y > act["start"] for x, y in gaps)
        if gap or model.data.tdi.regressor_series is None:
            actions.append(act)  # missing data: gated whatever it pulls
            continue
        act["shift"] = gate_shift(model, (act["start"], act["stop"]))
        act["shift"]["fails_a_band"] = _events_fail_a_band(model, [events[i] for i in act["events"]])
        if moves_the_fit("gate", act["shift"]):
            actions.append(act)
        else:
            skipped.append({**act, "reason": _not_moved(act["shift"])})
    for x in skipped:
        log.info("not advised: %s (%s)", x["text"], x["reason"])
    return {"actions": actions, "not_advised": skipped}


def _event_actions(model: ModelFit, tr: dict, residual: np.ndarray, checkpoint) -> tuple[list, list, list]:
    """The glitches of the events (:func:`transient_actions`), loudest first (each searched
    with the louder events' glitches in the model): ``(actions, spans to gate [start, stop,
    events, glitch tried], not advised)``; ``checkpoint(step)`` before each event (it may
    raise: :func:`ttlcore.diagnose.diagnoser.diagnose`)."""
    data = model.data
    s = data.context.settings
    events = tr["events"]
    hop = float(tr.get("hop", 0.0))
    analysed = float(np.count_nonzero(data.grid.mask)) / data.grid.fs  # [s]
    tf0 = residual_map(data, residual) if events else None
    actions, spans, prior, skipped = [], [], list[Effect](), []
    for i, e in enumerate(events):  # loudest first
        checkpoint(f"transient event {i + 1} of {len(events)}")
        if e["class"] in ("missing-coupling", "onset"):  # a change that has not ended is no transient
            continue
        span = (e["t_start"] - hop, e["t_stop"] + hop)
        if e["duration"] > MAX_GATE_FRACTION * analysed and e["class"] not in GLITCH_CLASSES:
            continue  # hours of signal (a long inspiral) are not a transient to gate
        tried = None
        also = e["class"] in GLITCH_ALSO and e["duration"] < NOISE_CHANGE_HOURS * 3600.0
        if (e["class"] in GLITCH_CLASSES or also) and data.context.tm is not None:
            act = _event_glitches(model, residual, tf0, e, span, s, prior, single=also)
            if act["advised"]:
                if also:
                    _reclass(tr, i, act["explained_fraction"])
                entries = [
                    {**g, "events": [i], "explained_fraction": act["explained_fraction"]} for g in act["glitches"]
                ]
                if moves_the_fit("glitch", act["shift"]):
                    prior += act["effects"]
                    actions += entries
                else:
                    skipped += [{**g, "reason": _not_moved(act["shift"])} for g in entries]
                continue
            tried = act
        spans.append([span[0], span[1], [i], tried])
    return actions, spans, skipped


def _gates(data, spans) -> list[dict]:
    """Gate actions over ``spans`` (``[start, stop, events, glitch tried]``) not gated yet,
    overlapping ones merged."""
    spans = sorted((x for x in spans if not in_gates(data, x[0], x[1])), key=lambda x: x[0])
    merged: list = []
    for a, b, ev, tried in spans:
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
            merged[-1][2] += ev
            merged[-1][3] = merged[-1][3] or tried
        else:
            merged.append([a, b, list(ev), tried])
    out = []
    for a, b, ev, tried in merged:
        g = Gate(start=round(a), stop=round(b))
        act = {
            "kind": "gate",
            "spec": g.spec(),
            "cli_spec": g.cli_spec(),
            "text": g.describe_text(),
            "events": ev,
            "start": float(g.span[0]),
            "stop": float(g.span[1]),
        }
        if tried is not None:
            act["glitch_tried"] = {k: v for k, v in tried.items() if k not in ("advised", "effects")}
        out.append(act)
    return out


def _events_fail_a_band(model: ModelFit, events) -> bool:
    """Whether the events' excess chi^2 (``snr^2``), all in the one adequacy band among
    those they cover where it weighs most, would alone fail that band (:func:`fails_a_band`)."""
    bands = model.bands
    excess = float(sum(e["snr"] ** 2 for e in events))
    if not events or excess <= 0:
        return False
    lo, hi = min(e["f_lo"] for e in events), max(e["f_hi"] for e in events)
    edges = np.asarray(bands.edges)
    over = (edges[1:] > lo) & (edges[:-1] < hi)
    return any(fails_a_band(np.where(np.arange(over.size) == g, excess, 0.0), bands) for g in np.flatnonzero(over))


def _not_moved(shift: dict) -> str:
    text = f"moves the TTL fit by at most {shift['max_shift_sigma']:.2f} sigma"
    if "max_z" in shift:
        text += f", {shift['max_z']:.1f} times what leaving out its noise gives"
    return text + ", and its chi2 alone fails no band"


def _reclass(tr: dict, i: int, frac: float) -> None:
    """Event ``i`` of the report's transients re-classed ``glitch`` (a glitch template takes
    ``frac`` of its excess), with the class of the excess as a whole."""
    e = tr["events"][i]
    e["evidence"] = list(e.get("evidence", [])) + [
        f"read as {e['class']} by T's share; a glitch template takes {100 * frac:.0f} % of its excess"
    ]
    e["class"] = "glitch"
    verdict = tr.get("classification") or {}
    if "classes" in verdict:
        verdict["classes"] = sorted({ev["class"] for ev in tr["events"]})
    if verdict.get("class") == "gravitational-wave" and verdict.get("signal") and set(verdict["classes"]) == {"glitch"}:
        verdict["class"] = "glitch"


def _with_glitches(model: ModelFit, glitches) -> ModelFit:
    """``model`` refitted with the columns of the resolved ``glitches`` added (exact
    templates, :func:`~ttlcore.diagnose.glitches.glitch_columns`)."""
    if not glitches:
        return model
    data = model.data
    store = data.context.store
    sets = []
    for g in glitches:  # each template built once per diagnosis (an event's fits and shifts, the later events')
        key = ("transient-glitch", g.spec())
        sets.append(store.get(key, data) or store.put(key, data, glitch_columns(data, g)))
    return solve(data, concat(model.columns, *sets), tuple(model.effects) + tuple(glitches), model.expansion)


def _event_glitches(model: ModelFit, residual: np.ndarray, tf0, event: dict, span, s, prior=(), single=False) -> dict:
    """Glitches for one event: searched one after the other (each against the model with
    the ones found before, on the residual without them) while significant and, after the
    first, while each takes :data:`GLITCH_MORE` more of the event's excess, at most
    :data:`MAX_GLITCHES_PER_EVENT` (one when ``single``), until they take :data:`GLITCH_DONE`
    of the event's excess; with several, each is searched again against the model with
    the others (:data:`REFINE_PASSES` passes, on its placement, within :data:`REFINE_SPAN`
    of its time: overlapping glitches bias each other's damping and time), and their
    velocity steps fitted jointly.  The glitches of louder events (``prior``) are in the
    model throughout: an unfitted glitch an hour away biased a 40-s damping's estimate by
    20 % and its step by 27 % (12-h day; alone: exact).  Returns the glitch action
    (:func:`transient_actions`) of the set: ``advised`` when every one is significant and
    together they take at least :data:`GLITCH_EXPLAINED` (:data:`GLITCH_DONE` when
    ``single``) of the event's excess; ``shift`` the largest change of a TTL coefficient
    they make, in its sigmas (:func:`ttl_shift`)."""
    before = event_excess(tf0, event["t_start"], event["t_stop"])
    search_span = Glitch(span=f"{span[0]:.0f}-{span[1]:.0f}")
    found, results = list[Glitch](), []
    taken = 0.0  # share of the event's excess the glitches found take
    for _ in range(1 if single else MAX_GLITCHES_PER_EVENT):
        base = _with_glitches(model, list(prior) + found)
        res = glitch_search(base, search_span)
        p = float(stats.chi2.sf(max(res.delta_chi2, 0.0), 4))
        if not (p < s.alpha and res.log_bayes_factor > s.log_bf_threshold):
            if not found:
                results.append(res)
            break
        assert isinstance(res.effect, Glitch)  # glitch_search's
        share = _explained(model, residual, tf0, event, list(prior) + found + [res.effect], before)[0]
        if found and share - taken < GLITCH_MORE:
            log.info(
                "a further glitch at %.2f h takes %.1f %% more of the event's excess: not kept",
                float(res.effect.options["t"]) / 3600,
                100 * (share - taken),
            )
            break
        found.append(res.effect)
        results.append(res)
        taken = share
        if share >= GLITCH_DONE:
            break
    if len(found) > 1:
        _refine(model, prior, found, results)
    if not found:
        res = results[0]
        assert isinstance(res.effect, Glitch)  # glitch_search's
        return {
            "kind": "glitch",
            "advised": False,
            "significant": False,
            "explained_fraction": 0.0,
            "text": f"add {res.effect.describe_text()}",
            "delta_chi2": float(res.delta_chi2),
            "log_bayes_factor": float(res.log_bayes_factor),
            "cli_spec": res.effect.cli_spec(),
        }
    frac, fit = _explained(model, residual, tf0, event, list(prior) + found, before)
    base = _with_glitches(model, list(prior))
    shift = ttl_shift(base, fit)
    moved = {
        "max_shift_sigma": float(np.max(np.abs(shift))) if shift.size else 0.0,
        "fails_a_band": fails_a_band((base.chi2_seg_band - fit.chi2_seg_band).sum(axis=0), model.bands),
    }
    names = [g.column_name() for g in found]
    dv = {n: float(fit.theta[list(fit.names).index(n)]) for n in names}
    sdv = {n: float(fit.sigma[list(fit.names).index(n)]) for n in names}
    acts = [_glitch_action(g, res, dv[g.column_name()], sdv[g.column_name()], moved) for g, res in zip(found, results)]
    log.info(
        "glitches for the event at %.2f h: %s, together %.0f %% of its excess, moving the TTL fit by %.2f sigma",
        event["t_start"] / 3600,
        ", ".join(a["cli_spec"] for a in acts),
        100 * frac,
        acts[0]["shift"]["max_shift_sigma"],
    )
    return {
        "kind": "glitches",
        "glitches": acts,
        "effects": found,
        "explained_fraction": frac,
        "significant": True,
        "advised": frac >= (GLITCH_DONE if single else GLITCH_EXPLAINED),
        "shift": acts[0]["shift"],
        "text": "; ".join(a["text"] for a in acts),
        "cli_spec": ",".join(a["cli_spec"] for a in acts),
    }


def _refine(model: ModelFit, prior, found: list, results: list) -> None:
    """Each glitch of ``found`` searched again with the others (and ``prior``) in the model,
    on its placement, within :data:`REFINE_SPAN` of its time (:data:`REFINE_PASSES` passes):
    ``found`` and their search ``results`` replaced in place."""
    for _ in range(REFINE_PASSES):
        for j in range(len(found)):
            others = list(prior) + found[:j] + found[j + 1 :]
            g = found[j]
            t = float(g.options["t"])
            assert g.where is not None  # placed by its search
            again = Glitch(
                span=f"{t - REFINE_SPAN:.1f}-{t + REFINE_SPAN:.1f}",
                **{("tm" if g.where.startswith("tm") else "link"): g.where[-2:]},
            )
            res = glitch_search(_with_glitches(model, others), again)
            assert isinstance(res.effect, Glitch)  # glitch_search's
            found[j], results[j] = res.effect, res


def _glitch_action(g: Glitch, res, dv: float, sdv: float, moved: dict) -> dict:
    """One glitch of an event's set as an action of the advice: its spec, its fitted
    velocity step ``dv`` +- ``sdv`` [m/s] and damping, its search ``res`` and the set's
    ``moved`` (the shift of the TTL fit and whether it fails a band without them)."""
    return {
        "kind": "glitch",
        "spec": g.spec(),
        "cli_spec": g.cli_spec(),
        "text": f"add {g.describe_text()} (dv {dv:.3g} +- {sdv:.2g} m/s, beta {float(g.options['beta']):.3g} s)",
        "dv": dv,
        "sigma_dv": sdv,
        "beta": float(g.options["beta"]),
        "t": float(g.options["t"]),
        "where": g.where,
        "delta_chi2": float(res.delta_chi2),
        "p_value": float(stats.chi2.sf(max(res.delta_chi2, 0.0), 4)),
        "log_bayes_factor": float(res.log_bayes_factor),
        "search": res.to_json(),
        "shift": moved,
    }


def _explained(model, residual, tf0, event, glitches, before) -> tuple[float, ModelFit]:
    """Share of ``event``'s excess (``before``) the ``glitches`` take, fitted jointly with
    the model: ``1 - X_after / X_before`` on the residual without them, and that fit."""
    fit = _with_glitches(model, glitches)
    after = np.array(residual, dtype=float)
    for g in glitches:
        dv = float(fit.theta[list(fit.names).index(g.column_name())])
        after -= dv * glitch_series(model.data, g.where, float(g.options["t"]), float(g.options["beta"]))
    tf1 = residual_map(model.data, after, tf0.duration)
    left = event_excess(tf1, event["t_start"], event["t_stop"], tf0.background)
    frac = float(np.clip(1.0 - max(left, 0.0) / before, 0.0, 1.0)) if before > 0 else 0.0
    return frac, fit
