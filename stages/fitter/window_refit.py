"""The fitter's window refit: the window's telemetry refitted with the model, as ``ttl refit``.

Every ``adequacy_every`` segments, on the first segment of a new model and on every segment
of an extended model the rolling fit cannot carry, the fitter refits its window's telemetry
with the model under the instrument noise model (:func:`ttlcore.diagnose.diagnoser.refit`,
searched parameters searched again on the window).  :func:`window_refit` runs it;
:func:`window_refit_meta` turns the refit into the fit message's meta: ``adequacy``
(chi^2/dof per band), for an extended model its coefficients, ``extra_parameters``,
``model_parts`` and ``model_update: "window refit"``, on a model change ``model_change``
(both models on the same window), and the ranked ``candidates`` when asked for.
"""

from __future__ import annotations

import logging

import numpy as np

from streamer.tools.refit import refit_settings
from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.diagnose.candidates import candidates
from ttlcore.diagnose.diagnoser import refit
from ttlcore.diagnose.diagnosis import Candidate, Refit
from ttlcore.diagnose.prediction import effect_predictions
from ttlcore.diagnose.whitened import WhitenedData
from ttlcore.effects.gate import Gate
from ttlcore.errors import ConfigError
from ttlcore.io.telemetry import Telemetry

#: Candidates reported in a fit message.
TOP_CANDIDATES = 3


def transient_gates(window: Telemetry, excluded) -> list[str]:
    """Gates over the FFT segments the rolling fit left out as outliers (``excluded``: its
    :attr:`ttlcore.estimate.rolling.RollingFit.excluded`, a glitch, a merger, a noise burst)
    within ``window``: the window refit is not pulled by what the rolling fit is not.  (A
    merger and a glitch the live model did not gate, refitted with them, moved the last fit
    of a live day to 0.032 mm/rad from the truth, pull RMS 1.58; the rolling fit without
    them: 0.026.)  The FFT segments a gate of the model left out are gated by the model."""
    t_lo, t_hi = float(window.t0), float(window.t0) + window.size / float(window.fs)
    spans = [
        (max(float(e["t_start"]), t_lo), min(float(e["t_stop"]), t_hi))
        for e in excluded
        if "gate" not in e and float(e["t_stop"]) > t_lo and float(e["t_start"]) < t_hi
    ]
    return [Gate(start=a, stop=b).spec() for a, b in spans if b > a]


def window_refit(
    window: Telemetry,
    effects: list[str],
    baseline: list[str],
    *,
    dws_asd,
    band: tuple | None,
    effect_modules=(),
    transients=(),
    log: logging.Logger | logging.LoggerAdapter | None = None,
    whitened: WhitenedData | None = None,
) -> Refit | None:
    """Refit the window's telemetry with the model ``effects`` (and ``baseline``) under the
    instrument noise model, as ``ttl refit`` does, the rolling fit's outlying FFT segments
    ``transients`` gated (:func:`transient_gates`); None when the window is still too short
    for it (logged on ``log``).  ``whitened``: the window's whitened data under the same
    settings, when built already (the refit starts from them)."""
    effects = list(effects) + transient_gates(window, transients)
    try:
        # no time table: the live diagnosis gives the failing hours; without it the refit
        # keeps no column series (~110 MB less at its peak for a day, the same numbers)
        return refit(
            window if whitened is None else whitened,
            effects,
            settings=refit_settings(dws_asd, band),
            effect_modules=effect_modules,
            baseline=baseline,
            time_table=False,
        )
    except ConfigError as exc:
        if log is not None:
            log.info("no window refit yet: %s", exc)
        return None


def window_refit_meta(
    r: Refit,
    *,
    change: dict | None,
    extended: bool,
    window: tuple[int, int, int],
    ranked: bool,
) -> dict:
    """Meta (and, under ``arrays``, arrays) of a fit message from a window refit.

    Parameters
    ----------
    r : Refit
        The refit of :func:`window_refit`.
    change : dict or None
        The model change it reports (``before``, ``after``): ``model_change``.
    extended : bool
        The model holds more than ``linear-ttl``: its coefficients, ``extra_parameters`` and,
        for the newest segment, ``model_parts``.
    window : (int, int, int)
        The first and last segment of the window, and the newest segment's samples.
    ranked : bool
        The candidates not in the model are ranked (``candidates``): every
        ``--candidates-every`` segments, and on a change when no live diagnosis ranks them
        (the fitter's :meth:`~stages.fitter.fitter.Fitter.window_fit`).
    """
    model = r.fit
    adequacy = r.model.adequacy
    out: dict = {
        "adequacy": {
            "noise_model": "instrument (analytic secondary noises + DWS readout noise), not re-estimated",
            "chi2_dof": adequacy.chi2_dof,
            "fails": adequacy.fails,
            "summary": list(adequacy.summary),
            "bands": [
                {"f_lo": b.f_lo, "f_hi": b.f_hi, "chi2_dof": b.chi2_dof, "p_value": b.p_value, "fails": b.fails}
                for b in adequacy.bands
            ],
            # the model's, and the transients' (transient_gates)
            "gates": [[a, b] for a, b in r.model.gates],
        }
    }
    if extended:
        first, last, n_last = window
        k = [model.parameter_names.index(n) for n in COEFFICIENT_NAMES]
        out["arrays"] = {
            "coefficients": model.ttl_coefficients(),
            "sigma": model.ttl_sigma(),
            "covariance": model.robust_covariance[np.ix_(k, k)],
        }
        out["extra_parameters"] = {
            n: [float(v), float(s)]
            for n, v, s in zip(model.names, model.theta, model.robust_sigma)
            if n not in COEFFICIENT_NAMES
        }
        predictions = effect_predictions(model)
        if predictions:
            out["arrays"]["model_parts"] = np.stack([p[:, -n_last:] for p in predictions.values()])
            out["model_parts"] = list(predictions)
        out["window"] = {"first": first, "last": last}
        out["model_update"] = "window refit"
    if change is not None:
        c = r.change
        out["model_change"] = {
            "before": change["before"],
            "after": change["after"],
            "chi2_dof_before": c.chi2_dof_before,
            "chi2_dof_after": c.chi2_dof_after,
            "bands_before": list(c.bands_before),
            "bands_after": list(c.bands_after),
            "delta_chi2": c.delta_chi2,
            "log_bayes_factor": c.log_bayes_factor,
            "band_edges": adequacy.band_edges,
        }
    if ranked:
        ranking = [Candidate.from_json(c) for c in candidates(model)[:TOP_CANDIDATES]]
        out["candidates"] = [
            {
                "effect": c.effect,
                "spec": c.spec,
                "delta_chi2": c.delta_chi2,
                "log_bayes_factor": c.log_bayes_factor,
                "explained_fraction": c.explained_fraction,
                "significant": c.significant,
            }
            for c in ranking
        ]
    return out
