"""The live diagnosis a fit message carries (meta ``diagnosis``) as a value: :class:`LiveDiagnosis`,
with its :class:`LiveRecommendation` and :class:`Adoption`.

The fitter builds the diagnosis as JSON (:func:`stages.fitter.live_diagnosis.diagnosis_meta`, the
adoption set by ``stages/fitter/fitter.py``) and gives it to :meth:`streamer.bus.fit_record.FitMessage.with_fields`;
:attr:`streamer.bus.fit_record.FitMessage.diagnosis` is then a :class:`LiveDiagnosis`, and so is the
``diagnosis`` of a recorded ``fit/summary`` (:class:`streamer.bus.fit_record.FitSummary`).  Readers
(the monitor, ``ttl inspect``) read attributes.

The diagnosis is the diagnosis report's reading of the window, and its keys follow the report
(:mod:`ttlcore.diagnose.report`): the keys read here are typed and checked (a value of the
wrong type is a :class:`~streamer.bus.message_schema.MessageError` naming
``diagnosis.<key>``), the others are kept as they came, and :meth:`LiveDiagnosis.to_json`
gives the object back as it was on the wire (the fit message's schema covers its presence,
not its inner keys: the report's own schema does).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from .message_schema import MessageError, check

__all__ = ["Adoption", "LiveDiagnosis", "LiveRecommendation", "MessageError"]


def _read(obj, where: str, name: str, kinds: Mapping[str, str]) -> dict[str, Any]:
    """The keys of ``kinds`` present and not None in the JSON object ``obj`` (field ``name``
    of message ``where``), type-checked; lists of strings and numbers as tuples."""
    check(where, name, "dict", obj)
    out: dict[str, Any] = {}
    for key, kind in kinds.items():
        v = obj.get(key)
        if v is not None:
            check(where, f"{name}.{key}", kind, v)
            out[key] = tuple(v) if kind in ("strs", "numbers", "list") else v
    return out


@dataclass(frozen=True)
class Adoption:
    """Whether the fitter adopted the diagnosis' recommendation (``diagnosis.adoption``):
    ``mode`` (``--adopt``), ``adopted``, and why (``reason``)."""

    mode: str | None = None
    adopted: bool = False
    reason: str | None = None
    raw: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def from_json(cls, obj, where: str, name: str = "diagnosis.adoption") -> Adoption:
        v = _read(obj, where, name, {"mode": "str", "adopted": "bool", "reason": "str"})
        return cls(**v, raw=copy.deepcopy(dict(obj)))

    def to_json(self) -> dict:
        return copy.deepcopy(dict(self.raw))


#: The keys of a recommendation read by attribute, and their kinds.
_RECOMMENDATION = {
    "spec": "str",
    "option": "str",
    "command": "str",
    "effects": "strs",
    "explains": "bool",
    "message": "str",
    "log_bayes_factor": "number",
}


@dataclass(frozen=True)
class LiveRecommendation:
    """What the diagnosis recommends (``diagnosis.recommendation``: the report's
    recommendation, :mod:`ttlcore.diagnose.report`, with the live fitter's additions):
    the candidate's ``spec``; the ``option`` that applies it offline and the ``effects`` and
    ``ttl control`` ``command`` that apply it live (both only when it is advised); whether it
    ``explains`` the excess; the ``message``; the candidate's ``log_bayes_factor``."""

    spec: str | None = None
    option: str | None = None
    command: str | None = None
    effects: tuple[str, ...] | None = None
    explains: bool | None = None
    message: str | None = None
    log_bayes_factor: float | None = None
    raw: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def from_json(cls, obj, where: str, name: str = "diagnosis.recommendation") -> LiveRecommendation:
        return cls(**_read(obj, where, name, _RECOMMENDATION), raw=copy.deepcopy(dict(obj)))

    @property
    def advised(self) -> str | None:
        """The spec advised: only with an option (offline) or a command (live); a best
        candidate that explains nothing is in the message, not recommended."""
        return self.spec if self.option or self.command else None

    def to_json(self) -> dict:
        return copy.deepcopy(dict(self.raw))


#: The keys of a live diagnosis read by attribute, and their kinds.
_DIAGNOSIS = {
    "index": "int",
    "segments": "list",
    "model": "strs",
    "chi2_dof": "number",
    "fails": "bool",
    "bands": "list",
    "failing_hours": "list",
    "summary": "strs",
    "text": "str",
    "removal": "list",
}


@dataclass(frozen=True)
class LiveDiagnosis:
    """The live diagnosis of the window (meta ``diagnosis``; see the module's docstring).

    Attributes
    ----------
    index : int or None
        The segment whose fit message carries it.
    segments : tuple or None
        The first and last segment of the window diagnosed.
    model : tuple of str or None
        The model in force.
    chi2_dof, fails
        The model against the instrument noise model.
    bands : tuple of dict or None
        Per band: ``f_lo``, ``f_hi`` [Hz], ``chi2_dof``, ``fails`` (:attr:`failing_bands`).
    failing_hours : tuple or None
        The ``[t_start, t_stop]`` [s] of the failing hours.
    summary : tuple of str or None
        The adequacy's summary lines.
    text : str or None
        The diagnosis in words.
    recommendation : LiveRecommendation or None
    adoption : Adoption or None
    removal : tuple of dict or None
        The model's effects whose evidence is gone, each with the command removing it.
    """

    index: int | None = None
    segments: tuple | None = None
    model: tuple[str, ...] | None = None
    chi2_dof: float | None = None
    fails: bool | None = None
    bands: tuple | None = None
    failing_hours: tuple | None = None
    summary: tuple[str, ...] | None = None
    text: str | None = None
    removal: tuple | None = None
    recommendation: LiveRecommendation | None = None
    adoption: Adoption | None = None
    raw: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def from_json(cls, obj, where: str, name: str = "diagnosis") -> LiveDiagnosis:
        """The value of a diagnosis ``obj`` (field ``name`` of message ``where``); a
        :class:`MessageError` naming ``<name>.<key>`` on a value of the wrong type."""
        values = _read(obj, where, name, _DIAGNOSIS)
        rec, adoption = obj.get("recommendation"), obj.get("adoption")
        if rec is not None:
            values["recommendation"] = LiveRecommendation.from_json(rec, where, f"{name}.recommendation")
        if adoption is not None:
            values["adoption"] = Adoption.from_json(adoption, where, f"{name}.adoption")
        for key in ("bands", "removal"):
            for i, item in enumerate(values.get(key, ())):
                check(where, f"{name}.{key}[{i}]", "dict", item)
        return cls(**values, raw=copy.deepcopy(dict(obj)))

    def to_json(self) -> dict:
        """The diagnosis as it was on the wire."""
        return copy.deepcopy(dict(self.raw))

    @property
    def failing_bands(self) -> list[list]:
        """``[f_lo, f_hi, chi2_dof]`` of each failing band."""
        return [[b.get("f_lo"), b.get("f_hi"), b.get("chi2_dof")] for b in self.bands or () if b.get("fails")]

    @property
    def adopted(self) -> Adoption | None:
        """The adoption when the fitter adopted the recommendation."""
        return self.adoption if self.adoption is not None and self.adoption.adopted else None
