"""``fd-coupling``: a witness coupled through a frequency-dependent path (a resonance, a first-
order path) whose poles the diagnosis searches.
"""

from __future__ import annotations

import functools

from ..conventions import (
    ANGLES,
)
from ..errors import ConfigError
from ..tdi.regressors import witness_placement as placement
from .columns import Column, Part
from .filters import rational_basis
from .placed import _Placed


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
