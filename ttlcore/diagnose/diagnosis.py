"""The diagnosis as values: what :func:`~ttlcore.diagnose.diagnoser.diagnose` returns
(:class:`Diagnosis`) and :func:`~ttlcore.diagnose.diagnoser.refit` returns (:class:`Refit`).

Each is a frozen value read by attribute: the fitted model (:class:`~ttlcore.diagnose.model_fit.ModelFit`,
with its :class:`~ttlcore.diagnose.whitened.WhitenedData`) and the parts a reader needs
(:class:`ModelReport`, :class:`Adequacy`, :class:`Change`, :class:`Candidate`,
:class:`Witnesses`, :class:`Transients`, :class:`Recommendation`).  ``to_json()`` gives the
JSON report (schema in ``docs/diagnostics.md``, "JSON report"), the live objects never in it.

Every value is made once from the JSON part the diagnosis built (``from_json``): the
attributes are read from it there, and the part is kept, unchanged, for ``to_json`` (a fresh
copy each call), so that the report written is exactly the one built.  This module is the one
place that reads the report's fields by name; everything else reads the attributes.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from .model_fit import ModelFit
from .report import text_report
from .whitened import WhitenedData

__all__ = [
    "Adequacy",
    "Band",
    "Candidate",
    "Change",
    "Coefficients",
    "Diagnosis",
    "ModelReport",
    "Recommendation",
    "Refit",
    "TimeSlice",
    "TransientEvent",
    "Transients",
    "Witness",
    "Witnesses",
]

Json = dict[str, Any]


def _opt_float(x) -> float | None:
    return None if x is None else float(x)


def _json_field() -> Any:
    """The JSON part a value was made from: kept for ``to_json``, not compared or shown."""
    return field(repr=False, compare=False)


@dataclass(frozen=True)
class Band:
    """One frequency band of an adequacy table (``adequacy.bands[i]``).

    Attributes
    ----------
    f_lo, f_hi : float
        The band's edges [Hz].
    chi2, dof : float
        chi^2 of the whitened residual in the band and its degrees of freedom.
    chi2_dof : float or None
        Their ratio (None when not finite).
    p_value : float or None
        Of the chi^2 against the noise model with its tolerance.
    fails : bool
        The band fails the noise test.
    """

    f_lo: float
    f_hi: float
    chi2: float
    dof: float
    chi2_dof: float | None
    p_value: float | None
    fails: bool

    @classmethod
    def from_json(cls, d: Mapping) -> Band:
        """The band of a report's ``bands`` entry."""
        return cls(
            f_lo=float(d["f_lo"]),
            f_hi=float(d["f_hi"]),
            chi2=float(d["chi2"]),
            dof=float(d["dof"]),
            chi2_dof=_opt_float(d["chi2_dof"]),
            p_value=_opt_float(d["p_value"]),
            fails=bool(d["fails"]),
        )


@dataclass(frozen=True)
class TimeSlice:
    """One time slice of the adequacy in time (``adequacy.time.segments[i]``): its span
    ``t_start``-``t_stop`` [s], ``chi2_dof`` and whether it ``fails``."""

    t_start: float
    t_stop: float
    chi2_dof: float | None
    fails: bool

    @classmethod
    def from_json(cls, d: Mapping) -> TimeSlice:
        """The slice of a report's ``time.segments`` entry."""
        return cls(float(d["t_start"]), float(d["t_stop"]), _opt_float(d.get("chi2_dof")), bool(d.get("fails")))


@dataclass(frozen=True)
class Adequacy:
    """A model's residual against the instrument noise model (a report's ``adequacy``).

    Attributes
    ----------
    chi2_dof : float
        Over the band.
    fails : bool
        A band or a time slice fails.
    summary : tuple of str
        Where the model fails, in words.
    bands : tuple of Band
        Per band.
    time : tuple of TimeSlice
        Per time slice (empty without the time table).
    noise_kind : str or None
        The noise model's kind (``"fitted"``, ``"fixed"``).
    segments : int
        FFT segments of the data.
    """

    chi2_dof: float
    fails: bool
    summary: tuple[str, ...]
    bands: tuple[Band, ...]
    time: tuple[TimeSlice, ...]
    noise_kind: str | None
    segments: int
    _json: Json = _json_field()

    @classmethod
    def from_json(cls, d: Json) -> Adequacy:
        """The adequacy of a report's ``adequacy`` part (kept for :meth:`to_json`)."""
        return cls(
            chi2_dof=float(d["chi2_dof"]),
            fails=bool(d["fails"]),
            summary=tuple(d["summary"]),
            bands=tuple(Band.from_json(b) for b in d["bands"]),
            time=tuple(TimeSlice.from_json(r) for r in (d.get("time") or {}).get("segments", [])),
            noise_kind=(d.get("noise_model") or {}).get("kind"),
            segments=int(d["segments"]),
            _json=d,
        )

    @property
    def band_edges(self) -> list[float]:
        """The bands' edges [Hz]: the lower edge of each, then the upper edge of the last."""
        return [b.f_lo for b in self.bands] + [self.bands[-1].f_hi] if self.bands else []

    def to_json(self) -> Json:
        """The report's ``adequacy`` part (a copy)."""
        return copy.deepcopy(self._json)


@dataclass(frozen=True)
class Coefficients:
    """A model's fitted columns (a report's ``model.coefficients``): ``values`` and robust
    ``sigma`` by column name; ``offsets``, the fitted offsets [s] of linearised effects by
    group, ``(value, sigma)``."""

    values: Mapping[str, float]
    sigma: Mapping[str, float]
    offsets: Mapping[str, tuple[float, float]]

    @classmethod
    def from_json(cls, d: Mapping) -> Coefficients:
        """The coefficients of a report's ``coefficients`` part."""
        return cls(
            values=dict(d.get("values") or {}),
            sigma=dict(d.get("sigma") or {}),
            offsets={
                k: (float(o["value"]), float(o["sigma"]))
                for k, o in (d.get("offsets") or {}).items()
                if isinstance(o, Mapping)
            },
        )


@dataclass(frozen=True)
class ModelReport:
    """A fitted model as reported (``model``, ``before``, ``baseline``).

    Attributes
    ----------
    effects : tuple of str
        Its effects' specs, its gates included.
    n_parameters : int
        Fitted columns.
    chi2_dof : float
        Over the band.
    adequacy : Adequacy
        Against the noise model.
    coefficients : Coefficients
        The fitted columns.
    gates : tuple of (float, float)
        The model's gated spans [s].
    """

    effects: tuple[str, ...]
    n_parameters: int
    chi2_dof: float
    adequacy: Adequacy
    coefficients: Coefficients
    gates: tuple[tuple[float, float], ...]
    _json: Json = _json_field()

    @classmethod
    def from_json(cls, d: Json) -> ModelReport:
        """The model of a report's ``model`` (``before``, ``baseline``) part."""
        return cls(
            effects=tuple(d["effects"]),
            n_parameters=int(d["n_parameters"]),
            chi2_dof=float(d["chi2_dof"]),
            adequacy=Adequacy.from_json(d["adequacy"]),
            coefficients=Coefficients.from_json(d["coefficients"]),
            gates=tuple((float(a), float(b)) for a, b in d.get("gates") or ()),
            _json=d,
        )

    def to_json(self) -> Json:
        """The report's part (a copy)."""
        return copy.deepcopy(self._json)


@dataclass(frozen=True)
class Change:
    """The evidence for a model against another on the same data (``change``).

    Attributes
    ----------
    delta_chi2, log_bayes_factor : float or None
        None when the models cannot be compared.
    chi2_dof_before, chi2_dof_after : float
        Of the baseline and of the model.
    bands_before, bands_after : tuple of float or None
        chi^2/dof per band.
    added : tuple of str
        What the model adds to ``linear-ttl`` (a diagnosis'; empty for a refit).
    """

    delta_chi2: float | None
    log_bayes_factor: float | None
    chi2_dof_before: float
    chi2_dof_after: float
    bands_before: tuple[float | None, ...]
    bands_after: tuple[float | None, ...]
    added: tuple[str, ...]
    _json: Json = _json_field()

    @classmethod
    def from_json(cls, d: Json) -> Change:
        """The change of a report's ``change`` part."""
        return cls(
            delta_chi2=_opt_float(d["delta_chi2"]),
            log_bayes_factor=_opt_float(d["log_bayes_factor"]),
            chi2_dof_before=float(d["chi2_dof_before"]),
            chi2_dof_after=float(d["chi2_dof_after"]),
            bands_before=tuple(map(_opt_float, d["bands_before"])),
            bands_after=tuple(map(_opt_float, d["bands_after"])),
            added=tuple(d.get("added") or ()),
            _json=d,
        )

    def to_json(self) -> Json:
        """The report's ``change`` part (a copy)."""
        return copy.deepcopy(self._json)


@dataclass(frozen=True)
class Candidate:
    """An effect not in the model, scored against it (``candidates[i]``): ``effect`` (its
    name), ``spec``/``cli_spec``, ``n_parameters``, ``delta_chi2``, ``log_bayes_factor``,
    ``explained_fraction`` (of the excess), whether it is ``significant``, the ``seconds``
    its scoring took, and the spec of the model's effect it ``replaces`` (its shape searched
    again) or None (it is added)."""

    effect: str | None
    spec: str | None
    cli_spec: str | None
    n_parameters: int | None
    delta_chi2: float | None
    log_bayes_factor: float | None
    explained_fraction: float | None
    significant: bool
    seconds: float | None
    replaces: str | None
    _json: Json = _json_field()

    @classmethod
    def from_json(cls, d: Json) -> Candidate:
        """The candidate of a ranking's entry (:func:`ttlcore.diagnose.candidates.candidates`)."""
        n = d.get("n_parameters")
        return cls(
            effect=d.get("effect"),
            spec=d.get("spec"),
            cli_spec=d.get("cli_spec"),
            n_parameters=None if n is None else int(n),
            delta_chi2=_opt_float(d.get("delta_chi2")),
            log_bayes_factor=_opt_float(d.get("log_bayes_factor")),
            explained_fraction=_opt_float(d.get("explained_fraction")),
            significant=bool(d.get("significant")),
            seconds=_opt_float(d.get("seconds")),
            replaces=d.get("replaces"),
            _json=d,
        )

    def to_json(self) -> Json:
        """The ranking's entry (a copy)."""
        return copy.deepcopy(self._json)


@dataclass(frozen=True)
class Witness:
    """One of the witnesses ranked over the band (``witnesses.overall[i]``): its ``name``,
    the effect ``spec`` it stands for, ``delta_chi2`` and the band where it takes most,
    ``best_band`` [Hz]."""

    name: str
    spec: str | None
    delta_chi2: float
    best_band: tuple[float, float]

    @classmethod
    def from_json(cls, d: Mapping) -> Witness:
        """The witness of an ``overall`` entry."""
        lo, hi = d["best_band"]
        return cls(str(d["name"]), d.get("spec"), float(d["delta_chi2"]), (float(lo), float(hi)))


@dataclass(frozen=True)
class Witnesses:
    """The witness search (``witnesses``): the ``overall`` ranking, best first, of the
    ``n_witnesses`` tried."""

    overall: tuple[Witness, ...]
    n_witnesses: int
    _json: Json = _json_field()

    @classmethod
    def from_json(cls, d: Json) -> Witnesses:
        """The witnesses of a report's ``witnesses`` part."""
        overall = tuple(Witness.from_json(w) for w in d.get("overall") or ())
        return cls(overall, int(d.get("n_witnesses") or 0), _json=d)

    def to_json(self) -> Json:
        """The report's ``witnesses`` part (a copy)."""
        return copy.deepcopy(self._json)


@dataclass(frozen=True)
class TransientEvent:
    """An event of the transient finder (``transients.events[i]``): its ``kind`` (the
    report's ``class``: gravitational-wave, glitch, ...), span ``t_start``-``t_stop`` [s],
    band ``f_lo``-``f_hi`` [Hz] and ``snr``."""

    kind: str | None
    t_start: float | None
    t_stop: float | None
    f_lo: float | None
    f_hi: float | None
    snr: float | None

    @classmethod
    def from_json(cls, d: Mapping) -> TransientEvent:
        """The event of an ``events`` entry."""
        return cls(
            d.get("class"),
            _opt_float(d.get("t_start")),
            _opt_float(d.get("t_stop")),
            _opt_float(d.get("f_lo")),
            _opt_float(d.get("f_hi")),
            _opt_float(d.get("snr")),
        )


@dataclass(frozen=True)
class Transients:
    """The transient finder's reading (``transients``): the class of the excess
    (``excess_class``), whether it is a ``signal`` or defect of the data (no effect then),
    its ``events``, the data's ``gaps`` ``(start, stop)`` [s] and, in words, the transients
    found but ``not_advised`` (they do not move the TTL fit)."""

    excess_class: str | None
    signal: bool
    events: tuple[TransientEvent, ...]
    gaps: tuple[tuple[float, float], ...]
    not_advised: tuple[str, ...]
    _json: Json = _json_field()

    @classmethod
    def from_json(cls, d: Json) -> Transients:
        """The transients of a report's ``transients`` part."""
        verdict = d.get("classification") or {}
        return cls(
            excess_class=verdict.get("class"),
            signal=bool(verdict.get("signal")),
            events=tuple(TransientEvent.from_json(e) for e in d.get("events") or ()),
            gaps=tuple((float(a), float(b)) for a, b in d.get("gaps") or ()),
            not_advised=tuple(a["text"] for a in d.get("not_advised") or ()),
            _json=d,
        )

    def to_json(self) -> Json:
        """The report's ``transients`` part (a copy)."""
        return copy.deepcopy(self._json)


@dataclass(frozen=True)
class Recommendation:
    """The next step (``recommendation``, :func:`ttlcore.diagnose.report.recommendation`).

    Attributes
    ----------
    effect, spec, cli_spec : str or None
        What it adds (the first action's kind and every action's spec for transients).
    option : str
        ``--effects ...`` when advised, else ``""``.
    explains : bool
        It explains the excess.
    explained_fraction : float or None
        The share of the excess the candidate takes.
    action_specs : tuple of str
        The glitches and gates it adds at once (empty for an effect).
    action_kinds : tuple of str
        Their kinds (``"glitch"``, ``"gate"``).
    message : str or None
        In words.
    replaces : str or None
        The model's effect the candidate takes the place of (its shape searched again), or
        None when it is added.
    """

    effect: str | None
    spec: str | None
    cli_spec: str | None
    option: str
    explains: bool
    explained_fraction: float | None
    action_specs: tuple[str, ...]
    action_kinds: tuple[str | None, ...]
    message: str | None
    replaces: str | None
    _json: Json = _json_field()

    @classmethod
    def from_json(cls, d: Json) -> Recommendation:
        """The recommendation of a report's ``recommendation`` part."""
        return cls(
            effect=d.get("effect"),
            spec=d.get("spec"),
            cli_spec=d.get("cli_spec"),
            option=str(d.get("option") or ""),
            explains=bool(d.get("explains")),
            explained_fraction=_opt_float(d.get("explained_fraction")),
            action_specs=tuple(a["spec"] for a in d.get("actions") or ()),
            action_kinds=tuple(a.get("kind") for a in d.get("actions") or ()),
            message=d.get("message"),
            replaces=d.get("replaces"),
            _json=d,
        )

    def to_json(self) -> Json:
        """The report's ``recommendation`` part (a copy)."""
        return copy.deepcopy(self._json)


@dataclass(frozen=True)
class Diagnosis:
    """A full diagnosis (:func:`~ttlcore.diagnose.diagnoser.diagnose`).

    Attributes
    ----------
    model : ModelReport
        The model diagnosed.
    before : ModelReport or None
        The linear-only model on the same data, when the model holds more.
    change : Change or None
        The evidence for the model against ``before``.
    witnesses : Witnesses or None
        The witness search (None when not run).
    candidates : tuple of Candidate
        Every effect tried, ranked, best first.
    transients : Transients or None
        The transient finder's reading.
    recommendation : Recommendation or None
        The next step (None: the model is adequate and nothing is significant).
    timings : mapping of str to float
        Each step's wall time [s] (``timings_s``).
    fit : ModelFit
        The model's fit (its ``data``: the whitened data of the final noise model).
    transient_map : object or None
        The transient finder's time-frequency map (for its figure).
    """

    model: ModelReport
    before: ModelReport | None
    change: Change | None
    witnesses: Witnesses | None
    candidates: tuple[Candidate, ...]
    transients: Transients | None
    recommendation: Recommendation | None
    timings: Mapping[str, float]
    fit: ModelFit = field(repr=False, compare=False)
    transient_map: Any = field(repr=False, compare=False)
    _json: Json = _json_field()

    @classmethod
    def from_report(cls, report: Json, *, fit: ModelFit, transient_map=None) -> Diagnosis:
        """The diagnosis of a finished report (the builder's, in
        :mod:`ttlcore.diagnose.diagnoser`; kept for :meth:`to_json`) with its live objects."""
        before, change, w = report.get("before"), report.get("change"), report.get("witnesses")
        tr, rec = report.get("transients"), report.get("recommendation")
        return cls(
            model=ModelReport.from_json(report["model"]),
            before=None if before is None else ModelReport.from_json(before),
            change=None if change is None else Change.from_json(change),
            witnesses=None if w is None else Witnesses.from_json(w),
            candidates=tuple(Candidate.from_json(c) for c in report["candidates"]),
            transients=None if tr is None else Transients.from_json(tr),
            recommendation=None if rec is None else Recommendation.from_json(rec),
            timings=dict(report.get("timings_s") or {}),
            fit=fit,
            transient_map=transient_map,
            _json=report,
        )

    @property
    def adequacy(self) -> Adequacy:
        """The model's adequacy (the report's ``adequacy``, the same as ``model.adequacy``)."""
        return self.model.adequacy

    @property
    def data(self) -> WhitenedData:
        """The whitened data of the model's final noise model."""
        return self.fit.data

    def to_json(self) -> Json:
        """The JSON report (schema in ``docs/diagnostics.md``; a fresh copy the caller may
        add to, e.g. ``file``)."""
        return copy.deepcopy(self._json)

    def text(self, source: str = "", max_candidates: int = 5) -> str:
        """The one-minute text report (:func:`ttlcore.diagnose.report.text_report`)."""
        return text_report(self._json, source, max_candidates)


@dataclass(frozen=True)
class Refit:
    """Another model on the same data, against a baseline (:func:`~ttlcore.diagnose.diagnoser.refit`).

    Attributes
    ----------
    model, baseline : ModelReport
        The model and the baseline, both on the model's (gated) data.
    change : Change
        The evidence for the model against the baseline.
    fit, baseline_fit : ModelFit
        Their fits (``fit.data``: the whitened data of the model's final noise model).
    """

    model: ModelReport
    baseline: ModelReport
    change: Change
    fit: ModelFit = field(repr=False, compare=False)
    baseline_fit: ModelFit = field(repr=False, compare=False)

    @classmethod
    def from_report(cls, report: Json, *, fit: ModelFit, baseline_fit: ModelFit) -> Refit:
        """The refit of its report (``model``, ``baseline``, ``change``) with its fits."""
        return cls(
            model=ModelReport.from_json(report["model"]),
            baseline=ModelReport.from_json(report["baseline"]),
            change=Change.from_json(report["change"]),
            fit=fit,
            baseline_fit=baseline_fit,
        )

    @property
    def data(self) -> WhitenedData:
        """The whitened data of the model's final noise model."""
        return self.fit.data

    def to_json(self) -> Json:
        """The JSON report: ``model``, ``baseline``, ``change`` (a fresh copy)."""
        return {"model": self.model.to_json(), "baseline": self.baseline.to_json(), "change": self.change.to_json()}
