"""A simulation described in words: the options of ``ttl simulate``, and the
:class:`~ttlcore.sim.simulator.SimulationConfig` they describe.

The same options serve ``ttl simulate`` (:mod:`ttlcore.cli.main`) and a replay simulated on
the fly (``ttl run --simulate "<options>"``, the replayer stage): :func:`~ttlcore.cli.simulation_options.add_simulation_options`
declares them on any :mod:`argparse` parser, :func:`simulation_config_from_args` turns the
parsed options into a configuration, and :func:`simulation_config` does both for a string of
words.  Errors name the option at fault.
"""

from __future__ import annotations

import argparse
import shlex

from ..conventions import COEFFICIENT_NAMES, parse_duration
from ..effects.registry import injection_from_spec, split_effects
from ..errors import ConfigError, TTLError
from ..gw.injection import parse_gw_spec
from ..sim.coefficients import make_coefficients
from ..sim.orbits import make_orbit
from ..sim.simulator import NoiseSwitches, SimulationConfig
from .simulation_options import add_simulation_options


def _parse_assignments(text: str, option: str) -> dict[str, float]:
    """``"12.phi.rx=0.05,13.eta.tx=-0.02"`` -> mapping (values as given)."""
    out = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        name, sep, value = item.partition("=")
        if not sep:
            raise TTLError(f"{option}: expected NAME=VALUE, got {item!r}")
        if name not in COEFFICIENT_NAMES:
            raise TTLError(
                f"{option}: unknown coefficient {name!r}; names look like '12.phi.rx' ('<mosa>.<phi|eta>.<rx|tx>')"
            )
        try:
            out[name] = float(value)
        except ValueError:
            raise TTLError(f"{option}: bad number {value!r} for {name}") from None
    return out


def simulation_config_from_args(args, truth_noises=()):
    """A :class:`~ttlcore.sim.simulator.SimulationConfig` from the options of
    :func:`add_simulation_options`; errors name the option at fault."""

    duration = parse_duration(args.duration, "--duration")
    coeffs = make_coefficients(args.coeffs, seed=args.seed)
    if args.drift:
        coeffs = coeffs.with_drift({k: v * 1e-3 for k, v in _parse_assignments(args.drift, "--drift").items()})
    for step in args.step:
        when, sep, rest = step.partition(":")
        if not sep:
            raise TTLError(f"--step: expected T:NAME=MM,..., got {step!r}")
        t_step = parse_duration(when, "--step") if when.strip() not in ("0", "0.0") else 0.0
        if t_step >= args.t0 + duration:  # would change nothing in the data: surely not what was meant
            raise TTLError(
                f"--step {step}: {t_step:g} s is at or after the end of the simulation ({args.t0 + duration:g} s)"
            )
        coeffs = coeffs.with_step(t_step, {k: v * 1e-3 for k, v in _parse_assignments(rest, "--step").items()})
    make_orbit(args.orbit)  # validate early: clear error before any work
    gw = ()
    if getattr(args, "gw", ""):
        gw = parse_gw_spec(args.gw, t0=args.t0, duration=duration, seed=args.seed)
    return SimulationConfig(
        duration=duration,
        t0=args.t0,
        fs=args.fs,
        orbit=args.orbit,
        coefficients=coeffs,
        seed=args.seed,
        noises=NoiseSwitches.parse(args.noises),
        interpolation_order=args.order,
        truth_noises=tuple(truth_noises),
        injections=tuple(gw) + _effect_injections(args),
    )


def _effect_injections(args) -> tuple:
    """The ``--inject`` options as simulator injections (:mod:`ttlcore.effects`); one option
    may hold several effects, in the grammar of ``--effects`` (docs/cli.md, "Effect specs")."""
    if not getattr(args, "inject", None):
        return ()

    out = []
    count: dict[str, int] = {}
    for text in args.inject:
        try:
            specs = split_effects(text)
            injections = [injection_from_spec(spec, getattr(args, "effect_module", ()) or ()) for spec in specs]
        except TTLError as exc:
            raise TTLError(f"--inject {text}: {exc}") from None
        for inj in injections:
            # the same effect injected again (a glitch a day) is named glitch-2, glitch-3, ...:
            # the truth file keeps each injection under its own name
            count[inj.name] = count.get(inj.name, 0) + 1
            if count[inj.name] > 1:
                inj.name = f"{inj.name}-{count[inj.name]}"
            out.append(inj)
    return tuple(out)


def simulation_config(text: str) -> SimulationConfig:
    """A :class:`~ttlcore.sim.simulator.SimulationConfig` from ``ttl simulate`` options
    (without ``--out``) in one string, e.g. ``"--duration 12h --orbit unequal --seed 1"``,
    parsed and translated by the same code as ``ttl simulate``.

    Raises
    ------
    ConfigError
        Naming the option at fault.
    """
    p = argparse.ArgumentParser(prog="--simulate", add_help=False, exit_on_error=False)
    add_simulation_options(p)
    try:
        words = shlex.split(text)
        args, unknown = p.parse_known_args(words)
    except (argparse.ArgumentError, ValueError) as exc:
        raise ConfigError(f"--simulate: {exc}") from None
    if unknown:
        raise ConfigError(
            f"--simulate: unknown option(s) {' '.join(unknown)} "
            "(the options of 'ttl simulate' except --out, --chunk, --truth-noises, --quiet)"
        )
    try:
        return simulation_config_from_args(args)
    except TTLError as exc:  # ConfigError included: the message names the option
        raise ConfigError(f"--simulate {exc}") from None
