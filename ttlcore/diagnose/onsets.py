"""Onsets: an excess that begins inside the data and lasts to its end is a change, not a transient.

A coupling that switches on in the middle of a live window (after a micrometeoroid hit, a
re-pointing) leaves an excess from its onset to the window's end.  The transient finder
sees an event of a few hours at the window's end, broadband and instrumental, and
:func:`ttlcore.diagnose.event_class.classify` reads it as a change of the noise level. Gating it
threw away exactly the hours that hold the coupling.
- Measured on a mission week (`bench/mission.py`): the live loop gated 71.75-76 h and then
  71.75-80 h over a coupling that switched on at 72 h.
- Every hour after that was left out of the rolling fit as an outlier, until the gates
  reached their limit.
- The coupling was adopted 24 h after its onset, when the window no longer held an hour
  before it.

Here such an event is an **onset**: it is at least :data:`ONSET_MIN_HOURS` long, ends
within a tile and a hop of the data's end, is not a gap or a gravitational wave, and T
carries at least the instrumental share of its excess (a coupling puts 1/6 to 1/2 of it
there, measured 29-34 %; an inspiral building up to a merger after the window's end leaves T
nearly empty: a live window read the early chirp as an onset, left it ungated, and adopted
a spurious `second-order`).
- It is not gated and no glitch is fitted to it.
- The ranking's best couplings of a witness (at their searched shapes) and the witness
  search's best DWS placements are tried with their coupling switched on at the onset:
  ``witness:...,vary=step,t_step=T`` (one column, the placed witness times ``H(t - T)``),
  ``fd-coupling:...,vary=step,t_step=T``.
- ``T`` is searched (:func:`onset_time`): the best of them switched on at times about the
  event's start, to ~30 s. The named ``step`` candidate's time is no guide: a step of the 24
  coefficients fitted to a resonance that switched on came out 0.5 h late on a
  lisainstrument window. The candidates join the ranking, so a coupling that switched on
  is advised as one, and the excess's class follows from what it explains.
- An onset that nothing explains (a noise level that rose and stayed) gets no advice. Once
  it has ended, it is a transient like any other; once the window holds only the time
  after it, it is a stationary excess.
"""

from __future__ import annotations

import logging

import numpy as np

from ..effects import make_effects
from ..errors import ConfigError
from .candidates import CandidatePool, rank_key, score

__all__ = ["ONSET", "ONSET_MIN_HOURS", "add_onset_candidates", "onset_events", "onset_time", "reclassify_onsets"]

log = logging.getLogger(__name__)

#: The class of an event that begins inside the data and lasts to its end (not in
#: :data:`ttlcore.diagnose.transients.NOT_AN_EFFECT`: its hours are read, never gated).
ONSET = "onset"
#: Shortest onset [h]: a glitch or burst at the window's end is shorter (a 300-s damping
#: rings for ~30 min); the live fitter's sustained-excess diagnosis comes 3 segments after.
ONSET_MIN_HOURS = 2.0
#: Offsets [s] from an onset event's start at which its coupling's switch-on time is first
#: scored (:func:`onset_time`): the event's start is a tile's centre less a quarter tile.
ONSET_GRID = (-1800.0, -900.0, -450.0, 0.0, 450.0, 900.0, 1800.0)
#: DWS placements of the witness search tried with a switched-on coupling.
ONSET_PLACEMENTS = 2


def data_end(data) -> float:
    """Time [s] just after the last valid sample of the analysed data."""
    valid = np.flatnonzero(data.grid.mask)
    return float(data.grid.t0 + (valid[-1] + 1) / data.grid.fs) if valid.size else float(data.grid.t0)


def reclassify_onsets(events: list[dict], end: float, tile: float, hop: float) -> None:
    """Class the events (JSON entries, loudest first, changed in place) that are onsets
    (module docstring) as :data:`ONSET`, with the evidence why."""
    for e in events:
        open_ended = e["t_stop"] >= end - tile - hop
        if not open_ended or e["duration"] < ONSET_MIN_HOURS * 3600.0 or e["class"] in ("gap", "gravitational-wave"):
            continue
        if e["t_share"] < (e.get("t_share_threshold") or 0.0):
            continue  # T nearly empty: a signal building up to the window's end (an inspiral), not a coupling
        e["evidence"].append(
            f"it lasts to the end of the data ({end / 3600:.2f} h), {e['duration'] / 3600:.2f} h from its start: "
            f"a change that has not ended (was {e['class']}), not a transient to gate"
        )
        e["class"] = ONSET


def onset_events(events: list[dict]) -> list[dict]:
    return [e for e in events if e["class"] == ONSET]


def onset_time(model, spec: str, t_start: float, modules=()) -> float:
    """The time [s] a coupling ``spec`` switched on, near an onset event's start ``t_start``:
    the ``t_step`` of ``spec,vary=step,t_step=T`` with the largest delta chi^2 added to
    ``model``, on :data:`ONSET_GRID` about ``t_start`` and then halving steps from a quarter
    tile to a 32nd (13 fits of one column set)."""
    C = model.ttl_coefficients()
    found: dict[float, float] = {}

    def delta_chi2(t: float) -> float:
        t = round(float(t), 1)
        if t not in found:
            effect = switched_on(spec, t, modules)
            try:
                found[t] = float(score(model, effect, C)[0].delta_chi2)
            except ConfigError as exc:  # a switch outside the data: no column
                log.info("onset time %.1f s not scored: %s", t, exc)
                found[t] = -np.inf
        return found[t]

    best = max((t_start + dt for dt in ONSET_GRID), key=delta_chi2)
    for step in (225.0, 112.5, 56.25, 28.125):
        best = max((best - step, best, best + step), key=delta_chi2)
    log.info("onset of %s at %.1f s (event from %.1f s): delta chi2 %.1f", spec, best, t_start, delta_chi2(best))
    return float(best)


def switched_on(spec: str, t_step: float, modules=()):
    """The coupling ``spec`` switched on at ``t_step`` [s] (to 0.1 s)."""
    effect = make_effects([spec], modules)[0].switched_on(round(float(t_step), 1))
    if effect is None:
        raise ConfigError(f"{spec} cannot be switched on")
    return effect


def _switchable(report: dict, modules=()) -> list[str]:
    """What to try switched on: the ranking's best couplings of a witness that can be
    (:meth:`~ttlcore.effects.base.Effect.switched_on`; at their searched shapes: no search
    again; not a shape searched again in the place of the model's) and the witness search's
    best DWS placements, as specs (best first, each family's first :data:`ONSET_PLACEMENTS`)."""
    modules = modules or ()
    ranked = [
        c["spec"]
        for c in report.get("candidates") or []
        if not c.get("replaces") and make_effects([c["spec"]], modules)[0].switched_on(0.0) is not None
    ]
    placed = [
        w["spec"]
        for w in (report.get("witnesses") or {}).get("overall", [])
        if w.get("family") == "dws" and str(w.get("spec") or "").startswith("witness:")
    ]
    return list(dict.fromkeys(ranked[:ONSET_PLACEMENTS] + placed[:ONSET_PLACEMENTS]))


def add_onset_candidates(model, report: dict, events: list[dict], modules=()) -> list[dict]:
    """Score the switched-on couplings of every onset among ``events`` and merge them into
    ``report["candidates"]`` (best first, as :meth:`CandidatePool.ranked` orders them);
    returns the new entries (empty without an onset or a DWS witness)."""
    onsets = onset_events(events)
    switchable = _switchable(report, modules)
    specs = []
    for e in onsets if switchable else ():
        t = onset_time(model, switchable[0], float(e["t_start"]), modules)
        specs += [switched_on(spec, t, modules).spec() for spec in switchable]
    if not specs:
        return []
    with CandidatePool(model, 1) as pool:
        pool.submit(make_effects(list(dict.fromkeys(specs)), modules))
        new = pool.ranked()
    for c in new:
        c["onset"] = True
        log.info(
            "onset candidate %s: delta chi2 %.1f, %.0f %% of the excess",
            c["cli_spec"],
            c["delta_chi2"],
            100 * c["explained_fraction"],
        )
    merged = list(report.get("candidates") or []) + new
    merged.sort(key=rank_key)
    report["candidates"] = merged
    return new
