"""The monitor's status message's meta as a value: :class:`MonitorMessage` (schema :data:`SCHEMA`).

The monitor (``stages/monitor/monitor.py`` with ``stages/monitor/status.py``) builds one
:class:`MonitorMessage` per TDI segment and puts :meth:`MonitorMessage.to_header` on the wire
as the ``meta`` of ``ttl/<run>/monitor/<i>``; the recording's ``monitor/summary`` repeats the
fields without ``schema`` (:meth:`MonitorMessage.summary_fields`).  A reader (a dashboard, the
tests) turns the ``meta`` into a value with :meth:`MonitorMessage.from_header`.

Schema rule (:mod:`streamer.bus.message_schema`, as for the fit and the residual): a header at
the current schema is read strictly (a missing required field, an unknown one or one of the
wrong type is a :class:`~streamer.bus.message_schema.MessageError` naming the message and the
field); a header without ``"schema"`` (recordings written before it) is read as schema 0:
every field optional, unknown fields dropped, types still checked.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from .message_schema import MessageError, check, read_fields, to_jsonable

__all__ = ["SCHEMA", "MessageError", "MonitorMessage"]

#: The schema version written in the ``"schema"`` field of a monitor message's meta.
SCHEMA = 1

#: The fields of :class:`MonitorMessage` on the wire, in the monitor's order: (type, required
#: at the current schema; a required field may be null).
_FIELDS: dict[str, tuple[str, bool]] = {
    "names": ("strs", True),
    "alerts": ("list", True),
    "drifting": ("strs", True),
    "drift_windows": ("int", True),
    "model_epoch": ("dict", True),
    "residual_over_expected": ("dict", True),
    "fit": ("dict", True),
    "segments_total": ("int", True),
}


@dataclass(frozen=True)
class MonitorMessage:
    """The meta of a monitor message ``ttl/<run>/monitor/<i>``: the trend state and the alerts
    raised since the previous message.

    Attributes
    ----------
    names : tuple of str
        The coefficients of the arrays ``drift_rate`` and ``drift_significance``.
    alerts : tuple of dict
        The alerts raised since the previous message
        (:meth:`ttlcore.diagnose.trends.Alert.to_json`; JSON schema ``ttl.Alert``).
    drifting : tuple of str
        The coefficients drifting now.
    drift_windows : int
        The fit windows of the latest trend evaluation (0 before the first).
    model_epoch : dict or None
        The model epoch the trends are in (:meth:`ttlcore.diagnose.trends.ModelEpoch.to_json`),
        None before the first fit.
    residual_over_expected : dict or None
        The latest in-band median ASD ratio of the residual to the expected noise: ``index``,
        ``ratio``.
    fit : dict or None
        The latest fit: ``index``, ``chi2_dof``, ``t_start``, ``t_stop``.
    segments_total : int or None
        The run's segments, when known.
    """

    names: tuple[str, ...] | None = None
    alerts: tuple[Mapping[str, Any], ...] | None = None
    drifting: tuple[str, ...] | None = None
    drift_windows: int | None = None
    model_epoch: Mapping[str, Any] | None = None
    residual_over_expected: Mapping[str, Any] | None = None
    fit: Mapping[str, Any] | None = None
    segments_total: int | None = None
    schema: int = field(default=SCHEMA, compare=False)

    @classmethod
    def from_header(cls, meta, message: str = "monitor message") -> MonitorMessage:
        """The value of a monitor message's ``meta`` (``message`` names it in errors).
        Raises :class:`MessageError` on a field missing, unknown or of the wrong type (a
        header without ``schema`` is read leniently, see the module's docstring)."""
        schema, raw = read_fields(meta, message, _FIELDS, SCHEMA)
        for i, a in enumerate(raw.get("alerts", ())):
            check(message, f"alerts[{i}]", "dict", a)
        values: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in raw.items()}
        return cls(schema=schema, **values)

    @classmethod
    def build(cls, message: str = "monitor message", **fields) -> MonitorMessage:
        """The value the monitor builds from wire ``fields`` (numpy values converted), checked
        as :meth:`from_header` checks a header at the current schema."""
        return cls.from_header({**to_jsonable(fields), "schema": SCHEMA}, message)

    def summary_fields(self) -> dict:
        """The fields as JSON, in the monitor's order, without ``schema`` (what the recorded
        ``monitor/summary`` repeats)."""
        return {name: _json(getattr(self, name)) for name in _FIELDS}

    def to_header(self) -> dict:
        """The ``meta`` put on the wire: every field (None when absent) and ``schema``."""
        return {**self.summary_fields(), "schema": SCHEMA}


def _json(v):
    if isinstance(v, tuple):
        return [_json(x) for x in v]
    return v
