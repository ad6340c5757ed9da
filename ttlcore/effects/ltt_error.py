"""``ltt-error``: an error in the light travel time that places the delayed (tx) terms."""

from __future__ import annotations

from ..conventions import (
    COEFFICIENT_NAMES,
    LINKS,
    reverse,
)
from .base import split_list
from .shifted import ShiftInjection, _Linearised, _offset_parameters


class LightTravelTimeError(_Linearised):
    name = "ltt-error"
    title = "error in the light travel time of the delayed (tx) terms"
    physics = (
        "The tx jitter reaches the receiver one light travel time after emission; if the delay used to "
        "place the tx witnesses (the telemetry's ranging) is off by eps on link ij, the fit misses "
        "C D_ij [w(t - eps) - w] = C D_ij [-eps w' + eps^2/2 w'']. One eps per link."
    )
    parameters = {"links": "all", **_offset_parameters(LINKS)}

    d1_sign = -1.0

    def _shifts_delay(self):
        return True

    def _groups(self):
        links = split_list(self.options.get("links"), LINKS, "effect 'ltt-error' links")
        groups: dict = {}
        for cname in COEFFICIENT_NAMES:
            m, _, s = cname.split(".")
            if s == "tx" and reverse(m) in links:
                groups.setdefault(reverse(m), []).append(cname)
        return groups

    def columns(self, data):
        cols = super().columns(data)
        for c in cols:  # data hold w(t - eps): first order -eps w'
            if c.name.endswith(".d1"):
                for p in c.parts:
                    p.series = -p.series
        return cols

    def injection(self, values, name=None):
        return ShiftInjection(self, values, name)
