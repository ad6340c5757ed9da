"""What every typed message's ``meta`` shares: the error naming the message and the field
(:class:`MessageError`), the field type checks (:func:`check`) and the read of a header
against a field table and a schema version (:func:`read_fields`); :func:`to_jsonable`, a
value with numpy types and non-finite floats made JSON (every message and recording uses it).

The values themselves are in their own modules: the fit (:mod:`streamer.bus.fit_record`), the
residual (:mod:`streamer.bus.residual_record`) and the monitor's status
(:mod:`streamer.bus.monitor_record`).  Each has a ``SCHEMA`` (the ``"schema"`` field of its
header) and a field table ``{name: (kind, required)}`` (``kind`` one of :data:`KINDS`).

Schema rule (the same for every message): a header at schema 1 or later is read strictly (a
missing required field, an unknown field or a field of the wrong type is a
:class:`MessageError`); a header without ``"schema"`` (written before the field existed: the
recordings on disk) is read as schema 0: every field optional, unknown fields dropped
(logged at debug level), types still checked.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

log = logging.getLogger(__name__)


class MessageError(ValueError):
    """A message's meta that is not what its schema says: names the message and the field."""

    def __init__(self, message: str, field_name: str, what: str):
        self.message = message
        self.field = field_name
        super().__init__(f"{message}: meta field {field_name!r}: {what}")


def is_number(v) -> bool:
    """An int or a float, not a bool."""
    return isinstance(v, (int, float)) and not isinstance(v, bool)


#: The kinds of a field table and what each accepts (None is the caller's to allow).
KINDS = {
    "number": is_number,
    "int": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "bool": lambda v: isinstance(v, bool),
    "str": lambda v: isinstance(v, str),
    "strs": lambda v: isinstance(v, (list, tuple)) and all(isinstance(x, str) for x in v),
    "numbers": lambda v: isinstance(v, (list, tuple)) and all(is_number(x) or x is None for x in v),
    "dict": lambda v: isinstance(v, Mapping),
    "list": lambda v: isinstance(v, (list, tuple)),
}


def check(where: str, name: str, kind: str, v) -> None:
    """Raise a :class:`MessageError` when ``v`` is not of ``kind`` (None is checked by the caller)."""
    if not KINDS[kind](v):
        raise MessageError(where, name, f"expected {kind}, got {type(v).__name__} {str(v)[:60]!r}")


def read_fields(
    meta, message: str, fields: Mapping[str, tuple[str, bool]], schema_now: int
) -> tuple[int, dict[str, Any]]:
    """``(schema, values)`` of a header ``meta`` read against the field table ``fields`` (the
    module's docstring says how strictly): the fields present and not None, type-checked,
    as they are on the wire."""
    if not isinstance(meta, Mapping):
        raise MessageError(message, "meta", f"expected a mapping, got {type(meta).__name__}")
    schema = meta.get("schema", 0)
    if not isinstance(schema, int) or isinstance(schema, bool) or not 0 <= schema <= schema_now:
        raise MessageError(message, "schema", f"this reader knows schemas 0 to {schema_now}, got {schema!r}")
    strict = schema >= 1
    unknown = sorted(set(meta) - set(fields) - {"schema"})
    if unknown and strict:
        raise MessageError(message, unknown[0], "unknown field" + (f" (and {unknown[1:]})" if unknown[1:] else ""))
    if unknown:
        log.debug("%s: schema-0 meta fields not read: %s", message, unknown)
    values: dict[str, Any] = {}
    for name, (kind, required) in fields.items():
        if name not in meta:
            if strict and required:
                raise MessageError(message, name, "missing")
            continue
        v = meta[name]
        if v is None:
            continue
        check(message, name, kind, v)
        values[name] = v
    return schema, values


def object_fields(where: str, name: str, obj, known: tuple[str, ...], required: tuple[str, ...] = ()) -> Mapping:
    """A nested JSON object ``obj`` (field ``name`` of message ``where``) checked to be a
    mapping with only the ``known`` keys and every ``required`` one."""
    check(where, name, "dict", obj)
    unknown = sorted(set(obj) - set(known))
    if unknown:
        raise MessageError(where, name, f"unknown fields {unknown}")
    for key in required:
        if key not in obj:
            raise MessageError(where, f"{name}.{key}", "missing")
    return obj


class WireObject:
    """A nested JSON object of a message's meta as a frozen value (a dataclass that derives
    from this one): :attr:`KINDS` is its field table ``{key: (kind, required)}``, and its
    ``keys`` field (compare=False) the keys the object had on the wire, in their order, so
    that :meth:`to_json` gives back the same object (an absent key and a null one differ)."""

    NAME: ClassVar[str]
    KINDS: ClassVar[dict[str, tuple[str, bool]]]
    keys: tuple[str, ...]

    @classmethod
    def from_json(cls, obj, where: str, name: str | None = None):
        """The value of ``obj`` (field ``name``, default :attr:`NAME`, of message ``where``);
        a :class:`MessageError` on an unknown or missing key or a value of the wrong type."""
        name = name or cls.NAME
        required = tuple(k for k, (_, req) in cls.KINDS.items() if req)
        object_fields(where, name, obj, tuple(cls.KINDS), required)
        values: dict[str, Any] = {}
        for key, (kind, _) in cls.KINDS.items():
            v = obj.get(key)
            if v is not None:
                check(where, f"{name}.{key}", kind, v)
                values[key] = tuple(v) if kind in ("strs", "numbers") else v
        return cls(**values, keys=tuple(obj))  # type: ignore[call-arg]

    def to_json(self) -> dict:
        """The object as it was on the wire (every field, in :attr:`KINDS` order, when the
        value was not read from one)."""
        out = {}
        for key in self.keys or tuple(self.KINDS):
            v = getattr(self, key)
            out[key] = list(v) if isinstance(v, tuple) else v
        return out


def to_jsonable(obj):
    """``obj`` with numpy types turned into Python ones and non-finite floats into None."""
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj
