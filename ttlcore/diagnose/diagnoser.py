"""Model against measurement: fit a model (a list of effects), test it against the
instrument noise model, rank the missing effects and the generic witnesses
(docs/diagnostics.md; ``ttl diagnose``, ``ttl refit``, the pipeline's model changes).

The entry points :func:`diagnose` (the full report) and :func:`refit` (another model on the
same data, the change reported) orchestrate the pieces, each a value or a pure function:

- :mod:`ttlcore.diagnose.whitened`: the whitened data, built once
  (:func:`~ttlcore.diagnose.whitened.whiten_telemetry`, :func:`~ttlcore.diagnose.whitened.whiten_tdi`);
- :mod:`ttlcore.diagnose.columns`: an effect's whitened columns for given parameters;
- :mod:`ttlcore.diagnose.model_fit`: the GLS fit with errors in variables (:class:`ModelFit`);
- :mod:`ttlcore.diagnose.fitting`: a model of effects fitted (searched parameters resolved,
  shifted-witness effects expanded) - the one code path of the model, the candidates' trial
  models and the refits;
- :mod:`ttlcore.diagnose.evidence`: the evidence for a change (:class:`Evidence`);
- :mod:`ttlcore.diagnose.search`: profile searches of nonlinear parameters (step time,
  offsets, poles, plugins);
- :mod:`ttlcore.diagnose.candidates`, :mod:`ttlcore.diagnose.report`: the ranking and the
  report.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from scipy import fft as sp_fft

from ..effects.gate import Gate, split_gates
from ..effects.registry import make_effects
from ..errors import ConfigError
from ..tdi.data import TDIData
from .candidates import CandidatePool, named_candidates
from .diagnosis import Diagnosis, Refit
from .evidence import change
from .excess import transient_report
from .fitting import fit_model
from .gated_ranking import rank_on_gated, reordered
from .gating import GatedGrid, gated_data, missing_data, with_gates
from .model_fit import ModelFit
from .noise_model import profile_noise_model
from .onsets import add_onset_candidates
from .report import (
    fine_band_table,
    model_json,
    recommendation,
    text_report,
)
from .settings import DiagnoseSettings
from .transient_advice import transient_actions
from .transients import NOT_AN_EFFECT
from .whitened import WhitenedData, whiten_tdi, whiten_telemetry
from .witnesses import witness_candidates, witness_search

__all__ = [
    "DiagnoseSettings",
    "Diagnosis",
    "Refit",
    "diagnose",
    "refit",
    "text_report",
    "fine_band_table",
    "concatenate_tdi",
    "ModelFit",
    "WhitenedData",
]

log = logging.getLogger(__name__)


def diagnose(
    tm,
    effects=("linear-ttl",),
    *,
    settings: DiagnoseSettings | None = None,
    effect_modules=(),
    candidates=None,
    truth_coefficients=None,
    witnesses: bool | None = None,
    progress=None,
    whitened: WhitenedData | None = None,
    checkpoint=None,
) -> Diagnosis:
    """Full diagnosis of telemetry ``tm`` with a model (list of effect specs).

    Fits the model under the instrument noise model, tests its adequacy per band and per
    time slice, ranks every other available effect (named, entry points, ``effect_modules``)
    and the witness library.  If the model holds more than ``linear-ttl``, the linear-only
    model is fitted too and reported as ``before``, with the evidence for the change.
    ``truth_coefficients`` (24,) only adds coefficient errors; nothing else reads truth.
    ``whitened``: the whitened data of ``tm`` under ``settings``, when built already
    (:func:`~ttlcore.diagnose.whitened.whiten_telemetry`; the live fitter's window refit and
    diagnosis of one segment share them); a :class:`ConfigError` when built under other settings.
    ``progress(step)`` is told each step; ``checkpoint(step)`` is called before each step and
    at finer points (each candidate, each transient event) and may raise to abandon the
    diagnosis (a live fitter told to stop leaves within seconds, not after a whole step).

    Returns
    -------
    Diagnosis
        The diagnosis (:class:`~ttlcore.diagnose.diagnosis.Diagnosis`): its parts by
        attribute, the model's fit (``fit``, its whitened data ``data`` of the final noise
        model) and the transient map; ``to_json()`` the JSON report (schema in
        ``docs/diagnostics.md``).
    """
    s = settings or DiagnoseSettings()
    check = checkpoint or (lambda step: None)

    def say(step: str) -> None:
        check(step)
        if progress is not None:
            progress(step)

    clock = time.monotonic()
    timings: dict[str, float] = {}
    eff = make_effects(list(effects), effect_modules)
    gates, fitted = split_gates(eff)  # gates change the data, not the columns
    if not any(e.is_linear_ttl for e in eff):
        log.warning("model without linear-ttl: the 24 linear coefficients are not fitted")
    # FFTs on every core while nothing else runs; one per thread once the candidates'
    # threads start (the diagnosis' transforms take the calling thread's default)
    with sp_fft.set_workers(-1):
        say("TDI and spectra")
        if whitened is not None and whitened.context.settings != s:
            raise ConfigError("diagnose: the whitened data given were built under other settings")
        ungated = whitened if whitened is not None else whiten_telemetry(tm, s, effect_modules)
        del whitened
        gaps = missing_data(ungated)  # gated before anything is fitted: the data's, not an effect
        data = gated_data(ungated, gates, gaps)
        # the ungated data a refit of the transient phase gates anew: whitened again from
        # ``tm`` when asked for (the same numbers), not held through the candidates (a day's:
        # 220 MB, the mission week's peak)
        regate = _ungated_source(ungated, tm, s, effect_modules) if data is not ungated else None
        del ungated
        clock = _lap(timings, "tdi_and_spectra", clock)
        say("fit")
        fits = [fit_model(data, fitted)]
        if s.noise_model == "fitted":
            say("noise model")
        model = _with_noise_levels(fits) if s.noise_model == "fitted" else fits.pop()
        clock = _lap(timings, "fit", clock)
    report: dict = {"model": with_gates(model_json(model, truth_coefficients), gates)}
    report["adequacy"] = report["model"]["adequacy"]
    if len(eff) > 1 or not eff[0].is_linear_ttl:
        _before_after(report, model, eff, truth_coefficients)
        clock = _lap(timings, "before", clock)
    use_witnesses = s.witnesses if witnesses is None else witnesses
    mark = model.data.context.store.mark()
    clock = _candidates(report, tm, model, s, candidates, effect_modules, use_witnesses, (say, check), (timings, clock))
    # the candidates' columns (a day's: 0.4-0.5 GB) are not asked for again: not kept through
    # the transient phase, the diagnosis' peak
    model.data.context.store.release_since(mark)
    refit = functools.partial(gated_model, model, fitted, ungated=regate, gates=gates, gaps=gaps)
    onsets = functools.partial(add_onset_candidates, model, report, modules=effect_modules)
    _transients(report, model, (refit, onsets, check), s, truth_coefficients)
    _lap(timings, "transients", clock)
    report["recommendation"] = recommendation(report, eff)
    report["settings"] = {
        "band": list(map(float, s.band)),
        "n_bands": s.n_bands,
        "segment_duration": model.data.grid.seg_duration,
        "time_segment": s.time_segment,
        "tolerance": s.tolerance,
        "alpha": s.alpha,
        "log_bf_threshold": s.log_bf_threshold,
        "dws_asd": model.data.tdi.dws_asd,
    }
    report["timings_s"] = timings
    transient_map = report["transients"].pop("_map")
    return Diagnosis.from_report(report, fit=model, transient_map=transient_map)


def _lap(timings: dict, name: str, since: float) -> float:
    """The step ``name`` of the diagnosis timed into ``timings`` [s, rounded to ms] from
    ``since`` (a :func:`time.monotonic` reading); returns the reading at its end."""
    now = time.monotonic()
    timings[name] = round(now - since, 3)
    return now


def _before_after(report: dict, model: ModelFit, eff: list, truth_coefficients) -> None:
    """The linear-only model fitted to the data of ``model`` (report's ``before``) and the
    evidence for the change to ``model`` (``change``)."""
    before = fit_model(model.data, make_effects(["linear-ttl"]))
    ev = change(before, model)
    report["before"] = model_json(before, truth_coefficients)
    report["change"] = {
        "added": [e.spec() for e in eff if not e.is_linear_ttl],
        "delta_chi2": None if ev is None else ev.delta_chi2,
        "log_bayes_factor": None if ev is None else ev.log_bayes_factor,
        "chi2_dof_before": before.chi2_dof,
        "chi2_dof_after": model.chi2_dof,
        "bands_before": [b["chi2_dof"] for b in report["before"]["adequacy"]["bands"]],
        "bands_after": [b["chi2_dof"] for b in report["adequacy"]["bands"]],
    }


def _candidates(
    report: dict, tm, model: ModelFit, s: DiagnoseSettings, candidates, effect_modules, use_witnesses: bool, says, laps
) -> float:
    """The report's ``witnesses`` and ranked ``candidates``: the named candidates are scored
    (by the pool's workers) while the witness search runs here; the witness candidates join
    them when it ends.  ``says`` is ``(progress, checkpoint)`` (:func:`diagnose`), ``laps``
    ``(timings, since)``; returns the clock reading at the end."""
    timings, clock = laps
    say, check = says
    with CandidatePool(model, s.n_workers(), checkpoint=check) as pool:
        pool.submit(named_candidates(model, candidates))
        if report["adequacy"]["fails"]:
            # the model's couplings with a searched shape, searched again on these data (a
            # shape adopted from the first hours after an onset; Effect.reshaped)
            pool.submit_reshapes()
        if use_witnesses:
            say("witness search")
            report["witnesses"] = witness_search(tm, model.data, model, s.top_witnesses)
            clock = _lap(timings, "witnesses", clock)
            # the searched ones (pole searches, seconds each) first, so that the threads end
            # together instead of one running the last search alone
            extra = _witness_extra(report, s, effect_modules)
            pool.submit(sorted(extra, key=lambda e: not e.unresolved()))
        else:
            report["witnesses"] = None
        say("candidates")
        report["candidates"] = pool.ranked()
    return _lap(timings, "candidates", clock)


def _witness_extra(report: dict, s: DiagnoseSettings, effect_modules) -> list:
    """The candidates of the top witnesses; those with searched parameters left out (and
    listed in ``witnesses.skipped_candidates``) when the model passes."""
    extra = witness_candidates(report["witnesses"], s.witness_candidates, effect_modules)
    if not report["adequacy"]["fails"]:
        # nothing to explain: the couplings with searched poles (seconds to a minute
        # each, most of a null day's diagnosis) would only fit noise; the witnesses'
        # own candidates still say how much each would take
        # (a step's time is searched too, but in seconds: a witness step on one channel
        # is kept, or the witness's coarse grid time would be all the report has)
        costly = [e for e in extra if set(e.unresolved()) - {"t_step"}]
        skipped = [e.spec() for e in costly]
        extra = [e for e in extra if e not in costly]
        report["witnesses"]["skipped_candidates"] = skipped
        log.info("the model passes: %d witness candidates with searched parameters not tried", len(skipped))
    return extra


def _transients(report: dict, model: ModelFit, hooks: tuple, s: DiagnoseSettings, truth_coefficients) -> None:
    """The report's ``transients`` (with their actions and the gated model) and, beside a
    signal, the candidates ranked again on the data with it gated.  ``hooks``: the model
    refitted with spans gated, and the onset candidates added
    (:func:`~ttlcore.diagnose.excess.transient_report`'s ``refit`` and ``onsets``), and the
    :func:`diagnose` ``checkpoint``."""
    refit, onsets, check = hooks
    report["transients"] = transient_report(model, report, refit=refit, onsets=onsets)
    residual = report["transients"].pop("_residual")
    # The gated model is read (its JSON, the candidates ranked on it) and let go before the
    # glitch searches of the actions: held through them, its data and columns were ~0.3 GB
    # of a day's diagnosis at its peak.  The actions only re-class events as glitches (a
    # signal, never a missing coupling): the verdict stays, the signals can only grow.
    gated = report["transients"].pop("_gated")
    gated_json = None if gated is None else gated_model_json(gated, truth_coefficients)
    ranking = None
    if gated is not None and report["transients"]["classification"]["class"] == "missing-coupling":
        # beside a signal, the candidates are ranked again on the data with it gated: the
        # simplest that explains the quiet data, not the shape that also takes the signal
        ranking = rank_on_gated(report["candidates"], gated, s.alpha, s.tolerance)
    del gated
    # actions, not_advised
    report["transients"].update(transient_actions(model, report, residual, checkpoint=check))
    del residual
    report["transients"]["gated_model"] = gated_json
    signals = [e for e in report["transients"]["events"] if e["class"] in NOT_AN_EFFECT]
    if ranking is not None and signals:
        report["candidates"] = reordered(report["candidates"], ranking)
        report["candidates_gated"] = ranking.to_json()


def _ungated_source(ungated: WhitenedData, tm, s: DiagnoseSettings, effect_modules) -> Callable[[], WhitenedData]:
    """The ungated data, whitened again from the telemetry ``tm`` each time they are asked
    for (the transient refit gates them once, and lets them go: its peak holds two copies of
    the day's regressors, not three); ``ungated`` itself when there is no telemetry to whiten
    again (a diagnosis of whitened data alone)."""
    if tm is None:
        return lambda: ungated
    return lambda: whiten_telemetry(tm, s, effect_modules)


def gated_model(model: ModelFit, effects, spans, ungated=None, gates=(), gaps=()) -> ModelFit | None:
    """``model`` refitted with the ``(start, stop)`` spans [s] gated out (a signal's hours, a
    gap), its noise levels profiled again when they were fitted; None when the gates leave
    too little data.  A model with gates of its own (``gates``) or gated gaps is gated anew
    from its ungated data (``ungated()``), its gates and the spans together.

    A loud signal pulls the linear fit (a chirp: by several sigma, ``transients.robustness``)
    and, through the whole day's mis-subtracted TTL noise, everything read outside it. With
    ``gaps``, the runs of missing data the data were gated for, are gated again with them.
    With its span gated (:func:`~ttlcore.diagnose.gating.gated_data`: cosine tapers, the same
    window in data and columns) the fit and the levels are those of the quiet data: what a
    user who follows the advice (``gate``) gets.  The transient finder reads the quiet
    tiles on it (:func:`~ttlcore.diagnose.excess.transient_report`'s ``refit``).
    """
    new = [Gate(start=float(a), stop=float(b)) for a, b in spans]
    try:
        data = gated_data(model.data, new) if ungated is None else gated_data(ungated(), [*gates, *new], gaps)
    except ConfigError as err:  # the gates leave too little data
        log.info("no gated model: %s", err)
        return None
    fits = [fit_model(data, list(effects))]
    return _with_noise_levels(fits) if model.data.noise.parameters is not None else fits.pop()


def gated_model_json(model: ModelFit, truth_coefficients=None) -> dict:
    """The ``transients.gated_model`` entry of a report: the spans gated [s], the adequacy
    (per band and per hour) and the coefficients of the model with them gated."""
    out = model_json(model, truth_coefficients)
    spans = [[float(a), float(b)] for a, b in getattr(model.data.grid, "gate_spans", ())]
    return {"spans": spans, "adequacy": out["adequacy"], "coefficients": out["coefficients"]}


def _with_noise_levels(fits: list, time_table: bool = True) -> ModelFit:
    """The model of ``fits`` (a list holding its first fit) refitted with the secondary-noise
    levels profiled (``noise_model="fitted"``).

    The first fit is handed over (popped from ``fits`` into the call), so that no frame
    keeps it while the noise model's passes replace it: its columns (~100 MB for a day) are
    freed after the first pass.  The model's searched parameters stay at the estimates the
    search found (its ``effects`` hold the effects at those estimates), and the search
    results are carried over; the offsets of shifted-witness effects, searched again with
    each fit's columns, are the refit's."""
    data, effects, searches = fits[0].data, list(fits[0].effects), dict(fits[0].searches)
    _, fitted = profile_noise_model(data, effects, first=fits.pop(), time_table=time_table)
    return replace(fitted, searches={**searches, **fitted.searches})


def refit(
    source,
    effects=("linear-ttl",),
    *,
    settings: DiagnoseSettings | None = None,
    effect_modules=(),
    dws_asd: float | None = None,
    baseline=("linear-ttl",),
    time_table: bool = True,
) -> Refit:
    """Refit already-computed data with a given list of effects and report the change.

    Parameters
    ----------
    source : Telemetry, TDIData, list of TDIData, or WhitenedData
        - a :class:`~ttlcore.io.telemetry.Telemetry`: every effect is available;
        - TDI outputs (one :class:`~ttlcore.tdi.data.TDIData`, or a list of contiguous
          segments such as the pipeline's hourly TDI, concatenated here): ``linear-ttl``,
          ``drift`` and ``step`` (modulated TDI regressors, no DWS series needed);
        - a :class:`~ttlcore.diagnose.whitened.WhitenedData` already built (its spectra and
          its column store are reused, so successive refits with changing models cost only
          the new columns).
    effects : sequence of str or Effect
        The model, e.g. ``["linear-ttl", "drift", "step:t_step=50400"]``.
    baseline : sequence
        The model the change is measured against (default the linear TTL alone), fitted
        on the model's data: its gates, if any, are not applied again (the data are gated
        as the model says).
    time_table : bool
        Test the model's adequacy in time slices too (``adequacy.time``); without, the
        fits (the same numbers) keep no time series of their columns (a day's: ~200 MB).

    Returns
    -------
    Refit
        The refit (:class:`~ttlcore.diagnose.diagnosis.Refit`): ``model`` and ``baseline``
        (effects, n_parameters, chi2_dof, adequacy, coefficients), ``change`` (delta_chi2,
        log_bayes_factor, bands_before, bands_after), their fits ``fit`` and
        ``baseline_fit`` (``data``: the :class:`~ttlcore.diagnose.whitened.WhitenedData` of
        the model's final noise model); ``to_json()`` the JSON report.
    """
    with sp_fft.set_workers(-1):  # serial: the FFTs on every core
        return _refit(source, effects, settings, effect_modules, dws_asd, baseline, time_table)


def _refit(source, effects, settings, effect_modules, dws_asd, baseline, time_table=True) -> Refit:
    if isinstance(source, WhitenedData):
        data = source
    elif isinstance(source, TDIData):
        data = whiten_tdi(source, settings, dws_asd=dws_asd, effect_modules=effect_modules)
    elif isinstance(source, (list, tuple)) and source and all(isinstance(x, TDIData) for x in source):
        data = whiten_tdi(concatenate_tdi(source), settings, dws_asd=dws_asd, effect_modules=effect_modules)
    elif hasattr(source, "dws_phi"):
        data = whiten_telemetry(source, settings, effect_modules)
    else:
        raise ConfigError(f"refit: cannot refit a {type(source).__name__}; give telemetry, TDI data or WhitenedData")
    modules = tuple(effect_modules) or data.context.effect_modules
    gates, fitted = split_gates(make_effects(list(effects), modules))
    if not isinstance(data.grid, GatedGrid):
        data = gated_data(data, gates, missing_data(data))
    fits = [fit_model(data, fitted, time_table=time_table)]
    model = _with_noise_levels(fits, time_table) if data.context.settings.noise_model == "fitted" else fits.pop()
    # the baseline on the same (gated) data: its own gates are not columns, and a comparison
    # needs one data set (a live model change from a shorter gate to a longer one, say)
    base = fit_model(model.data, split_gates(make_effects(list(baseline), modules))[1], time_table=time_table)
    ev = change(base, model)
    report = {
        "model": with_gates(model_json(model), gates),
        "baseline": model_json(base),
        "change": {
            "delta_chi2": None if ev is None else ev.delta_chi2,
            "log_bayes_factor": None if ev is None else ev.log_bayes_factor,
            "chi2_dof_before": base.chi2_dof,
            "chi2_dof_after": model.chi2_dof,
            "bands_before": [float(x) for x in base.bands.chi2_dof],
            "bands_after": [float(x) for x in model.bands.chi2_dof],
        },
    }
    return Refit.from_report(report, fit=model, baseline_fit=base)


def concatenate_tdi(segments) -> TDIData:
    """Join contiguous TDI segments (same channels, names and rate) into one."""
    first = segments[0]
    for a, b in zip(segments[:-1], segments[1:]):
        if b.channels != first.channels or b.names != first.names or b.fs != first.fs:
            raise ConfigError("TDI segments differ in channels, regressor names or rate")
        if abs(b.t0 - (a.t0 + a.size / a.fs)) > 0.5 / a.fs:
            raise ConfigError(
                f"TDI segments are not contiguous: one ends at {a.t0 + a.size / a.fs} s, the next starts at {b.t0} s"
            )
    return replace(
        first,
        data=np.concatenate([x.data for x in segments], axis=-1),
        regressors=np.concatenate([x.regressors for x in segments], axis=-1),
        ltt_mean=np.mean([x.ltt_mean for x in segments], axis=0),
    )
