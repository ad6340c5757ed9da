"""Typed settings: dataclasses checked and converted by their annotations, in one place.

A settings class (:class:`streamer.runtime.stage_config.StageConfig`,
:class:`streamer.launch.launch_plan.RunOptions`) is a plain dataclass whose fields are annotated
with the types below; it calls :func:`check_fields` in ``__post_init__`` and round-trips
through JSON with :func:`to_dict` and :func:`from_dict`.  A value that does not fit raises
:class:`SettingsError` naming the settings and the field::

    stage configuration: field 'hold': expected a number, got 'x'

Why dataclasses and one converter rather than pydantic or msgspec: neither is a dependency
of the project, the settings are a few flat dataclasses with plain types, and the stages
construct them directly in code and tests (keyword arguments, ``dataclasses.replace``) as
well as from JSON; about a hundred lines here keep them plain dataclasses and keep the JSON
form (written into every recording's metadata) exactly as it was.

Types understood: ``str``, ``int`` (not bool), ``float`` (int or float, kept as given),
``bool``, :class:`~pathlib.Path` (from str), ``dict`` (any mapping), ``list``/``tuple`` and
``tuple[X, ...]``/``list[X]`` (from a list or tuple), ``Literal[...]``, ``X | None``, ``Any``
and nested settings dataclasses (from a mapping).  A field's ``metadata["check"]`` is a
function of the value returning what is wrong with it, or None.
"""

from __future__ import annotations

import dataclasses
import math
import os
import types
import typing
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Literal, Union


class SettingsError(ValueError):
    """Settings that do not fit their dataclass (the message names the field)."""


def _describe(tp) -> str:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin in (Union, types.UnionType):
        return " or ".join(_describe(a) for a in args if a is not type(None))
    names = {str: "a string", int: "an integer", float: "a number", bool: "true or false", Path: "a path"}
    if tp in names:
        return names[tp]
    if tp is dict or origin is dict or (isinstance(tp, type) and dataclasses.is_dataclass(tp)):
        return "a mapping"
    if tp in (list, tuple) or origin in (list, tuple):
        return "a list"
    return getattr(tp, "__name__", str(tp))


#: Whether a value is of each plain type of the settings (a bool is neither an int nor a float).
_PLAIN: dict[type, Callable[[object], bool]] = {
    bool: lambda v: isinstance(v, bool),
    int: lambda v: isinstance(v, int) and not isinstance(v, bool),
    float: lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
    str: lambda v: isinstance(v, str),
}


def _convert(value, tp, error: Callable[[str], Exception]):
    """``value`` as type ``tp`` (or raises ``error(<what was expected>)``)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (Union, types.UnionType):
        return _convert_union(value, tp, args, error)
    if origin is Literal:
        ok, out = value in args, value
    elif tp in _PLAIN:
        ok, out = _PLAIN[tp](value), value
    else:
        ok, out = _convert_structured(value, tp, origin, args, error)
    if ok:
        return out
    raise error(f"expected {_describe(tp)}, got {value!r}")


def _convert_union(value, tp, args: tuple, error: Callable[[str], Exception]):
    """``value`` as the first option of the union ``tp`` (``args``) it converts to; None when allowed."""
    if value is None and type(None) in args:
        return None
    for option in (a for a in args if a is not type(None)):
        try:
            return _convert(value, option, error)
        except SettingsError:
            continue
    raise error(f"expected {_describe(tp)}, got {value!r}")


def _convert_structured(value, tp, origin, args: tuple, error: Callable[[str], Exception]) -> tuple[bool, Any]:
    """``(True, value as tp)`` for a path, mapping, list, tuple or settings dataclass ``tp``;
    ``(False, None)`` when ``value`` is not one; a TypeError for a type not understood."""
    if tp is Path:
        if isinstance(value, (str, os.PathLike)):
            return True, value if isinstance(value, Path) else Path(value)
    elif tp is dict or origin is dict:
        if isinstance(value, Mapping):
            return True, value if isinstance(value, dict) else dict(value)
    elif tp in (list, tuple) or origin in (list, tuple):
        if isinstance(value, (list, tuple)):
            item = args[0] if args and (origin is list or args[-1] is Ellipsis) else Any
            items = [_convert(v, item, error) for v in value]
            return True, list(items) if list in (tp, origin) else tuple(items)
    elif isinstance(tp, type) and dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return True, value
        if isinstance(value, Mapping):
            return True, tp.from_dict(value) if hasattr(tp, "from_dict") else from_dict(tp, value, tp.__name__)
    else:
        raise TypeError(f"settings: type {tp!r} not understood")
    return False, None


def check_fields(obj, what: str) -> None:
    """Check (and convert: str to Path, list to tuple) every field of the dataclass ``obj``
    by its annotation and its ``metadata["check"]``; called from ``__post_init__``.

    Raises
    ------
    SettingsError
        ``<what>: field '<name>': <what is wrong>``.
    """
    hints = typing.get_type_hints(type(obj))
    for f in dataclasses.fields(obj):
        name = f.name

        def error(problem: str, name=name) -> SettingsError:
            return SettingsError(f"{what}: field {name!r}: {problem}")

        value = _convert(getattr(obj, name), hints[name], error)
        check = f.metadata.get("check")
        problem = check(value) if check is not None and value is not None else None
        if problem:
            raise error(problem)
        object.__setattr__(obj, name, value)


def to_dict(obj) -> dict:
    """The JSON form of a settings dataclass: paths as strings, tuples as lists, nested
    settings as their own ``to_dict``; everything else as it is."""

    def plain(v):
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            return v.to_dict() if hasattr(v, "to_dict") else to_dict(v)
        if isinstance(v, Path):
            return str(v)
        if isinstance(v, tuple):
            return [plain(x) for x in v]
        return v

    return {f.name: plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}


def from_dict(cls, d: Mapping[str, Any] | None, what: str, error: type[Exception] = SettingsError):
    """The settings ``cls`` from their JSON form ``d`` (inverse of :func:`to_dict`): unknown
    and missing fields, and values that do not fit, raise ``error`` naming the field."""
    if d is not None and not isinstance(d, Mapping):
        raise error(f"{what}: expected a mapping of fields, got {d!r}")
    d = dict(d or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(d) - names
    if unknown:
        raise error(f"{what}: unknown field {sorted(unknown)[0]!r}")
    required = [
        f.name
        for f in dataclasses.fields(cls)
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    ]
    for name in required:
        if name not in d:
            raise error(f"{what}: field {name!r} missing")
    try:
        return cls(**d)
    except SettingsError as exc:
        if error is SettingsError:
            raise
        raise error(str(exc)) from None


# ---------------------------------------------------------------------------- checks of values
def at_least(low: float) -> Callable[[float], str | None]:
    """A ``metadata["check"]``: a finite number >= ``low``."""
    return lambda v: None if math.isfinite(v) and v >= low else f"expected a number >= {low:g}, got {v!r}"


def above(low: float) -> Callable[[float], str | None]:
    """A ``metadata["check"]``: a finite number > ``low``."""
    return lambda v: None if math.isfinite(v) and v > low else f"expected a number > {low:g}, got {v!r}"
