"""The fit message's meta as a value: :class:`FitMessage` (schema :data:`SCHEMA`).

The fitter (``stages/fitter/fitter.py``, with ``stages/fitter/message.py``, ``window_refit.py``,
``rolling_model.py`` and ``live_diagnosis.py``) builds one :class:`FitMessage` per segment and
puts :meth:`FitMessage.to_header` on the wire as the ``meta`` of ``ttl/<run>/fit/<i>``; every
reader (the subtractor, the monitor, ``ttl inspect``, ``ttl refit``/``reprocess``, the planner)
turns the ``meta`` it receives into a :class:`FitMessage` with :meth:`FitMessage.from_header`
and reads attributes.

Schema rule: :data:`SCHEMA` is the ``"schema"`` field of the header.  A header at the current
schema is read strictly: a missing required field, an unknown field or a field of the wrong
type is a :class:`MessageError` naming the message and the field (the rule and the checks
are :mod:`streamer.bus.message_schema`'s, shared with the residual and the monitor's status).  A header without
``"schema"`` (written before the field existed: the recordings on disk) is read as schema 0:
the same fields, all optional (absent ones are None), unknown fields dropped (logged at debug
level), types still checked.  Adding a field: add it to :class:`FitMessage` (optional, default
None, and to :data:`_FIELDS` with its type) and bump :data:`SCHEMA` when a reader of the older
schema would misread the new header; removing or renaming one always bumps it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from .diagnosis_record import Adoption, LiveDiagnosis
from .message_schema import MessageError, WireObject, check, read_fields, to_jsonable

#: The schema version written in the ``"schema"`` field of a fit message's meta.
SCHEMA = 1

#: Meta of the fit message that the recorded summary (``fit/summary``) repeats, when present.
SUMMARY_META = (
    "model",
    "adequacy",
    "model_change",
    "candidates",
    "extra_parameters",
    "model_parts",
    "diagnosis",
    "model_update",
    "rolling",
)


@dataclass(frozen=True)
class AdequacyBand:
    """The adequacy of a fit in one frequency band [Hz]."""

    f_lo: float
    f_hi: float
    chi2_dof: float | None
    p_value: float | None
    fails: bool

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class Adequacy:
    """The fit's model against the instrument noise model (meta ``adequacy``)."""

    chi2_dof: float | None
    fails: bool
    summary: tuple[str, ...] = ()
    bands: tuple[AdequacyBand, ...] = ()
    gates: tuple[tuple[float, float], ...] | None = None
    noise_model: str | None = None

    def to_json(self) -> dict:
        out: dict[str, Any] = {}
        if self.noise_model is not None:
            out["noise_model"] = self.noise_model
        out.update(chi2_dof=self.chi2_dof, fails=self.fails, summary=list(self.summary))
        out["bands"] = [b.to_json() for b in self.bands]
        if self.gates is not None:
            out["gates"] = [list(g) for g in self.gates]
        return out

    @classmethod
    def from_json(cls, obj, where: str) -> Adequacy:
        name = "adequacy"
        check(where, name, "dict", obj)
        unknown = set(obj) - {"noise_model", "chi2_dof", "fails", "summary", "bands", "gates"}
        if unknown:
            raise MessageError(where, name, f"unknown fields {sorted(unknown)}")
        for key in ("chi2_dof", "fails"):
            if key not in obj:
                raise MessageError(where, f"{name}.{key}", "missing")
        bands = []
        for i, b in enumerate(obj.get("bands") or ()):
            w = f"{name}.bands[{i}]"
            check(where, w, "dict", b)
            try:
                bands.append(AdequacyBand(**b))
            except TypeError as exc:
                raise MessageError(where, w, str(exc)) from None
        gates = obj.get("gates")
        if obj["chi2_dof"] is not None:
            check(where, f"{name}.chi2_dof", "number", obj["chi2_dof"])
        check(where, f"{name}.fails", "bool", obj["fails"])
        check(where, f"{name}.summary", "strs", obj.get("summary") or ())
        return cls(
            chi2_dof=obj["chi2_dof"],
            fails=obj["fails"],
            summary=tuple(obj.get("summary") or ()),
            bands=tuple(bands),
            gates=None if gates is None else tuple((float(a), float(b)) for a, b in gates),
            noise_model=obj.get("noise_model"),
        )


@dataclass(frozen=True)
class RollingEstimate:
    """The rolling fit's coefficients and sigmas [m/rad] of a segment whose published fit is
    the window refit's (meta ``rolling``): what the monitor's trends follow."""

    coefficients: tuple[float, ...]
    sigma: tuple[float, ...]

    def to_json(self) -> dict:
        return {"coefficients": list(self.coefficients), "sigma": list(self.sigma)}

    @classmethod
    def from_json(cls, obj, where: str) -> RollingEstimate:
        check(where, "rolling", "dict", obj)
        if set(obj) != {"coefficients", "sigma"}:
            raise MessageError(where, "rolling", f"expected coefficients and sigma, got {sorted(obj)}")
        check(where, "rolling.coefficients", "numbers", obj["coefficients"])
        check(where, "rolling.sigma", "numbers", obj["sigma"])
        return cls(tuple(obj["coefficients"]), tuple(obj["sigma"]))


@dataclass(frozen=True)
class ModelChange(WireObject):
    """A model change the window refit reports (meta ``model_change``): the models
    ``before`` and ``after`` (effect specs) refitted on the same window, their chi^2/dof
    overall and per band (edges ``band_edges`` [Hz]), and the evidence for ``after``
    (``delta_chi2``, ``log_bayes_factor``; None when the models cannot be compared)."""

    NAME: ClassVar[str] = "model_change"
    KINDS: ClassVar[dict[str, tuple[str, bool]]] = {
        "before": ("strs", True),
        "after": ("strs", True),
        "chi2_dof_before": ("number", False),
        "chi2_dof_after": ("number", False),
        "bands_before": ("numbers", False),
        "bands_after": ("numbers", False),
        "delta_chi2": ("number", False),
        "log_bayes_factor": ("number", False),
        "band_edges": ("numbers", False),
    }

    before: tuple[str, ...]
    after: tuple[str, ...]
    chi2_dof_before: float | None = None
    chi2_dof_after: float | None = None
    bands_before: tuple[float | None, ...] | None = None
    bands_after: tuple[float | None, ...] | None = None
    delta_chi2: float | None = None
    log_bayes_factor: float | None = None
    band_edges: tuple[float, ...] | None = None
    keys: tuple[str, ...] = field(default=(), compare=False, repr=False)


@dataclass(frozen=True)
class RankedCandidate(WireObject):
    """An effect not in the model ranked by the window refit (an entry of meta
    ``candidates``, best first): its name and spec, ``delta_chi2``, ``log_bayes_factor``,
    the ``explained_fraction`` of the excess and whether it is ``significant``."""

    NAME: ClassVar[str] = "candidates[]"
    KINDS: ClassVar[dict[str, tuple[str, bool]]] = {
        "effect": ("str", True),
        "spec": ("str", False),
        "delta_chi2": ("number", False),
        "log_bayes_factor": ("number", False),
        "explained_fraction": ("number", False),
        "significant": ("bool", False),
    }

    effect: str
    spec: str | None = None
    delta_chi2: float | None = None
    log_bayes_factor: float | None = None
    explained_fraction: float | None = None
    significant: bool | None = None
    keys: tuple[str, ...] = field(default=(), compare=False, repr=False)


#: The fields of :class:`FitMessage` on the wire: (type, required at the current schema).
_FIELDS: dict[str, tuple[str, bool]] = {
    "names": ("strs", True),
    "chi2_dof": ("number", True),
    "t_start": ("number", True),
    "t_stop": ("number", True),
    "segments": ("int", True),
    "band": ("numbers", True),
    "converged": ("bool", True),
    "chi2": ("number", True),
    "dof": ("number", True),
    "iterations": ("int", True),
    "method": ("str", True),
    "window_duration": ("number", True),
    "fft_segment": ("number", True),
    "segments_total": ("int", True),
    "model": ("strs", True),
    "extra_parameters": ("dict", False),
    "model_parts": ("strs", False),
    "model_update": ("str", False),
    "rolling": ("dict", False),
    "adequacy": ("dict", False),
    "window": ("dict", False),
    "model_change": ("dict", False),
    "candidates": ("list", False),
    "diagnosis": ("dict", False),
    "stale": ("dict", False),
    "excluded": ("dict", False),
    "recorded": ("dict", False),
}


@dataclass(frozen=True)
class FitMessage:
    """The meta of a fit message ``ttl/<run>/fit/<i>`` (see the module's docstring).

    The required fields are the rolling fit's (names, quality, window, settings, model in
    force); the optional ones (None when absent) are what the rolling model (``extra_parameters``,
    ``model_parts``, ``model_update``), the window refit (``adequacy``, ``window``,
    ``model_change``, ``candidates``, ``rolling``), the live diagnosis (``diagnosis``), the
    staleness check (``stale``), the left-out FFT segment (``excluded``) and the recorder
    (``recorded``) add.  Nested values a reader needs the fields of are values
    (:class:`Adequacy`, :class:`RollingEstimate`, :class:`ModelChange`,
    :class:`RankedCandidate`, :class:`streamer.bus.diagnosis_record.LiveDiagnosis`); the others
    stay JSON (dicts and lists).
    """

    names: tuple[str, ...] | None = None
    chi2_dof: float | None = None
    t_start: float | None = None
    t_stop: float | None = None
    segments: int | None = None
    band: tuple[float, ...] | None = None
    converged: bool | None = None
    chi2: float | None = None
    dof: float | None = None
    iterations: int | None = None
    method: str | None = None
    window_duration: float | None = None
    fft_segment: float | None = None
    segments_total: int | None = None
    model: tuple[str, ...] | None = None
    extra_parameters: Mapping[str, Any] | None = None
    model_parts: tuple[str, ...] | None = None
    model_update: str | None = None
    rolling: RollingEstimate | None = None
    adequacy: Adequacy | None = None
    window: Mapping[str, Any] | None = None
    model_change: ModelChange | None = None
    candidates: tuple[RankedCandidate, ...] | None = None
    diagnosis: LiveDiagnosis | None = None
    stale: Mapping[str, Any] | None = None
    excluded: Mapping[str, Any] | None = None
    recorded: Mapping[str, Any] | None = None
    schema: int = field(default=SCHEMA, compare=False)

    # ------------------------------------------------------------------ reading
    @classmethod
    def from_header(cls, meta, message: str = "fit message") -> FitMessage:
        """The value of a fit message's ``meta`` (``message`` names it in errors: its key or
        index).  Raises :class:`MessageError` on a field missing, unknown or of the wrong type
        (a header without ``schema`` is read leniently, see the module's docstring)."""
        schema, raw = read_fields(meta, message, _FIELDS, SCHEMA)
        return cls(schema=schema, **{name: _value(name, v, message) for name, v in raw.items()})

    # ------------------------------------------------------------------ writing
    def to_header(self) -> dict:
        """The ``meta`` put on the wire: the fields in the order the fitter writes them (None
        for an absent required field, optional ones left out when None), and ``schema``."""
        out: dict[str, Any] = {}
        for name, (_, required) in _FIELDS.items():
            v = getattr(self, name)
            if v is None and not required:
                continue
            out[name] = _json(v)
        out["schema"] = SCHEMA
        return out

    def with_fields(self, fields: Mapping[str, Any], message: str = "fit message") -> FitMessage:
        """A copy with the wire ``fields`` (as a producer builds them: JSON values) set,
        checked as :meth:`from_header` checks them."""
        unknown = sorted(set(fields) - set(_FIELDS))
        if unknown:
            raise MessageError(message, unknown[0], "unknown field")
        values = {}
        for name, v in fields.items():
            v = to_jsonable(v)
            if v is not None:
                check(message, name, _FIELDS[name][0], v)
                v = _value(name, v, message)
            values[name] = v
        return dataclasses.replace(self, **values)

    def summary_fields(self) -> dict:
        """The meta the recorded summary repeats (:data:`SUMMARY_META`), as JSON."""
        return {k: _json(getattr(self, k)) for k in SUMMARY_META if getattr(self, k) is not None}

    # ------------------------------------------------------------------ derived
    @property
    def adopted(self) -> Adoption | None:
        """The live diagnosis' adoption (``diagnosis.adoption``) when it adopted a model."""
        return self.diagnosis.adopted if self.diagnosis is not None else None


def _value(name: str, v, message: str):
    """A wire value as the attribute holds it."""
    if name == "adequacy":
        return Adequacy.from_json(v, message)
    if name == "rolling":
        return RollingEstimate.from_json(v, message)
    if name in ("names", "model", "model_parts", "band"):
        return tuple(v)
    if name == "diagnosis":
        return LiveDiagnosis.from_json(v, message)
    if name == "model_change":
        return ModelChange.from_json(v, message)
    if name == "candidates":
        return tuple(RankedCandidate.from_json(c, message, f"candidates[{i}]") for i, c in enumerate(v))
    return v


def _json(v):
    """An attribute's value on the wire."""
    if isinstance(v, (Adequacy, RollingEstimate, WireObject, LiveDiagnosis)):
        return v.to_json()
    if isinstance(v, tuple):
        return [_json(x) for x in v]
    return v


@dataclass(frozen=True)
class FitSummary:
    """A recorded fit summary (``fit/summary``, JSON schema ``ttl.Fit``;
    :func:`stages.fitter.message.fit_summary` writes it): the fit published for segment
    ``index`` and the model's meta.

    Two layouts are read: the fitter's (``coefficients``/``sigma`` lists in the order of
    ``names``, ``t_start``, ``t_end``, the whole result under ``fit``, then the meta of
    :data:`SUMMARY_META`) and a bare :meth:`ttlcore.estimate.fit.FitResult.to_json`
    (coefficients and sigma by name, the window under ``fit.window``).  :meth:`to_dict` gives
    the record back as it was.

    Attributes
    ----------
    index : int
    names : tuple of str
    coefficients, sigma : list of float or None
        In the order of ``names`` [m/rad].
    covariance : list of list of float or None
    t_start, t_stop : float or None
        The fitted window [s].
    chi2_dof : float or None
    converged : bool or None
    meta : FitMessage
        The model's meta the summary repeats (:data:`SUMMARY_META`: ``model``,
        ``adequacy``, ``diagnosis``...), read as a fit message without a schema.
    """

    index: int
    names: tuple[str, ...]
    coefficients: list | None
    sigma: list | None
    covariance: list | None
    t_start: float | None
    t_stop: float | None
    chi2_dof: float | None
    converged: bool | None
    meta: FitMessage
    record: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def from_dict(cls, d, where: str = "fit/summary") -> FitSummary:
        """The value of a recorded summary ``d``; a :class:`MessageError` naming ``where`` and
        the field when ``d`` is not one (no integer ``index``, a field of the wrong type)."""
        check(where, "record", "dict", d)
        index = d.get("index")
        check(where, "index", "int", index)
        where = f"{where} {index}"
        fit = _object(d.get("fit"))
        names = d.get("names") or fit.get("names") or []
        check(where, "names", "strs", names)
        coefficients, sigma = d.get("coefficients"), d.get("sigma")
        if isinstance(coefficients, Mapping):  # FitResult.to_json layout
            coefficients = [coefficients.get(n) for n in names]
        if isinstance(sigma, Mapping):
            sigma = [sigma.get(n) for n in names]
        window = _object(fit.get("window"))
        values = {
            "t_start": d.get("t_start", window.get("t_start")),
            "t_stop": d.get("t_end", d.get("t_stop", window.get("t_stop"))),
            "chi2_dof": d.get("chi2_dof", fit.get("chi2_dof")),
        }
        for name, v in values.items():
            if v is not None:
                check(where, name, "number", v)
        converged = fit.get("converged", d.get("converged"))
        if converged is not None:
            check(where, "converged", "bool", converged)
        meta = FitMessage.from_header({k: d[k] for k in SUMMARY_META if k in d}, where)
        return cls(
            index=index,
            names=tuple(names),
            coefficients=coefficients,
            sigma=sigma,
            covariance=d.get("covariance"),
            converged=converged,
            meta=meta,
            record=d,
            **values,
        )

    def to_dict(self) -> dict:
        """The summary as it was recorded."""
        return dict(self.record)


def _object(v) -> Mapping[str, Any]:
    """A JSON object, or an empty one for anything else."""
    return v if isinstance(v, Mapping) else {}
