"""The effect base class: a named group of extra regressors for the TTL fit.

The linear TTL model (docs/physics.md, measurement model; paper eq. (3) differentiated)

    ttl_ij = -(1/c) [ C[ij,phi,rx] phi'_ij + C[ij,eta,rx] eta'_ij
                      + D_ij( C[ji,phi,tx] phi'_ji + C[ji,eta,tx] eta'_ji ) ]

is one hypothesis among many.  An *effect* is a physically motivated set of extra terms in
``eta``, linear in its parameters, written as regressor columns
(:class:`ttlcore.effects.columns.Column`); a column enters TDI exactly as the 24 TTL
regressors do (:func:`ttlcore.effects.column_tdi.columns_tdi`), so
``eta = sum_k C_k w_k + sum_e theta_e col_e + noise`` is fitted by the same generalised
least squares (:mod:`ttlcore.estimate.fit`).

The same column definitions, evaluated on the *true* angular velocities of a simulated
chunk, give the effect's injection (:class:`ttlcore.effects.injection.EffectInjection`).
Subclass :class:`Effect` for a plugin (docs/diagnostics.md).
"""

from __future__ import annotations

from typing import ClassVar, Self

import numpy as np

from ..conventions import (
    ANGLES,
    COEFFICIENT_NAMES,
    LINKS,
    MOSAS,
    SIDES,
    reverse,
)
from ..errors import ConfigError
from .columns import Column, EffectInput
from .filters import filtered
from .injection import EffectInjection


def split_list(value, allowed, what) -> tuple:
    """An option's selection: ``None`` or ``"all"`` -> every item of ``allowed``; a list, or a
    string separated by ``,`` or ``+`` (``"12+13"``) -> its items, ConfigError naming ``what``
    for an unknown one."""
    if value is None or value == "all":
        return tuple(allowed)
    items = value if isinstance(value, (list, tuple)) else [s for s in str(value).replace("+", ",").split(",") if s]
    bad = [s for s in items if s not in allowed]
    if bad:
        raise ConfigError(f"{what}: unknown {bad}; known: {', '.join(allowed)}")
    return tuple(items)


class Effect:
    """Base class of model effects (subclass it for a plugin, see ``docs/diagnostics.md``).

    Class attributes
    ----------------
    name : str
        Registry name (``--effects``, ``--inject``).
    title : str
        One line.
    physics : str
        The physical explanation shown in reports and docs.
    parameters : dict
        Options with their defaults (``mosas``, ``angles``, ``sides`` restrict the effect
        to a subset of MOSAs, angles and sides where meaningful).
    needs_coefficients : bool
        Columns use the linear coefficients (linearised effects).
    searched : dict
        ``option -> (low, high, "log"|"linear")``: nonlinear parameters the diagnosis
        searches when the option is not given (:func:`ttlcore.diagnose.search.profile_search`).

    Instances hold the option values (``Effect(**options)``); :meth:`columns` builds the
    regressor columns, :meth:`injection` the simulator injection.
    """

    name = "effect"
    title = ""
    physics = ""
    parameters: dict = {}
    needs_coefficients = False
    #: the columns use the angles (:attr:`ttlcore.effects.columns.EffectInput.angles`,
    #: the running integral of the velocities): the injection then carries the integral
    #: from chunk to chunk and needs the chunks in order
    integrates_angles = False
    #: where a plugin effect class was loaded from (:func:`load_effect_module`)
    _ttl_module_path: ClassVar[str]

    def __init__(self, **options):
        unknown = set(options) - set(self.parameters)
        if unknown:
            raise ConfigError(
                f"effect {self.name!r}: unknown option(s) {sorted(unknown)}; "
                f"options: {', '.join(self.parameters) or 'none'}"
            )
        self.options = {**self.parameters, **options}
        for key in ("mosas", "angles", "sides"):  # validate the selections now, naming the option
            if key in self.parameters:
                getattr(self, key)

    # selections shared by the coefficient-based effects
    @property
    def mosas(self) -> tuple:
        return split_list(self.options.get("mosas"), MOSAS, f"effect {self.name!r} mosas")

    @property
    def angles(self) -> tuple:
        return split_list(self.options.get("angles"), ANGLES, f"effect {self.name!r} angles")

    @property
    def sides(self) -> tuple:
        return split_list(self.options.get("sides"), SIDES, f"effect {self.name!r} sides")

    def columns(self, data: EffectInput) -> list[Column]:
        """The regressor columns built from ``data``."""
        raise NotImplementedError

    def active_span(self) -> tuple[float, float] | None:
        """The mission-time span ``(start, stop)`` [s] outside which the effect's columns
        vanish (a transient: a glitch, a gate), or None for an effect that acts all the time
        (a coupling) or whose time is still to be searched.  A live model drops a transient
        whose span has left its window (docs/diagnostics.md, "A model that lives for weeks")."""
        return None

    def column_names(self) -> list[str]:
        """Names of the columns (without building them), for parsing injection values."""
        t = np.arange(64.0)
        z = np.zeros((6, 64))
        data = EffectInput(
            t=t,
            fs=1.0,
            phi_dot=z,
            eta_dot=z,
            ltt=z + 8.3,
            coefficients=np.zeros(len(COEFFICIENT_NAMES)),
            names_only=True,
        )
        return [c.name for c in self.columns(data)]

    def describe(self) -> dict:
        d = {"effect": self.name, "options": {k: v for k, v in self.options.items() if v != self.parameters.get(k)}}
        module = getattr(type(self), "_ttl_module_path", None)
        if module:
            d["effect_module"] = module
        return d

    def spec(self, sep: str = ",") -> str:
        """The spelling ``name[:key=value,...]`` of this effect (:func:`parse_effect_spec`);
        ``sep=";"`` gives the command line's (``--effects``, where ``,`` separates effects)."""
        opts = {k: v for k, v in self.options.items() if v != self.parameters.get(k)}
        if not opts:
            return self.name
        return (
            self.name
            + ":"
            + sep.join(f"{k}={'+'.join(v) if isinstance(v, (list, tuple)) else v}" for k, v in opts.items())
        )

    def cli_spec(self) -> str:
        """The ``--effects`` spelling (options separated by ``;``)."""
        return self.spec(";")

    #: nonlinear parameters the diagnosis searches when their option is not given:
    #: ``option -> (low, high, scale)`` with scale ``"log"`` or ``"linear"``
    #: (:func:`ttlcore.diagnose.search.profile_search`)
    searched: dict = {}

    def unresolved(self) -> list[str]:
        """Searched options without a value (the diagnosis finds them)."""
        return [k for k in self.searched if self.options.get(k) is None]

    def with_options(self, **options) -> Self:
        """A copy with some options replaced (searched parameters filled in)."""
        new = type(self)(**{**{k: v for k, v in self.options.items() if v != self.parameters.get(k)}, **options})
        return new

    def injection(self, values: dict, name: str | None = None) -> EffectInjection:
        """Simulator injection adding ``sum_col values[col] * col`` (true angles) to eta."""
        return EffectInjection(self, values, name)

    def signal(self, data: EffectInput, values: dict, delayed_onto_links, history: int) -> np.ndarray:
        """The injected eta signal (6, n) for ``values`` (column name -> parameter value):
        Rx parts are taken after ``history`` samples, Tx parts through
        ``delayed_onto_links`` (the simulator's true delays)."""
        n = data.n - history
        out = np.zeros((6, n))
        tx = np.zeros((6, data.n))
        for col in self.columns(data):
            v = values.get(col.name, 0.0)
            if v == 0.0:
                continue
            for p in col.parts:
                series = p.series if col.response is None else filtered(p.series, data.fs, col.response)
                if int(p.delayed) > 1:
                    raise ConfigError(
                        f"effect {self.name!r}: the simulator injects one delay per part, not {int(p.delayed)}"
                    )
                if p.delayed:  # D_ij x_ji: row of the transmitting MOSA ji
                    tx[LINKS.index(reverse(p.link))] += v * series
                else:
                    out[LINKS.index(p.link)] += v * series[history:]
        if np.any(tx):
            out += delayed_onto_links(tx)
        return out
