"""Effects placed on links from the witness library: ``witness`` and ``fd-coupling``.

Either one ``source`` (a library witness: channel, link, delay) or the standard placements of
``mosas``/``angles``/``sides``; a constant coupling (``witness``) or a frequency-dependent one
(``fd-coupling``, the rational basis of :func:`ttlcore.effects.filters.rational_basis`), each
optionally varying in time (``vary``: drift, step, cycle).
"""

from __future__ import annotations

import functools

import numpy as np

from ..conventions import (
    ANGLES,
    DAY,
    LINKS,
    MOSAS,
    C,
    format_time,
    parse_duration,
)
from ..errors import ConfigError
from ..tdi.regressors import witness_placement as placement
from .base import Effect, split_list
from .columns import Column, EffectInput, Part
from .coupling import SecondOrder
from .filters import derivative, derivative_response, rational_basis


def witness_series(data: EffectInput, source: str, derivative_order: int = 0) -> tuple[np.ndarray, tuple | None, str]:
    """A witness series of the library (:mod:`ttlcore.witnesses`) from ``data``.

    ``source`` is ``"<mosa>.<phi|eta>"`` (the witness ``-DWS/c``, its time derivative with
    ``derivative_order=1``) or ``"<mosa>.<phiphi|etaeta|phieta>"`` (``-d/dt(a b) / c``, angles
    integrated from the DWS, as :class:`SecondOrder`).

    Returns
    -------
    series : ndarray (n,)
    channel : tuple or None
        ``(mosa, angle)`` of a plain witness (its readout noise enters the
        errors-in-variables term), None for products.
    unit : str
        Unit of the coefficient.
    """
    mosa, _, kind = str(source).partition(".")
    if mosa not in MOSAS or kind not in ANGLES + SecondOrder.TERMS:
        raise ConfigError(
            f"witness source {source!r}: expected <mosa>.<phi|eta> or <mosa>.<phiphi|etaeta|phieta> "
            f"with mosa in {', '.join(MOSAS)}"
        )
    if kind in ANGLES:
        w = data.witness(mosa, kind)
        if derivative_order:
            return derivative(w, data.fs, 1), (mosa, kind), "m s/rad"
        return w, (mosa, kind), "m/rad"
    if derivative_order:
        raise ConfigError(f"witness source {source!r}: products have no derivative option")
    k = MOSAS.index(mosa)
    ang = dict(zip(ANGLES, data.angles))
    a, b = kind[:3], kind[3:]
    return -(data.velocity(a)[k] * ang[b][k] + ang[a][k] * data.velocity(b)[k]) / C, None, "m/rad^2"


def _int_option(effect, key, allowed) -> int:
    try:
        v = int(float(effect.options.get(key) or 0))
    except ValueError:
        raise ConfigError(
            f"effect {effect.name!r} {key}: expected an integer, got {effect.options.get(key)!r}"
        ) from None
    if v not in allowed:
        raise ConfigError(f"effect {effect.name!r} {key}: expected one of {sorted(allowed)}, got {v}")
    return v


#: How long [s] after its switch-on a ``vary=step`` coupling's columns are the plain ones on
#: data that start then (:meth:`_Placed.settled`): the columns' history (30 min) and more.
SETTLED_AFTER = 3600.0

#: Time variations of a placed effect's coupling (option ``vary``, :meth:`_Placed.modulations`).
VARY = ("none", "drift", "step", "cycle")
#: Searched range of the period [s] of ``vary=cycle``: 1 h to 4 days (clipped to twice the
#: analysed span; a longer period is a drift), log scale.
CYCLE_PERIOD = (3600.0, 4 * DAY, "log")


class _Placed(Effect):
    """Effects built on witness series placed on links: either one ``source`` (a library
    witness: channel, link, delay) or the standard placements of ``mosas``/``angles``/``sides``
    (rx: the MOSA's own link, undelayed; tx: the link it transmits on, one delay), optionally
    restricted to ``links``."""

    def placements(self) -> list[tuple[str, str, int]]:
        """``[(source, link, n_delays), ...]``."""
        src = self.options.get("source")
        links = split_list(self.options.get("links"), LINKS, f"effect {self.name!r} links")
        if src:
            mosa = str(src).split(".")[0]
            link = self.options.get("link") or mosa
            if link not in LINKS:
                raise ConfigError(f"effect {self.name!r} link: unknown {link!r}; known: {', '.join(LINKS)}")
            out = [(str(src), link, _int_option(self, "delay", (0, 1, 2)))]
        elif self.options.get("mosas") is not None:
            out = []
            for m in self.mosas:
                for a in self.angles:
                    for sd in self.sides:
                        link, delayed = placement(m, sd)
                        out.append((f"{m}.{a}", link, int(delayed)))
        else:
            raise ConfigError(
                f"effect {self.name!r} needs source=<mosa>.<angle> (with link=, delay=) "
                f"or mosas= (with angles=, sides=)"
            )
        return [p for p in out if p[1] in links]

    @staticmethod
    def placement_label(source, link, n) -> str:
        return f"{source}>{link}" + (f"+{n}L" if n else "")

    @property
    def vary(self) -> str:
        v = self.options.get("vary") or "none"
        if v not in VARY:
            raise ConfigError(f"effect {self.name!r} vary: expected one of {', '.join(VARY)}, got {v!r}")
        return v

    def settled(self, t_start: float) -> Effect | None:
        """With ``vary=step`` and ``t_step`` more than :data:`SETTLED_AFTER` before
        ``t_start``: the same coupling without ``vary`` (its columns are the plain ones from
        ``t_start`` on, the filters' ring-in after the switch long over); else None."""
        t_step = self.options.get("t_step")
        if self.vary != "step" or t_step is None or float(t_step) > t_start - SETTLED_AFTER:
            return None
        kept = {k: v for k, v in self.options.items() if k not in ("vary", "t_step") and v != self.parameters.get(k)}
        return type(self)(**kept)

    named_candidate = False  # a placement is needed: tried from the witness search

    @property
    def trial_columns(self) -> bool:
        """True: a witness's coupling (:meth:`Effect.trial_columns`)."""
        return True

    def switched_on(self, t_step: float) -> Effect | None:
        """This coupling with ``vary=step`` at ``t_step`` [s]; None when it varies already."""
        if self.vary != "none":
            return None
        return self.with_options(vary="step", t_step=round(float(t_step), 1))

    @property
    def searched(self) -> dict:  # type: ignore[override]  # a class attribute in Effect (plugins set it so), computed here
        """The filter's searched poles (:meth:`filter_searched`) and, with ``vary=cycle``,
        the period [s] of the cycle (:data:`CYCLE_PERIOD`)."""
        out = dict(self.filter_searched())
        if self.vary == "cycle":
            out["period"] = CYCLE_PERIOD
        return out

    def filter_searched(self) -> dict:
        return {}

    def modulations(self, data) -> list[tuple[str, np.ndarray | None]]:
        """Time variation of the effect's coupling (option ``vary``): ``(suffix, factor)``
        pairs, one column per pair and placement.  ``none``: one constant coupling;
        ``drift`` multiplies the witness by ``(t - t_ref) / day`` (the coefficients are the
        rate, per day); ``step`` by ``H(t - t_step)`` (the jump); ``cycle`` by
        ``sin(2 pi (t - t_ref) / period)`` and ``cos(...)`` (a slow periodic variation such
        as a thermal cycle: amplitude and phase are the two linear coefficients, the period
        is searched when not given).  A slow modulation commutes with the filters of
        ``fd-coupling`` to ``1 / (f T)``.  Factors are None on a names-only input."""
        vary = self.vary
        if vary == "none":
            return [("", None)]
        if vary == "cycle":
            suffixes = (".sin", ".cos")
            if data.names_only:
                return [(x, None) for x in suffixes]
            if self.options.get("period") is None:
                raise ConfigError(
                    f"effect {self.name!r} vary=cycle: period not given (the diagnosis searches it: "
                    "ttl diagnose, refit)"
                )
            t_ref = data.t_ref if self.options.get("t_ref") is None else float(self.options["t_ref"])
            phase = (
                2 * np.pi * (data.t - t_ref) / parse_duration(self.options["period"], f"effect {self.name!r} period")
            )
            return [(".sin", np.sin(phase)), (".cos", np.cos(phase))]
        if data.names_only:
            return [("", None)]
        if vary == "drift":
            t_ref = data.t_ref if self.options.get("t_ref") is None else float(self.options["t_ref"])
            return [("", (data.t - t_ref) / DAY)]
        if self.options.get("t_step") is None:
            raise ConfigError(f"effect {self.name!r} vary=step needs t_step")
        return [("", (data.t >= float(self.options["t_step"])).astype(float))]

    @staticmethod
    def _series(data, src, mod):
        series, channel, unit = witness_series(data, src, 0)
        if mod is not None:
            series = series * mod
        return series, channel, unit

    def _label(self, label, suffix="") -> str:
        vary = self.vary
        at = {
            "drift": self.options.get("t_ref"),
            "step": self.options.get("t_step"),
            "cycle": self.options.get("period"),
        }.get(vary)
        return (
            label if vary == "none" else f"{label}~{vary}" + (f"@{format_time(at)}" if at is not None else "")
        ) + suffix


class WitnessEffect(_Placed):
    name = "witness"
    title = "a witness series of the library, fitted with one coefficient each"
    physics = (
        "Any series of the witness library (ttlcore.witnesses: a DWS channel on any link, undelayed or "
        "delayed by one or two light travel times, its time derivative, a product of angles) can couple "
        "into the data with a constant coefficient. The column is the series placed on the link through "
        "the exact time-varying TDI delays; a plain DWS channel carries its readout noise into the "
        "errors-in-variables term."
    )
    parameters = {
        "source": None,
        "link": None,
        "delay": 0,
        "derivative": 0,
        "mosas": None,
        "angles": "all",
        "sides": "rx",
        "links": "all",
        "vary": "none",
        "t_ref": None,
        "t_step": None,
        "period": None,
    }
    units = {"delay": "count", "derivative": "count", "t_ref": "s", "t_step": "s", "period": "s"}

    def columns(self, data):
        der = _int_option(self, "derivative", (0, 1))
        cols = []
        for src, link, n in self.placements():
            if der and src.split(".")[1] not in ANGLES:
                raise ConfigError(f"effect 'witness' source {src!r}: products have no derivative option")
            for suffix, mod in self.modulations(data):
                series, channel, unit = self._series(data, src, mod)
                label = self._label(("d/dt:" if der else "") + self.placement_label(src, link, n), suffix)
                prior = {"m/rad": 1e-3, "m/rad^2": 1e3}[unit]
                # the time derivative as the filter 2 pi i f: its readout noise follows exactly
                cols.append(
                    Column(
                        f"witness.{label}",
                        [Part(link, series, n, channel, mod)],
                        "m s/rad" if der else unit,
                        prior * 10 if der else prior,
                        response=derivative_response if der else None,
                    )
                )
        return cols


class FrequencyCoupling(_Placed):
    name = "fd-coupling"
    title = "frequency-dependent coupling of a witness (resonance, first-order path)"
    physics = (
        "A witness couples through a path whose gain varies with frequency: a mechanical resonance of "
        "unknown frequency and quality factor (filter=pole2, the default: 1/D, x/D, x^2/D with "
        "D = 1 + x/q + x^2, x = i f/f0) or a first-order low- or high-pass path of unknown corner "
        "(filter=pole1: 1/(1+x), x/(1+x), x = i f/fc). Linear in the numerator coefficients; the poles "
        "(f0, q or fc) are searched by the diagnosis when not given. Place it with source=, link=, "
        "delay= (a library witness) or mosas=, angles=, sides=, links=. On the placement of a linear TTL "
        "coefficient (its own link undelayed, or the link it transmits on after one delay) the constant "
        "coupling is that coefficient: the basis drops one column there (flat=auto, the default; "
        "flat=keep for a model without linear-ttl)."
    )
    parameters = {
        "source": None,
        "link": None,
        "delay": 0,
        "mosas": None,
        "angles": "all",
        "sides": "rx",
        "links": "all",
        "filter": "pole2",
        "f0": None,
        "q": None,
        "fc": None,
        "vary": "none",
        "t_ref": None,
        "t_step": None,
        "period": None,
        "flat": "auto",
    }
    units = {"delay": "count", "t_ref": "s", "t_step": "s", "period": "s", "f0": "Hz", "q": "", "fc": "Hz"}

    @property
    def kind(self) -> str:
        k = self.options.get("filter") or "pole2"
        if k not in ("pole1", "pole2"):
            raise ConfigError(f"effect 'fd-coupling' filter: expected pole1 or pole2, got {k!r}")
        return k

    def filter_searched(self) -> dict:
        if self.kind == "pole1":
            return {"fc": (1e-3, 2.0, "log")}
        return {"f0": (1e-3, 2.0, "log"), "q": (0.5, 300.0, "log")}

    def response_functions(self) -> list:
        """The basis responses ``f -> complex`` for the current poles.  They share the
        basis: computed once for the frequency array they are called with in turn (the same
        array object, which must not change in place between the calls)."""
        poles: tuple[float, ...]
        if self.kind == "pole1":
            poles, n = (float(self.options["fc"]),), 2
        else:
            poles, n = (float(self.options["f0"]), float(self.options["q"])), 3
        last: list = []  # [(f, basis)]: the last frequency array and its basis

        def basis(f):
            if not (last and last[0][0] is f):
                last[:] = [(f, rational_basis(self.kind, f, *poles))]
            return last[0][1]

        return [functools.partial(lambda f, j: basis(f)[j], j=j) for j in range(n)]

    def holds_flat(self, source: str, link: str, n_delays: int) -> bool:
        """Whether the basis keeps all its columns on this placement.

        The basis spans the constant coupling (``1/(1+x) + x/(1+x) = 1``;
        ``1/D + (x/D)/q + x^2/D = 1``).  On the placement of a linear TTL coefficient
        (:func:`ttlcore.tdi.regressors.witness_placement`: rx on the MOSA's own link,
        undelayed; tx on the link it transmits on, one delay) that constant coupling *is*
        the coefficient's column, so with ``linear-ttl`` in the model the full basis would
        be collinear with it: with ``flat=auto`` (default) and no time variation the last
        basis column is dropped there (the remaining ones and the coefficient span the
        same couplings); ``flat=keep`` keeps it (a model without ``linear-ttl``)."""
        flat = self.options.get("flat") or "auto"
        if flat not in ("auto", "keep"):
            raise ConfigError(f"effect 'fd-coupling' flat: expected auto or keep, got {flat!r}")
        if flat == "keep" or self.vary != "none":
            return True
        mosa, _, angle = source.partition(".")
        return (
            angle not in ANGLES
            or (link, bool(n_delays)) not in (placement(mosa, "rx"), placement(mosa, "tx"))
            or n_delays > 1
        )

    def columns(self, data):
        n_basis = 2 if self.kind == "pole1" else 3
        poles = [k for k in self.unresolved() if k != "period"]
        if poles:
            if not data.names_only:
                raise ConfigError(
                    f"effect 'fd-coupling': {', '.join(poles)} not given "
                    "(the diagnosis searches them: ttl diagnose, refit)"
                )
            resp = [None] * n_basis
        else:
            resp = self.response_functions()
        cols = []
        for src, link, n in self.placements():
            for suffix, mod in self.modulations(data):
                if data.names_only:  # names and responses only (the searches evaluate many poles)
                    series, channel = None, None
                    unit = "m/rad" if src.partition(".")[2] in ANGLES else "m/rad^2"
                else:
                    series, channel, unit = self._series(data, src, mod)
                label = self._label(self.placement_label(src, link, n), suffix)
                parts = [Part(link, series, n, channel, mod)]
                for j in range(n_basis if self.holds_flat(src, link, n) else n_basis - 1):
                    cols.append(
                        Column(
                            f"fd.{label}.b{j}",
                            parts,
                            unit,
                            1e-3 if unit == "m/rad" else 1e3,
                            response=resp[j],
                            base=label,
                        )
                    )
        return cols
