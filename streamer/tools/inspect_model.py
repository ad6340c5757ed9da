"""The fitter's coefficients and model over a run, from its recordings (for ``ttl inspect``,
:func:`streamer.tools.inspect.inspect_run`): the fits, their trends with the GLS drift rate of
:mod:`ttlcore.diagnose.trends`, the truth over a fit window (and the last fit's sigmas tested
against it), the model's changes and the
live diagnoses."""

from __future__ import annotations

import logging

import numpy as np

from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.diagnose.trends import TrendSettings, trend_estimates
from ttlcore.estimate.monitoring import FileTruth
from ttlcore.estimate.pulls import pull_summary

from ..bus.diagnosis_record import LiveRecommendation
from ..bus.fit_record import FitMessage, FitSummary
from ..bus.message_schema import MessageError
from ..recording.recorder import RecordedSegment, Recording

log = logging.getLogger(__name__)

#: Span of the drift rate in the report [days] (ttlcore.diagnose.trends.TrendSettings.drift_lookback).
LOOKBACK_DAYS = 3.0


def fit_summaries(rec: Recording) -> list[FitSummary]:
    """The fit summaries (``fit/summary``) of a recording as values; a record that is not one
    (no integer index, a field of the wrong type) is left out and logged."""
    out = []
    for d in rec.json("fit/summary"):
        try:
            out.append(FitSummary.from_dict(d, f"{rec.path.name}: fit/summary"))
        except MessageError as exc:
            log.warning("%s: left out", exc)
    return out


def recorded_fits(recs: list[Recording]) -> list[dict]:
    """The fits of the fitter's recordings, one per index (a later file's fit wins)."""
    fits: dict[int, dict] = {}
    for rec in recs:
        summaries = fit_summaries(rec)
        if summaries:
            fits.update((s.index, _summary_fit(s)) for s in summaries)
        else:  # no summaries: the fit segments themselves
            fits.update((m.header.index, _segment_fit(m)) for m in rec.segments("fit") if "coefficients" in m.arrays)
    return [f for f in sorted(fits.values(), key=lambda f: f["index"]) if _usable(f)]


def _summary_fit(s: FitSummary) -> dict:
    """The fit of a ``fit/summary`` record."""
    return {
        "index": s.index,
        "names": list(s.names),
        "t_start": s.t_start,
        "t_stop": s.t_stop,
        "chi2_dof": s.chi2_dof,
        "converged": s.converged,
        "coefficients": s.coefficients,
        "sigma": s.sigma,
        "covariance": s.covariance,
    }


def _segment_fit(m: RecordedSegment) -> dict:
    """The fit of a recorded ``fit`` segment (with its coefficients)."""
    a, meta = m.arrays, FitMessage.from_header(m.header.meta, f"fit {m.header.index}")
    return {
        "index": m.header.index,
        "names": list(meta.names or []),
        "t_start": meta.t_start,
        "t_stop": meta.t_stop,
        "chi2_dof": meta.chi2_dof,
        "converged": meta.converged,
        "coefficients": a["coefficients"].tolist(),
        "sigma": a["sigma"].tolist() if "sigma" in a else None,
        "covariance": a["covariance"].tolist() if "covariance" in a else None,
    }


def _usable(f: dict) -> bool:
    """Whether a fit has a vector of coefficients and sigma of the same shape (sigma may be missing)."""
    try:
        c = np.asarray(f["coefficients"], dtype=float)
        s = np.asarray(f["sigma"], dtype=float) if f["sigma"] is not None else np.full(c.shape, np.nan)
    except (TypeError, ValueError):
        return False
    return bool(c.ndim == 1 and c.shape == s.shape and c.size)


def coefficient_trends(fits: list[dict]) -> dict:
    """Per coefficient: latest value and sigma, range, and the GLS drift rate of ttlcore.diagnose.trends [mm/rad]."""
    if not fits:
        return {}
    names = fits[-1]["names"] or [f"c{i}" for i in range(len(fits[-1]["coefficients"]))]
    same = [f for f in fits if len(f["coefficients"]) == len(names)]
    C = np.array([f["coefficients"] for f in same], dtype=float) * 1e3
    S = np.array([f["sigma"] for f in same], dtype=float) * 1e3
    out = {
        n: {
            "latest": float(C[-1, p]),
            "sigma": float(S[-1, p]),
            "first": float(C[0, p]),
            "min": float(np.nanmin(C[:, p])),
            "max": float(np.nanmax(C[:, p])),
            "rate": None,
            "rate_se": None,
            "significance": None,
        }
        for p, n in enumerate(names)
    }
    windows = [(f["t_start"], f["t_stop"]) for f in same]
    ok = all(isinstance(a, (int, float)) and isinstance(b, (int, float)) and b > a for a, b in windows)
    if ok and len(same) >= 3 and np.all(np.isfinite(S)):
        try:
            te = np.array([b for _, b in windows])
            order = np.argsort(te, kind="stable")
            keep = order[np.concatenate([[True], np.diff(te[order]) > 0])]
            est = trend_estimates(
                te[keep],
                C[keep],
                S[keep],
                t_start=np.array([a for a, _ in windows])[keep],
                names=names,
                units="mm/rad",
                settings=TrendSettings(drift_min_windows=3, drift_lookback=LOOKBACK_DAYS * 86400.0),
            )
            for p, n in enumerate(names):
                if np.isfinite(est.rate[p]):
                    out[n].update(
                        rate=float(est.rate[p]), rate_se=float(est.se[p]), significance=float(est.significance[p])
                    )
        except ValueError:
            pass
    return out


def truth_over_window(truth_path, t_start: float, t_stop: float, names) -> dict:
    """True coefficients [mm/rad] averaged over ``[t_start, t_stop)`` from a truth file
    (:class:`ttlcore.estimate.monitoring.FileTruth`, as the monitor draws them); empty when
    the window is outside the file."""
    mean = FileTruth(truth_path).mean(t_start, t_stop)
    if mean is None:
        return {}
    by_name = dict(zip(COEFFICIENT_NAMES, mean * 1e3))
    return {n: float(by_name[n]) for n in names if n in by_name}


def truth_test(fit: dict, truth_path) -> dict | None:
    """A recorded fit (:func:`recorded_fits`) against the truth averaged over its window:
    its errors and whether its sigmas are honest (:func:`ttlcore.estimate.pulls.pull_summary`,
    in m/rad); None without a covariance, a truth over the window or the 24 coefficients."""
    mean = FileTruth(truth_path).mean(fit["t_start"], fit["t_stop"])
    names, cov = fit.get("names") or [], fit.get("covariance")
    if mean is None or cov is None or any(n not in names for n in COEFFICIENT_NAMES):
        return None
    k = [names.index(n) for n in COEFFICIENT_NAMES]
    C = np.asarray(fit["coefficients"], dtype=float)[k]
    return pull_summary(C, np.asarray(cov, dtype=float)[np.ix_(k, k)], mean).to_json()


def model_report(recs: list[Recording]) -> dict:
    """The fitter's model over the run: its changes (``model`` events: from which segment,
    by whom - a control message or ``--adopt auto`` - and why) and the live diagnoses (the
    ``diagnosis`` of the fit summaries: window, chi^2/dof, failing bands, recommendation and
    the ``ttl control`` command applying it, adoption)."""
    changes, diagnoses, last_model = [], {}, None
    for rec in recs:
        for e in rec.json("events"):
            if isinstance(e, dict) and e.get("kind") == "model":
                d = e.get("details") or {}
                changes.append(
                    {
                        "from_index": d.get("from_index"),
                        "effects": d.get("effects"),
                        "before": d.get("before"),
                        "by": d.get("by"),
                        "reason": d.get("reason"),
                        "file": rec.path.name,
                    }
                )
        for summary in fit_summaries(rec):
            meta = summary.meta
            if meta.model is not None:
                last_model = (summary.index, list(meta.model))
            diag = meta.diagnosis
            if diag is not None:
                rec_ = diag.recommendation or LiveRecommendation()
                diagnoses[summary.index] = {
                    "index": summary.index,
                    "segments": _list(diag.segments),
                    "model": _list(diag.model),
                    "chi2_dof": diag.chi2_dof,
                    "fails": diag.fails,
                    "failing_bands": diag.failing_bands,
                    "failing_hours": _list(diag.failing_hours),
                    "summary": _list(diag.summary),
                    # advised only with an option (offline) or a command (live): a best
                    # candidate that explains nothing is in the message, not recommended
                    "recommendation": rec_.advised,
                    "effects": _list(rec_.effects),
                    "explains": rec_.explains,
                    "command": rec_.command,
                    "message": rec_.message,
                    "adoption": diag.adoption.to_json() if diag.adoption is not None else None,
                    "removal": _list(diag.removal) or [],
                    "text": diag.text,
                }
    return {
        "model": None if last_model is None else {"index": last_model[0], "effects": last_model[1]},
        "changes": changes,
        "diagnoses": [diagnoses[i] for i in sorted(diagnoses)],
    }


def _list(v) -> list | None:
    """A tuple attribute as the report's list (None stays None)."""
    return None if v is None else list(v)
