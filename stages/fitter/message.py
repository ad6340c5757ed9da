"""The fitter's output: the fit message's meta, its recorded summary, and what it warns about.

A fit message ``ttl/<run>/fit/<i>`` carries the arrays ``coefficients``, ``sigma``,
``covariance`` (and ``model_parts`` for an extended model) with the meta of
:func:`fit_meta` (a :class:`streamer.bus.fit_record.FitMessage`) plus what the rolling model, the window refit and the live diagnosis add;
:func:`fit_summary` is what goes into the recording on ``fit/summary`` (schema ``ttl.Fit``).
The texts of the warnings and events a fit raises (a left-out FFT segment, a model that
fails against the instrument noise model) are :func:`excluded_message` and
:func:`inadequate_message`; the stage records them.
"""

from __future__ import annotations

import logging

from streamer.bus.fit_record import SUMMARY_META, FitMessage

log = logging.getLogger(__name__)

#: Units of the fit message's arrays.
UNITS = {"coefficients": "m/rad", "sigma": "m/rad", "covariance": "m^2/rad^2", "model_parts": "fractional frequency"}
__all__ = ["SUMMARY_META", "UNITS", "fit_meta", "fit_summary", "notices", "rolling_estimate"]


def fit_meta(
    res, *, window_duration: float, fft_segment: float, segments_total: int | None, model: list[str]
) -> FitMessage:
    """The meta of a fit message from a rolling fit's result ``res``
    (:class:`ttlcore.estimate.fit.FitResult`): the window fitted, the fit's quality, the
    rolling fit's settings and the model in force."""
    fields = {
        "names": list(res.names),
        "chi2_dof": res.chi2_dof,
        "t_start": res.t_start,
        "t_stop": res.t_stop,
        "segments": int(res.n_segments),
        "band": list(res.band),
        "converged": bool(res.converged),
        "chi2": res.chi2,
        "dof": res.dof,
        "iterations": int(res.iterations),
        "method": res.method,
        "window_duration": window_duration,
        "fft_segment": fft_segment,
        "segments_total": segments_total,
        "model": list(model),
    }
    return FitMessage().with_fields(fields)


def rolling_estimate(arrays: dict) -> dict:
    """The rolling fit's coefficients and sigmas [m/rad] of a segment whose published fit is
    the window refit's (meta ``rolling``): the monitor's trends follow one estimator, the
    rolling fit, since the two GLS estimates of the window (the residual CSD of 1-h segments
    against the instrument noise model) differ by up to ~2 sigma - a jump every day that
    the step test would read as a step."""
    return {"coefficients": arrays["coefficients"].tolist(), "sigma": arrays["sigma"].tolist()}


def fit_summary(run: str, index: int, res, meta: FitMessage, arrays: dict) -> dict:
    """The recorded summary of the fit message of segment ``index`` (``fit/summary``): the
    coefficients published, the fit's quality, the whole result under ``fit``, and the
    model's meta (:data:`SUMMARY_META`)."""
    return {
        "run": run,
        "index": index,
        "names": list(meta.names or ()),
        "coefficients": arrays["coefficients"],
        "sigma": arrays["sigma"],
        "covariance": arrays["covariance"],
        "chi2": res.chi2,
        "dof": res.dof,
        "chi2_dof": res.chi2_dof,
        "t_start": res.t_start,
        "t_end": res.t_stop,
        "segments": int(res.n_segments),
        "fit": res.to_json(),
        **meta.summary_fields(),
    }


def excluded_message(index: int, excluded: dict) -> str:
    """Why the FFT segment ``excluded`` (the rolling fit's ``extra["excluded"]``) is left out
    of the fit of segment ``index``: a gate of the model or a gap in the data (events), or an
    outlier (a warning)."""
    if excluded.get("gap"):
        return (
            f"fit {index}: the FFT segment [{excluded['t_start']:.0f}, {excluded['t_stop']:.0f}] s "
            "holds less than half valid samples (a gap in the data): the window's fit stands"
        )
    if "gate" in excluded:
        return (
            f"fit {index}: the FFT segment [{excluded['t_start']:.0f}, {excluded['t_stop']:.0f}] s "
            f"overlaps the model's gate {excluded['gate']} s: left out of the rolling fit"
        )
    return (
        f"fit {index}: the FFT segment [{excluded['t_start']:.0f}, "
        f"{excluded['t_stop']:.0f}] s is left out of the rolling fit: chi2/dof "
        f"{excluded['chi2_dof']:.3f} at its own best fit, {excluded['z']:.0f} sigma "
        f"above the window's {excluded['reference']:.3f} (a transient: a glitch, a "
        "merger, a noise burst)"
    )


def inadequate_message(index: int, meta: FitMessage) -> str:
    """The warning of a fit whose model fails against the instrument noise model."""
    assert meta.adequacy is not None
    chi2 = meta.adequacy.chi2_dof if meta.adequacy.chi2_dof is not None else float("nan")
    return (
        f"fit {index}: the model {','.join(meta.model or ())} fails against "
        f"the instrument noise model (chi2/dof {chi2:.3f}; " + "; ".join(meta.adequacy.summary) + ")"
    )


def notices(index: int, res, meta: FitMessage) -> tuple[list[tuple[str, str, str, dict]], FitMessage]:
    """What the fit of segment ``index`` says beyond its numbers, as ``(level, kind, message,
    details)`` with level ``"event"`` or ``"warning"``, and the meta with ``excluded``: an FFT
    segment left out (copied to ``excluded``; an event for a gap or a gate, a warning for an outlier), no
    convergence, a model that fails against the instrument noise model."""
    out: list[tuple[str, str, str, dict]] = []
    excluded = res.extra.get("excluded")
    if excluded:
        meta = meta.with_fields({"excluded": excluded})
        kind = "segment-gap" if excluded.get("gap") else "segment-gated" if "gate" in excluded else "segment-excluded"
        level = "warning" if kind == "segment-excluded" else "event"
        out.append((level, kind, excluded_message(index, excluded), dict(excluded)))
    if not res.converged:
        out.append(
            (
                "warning",
                "not-converged",
                f"fit {index} did not converge in {res.iterations} iterations (the last moved a "
                f"coefficient by {res.extra.get('last_change_sigma', float('nan')):.2g} sigma): its "
                "sigmas hold, its values may still move by about that much",
                {"iterations": int(res.iterations), "last_change_sigma": res.extra.get("last_change_sigma")},
            )
        )
    adequacy = meta.adequacy
    if adequacy is not None:
        log.info(
            "segment %d: model %s, chi2/dof against the instrument noise model %s%s",
            index,
            ",".join(meta.model or ()),
            f"{adequacy.chi2_dof:.3f}" if adequacy.chi2_dof is not None else "nan",
            " (fails)" if adequacy.fails else "",
        )
        if adequacy.fails:
            out.append(
                ("warning", "model-inadequate", inadequate_message(index, meta), {"chi2_dof": adequacy.chi2_dof})
            )
    return out, meta
