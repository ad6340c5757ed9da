"""JSON text from an untrusted peer, parsed with every size bounded (the segment headers of
:mod:`streamer.bus.codec`): nesting depth (checked before parsing: Python's parser recurses once
per level), number literals (length and range) and string lengths.  A failure is a
:class:`BoundedJSONError` naming the field (``meta.truth.coefficients[3]``)."""

from __future__ import annotations

import json
import math

import numpy as np

#: Deepest nesting of JSON objects and lists in a header (the header itself is level 1; the
#: producers' deepest ``meta`` reaches 5).  Python's JSON parser recurses once per level, so a
#: deeper header is refused before it is parsed.
MAX_DEPTH = 32
#: Longest string anywhere in a header (a key or a value) [characters].
MAX_STRING_CHARS = 1 << 16
#: Longest number literal in a header [characters]; integers must also lie within
#: ``[-2**63, 2**64)``.  Longer literals are refused unconverted (Python refuses to convert
#: integers of more than 4300 digits with a ValueError, and 2000-digit ones take time).
MAX_NUMBER_CHARS = 40


class BoundedJSONError(ValueError):
    """JSON text refused; ``field`` is where (``"header"`` for the text as a whole)."""

    def __init__(self, field: str, what: str):
        self.field, self.what = field, what
        super().__init__(f"field {field!r}: {what}")


class _BadNumber:
    """A number literal refused by the parser's hooks, kept as a marker so that the walk
    over the parsed header (:func:`_check_values`) can name the field it sits in."""

    __slots__ = ("text", "why")

    def __init__(self, text: str, why: str):
        self.text, self.why = text, why


def _parse_int(text: str):
    if len(text) > MAX_NUMBER_CHARS:
        return _BadNumber(text, f"an integer of {len(text)} characters (at most {MAX_NUMBER_CHARS})")
    value = int(text)
    if not -(1 << 63) <= value < (1 << 64):
        return _BadNumber(text, "an integer outside [-2**63, 2**64)")
    return value


def _parse_float(text: str):
    if len(text) > MAX_NUMBER_CHARS:
        return _BadNumber(text, f"a number of {len(text)} characters (at most {MAX_NUMBER_CHARS})")
    value = float(text)
    if not math.isfinite(value):  # 1e999 parses as inf
        return _BadNumber(text, f"{text} overflows to a non-finite number")
    return value


def _parse_constant(text: str):
    return _BadNumber(text, f"non-finite number {text} in JSON")


_BRACKET = np.zeros(256, dtype=np.int8)
_BRACKET[[ord("["), ord("{")]] = 1
_BRACKET[[ord("]"), ord("}")]] = -1


def nesting_depth(raw: bytes) -> int:
    """Deepest nesting of objects and lists in JSON text ``raw``, without parsing it.

    Linear and vectorised (a hostile header is up to :data:`streamer.bus.codec.MAX_HEADER_BYTES`): a quote
    preceded by an odd run of backslashes is escaped; the others open and close strings,
    and brackets count only outside strings.  For text that is not valid JSON the count is
    exact up to the first error, which is as far as the parser gets.
    """
    a = np.frombuffer(raw, dtype=np.uint8)
    if a.size == 0:
        return 0
    pos = np.arange(a.size)
    # position of the last character that is not a backslash, at or before each position
    last_plain = np.maximum.accumulate(np.where(a != ord("\\"), pos, -1))
    quotes = np.flatnonzero(a == ord('"'))
    before = np.where(quotes > 0, last_plain[np.maximum(quotes - 1, 0)], 0)
    run = np.where(quotes > 0, quotes - 1 - before, 0)  # backslashes right before each quote
    toggles = np.zeros(a.size, dtype=np.int32)
    toggles[quotes[run % 2 == 0]] = 1
    outside = np.cumsum(toggles) % 2 == 0  # a closing quote itself counts as outside
    steps = np.where(outside, _BRACKET[a], 0).astype(np.int32)
    return int(np.cumsum(steps).max(initial=0))


def load_bounded(raw: bytes, root: str = "header"):
    """``json.loads`` of a header with every size bounded: nesting depth (checked before
    parsing: the parser recurses), number literals, string lengths.  Every failure is a
    :class:`BoundedJSONError` naming the field (``root``: what the text is, for a failure of
    the text as a whole, e.g. ``"payload"`` for a control message)."""
    depth = nesting_depth(raw)
    if depth > MAX_DEPTH:
        raise BoundedJSONError(root, f"JSON nested {depth} levels deep (at most {MAX_DEPTH})")
    try:
        obj = json.loads(
            raw.decode("utf-8"), parse_int=_parse_int, parse_float=_parse_float, parse_constant=_parse_constant
        )
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BoundedJSONError(root, f"not valid JSON: {exc}") from None
    except (ValueError, RecursionError, MemoryError) as exc:  # belt and braces: nothing else escapes
        raise BoundedJSONError(root, f"unreadable JSON: {type(exc).__name__}: {exc}") from None
    _check_values(obj, "")
    return obj


def _check_values(value, path: str) -> None:
    """Refuse a marked number or an over-long string anywhere in ``value``, naming its field
    (``meta.truth.coefficients[3]``).  Recursion is bounded by :data:`MAX_DEPTH`."""
    if isinstance(value, _BadNumber):
        raise BoundedJSONError(path or "header", value.why)
    if isinstance(value, str):
        if len(value) > MAX_STRING_CHARS:
            raise BoundedJSONError(
                path or "header", f"a string of {len(value)} characters (at most {MAX_STRING_CHARS})"
            )
    elif isinstance(value, dict):
        for name, item in value.items():
            where = f"{path}.{name[:40]}" if path else name[:40]
            if len(name) > MAX_STRING_CHARS:
                raise BoundedJSONError(
                    path or "header", f"a key of {len(name)} characters (at most {MAX_STRING_CHARS})"
                )
            _check_values(item, where)
    elif isinstance(value, list):
        for i, item in enumerate(value):
            _check_values(item, f"{path}[{i}]")
