"""``drift``: the linear coefficients drifting linearly in time, ``C(t) = C + r (t - t_ref)``."""

from __future__ import annotations

from ..conventions import (
    DAY,
)
from .base import Effect
from .columns import Column, Part


class Drift(Effect):
    name = "drift"
    title = "coefficients drifting linearly in time"
    physics = (
        "Thermal relaxation or slow alignment changes make the coupling coefficients vary with time: "
        "C(t) = C + r (t - t_ref). The extra term r (t - t_ref) w enters each link like the coefficient "
        "it modifies (rx undelayed, tx after the light travel time, with the time of emission)."
    )
    parameters = {"mosas": "all", "angles": "all", "sides": "all", "t_ref": None}
    units = {"t_ref": "s"}
    modulates_coefficients = True

    def coefficient_modulation(self, t, t_mid):
        """``(t - t_ref) / day`` (``t_ref`` default the middle of the data): the rate, per day."""
        t_ref = t_mid if self.options.get("t_ref") is None else float(self.options["t_ref"])
        return (t - t_ref) / DAY, "drift", "m/rad/day"

    def columns(self, data):
        t_ref = data.t_ref if self.options.get("t_ref") is None else float(self.options["t_ref"])
        tau = (data.t - t_ref) / DAY
        return [
            Column(
                f"drift.{m}.{a}.{s}", [Part(link, tau * data.witness(m, a), delayed, (m, a), tau)], "m/rad/day", 1e-3
            )
            for m, a, s, link, delayed in self.coefficient_placements()
        ]
