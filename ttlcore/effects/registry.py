"""The effects by name: the registry, plugins and the spelling of an effect.

Effects are looked up by name (:data:`EFFECTS`), from a user's Python file
(``--effect-module PATH``, :func:`load_effect_module`) or from installed packages through
the entry-point group ``ttl.effects`` (:func:`available_effects`); see
``docs/diagnostics.md`` for the plugin interface.  :func:`split_effects` and
:func:`parse_effect_spec` read the one spelling ``NAME[:key=value,...]`` of every effect
(``--effects``, ``--inject``, reports; docs/cli.md, "Effect specs");
:func:`injection_from_description` is the hook :func:`ttlcore.sim.injection.injection_from_description`
calls for kind ``"effect"``.
"""

from __future__ import annotations

import functools
import logging
import shlex
from importlib import metadata
from pathlib import Path

from ..conventions import format_number
from ..errors import ConfigError
from ..sim.injection import load_module
from .base import Effect
from .cross_coupling import CrossCoupling
from .drift import Drift
from .fd_coupling import FrequencyCoupling
from .gate import Gate
from .glitch import Glitch
from .injection import EffectInjection
from .linear_ttl import LinearTTL
from .ltt_error import LightTravelTimeError
from .second_order import SecondOrder
from .shifted import OFFSET_OPTION, _Linearised
from .step import Step
from .timing_offset import TimingOffset
from .witness import WitnessEffect

log = logging.getLogger(__name__)


#: Entry-point group under which installed packages register effect classes.
ENTRY_POINT_GROUP = "ttl.effects"


#: The named effects (the transients ``glitch`` and ``gate`` included).
EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls
    for cls in (
        LinearTTL,
        Drift,
        Step,
        CrossCoupling,
        TimingOffset,
        SecondOrder,
        LightTravelTimeError,
        WitnessEffect,
        FrequencyCoupling,
        Glitch,
        Gate,
    )
}


def load_effect_module(spec: str) -> list[type[Effect]]:
    """Effect classes of a user module (a ``.py`` path or a dotted name).

    The module lists its classes in ``EFFECTS`` (a list, or a dict name -> class); without
    it, every :class:`Effect` subclass defined in the module is taken.  ConfigError names the
    module if it defines none.
    """
    module = load_module(spec)
    found = getattr(module, "EFFECTS", None)
    if isinstance(found, dict):
        found = list(found.values())
    if found is None:
        found = [
            v
            for v in vars(module).values()
            if isinstance(v, type) and issubclass(v, Effect) and v is not Effect and v.__module__ == module.__name__
        ]
    if not found:
        raise ConfigError(f"{spec}: defines no effect (an Effect subclass, or a list EFFECTS)")
    out = []
    for cls in found:
        if (
            not (isinstance(cls, type) and issubclass(cls, Effect))
            or not getattr(cls, "name", None)
            or cls.name == "effect"
        ):
            raise ConfigError(f"{spec}: {cls!r} is not an Effect subclass with a name")
        if spec.endswith(".py"):
            cls._ttl_module_path = str(Path(spec).resolve())
        else:
            cls._ttl_module_path = spec
        out.append(cls)
    return out


@functools.lru_cache(maxsize=1)
def _entry_point_effects() -> dict[str, type[Effect]]:
    """Effect classes registered by installed packages (scanned once per process)."""
    out: dict[str, type[Effect]] = {}
    eps = metadata.entry_points(group=ENTRY_POINT_GROUP)
    for ep in eps:
        try:
            obj = ep.load()
        except Exception as exc:  # a broken third-party package must not stop the analysis
            log.warning("entry point %s in %s: cannot load (%s)", ep.name, ENTRY_POINT_GROUP, exc)
            continue
        for cls in obj if isinstance(obj, (list, tuple)) else [obj]:
            if isinstance(cls, type) and issubclass(cls, Effect):
                out[cls.name] = cls
    return out


def available_effects(modules=()) -> dict[str, type[Effect]]:
    """Named effects, those of installed packages (entry points ``ttl.effects``) and those of
    the given plugin modules (later ones override earlier ones with the same name)."""
    out = dict(EFFECTS)
    out.update(_entry_point_effects())
    for spec in modules:
        for cls in load_effect_module(spec):
            out[cls.name] = cls
    return out


def split_effects(text: str) -> list[str]:
    """One string of effect specs -> one spec per effect (the grammar of every effect list:
    ``--effects``, ``--inject``, ``ttl refit --effects``, ``ttl control ... model``, configs
    and reports; docs/cli.md, "Effect specs").

    ``NAME[:key=value,key=value,...]``, several effects separated by ``,`` too:
    ``"linear-ttl,gate:start=15.2h,stop=15.8h,drift:mosas=12+13"`` -> ``["linear-ttl",
    "gate:start=15.2h,stop=15.8h", "drift:mosas=12+13"]``.  Unambiguous because an option
    is always ``key=value`` (``12.phi.rx=0.05``, ``all=1e-3``, ``mosas=12+13``: a list
    inside an option is joined by ``+``) while an effect starts with its name (a token
    without ``=``, or ``NAME:key=value``).  ``;`` between one effect's options, the former
    spelling of ``--effects`` (``gate:start=15.2h;stop=15.8h``), is still read.
    """
    out: list[str] = []
    for token in (s.strip() for s in str(text).replace(";", ",").split(",")):
        if not token:
            continue
        key, eq, _ = token.partition("=")
        if not eq or ":" in key:  # NAME or NAME:key=value: a new effect
            out.append(token)
        elif not out:
            raise ConfigError(f"{token!r}: an option before any effect (write NAME:{token})")
        elif ":" not in out[-1]:
            raise ConfigError(f"{token!r} follows {out[-1]!r}, which has no options (write {out[-1]}:{token})")
        else:
            out[-1] += "," + token
    return out


def parse_effect_spec(spec: str, modules=()) -> tuple[Effect, dict]:
    """``"NAME[:key=value,...]"`` (one effect, :func:`split_effects`) -> (effect instance,
    column values).

    Keys that are options of the effect set options; keys that are column names (with or
    without the effect prefix, e.g. ``12.phi.rx`` for ``drift.12.phi.rx``) or ``all`` set
    the parameter values of an injection (in the column's unit).  Lists inside an option
    use ``+`` (``mosas=12+13``); times carry their unit or are seconds (``t_step=15.2h``,
    ``beta=35s``, ``offset.sc1=0.35``), frequencies are hertz (``f0=0.0718`` or
    ``f0=0.0718Hz``).  This is the one reader of an effect's spelling.
    """
    specs = split_effects(spec)
    if len(specs) != 1:
        raise ConfigError(f"expected one effect, got {len(specs)}: {spec!r}")
    name, _, rest = specs[0].partition(":")
    name = name.strip()
    effects = available_effects(modules)
    if name not in effects:
        hint = " (a list inside an option is joined by '+': mosas=12+13)" if name[:1].isdigit() else ""
        raise ConfigError(f"unknown effect {name!r}; known: {', '.join(sorted(effects))}{hint}")
    cls = effects[name]
    options, raw_values = {}, {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, _, value = item.partition("=")
        # a shifted-witness plugin's offsets are options without being listed (shifted._Linearised)
        if key in cls.parameters or (key.startswith(OFFSET_OPTION) and issubclass(cls, _Linearised)):
            options[key] = value
        else:
            try:
                raw_values[key] = float(value)
            except ValueError:
                raise ConfigError(
                    f"effect {name!r}: {key!r} is neither an option ({', '.join(cls.parameters) or 'none'}) "
                    f"nor a column with a number (got {value!r})"
                ) from None
    effect = cls(**options)
    values = {}
    if raw_values:
        names = effect.column_names()
        for key, v in raw_values.items():
            if key == "all":
                values.update(dict.fromkeys(names, v))
                continue
            matches = [n for n in names if n == key or n == f"{_prefix(n)}.{key}" or n.endswith("." + key)]
            if not matches:
                raise ConfigError(
                    f"effect {name!r}: unknown column {key!r}; columns: {', '.join(names[:8])}"
                    + (", ..." if len(names) > 8 else "")
                )
            values.update(dict.fromkeys(matches, v))
    return effect, values


def _prefix(column_name: str) -> str:
    return column_name.split(".", 1)[0]


def make_effects(specs, modules=()) -> list[Effect]:
    """Effect instances from one string of specs (``"linear-ttl,gate:start=1h,stop=2h"``,
    :func:`split_effects`) or a list of specs (each one effect, or several in the same
    grammar) and effects."""
    if isinstance(specs, str):
        specs = [specs]
    out: list[Effect] = []
    for s in specs:
        if isinstance(s, Effect):
            out.append(s)
        else:
            out += [parse_effect_spec(one, modules)[0] for one in split_effects(s)]
    return out


def injection_from_description(description: dict):
    """Rebuild an effect injection from :meth:`EffectInjection.describe` (the hook
    :func:`ttlcore.sim.injection.injection_from_description` calls for kind ``"effect"``)."""
    name = description.get("effect")
    if not name:
        raise ConfigError(f"effect injection description needs 'effect': {description!r}")
    modules = [description["effect_module"]] if description.get("effect_module") else []
    effects = available_effects(modules)
    if name not in effects:
        raise ConfigError(f"unknown effect {name!r} in injection description; known: {', '.join(sorted(effects))}")
    effect = effects[name](**description.get("options", {}))
    return effect.injection(description.get("values", {}), description.get("name"))


def injection_from_spec(spec: str, modules=()) -> EffectInjection:
    """``--inject EFFECT[:key=value,...]`` -> injection (values in the columns' units)."""
    effect, values = parse_effect_spec(spec, modules)
    if not values:
        col = effect.named_columns()[0]
        value = format_number(col.prior_scale)
        example = f"{effect.spec()}{',' if ':' in effect.spec() else ':'}{col.name.split('.', 1)[-1]}={value}"
        raise ConfigError(
            f"--inject {spec}: no parameter value given; e.g. --inject {shlex.quote(example)} "
            f"(a value in {col.unit}; all={value} sets every column)"
        )
    return effect.injection(values)
