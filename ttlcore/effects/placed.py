"""The base of the effects placed on links from the witness library (``witness``,
:mod:`ttlcore.effects.witness`; ``fd-coupling``, :mod:`ttlcore.effects.fd_coupling`).

Either one ``source`` (a library witness: channel, link, delay) or the standard placements of
``mosas``/``angles``/``sides``; a constant coupling (``witness``) or a frequency-dependent one
(``fd-coupling``, the rational basis of :func:`ttlcore.effects.filters.rational_basis`), each
optionally varying in time (``vary``: drift, step, cycle).
"""

from __future__ import annotations

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
from .columns import EffectInput
from .filters import derivative
from .second_order import SecondOrder


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
