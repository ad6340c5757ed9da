"""The fitter's live diagnosis: the window diagnosed as ``ttl diagnose`` would, and its adoption.

Every ``diagnose_every`` segments and on the first segment of a new model, the fitter
diagnoses its window (:func:`ttlcore.diagnose.diagnoser.diagnose`, the witness search
included).  :func:`diagnosis_meta` turns the diagnosis into the fit message's meta
``diagnosis``: the failing bands and hours, the top witnesses and candidates, the reading of
the transients (:func:`transients_meta`), the text report, and the recommendation with the
model it leads to and the ``ttl control`` command that applies it (:func:`control_command`).
Whether the recommendation may be adopted without a person is :func:`adoptable`'s call; the
stage adopts it under ``--adopt auto``.
"""

from __future__ import annotations

import json
import math
import shlex
from collections.abc import Callable, Sequence

from scipy import stats

from streamer.tools.inspect_text import explained_in_words
from ttlcore.conventions import format_time
from ttlcore.diagnose.diagnosis import Candidate, Coefficients, Diagnosis, Recommendation, TimeSlice, Transients
from ttlcore.effects import make_effects
from ttlcore.effects.gate import merge_gates, split_gates


class DiagnosisStopped(Exception):
    """The stage is stopping: its live diagnosis is abandoned between two of its steps, two
    candidates or two transient events (raised by the ``checkpoint`` callback
    :func:`ttlcore.diagnose.diagnoser.diagnose` calls there; its candidate threads are
    cancelled on the way out)."""


def stop_check(stopping, between: Callable[[], None] | None = None) -> Callable[[str], None]:
    """A ``checkpoint`` callback for :func:`~ttlcore.diagnose.diagnoser.diagnose` that raises
    :class:`DiagnosisStopped` once ``stopping()`` is true: a stage told to stop (SIGTERM, its
    launcher gone, a stop message) leaves a day-long diagnosis within one of its steps
    (seconds to a minute) instead of after all of them (minutes: a mission week's fitter
    kept diagnosing for over 2 min after its launcher was gone).  Otherwise ``between()``
    runs: the fitter queues the control commands come meanwhile (recorded, their senders
    told; :meth:`streamer.runtime.controls.ControlDesk.defer`)."""

    def progress(step: str) -> None:
        if stopping():
            raise DiagnosisStopped(f"the stage is stopping (before the diagnosis' {step!r})")
        if between is not None:
            between()

    return progress


def transients_meta(transients: Transients | None) -> dict | None:
    """The live diagnosis' reading of the window's transients (meta ``diagnosis.transients``):
    the class of the excess (gravitational-wave, glitch, gap, noise-change, missing-coupling...),
    whether it is a signal or a defect of the data, and each event's class and span [s]."""
    if transients is None:
        return None
    return {
        "class": transients.excess_class,
        "signal": transients.signal,
        "events": [
            {"class": e.kind, "t_start": e.t_start, "t_stop": e.t_stop, "f_lo": e.f_lo, "f_hi": e.f_hi, "snr": e.snr}
            for e in transients.events
        ],
        "gaps": [[a, b] for a, b in transients.gaps],
    }


def adoptable(recommendation: dict | None, log_bf_threshold: float = 2.3) -> tuple[bool, str]:
    """Whether a diagnosis' recommendation may be adopted without a person, and why.

    Adopted only when every one of these holds: a candidate is recommended (``option`` set),
    the diagnosis says it explains the excess (``explains``: at least half of the chi^2
    beyond the tolerance, :func:`ttlcore.diagnose.report.recommendation`), and its evidence
    is decisive (log Bayes factor above ``log_bf_threshold`` - the diagnosis' own
    significance threshold, odds 10:1 - as the candidate's ``significant`` flag already
    requires together with p < alpha)."""
    if not recommendation or not recommendation.get("option") or not recommendation.get("spec"):
        return False, "nothing recommended"
    if not recommendation.get("explains"):
        return False, (
            f"the best candidate explains {100 * float(recommendation.get('explained_fraction') or 0):.0f} % "
            "of the excess: not adopted"
        )
    lbf = recommendation.get("log_bayes_factor")
    if lbf is not None and float(lbf) < log_bf_threshold:
        return False, f"log Bayes factor {float(lbf):.1f} below {log_bf_threshold:g}: not adopted"
    return True, explained_in_words(recommendation) + (
        f", log Bayes factor {float(lbf):.1f}" if lbf is not None else ""
    )


#: An effect (not a transient's glitch or gate) is adopted only from a window whose gates
#: leave at least this share of it: on the live merger day, a window of 16 h with 11 h gated
#: (the merger's hours) fitted the secondary-noise levels on the 5 h left - one at its lower
#: bound - and second-order "explained" the misfit (log B 2234); it was adopted.
MIN_UNGATED = 0.5


def enough_ungated(rows: Sequence[TimeSlice], effects: list[str], effect_modules, why: str) -> tuple[bool, str]:
    """Whether the window the diagnosis read (its time slices ``rows``, the adequacy's
    ``time``) keeps :data:`MIN_UNGATED` of its span outside the model's gates, and why not."""
    if not rows:
        return True, why
    a, b = rows[0].t_start, rows[-1].t_stop
    gates, _ = split_gates(make_effects(list(effects), effect_modules))
    gated = sum(max(0.0, min(g.span[1], b) - max(g.span[0], a)) for g in merge_gates(gates))
    if b > a and 1.0 - gated / (b - a) < MIN_UNGATED:
        return False, (
            f"the model's gates leave {(b - a - gated) / 3600:.1f} h of the window's {(b - a) / 3600:.1f} h: "
            "an effect waits for more ungated data"
        )
    return True, why


def outside_gaps(recommendation: Recommendation, gaps, why: str, effect_modules=()) -> tuple[bool, str]:
    """Whether the times a recommendation's effects name (a step's ``t_step``, a glitch's
    ``t``) lie outside the data's gaps ``[(start, stop), ...]`` [s], and why not: a time inside
    missing data is not determined by them (the mission week's planned gap had its edge
    adopted as a step inside it, and every coefficient after it came out 0)."""
    specs: list[str | None] = [*recommendation.action_specs] or [recommendation.spec]
    for effect in make_effects([s for s in specs if s], effect_modules):
        for key in ("t_step", "t"):
            if effect.options.get(key) is None:
                continue
            t = float(effect.options[key])  # seconds (the effect read the spec's unit)
            if any(float(a) <= t <= float(b) for a, b in gaps):
                return False, f"{effect.name} {key}={format_time(t)} lies in a gap of the data: not adopted"
    return True, why


#: An effect of the model whose parameters are jointly consistent with zero at this p-value or
#: above has lost its evidence: its removal is proposed (never done without a person).
STALE_P = 0.01


def stale_effects(fitted: Coefficients, effects: list[str], effect_modules) -> list[dict]:
    """The effects of the model in force whose evidence is gone: those (not ``linear-ttl``,
    not a transient) whose fitted parameters on the window (``fitted``) are consistent with zero, the sum
    of their ``(value / sigma)^2`` having p >= :data:`STALE_P` against chi^2 with one degree
    of freedom per parameter (a coupling that has switched off, or an adoption the data no
    longer support).  Each: ``spec``, ``chi2``, ``dof``, ``p``."""
    values, sigma = dict(fitted.values), dict(fitted.sigma)
    # a shifted effect's ``<effect>.<group>.d1`` column is the offset beyond its expansion
    # point (~0 once the point is right): its evidence is the whole offset, value and sigma
    for group, (value, sd) in fitted.offsets.items():
        if f"{group}.d1" in values:
            values[f"{group}.d1"], sigma[f"{group}.d1"] = value, sd
    out = []
    for spec, effect in zip(effects, make_effects(list(effects), effect_modules), strict=True):
        if effect.is_linear_ttl or effect.active_span() is not None:  # transients: their own rule
            continue
        try:
            names = effect.column_names()
        except Exception:  # noqa: BLE001 - an effect whose columns need the data: not judged here
            continue
        z = [
            values[n] / sigma[n]
            for n in names
            if values.get(n) is not None and sigma.get(n) and math.isfinite(sigma[n])
        ]
        if not z:
            continue
        chi2 = float(sum(v * v for v in z))
        p = float(stats.chi2.sf(chi2, len(z)))
        if p >= STALE_P:
            out.append({"spec": spec, "chi2": chi2, "dof": len(z), "p": p})
    return out


def control_command(run: str, stage: str, zenoh, effects: list[str]) -> str:
    """The ``ttl control`` command that puts ``effects`` in the model of the fitter ``stage``
    of run ``run``, reached as its Zenoh settings ``zenoh`` say (``connect``, ``credentials``)."""
    parts = ["ttl", "control", "--run", run]
    if getattr(zenoh, "connect", None):
        parts += ["--connect", str(list(zenoh.connect)[0])]
    if getattr(zenoh, "credentials", None):
        parts += ["--credentials", str(zenoh.credentials)]
    return shlex.join(parts + [stage, "model", json.dumps({"effects": list(effects)})])


def recommendation_meta(
    advice: Recommendation | None,
    candidates: Sequence[Candidate],
    effects: list[str],
    effect_modules,
    command: Callable[[list[str]], str],
) -> dict | None:
    """The diagnosis' recommendation ``advice`` (its JSON), with the evidence of its candidate
    among ``candidates`` (``log_bayes_factor``), the model it leads to (``effects``: the model
    in force plus what it adds, a gate overlapping one of the model's merged with it, or with
    the effect a reshaped candidate ``replaces`` in its place) and the command that applies it."""
    if advice is None:
        return None
    rec = advice.to_json()
    best = next((c for c in candidates if c.spec == advice.spec), None)
    if best is not None:
        rec["log_bayes_factor"] = best.log_bayes_factor
    if advice.spec and advice.option:
        # only what is advised gets a model and a command (offline: an ``option``): a
        # candidate that explains nothing, or a signal's best fit, is named in the message
        # alone, never with a command that would add it
        # a transient's advice adds several glitches and gates at once (``actions``)
        specs = [*effects, *(advice.action_specs or [advice.spec])]
        if advice.replaces and not advice.action_specs:  # a shape searched again: in the old one's place
            specs = [advice.spec if same_effect(e, advice.replaces, effect_modules) else e for e in effects]
            if specs == list(effects):  # not the model's effect: nothing to put it in place of
                return rec
        # a gate overlapping one of the model's (an ongoing signal, seen again) is merged
        model = make_effects(specs, effect_modules)
        rec["effects"] = [e.spec() for e in merge_gates(model)]
        rec["command"] = command(rec["effects"])
    return rec


def same_effect(spec: str, other: str, effect_modules) -> bool:
    """Whether two effect specs name the same effect (one spelling, :meth:`Effect.spec`)."""
    a, b = make_effects([spec, other], effect_modules)
    return a.spec() == b.spec()


def diagnosis_meta(
    diagnosis: Diagnosis,
    *,
    index: int,
    window: tuple[int, int],
    effects: list[str],
    effect_modules,
    mode: str,
    command: Callable[[list[str]], str],
) -> tuple[dict, bool]:
    """The fit message's meta ``diagnosis`` from a diagnosis of the window.

    Parameters
    ----------
    diagnosis : Diagnosis
        :func:`ttlcore.diagnose.diagnoser.diagnose`'s diagnosis.
    index : int
        The segment whose fit message carries it.
    window : (int, int)
        The first and last segment of the window diagnosed.
    effects : list of str
        The model in force.
    effect_modules : sequence of str
        Plugin modules defining effects.
    mode : str
        ``--adopt`` (``adoption.mode``).
    command : callable
        Effects -> the ``ttl control`` command that applies them (:func:`control_command`).

    Returns
    -------
    (dict, bool)
        The meta (``adoption.adopted`` False: the stage sets it when it adopts) and whether
        the recommendation may be adopted (:func:`adoptable`, and not held by the model already).
    """
    first, last = window
    adequacy, advice = diagnosis.adequacy, diagnosis.recommendation
    out: dict = {
        "index": index,
        "segments": [first, last],
        "model": list(effects),
        "chi2_dof": adequacy.chi2_dof,
        "fails": adequacy.fails,
        "bands": [{"f_lo": b.f_lo, "f_hi": b.f_hi, "chi2_dof": b.chi2_dof, "fails": b.fails} for b in adequacy.bands],
        "failing_hours": [[s.t_start, s.t_stop] for s in adequacy.time if s.fails],
        "summary": list(adequacy.summary),
        "witnesses": [
            {"name": w.name, "spec": w.spec, "delta_chi2": w.delta_chi2, "best_band": list(w.best_band)}
            for w in (diagnosis.witnesses.overall if diagnosis.witnesses is not None else ())[:3]
        ],
        "candidates": [
            {
                "spec": c.spec,
                "cli_spec": c.cli_spec,
                "delta_chi2": c.delta_chi2,
                "log_bayes_factor": c.log_bayes_factor,
                "explained_fraction": c.explained_fraction,
                "significant": c.significant,
                "seconds": c.seconds,
            }
            for c in diagnosis.candidates[:5]
        ],
        "transients": transients_meta(diagnosis.transients),
        "text": diagnosis.text(source=f"window {first}..{last}"),
        # where the diagnosis' minutes went: each step's wall time [s] (the fitter's cost)
        "timings_s": dict(diagnosis.timings),
    }
    rec = recommendation_meta(advice, diagnosis.candidates, effects, effect_modules, command)
    out["recommendation"] = rec
    ok, why = adoptable(rec)
    # (``advice`` is None exactly when ``rec`` is)
    if ok and advice is not None and not advice.action_specs and not adequacy.fails:
        # the model passes the instrument noise model: a candidate "significant" against
        # hundreds tried (the witness scan picks the best of ~600) is no reason to change it
        # without a person (a clean simulated day adopted a witness at log B 4.5)
        ok, why = (
            False,
            "the model is adequate (no failing band): an effect is adopted without a person only when it fails",
        )
    if ok and advice is not None and not advice.action_specs:
        ok, why = enough_ungated(adequacy.time, effects, effect_modules, why)
    if ok and advice is not None:
        gaps = diagnosis.transients.gaps if diagnosis.transients is not None else ()
        ok, why = outside_gaps(advice, gaps, why, effect_modules)
    if ok and rec is not None and rec.get("effects") in (None, list(effects)):
        ok, why = False, "the model already holds it"
    out["adoption"] = {"mode": mode, "adopted": False, "reason": why}
    stale = stale_effects(diagnosis.model.coefficients, effects, effect_modules)
    for s in stale:
        s["command"] = command([e for e in effects if e != s["spec"]])
        out["text"] += (
            f"\n  evidence gone: {s['spec']} (its {s['dof']} parameter(s) consistent with zero: chi2 "
            f"{s['chi2']:.1f}, p = {s['p']:.2g}); proposed for removal: {s['command']}"
        )
    out["removal"] = stale
    return out, ok
