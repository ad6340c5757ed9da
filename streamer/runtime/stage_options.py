"""A stage's options as one frozen value, parsed once at the boundary.

A stage's options come as a mapping (``StageConfig.options``: from its command line, the
``[stages.<name>]`` table of a run's configuration file, or ``ttl run``).  Each stage program
declares a frozen dataclass of them (a subclass of :class:`StageOptions`) whose fields say the
name, type, default and unit of each option and, in their metadata, how a given value is read
(:func:`option`).  :meth:`StageOptions.parse` turns the mapping into that value: an unknown
option, or a value that does not parse, is a :class:`~ttlcore.errors.ConfigError` naming the
stage and the option, at start, never a ``KeyError`` deep inside; ``None`` means the default.
The stage reads its options by attribute from then on.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

from ttlcore.conventions import parse_duration
from ttlcore.errors import ConfigError

__all__ = [
    "OrderedOptions",
    "StageOptions",
    "duration_s",
    "names",
    "band_hz",
    "nonnegative_float",
    "nonnegative_int",
    "one_of",
    "option",
    "positive_float",
    "positive_int",
]

O = TypeVar("O", bound="StageOptions")


def option(default: Any, parse: Callable[[Any], Any], doc: str = "") -> Any:
    """A field of a :class:`StageOptions`: its ``default`` and the function that reads a given value
    (raises ValueError or TypeError when it cannot)."""
    return dataclasses.field(default=default, metadata={"parse": parse, "doc": doc})


def duration_s(value) -> float:
    """A duration [s] > 0: seconds, or a number with a unit (``30min``, ``1h``, ``1d``)."""
    seconds = parse_duration(value)
    if not seconds > 0:
        raise ValueError(f"expected a duration > 0, got {value!r}")
    return seconds


def positive_float(value) -> float:
    x = float(value)
    if not (x > 0 and math.isfinite(x)):
        raise ValueError(f"expected a finite number > 0, got {value!r}")
    return x


def nonnegative_float(value) -> float:
    x = float(value)
    if not (x >= 0 and math.isfinite(x)):
        raise ValueError(f"expected a finite number >= 0, got {value!r}")
    return x


def positive_int(value) -> int:
    if isinstance(value, bool) or int(value) != float(value) or int(value) < 1:
        raise ValueError(f"expected an integer >= 1, got {value!r}")
    return int(value)


def nonnegative_int(value) -> int:
    if isinstance(value, bool) or int(value) != float(value) or int(value) < 0:
        raise ValueError(f"expected an integer >= 0, got {value!r}")
    return int(value)


def one_of(*choices: str) -> Callable[[Any], str]:
    """A reader of a value that must be one of ``choices``."""

    def parse(value) -> str:
        if value not in choices:
            raise ValueError(f"expected one of {', '.join(choices)}, got {value!r}")
        return str(value)

    return parse


def band_hz(value) -> tuple[float, float]:
    """A frequency band ``(fmin, fmax)`` [Hz] with ``0 < fmin < fmax``."""
    lo, hi = (float(x) for x in value)
    if not 0 < lo < hi:
        raise ValueError(f"expected FMIN FMAX with 0 < FMIN < FMAX, got {list(value)}")
    return lo, hi


def names(value) -> tuple[str, ...]:
    """Names given as a list, or as one comma-separated string."""
    items = value.split(",") if isinstance(value, str) else list(value)
    return tuple(str(x).strip() for x in items if str(x).strip())


@dataclass(frozen=True)
class StageOptions:
    """The options of a stage with none of its own (module docstring)."""

    @classmethod
    def parse(cls: type[O], options: Mapping[str, Any] | None, stage: str) -> O:
        """The options of stage ``stage`` from a mapping; ConfigError naming the option at fault."""
        given = dict(options or {})
        known = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(given) - set(known))
        if unknown:
            raise ConfigError(f"{stage}: unknown option {unknown[0]!r} (known: {', '.join(known) or 'none'})")
        values = {}
        for name, value in given.items():
            if value is None:
                continue
            try:
                values[name] = known[name].metadata["parse"](value)
            except (TypeError, ValueError) as exc:
                flag = "--" + name.replace("_", "-")
                raise ConfigError(f"{stage} option {name} ({flag}): {exc}") from None
        try:
            return cls(**values)
        except ValueError as exc:  # a check across options (__post_init__)
            raise ConfigError(f"{stage}: {exc}") from None


@dataclass(frozen=True)
class OrderedOptions(StageOptions):
    """The options of a stage that handles its input in index order
    (:class:`streamer.runtime.pipeline_stage.OrderedStage`)."""

    #: Seconds to collect cached history before choosing the first segment.
    settle: float = option(1.0, nonnegative_float)
    #: Seconds to wait for a missing segment while later ones wait, before skipping it.
    gap_timeout: float = option(60.0, positive_float)
