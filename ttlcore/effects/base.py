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

from collections.abc import Iterator
from typing import ClassVar, Self

import numpy as np

from ..conventions import (
    ANGLES,
    COEFFICIENT_NAMES,
    LINKS,
    MOSAS,
    SIDES,
    format_frequency,
    format_number,
    format_time,
    parse_frequency,
    parse_time,
    reverse,
)
from ..errors import ConfigError
from ..tdi.regressors import witness_placement
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


def parse_option(value, unit: str, what: str):
    """An option's value in its unit (:attr:`Effect.units`): ``"s"`` a time [s]
    (:func:`ttlcore.conventions.parse_time`: ``2.7h``, ``-480s``, ``30min`` or seconds),
    ``"Hz"`` a frequency (:func:`ttlcore.conventions.parse_frequency`), ``"count"`` an
    integer, any other unit (``"rad"``, ``""``) a number, optionally followed by that unit.
    None stays None; ConfigError naming ``what`` otherwise."""
    if value is None:
        return None
    if unit == "s":
        return parse_time(value, what)
    if unit == "Hz":
        return parse_frequency(value, what)
    text = value if isinstance(value, (int, float)) else str(value).strip()
    if unit and isinstance(text, str) and text.endswith(unit):
        text = text[: -len(unit)]
    try:
        number = float(text)
    except (TypeError, ValueError):
        number = float("nan")
    if unit == "count":
        if not number.is_integer():
            raise ConfigError(f"{what}: expected an integer, got {value!r}")
        return int(number)
    if not np.isfinite(number):
        raise ConfigError(f"{what}: expected a number{f' of {unit}' if unit else ''}, got {value!r}")
    return number


def format_option(value, unit: str | None) -> str:
    """An option's value as :meth:`Effect.spec` prints it, read back by :func:`parse_option`
    to the same value: a time with its unit (:func:`ttlcore.conventions.format_time`:
    ``1800s``, ``15.2h``, ``1.5d``), a frequency in ``Hz``, a number in ``rad`` with it, a
    list joined by ``+`` (``mosas=12+13``), other text as it is (its commas as ``+``)."""
    if isinstance(value, (list, tuple)):
        return "+".join(str(v) for v in value)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value).replace(",", "+")
    if unit == "s":
        return format_time(value)
    if unit == "Hz":
        return format_frequency(value)
    if unit == "count":
        return str(int(value))
    return format_number(value) + (unit or "")


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
    units : dict
        ``option -> unit`` of the options that are numbers: ``"s"`` (a time or duration,
        written ``1800s``, ``15.2h``, ``1.5d`` or seconds), ``"Hz"``, ``"rad"``, ``""``
        (dimensionless) or ``"count"`` (an integer).  The constructor reads them
        (:func:`parse_option`) and :meth:`spec` prints them with their unit
        (:func:`format_option`), so that the printed spec reads back as the same effect;
        options not listed are kept as given.

    Instances hold the option values (``Effect(**options)``); :meth:`columns` builds the
    regressor columns, :meth:`injection` the simulator injection.
    """

    name = "effect"
    title = ""
    physics = ""
    parameters: dict = {}
    units: dict = {}
    needs_coefficients = False
    #: the columns use the angles (:attr:`ttlcore.effects.columns.EffectInput.angles`,
    #: the running integral of the velocities): the injection then carries the integral
    #: from chunk to chunk and needs the chunks in order
    integrates_angles = False
    #: where a plugin effect class was loaded from (:func:`load_effect_module`)
    _ttl_module_path: ClassVar[str]
    #: the 24 linear TTL coefficients themselves (``linear-ttl``): the model every other
    #: effect extends, fitted by the rolling fit and predicted by the subtraction as such
    is_linear_ttl: ClassVar[bool] = False
    #: the columns are the linear coefficients' TDI regressors times a function of time
    #: (:meth:`coefficient_modulation`): they can be built from TDI outputs alone
    modulates_coefficients: ClassVar[bool] = False
    #: a transient of the data (a glitch, a gate), not a coupling: a live model drops it
    #: when it leaves the window, and a change of transients alone starts no new series of
    #: the coefficients (:func:`ttlcore.diagnose.trends.model_key`)
    transient: ClassVar[bool] = False
    #: tried as a candidate by its name, with its default options
    #: (:func:`ttlcore.diagnose.candidates.named_candidates`); an effect that means nothing
    #: without options (a witness's placement, a glitch's time) is tried where the diagnosis
    #: finds them (the witness search, the transient finder)
    named_candidate: ClassVar[bool] = True

    def __init__(self, **options):
        unknown = set(options) - set(self.parameters)
        if unknown:
            raise ConfigError(
                f"effect {self.name!r}: unknown option(s) {sorted(unknown)}; "
                f"options: {', '.join(self.parameters) or 'none'}"
            )
        self.options = {**self.parameters, **options}
        for key, value in self.options.items():
            unit = self.option_unit(key)
            if unit is not None:
                self.options[key] = parse_option(value, unit, f"effect {self.name!r} {key}")
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

    def coefficient_placements(self) -> Iterator[tuple[str, str, str, str, bool]]:
        """``(mosa, angle, side, link, delayed)`` of each linear coefficient the effect's
        selection holds (:attr:`mosas`, :attr:`angles`, :attr:`sides`), in the coefficients'
        order: where its witness enters the data (rx: its own link, undelayed; tx: the link
        it transmits on, after one delay; :func:`ttlcore.tdi.regressors.witness_placement`)."""
        for m in self.mosas:
            for a in self.angles:
                for s in self.sides:
                    link, delayed = witness_placement(m, s)
                    yield m, a, s, link, delayed

    def columns(self, data: EffectInput) -> list[Column]:
        """The regressor columns built from ``data``."""
        raise NotImplementedError

    def active_span(self) -> tuple[float, float] | None:
        """The mission-time span ``(start, stop)`` [s] outside which the effect's columns
        vanish (a transient: a glitch, a gate), or None for an effect that acts all the time
        (a coupling) or whose time is still to be searched.  A live model drops a transient
        whose span has left its window (docs/diagnostics.md, "A model that lives for weeks")."""
        return None

    def settled(self, t_start: float) -> Effect | None:
        """The simpler effect this one equals on data from ``t_start`` [s] on, or None when
        there is none: a coupling switched on (``vary=step``) well before ``t_start`` is the
        plain coupling there.  A live model puts it in this one's place once its window
        starts after the switch (docs/diagnostics.md, "Onsets")."""
        return None

    def coefficient_modulation(self, t: np.ndarray, t_mid: float) -> tuple[np.ndarray, str, str]:
        """The function of time [s] ``t`` that multiplies the linear coefficients' TDI
        regressors to give this effect's columns (:attr:`modulates_coefficients`), with the
        columns' name prefix and unit; ``t_mid`` [s] is the middle of the data.  ConfigError
        for an effect whose columns need the DWS series."""
        raise ConfigError(f"effect {self.name!r} needs the telemetry (DWS series); these segments carry TDI only")

    @property
    def trial_columns(self) -> bool:
        """Columns of a witness (``witness.*``, ``fd.*``): such candidates are scored by the
        hundred (the witness library), so their columns are built exactly, once, and never
        kept in the column store."""
        return any(c.startswith(("witness.", "fd.")) for c in self.column_names())

    def switched_on(self, t_step: float) -> Effect | None:
        """The same coupling switched on at ``t_step`` [s] (zero before, itself after), or
        None for an effect that cannot be (it varies already, or is no coupling of a witness).
        The diagnosis tries it where a coupling appears in the data (an onset)."""
        return None

    def column_names(self) -> list[str]:
        """Names of the columns (without building them), for parsing injection values."""
        return [c.name for c in self.named_columns()]

    def named_columns(self) -> list[Column]:
        """The columns with their names, units and prior scales, built on a names-only
        input (their series are placeholders)."""
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
        return self.columns(data)

    def describe(self) -> dict:
        d = {"effect": self.name, "options": {k: v for k, v in self.options.items() if v != self.parameters.get(k)}}
        module = getattr(type(self), "_ttl_module_path", None)
        if module:
            d["effect_module"] = module
        return d

    def option_unit(self, key: str) -> str | None:
        """The unit of option ``key`` (:attr:`units`), None for an option kept as given."""
        return self.units.get(key)

    def spec(self) -> str:
        """The spelling ``name[:key=value,...]`` of this effect, the one ``--effects``,
        ``--inject`` and every report use (:func:`ttlcore.effects.registry.parse_effect_spec`
        reads it back as the same effect): the options that differ from their defaults,
        times and frequencies with their unit (:func:`format_option`)."""
        opts = {k: v for k, v in self.options.items() if v != self.parameters.get(k)}
        if not opts:
            return self.name
        return self.name + ":" + ",".join(f"{k}={format_option(v, self.option_unit(k))}" for k, v in opts.items())

    def cli_spec(self) -> str:
        """:meth:`spec` (the command line's spelling is the same since the one grammar of
        docs/cli.md, "Effect specs"; kept for the callers and reports that name it)."""
        return self.spec()

    #: nonlinear parameters the diagnosis searches when their option is not given:
    #: ``option -> (low, high, scale)`` with scale ``"log"`` or ``"linear"``
    #: (:func:`ttlcore.diagnose.search.profile_search`)
    searched: dict = {}

    def unresolved(self) -> list[str]:
        """Searched options without a value (the diagnosis finds them)."""
        return [k for k in self.searched if self.options.get(k) is None]

    def reshaped(self) -> Self | None:
        """This effect with its searched options unset, for the diagnosis to search its shape
        again on new data, or None when it has no shape to search again: no searched option,
        one still unset, or a transient (a glitch's time and damping are searched where it
        is found, :meth:`active_span`).

        A live model adopts a coupling's shape (a pole's corner, a resonance's frequency and
        quality factor, a cycle's period) from the hours after its onset; a day later the
        window holds far more of it, and the shape is searched again as a candidate that
        replaces the effect (:func:`ttlcore.diagnose.candidates.replacement_evidence`)."""
        searched = list(self.searched)
        if not searched or self.unresolved() or self.active_span() is not None:
            return None
        return self.with_options(**dict.fromkeys(searched))

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
