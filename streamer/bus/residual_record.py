"""The residual message's meta as a value: :class:`ResidualMessage` (schema :data:`SCHEMA`).

The subtractor (``stages/subtractor.py``) builds one :class:`ResidualMessage` per TDI segment
and puts :meth:`ResidualMessage.to_header` on the wire as the ``meta`` of
``ttl/<run>/residual/<i>``; its readers (the monitor: ``stages/monitor/monitor.py``,
``stages/monitor/noise.py``) turn the ``meta`` they receive into a :class:`ResidualMessage`
with :meth:`ResidualMessage.from_header` and read attributes.

Schema rule (:mod:`streamer.bus.message_schema`, as for the fit message): a header at the current
schema is read strictly, a missing required field, an unknown field or a field of the wrong
type being a :class:`~streamer.bus.message_schema.MessageError` naming the message and the field;
a header without ``"schema"`` (the recordings written before it) is read as schema 0: every
field optional (absent ones are None), unknown fields dropped, types still checked.  Adding a
field: an optional attribute (default None) here and its type in :data:`_FIELDS`; renaming or
removing one, or a change an older reader would misread, bumps :data:`SCHEMA`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from .message_schema import MessageError, read_fields, to_jsonable

__all__ = ["SCHEMA", "MessageError", "ResidualMessage"]

#: The schema version written in the ``"schema"`` field of a residual message's meta.
SCHEMA = 1

#: The fields of :class:`ResidualMessage` on the wire, in the order the subtractor writes
#: them: (type, required at the current schema; a required field may be null).
_FIELDS: dict[str, tuple[str, bool]] = {
    "fit_index": ("int", True),
    "coefficients_t_start": ("number", True),
    "coefficients_t_stop": ("number", True),
    "segments_total": ("int", True),
    "effects": ("strs", True),
    "model_parts_missing": ("strs", False),
    "fit_stale": ("dict", False),
    "recorded": ("dict", False),
}


@dataclass(frozen=True)
class ResidualMessage:
    """The meta of a residual message ``ttl/<run>/residual/<i>`` (see the module's docstring).

    Attributes
    ----------
    fit_index : int or None
        The fit whose coefficients were subtracted (None: no fit yet, the residual is the data).
    coefficients_t_start, coefficients_t_stop : float or None
        That fit's window [s].
    segments_total : int or None
        The run's segments, when known.
    effects : tuple of str
        The effects whose model parts (array ``effect_model``, in this order) were subtracted
        besides the linear TTL.
    model_parts_missing : tuple of str or None
        The effects of the fit that were not subtracted (its parts were for another segment).
    fit_stale : dict or None
        The fit applied is an earlier one's again (the fit message's ``stale``).
    recorded : dict or None
        Added by the recorder to a recorded copy that leaves arrays out.
    """

    fit_index: int | None = None
    coefficients_t_start: float | None = None
    coefficients_t_stop: float | None = None
    segments_total: int | None = None
    effects: tuple[str, ...] | None = None
    model_parts_missing: tuple[str, ...] | None = None
    fit_stale: Mapping[str, Any] | None = None
    recorded: Mapping[str, Any] | None = None
    schema: int = field(default=SCHEMA, compare=False)

    @classmethod
    def from_header(cls, meta, message: str = "residual message") -> ResidualMessage:
        """The value of a residual message's ``meta`` (``message`` names it in errors: its key
        or index).  Raises :class:`MessageError` on a field missing, unknown or of the wrong
        type (a header without ``schema`` is read leniently, see the module's docstring)."""
        schema, raw = read_fields(meta, message, _FIELDS, SCHEMA)
        values: dict[str, Any] = {k: tuple(v) if _FIELDS[k][0] == "strs" else v for k, v in raw.items()}
        return cls(schema=schema, **values)

    @classmethod
    def build(cls, message: str = "residual message", **fields) -> ResidualMessage:
        """The value a producer builds from wire ``fields`` (JSON values; numpy scalars and
        arrays are converted), checked as :meth:`from_header` checks a header at the current
        schema: every required field given (it may be None), no unknown one."""
        return cls.from_header({**to_jsonable(fields), "schema": SCHEMA}, message)

    def to_header(self) -> dict:
        """The ``meta`` put on the wire: the fields in the order the subtractor writes them
        (None for an absent required field, optional ones left out when None), and
        ``schema``."""
        out: dict[str, Any] = {}
        for name, (_, required) in _FIELDS.items():
            v = getattr(self, name)
            if v is None and not required:
                continue
            out[name] = list(v) if isinstance(v, tuple) else v
        out["schema"] = SCHEMA
        return out
