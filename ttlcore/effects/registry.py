"""The effects by name: the registry, plugins and the spelling of an effect.

Effects are looked up by name (:data:`EFFECTS`), from a user's Python file
(``--effect-module PATH``, :func:`load_effect_module`) or from installed packages through
the entry-point group ``ttl.effects`` (:func:`available_effects`); see
``docs/diagnostics.md`` for the plugin interface.  :func:`parse_effect_spec` reads the
spelling ``NAME[:key=value,...]`` of ``--effects`` and ``--inject``;
:func:`injection_from_description` is the hook :func:`ttlcore.sim.injection.injection_from_description`
calls for kind ``"effect"``.
"""

from __future__ import annotations

import functools
import logging
from importlib import metadata
from pathlib import Path

from ..errors import ConfigError
from ..sim.injection import load_module
from .base import Effect
from .coupling import CrossCoupling, Drift, LinearTTL, SecondOrder, Step
from .glitch import Gate, Glitch
from .injection import EffectInjection
from .placed import FrequencyCoupling, WitnessEffect
from .shifted import LightTravelTimeError, TimingOffset

log = logging.getLogger(__name__)


#: Entry-point group under which installed packages register effect classes.
ENTRY_POINT_GROUP = "ttl.effects"


#: The named effects (the transients ``glitch`` and ``gate`` included).
EFFECTS: dict[str, type] = {
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


def parse_effect_spec(spec: str, modules=()) -> tuple[Effect, dict]:
    """``"NAME[:key=value,...]"`` -> (effect instance, column values).

    Keys that are options of the effect set options; keys that are column names (with or
    without the effect prefix, e.g. ``12.phi.rx`` for ``drift.12.phi.rx``) or ``all`` set
    the parameter values of an injection (in the column's unit).  Lists inside an option
    use ``+`` (``mosas=12+13``).
    """
    name, _, rest = str(spec).partition(":")
    name = name.strip()
    effects = available_effects(modules)
    if name not in effects:
        raise ConfigError(f"unknown effect {name!r}; known: {', '.join(sorted(effects))}")
    cls = effects[name]
    options, raw_values = {}, {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"effect {name!r}: expected key=value, got {item!r}")
        if key in cls.parameters:
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
    """Effect instances from a comma-free list of specs or one comma-separated string of
    names (``"linear-ttl,drift"``)."""
    if isinstance(specs, str):
        specs = [s for s in specs.split(",") if s.strip()]
    return [s if isinstance(s, Effect) else parse_effect_spec(s, modules)[0] for s in specs]


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
        raise ConfigError(
            f"--inject {spec}: no parameter value given; e.g. --inject "
            f"{effect.name}:{effect.column_names()[0].split('.', 1)[-1]}=VALUE (or all=VALUE)"
        )
    return effect.injection(values)
