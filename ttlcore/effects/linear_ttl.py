"""The linear TTL coupling: the 24 coefficients of the paper (eq. 3), one per MOSA, angle and
side.
"""

from __future__ import annotations

from ..conventions import (
    ANGLES,
    MOSAS,
    SIDES,
)
from ..tdi.regressors import witness_placement as placement
from .base import Effect
from .columns import Column, Part


class LinearTTL(Effect):
    name = "linear-ttl"
    title = "linear tilt-to-length coupling (the 24 coefficients)"
    physics = (
        "Angular jitter of the receiving (rx) and transmitting (tx) MOSA couples linearly into the "
        "measured length, with one coefficient per MOSA, angle and side (paper eq. 3; docs/physics.md)."
    )
    parameters = {"mosas": "all", "angles": "all", "sides": "all"}
    is_linear_ttl = True

    def columns(self, data):
        cols = []
        for m in MOSAS:
            for a in ANGLES:
                for s in SIDES:
                    if m in self.mosas and a in self.angles and s in self.sides:
                        link, delayed = placement(m, s)
                        cols.append(
                            Column(f"{m}.{a}.{s}", [Part(link, data.witness(m, a), delayed, (m, a))], "m/rad", 2.3e-3)
                        )
        return cols
