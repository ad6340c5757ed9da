"""Glitches: a transient a user (or the diagnosis' advice) adds to a model.

docs/diagnostics.md, "Glitches and gates".  An effect that acts on a short span of the data
instead of the whole of it, for the excess the transient finder
(:mod:`ttlcore.diagnose.transients`) localises (the other is the gate,
:mod:`ttlcore.effects.gate`):

**glitch** - the LISA Pathfinder glitch shape, the one ``lisaglitch``'s
``IntegratedShapeletGlitch`` injects (the integrated single-component exponential
shapelet that fitted the Pathfinder catalogue): a test-mass velocity

    v(t) = dv [1 - (1 + x) exp(-x)],   x = (t - t_g) / beta  (t >= t_g; 0 before),

a velocity step ``dv`` [m/s] reached over the damping time ``beta`` [s].  A glitch of
test mass ``ij`` (MOSA ``ij``, received at ``i``) moves the far end of link ``ji`` and the
near end of link ``ij``: it enters ``eta_ij`` as ``2 v(t) / c`` undelayed and ``eta_ji``
as ``D_ji 2 v / c`` (the light leaving test mass ``ij`` reaches ``j`` one light travel
time later) - as lisainstrument and the blind generator inject it.  A glitch of one link's
optical path (``link=ij``) enters ``eta_ij`` alone, as ``v(t) / c``.  The column is that
series through the exact TDI (a velocity step that stays is cancelled by TDI once every
delay has seen it: the column is localised, ~70 s plus a few ``beta``); its one linear
parameter is ``dv``.  Time, damping and the test mass (or link) are searched when not given
(by the diagnosis: :func:`ttlcore.diagnose.glitches.glitch_search`).

The effect class and the shapelet live here, on the simulator's floor below the diagnosis, so
that the registry of effects (:data:`ttlcore.effects.registry.EFFECTS`) is complete without
the diagnosis; the glitch search and the gated data are the diagnosis'
(:mod:`ttlcore.diagnose.glitches`, :mod:`ttlcore.diagnose.gating`).
"""

from __future__ import annotations

import re

import numpy as np

from ..conventions import (
    LINKS,
    MOSAS,
    C,
    format_time,
    parse_time,
    reverse,
)
from ..errors import ConfigError
from .base import Effect
from .columns import Column, Part

BETA_RANGE = (1.0, 3000.0)


#: Damping times of the search's first grid [s].
BETA_GRID = tuple(float(x) for x in np.geomspace(2.0, 2000.0, 10))


#: Prior scale [m/s] of a glitch's velocity step (the Bayes factor's Gaussian prior).
GLITCH_PRIOR = 1e-10


#: How long a glitch's column lasts after its time, in damping times: ``(1 + x) exp(-x)``
#: is 2e-9 at x = 25, so the velocity has reached its step (which TDI then cancels).
GLITCH_DAMPING_SPAN = 25.0


#: Reach [s] of the second-generation TDI around a sample: the nested delays (four round
#: trips of ~8.3 s) and the interpolation stencil, with margin.
TDI_REACH = 120.0


def glitch_velocity(t, t_glitch: float, beta: float) -> np.ndarray:
    """``v(t) / dv = 1 - (1 + x) exp(-x)``, ``x = (t - t_glitch) / beta`` (0 before): the
    Pathfinder shape of unit velocity step (module docstring)."""
    x = (np.asarray(t, dtype=float) - float(t_glitch)) / float(beta)
    out = np.zeros_like(x)
    on = x >= 0
    out[on] = 1.0 - (1.0 + x[on]) * np.exp(-x[on])
    return out


#: ``START-STOP``: two times (seconds, signed, with an exponent, or with a unit such as ``2.5h``;
#: :func:`ttlcore.conventions.parse_time`) joined by a minus sign; a negative start (an event
#: widened before the first sample) is a time.
_SPAN = re.compile(r"\s*(-?[0-9.]+(?:[eE][-+]?[0-9]+)?[a-z]*)\s*-\s*(-?[0-9.]+(?:[eE][-+]?[0-9]+)?[a-z]*)\s*")


def _parse_span(text) -> tuple[float, float] | None:
    """``"a-b"`` (times, :func:`ttlcore.conventions.parse_time`) -> (a, b) [s]; either may be
    negative (``"-480-3000"``, ``"-480s-50min"``)."""
    if text is None:
        return None
    m = _SPAN.fullmatch(str(text))
    if m is None:
        raise ConfigError(f"span {text!r}: expected START-STOP (e.g. glitch:span=9000-11000 or glitch:span=2.5h-3h)")
    lo, hi = parse_time(m.group(1), "span"), parse_time(m.group(2), "span")
    if hi <= lo:
        raise ConfigError(f"span {text!r}: stop before start")
    return lo, hi


def placement_parts(where: str) -> list[tuple[str, int, float]]:
    """``"tm12"`` -> ``[("12", 0, 2), ("21", 1, 2)]`` (link, delays, factor of ``v / c``);
    ``"link12"`` -> ``[("12", 0, 1)]`` (module docstring)."""
    if where.startswith("tm"):
        m = where[2:]
        return [(m, 0, 2.0), (reverse(m), 1, 2.0)]
    return [(where[4:], 0, 1.0)]


#: The placements a glitch search tries when neither ``tm`` nor ``link`` is given.
PLACEMENTS = tuple(f"tm{m}" for m in MOSAS) + tuple(f"link{k}" for k in LINKS)


class Glitch(Effect):
    name = "glitch"
    transient = True
    named_candidate = False
    title = "a test-mass (or link) glitch of the LISA Pathfinder shape"
    physics = (
        "A test mass kicked by outgassing, a discharge or a micrometeoroid changes velocity by dv over a "
        "damping time beta: v(t) = dv [1 - (1 + x) exp(-x)], x = (t - t_g)/beta (the integrated shapelet "
        "that fits the LISA Pathfinder glitches, lisaglitch's IntegratedShapeletGlitch). Test mass ij enters "
        "eta_ij as 2v/c and eta_ji as D_ji 2v/c; a link glitch (link=ij) eta_ij alone as v/c. One linear "
        "parameter, dv [m/s]; the time t, the damping beta and the test mass are searched when not given "
        "(span=START-STOP restricts the time searched)."
    )
    parameters = {"t": None, "tm": None, "link": None, "beta": None, "span": None}
    units = {"t": "s", "beta": "s"}
    searched = {"t": (-np.inf, np.inf, "linear"), "beta": (BETA_RANGE[0], BETA_RANGE[1], "log")}

    def __init__(self, **options):
        super().__init__(**options)
        tm, link = self.options.get("tm"), self.options.get("link")
        if tm is not None and link is not None:
            raise ConfigError("effect 'glitch': give tm= (a test mass) or link= (one link), not both")
        for key, value in (("tm", tm), ("link", link)):
            if value is not None and str(value) not in LINKS:
                raise ConfigError(f"effect 'glitch' {key}: unknown {value!r}; known: {', '.join(LINKS)}")
            if value is not None:
                self.options[key] = str(value)
        beta = self.options.get("beta")
        if beta is not None and not beta > 0:
            raise ConfigError(f"effect 'glitch' beta: a damping time > 0 s, got {beta:g} s")
        span = _parse_span(self.options.get("span"))
        if span is not None:  # printed with its units (as every time of a spec)
            self.options["span"] = f"{format_time(span[0])}-{format_time(span[1])}"

    @property
    def where(self) -> str | None:
        """``"tm12"``, ``"link12"`` or None (searched)."""
        if self.options.get("tm") is not None:
            return f"tm{self.options['tm']}"
        if self.options.get("link") is not None:
            return f"link{self.options['link']}"
        return None

    def unresolved(self) -> list[str]:
        out = super().unresolved()
        return out + (["tm"] if self.where is None else [])

    def column_name(self) -> str:
        t = self.options.get("t")
        return f"glitch.{self.where or '?'}@{'?' if t is None else f'{float(t):.1f}'}"

    def columns(self, data):
        if self.unresolved():
            if data.names_only:
                return [Column(self.column_name(), [], "m/s", GLITCH_PRIOR)]
            raise ConfigError(
                f"effect 'glitch': {', '.join(self.unresolved())} not given (the diagnosis searches "
                "them: ttl diagnose, refit)"
            )
        v = glitch_velocity(data.t, self.options["t"], self.options["beta"])
        assert self.where is not None  # resolved above (unresolved() names it otherwise)
        parts = [Part(link, factor * v / C, n) for link, n, factor in placement_parts(self.where)]
        return [Column(self.column_name(), parts, "m/s", GLITCH_PRIOR)]

    def active_span(self) -> tuple[float, float] | None:
        """From the glitch's time to :data:`GLITCH_DAMPING_SPAN` damping times and the TDI's
        reach after it (None while its time or damping is searched)."""
        t, beta = self.options.get("t"), self.options.get("beta")
        if t is None or beta is None:
            return None
        return float(t), float(t) + GLITCH_DAMPING_SPAN * float(beta) + TDI_REACH

    def describe_text(self) -> str:
        """``"glitch at 2.70 h on tm 12"`` (or ``on link 12``)."""
        w = self.where or "?"
        on = f"tm {w[2:]}" if w.startswith("tm") else f"link {w[4:]}"
        return f"glitch at {float(self.options['t']) / 3600:.2f} h on {on}"
