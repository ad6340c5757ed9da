"""``gate``: a span of the data down-weighted to zero with cosine tapers, as lisa-gap smooths a gap.

The A, E, T series of the data and of every column are multiplied by

    g(t) = 0 inside [start, stop],  1/2 - 1/2 cos(pi d / taper) for the distance d < taper
           outside it,  1 beyond,

before the segments are windowed (the diagnosis' :class:`ttlcore.diagnose.gating.GatedGrid`),
so that the fit ignores the span and no hard edge leaks (docs/diagnostics.md, "Glitches and gates").
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .base import Effect

#: Taper [s] of each side of a gate (a cosine, as lisa-gap's smoothed gaps).  A ramp of T
#: seconds spreads a series' power over ~1/T Hz, and TDI's power below the band (test-mass
#: noise, the arms' slow changes) is orders of magnitude above the band's: the ramps must
#: keep 1/T well under the band's 3 mHz.  Measured on a simulated day gated three times
#: 24 min (``ttl diagnose --effects``, against the same day ungated): 300-s ramps moved the
#: coefficients by 1.06 sigma RMS (pull RMS 1.39), 30-s ramps by 137 sigma; 600 s and 900 s
#: by 0.37 sigma (pull 1.15, 1.10), what losing that share of the data should (~0.3).
GATE_TAPER = 900.0


def gate(n: int, fs: float, t0: float, spans, taper: float = GATE_TAPER) -> np.ndarray:
    """A gate (n,): 0 inside each ``(start, stop)`` span [s], 1 outside, with cosine ramps of
    ``taper`` seconds outside the spans (lisa-gap's smoothed gap)."""
    t = t0 + np.arange(n) / fs
    g = np.ones(n)
    for a, b in spans:
        d = np.maximum(np.maximum(a - t, t - b), 0.0)  # distance outside the span [s]
        ramp = np.where(d >= taper, 1.0, 0.5 - 0.5 * np.cos(np.pi * np.clip(d / taper, 0, 1)))
        g = np.minimum(g, ramp)
    return g


class Gate(Effect):
    name = "gate"
    transient = True
    named_candidate = False
    title = "a span of the data gated out (tapered window, as lisa-gap smooths a gap)"
    physics = (
        "The data between start and stop (a loud transient, a gap with hard edges, hours of changed noise) "
        "are down-weighted to zero with cosine tapers of 'taper' seconds outside the span, in the data and in "
        "every column alike, so that the fit ignores them (lisa-gap's smoothed gap). Not a physical effect: no "
        "parameter is fitted; the gated hours are left out of the fit and of the adequacy tests."
    )
    parameters = {"start": None, "stop": None, "taper": GATE_TAPER}
    units = {"start": "s", "stop": "s", "taper": "s"}

    def __init__(self, **options):
        super().__init__(**options)
        if self.options.get("start") is None or self.options.get("stop") is None:
            raise ConfigError("effect 'gate' needs start= and stop= (e.g. gate:start=15.2h,stop=15.8h)")
        if not self.options["taper"] > 0:
            raise ConfigError(f"effect 'gate' taper: a duration > 0 s, got {self.options['taper']:g} s")
        if self.options["stop"] <= self.options["start"]:
            raise ConfigError(
                f"effect 'gate': stop ({self.options['stop']:g} s) before start ({self.options['start']:g} s)"
            )

    @property
    def span(self) -> tuple[float, float]:
        return float(self.options["start"]), float(self.options["stop"])

    def columns(self, data):
        return []

    def active_span(self) -> tuple[float, float]:
        """The gated span with its tapers."""
        a, b = self.span
        taper = float(self.options["taper"])
        return a - taper, b + taper

    def describe_text(self) -> str:
        a, b = self.span
        return f"gate {a / 3600:.2f}-{b / 3600:.2f} h"


def split_gates(effects) -> tuple[list, list]:
    """``(gates, others)`` of a model's effects."""
    gates = [e for e in effects if isinstance(e, Gate)]
    return gates, [e for e in effects if not isinstance(e, Gate)]


def merge_gates(effects) -> list:
    """A model's effects with overlapping or touching gates merged into one gate over their
    union (the widest taper), after the other effects in their order.  The live fitter
    adopts a gate for an ongoing signal at each diagnosis (a chirp in band for hours: the
    span to the window's end, then on from there): one gate per signal, not one per look."""
    gates, others = split_gates(effects)
    merged: list[list[float]] = []
    for g in sorted(gates, key=lambda g: g.span):
        a, b = g.span
        taper = float(g.options["taper"])
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
            merged[-1][2] = max(merged[-1][2], taper)
        else:
            merged.append([a, b, taper])
    return list(others) + [Gate(start=a, stop=b, taper=t) for a, b, t in merged]
