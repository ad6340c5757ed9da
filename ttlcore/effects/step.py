"""``step``: a step of the linear coefficients at a given or searched time, ``C(t) = C + J H(t
- t_step)``.
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .base import Effect
from .columns import Column, Part


class Step(Effect):
    name = "step"
    title = "coefficient step at a given or searched time"
    physics = (
        "A realignment, a thermal event or a micrometeoroid hit changes the coupling abruptly at t_step: "
        "C(t) = C + J H(t - t_step). The jump J multiplies the witness from t_step on (tx: emission time)."
    )
    parameters = {"mosas": "all", "angles": "all", "sides": "all", "t_step": None}
    units = {"t_step": "s"}
    #: the step time [s], searched over the data (its own evaluator: :func:`ttlcore.diagnose.step_search.step_time_search`)
    searched = {"t_step": (-np.inf, np.inf, "linear")}
    modulates_coefficients = True

    def coefficient_modulation(self, t, t_mid):
        """``H(t - t_step)``: the jump."""
        if self.options.get("t_step") is None:
            raise ConfigError("effect 'step' needs t_step in a model (ttl diagnose reports the searched time)")
        return (t >= float(self.options["t_step"])).astype(float), "step", "m/rad"

    def columns(self, data):
        if self.options.get("t_step") is None and data.names_only:
            return [
                Column(f"step.{m}.{a}.{s}", [], "m/rad", 1e-3)
                for m in self.mosas
                for a in self.angles
                for s in self.sides
            ]
        if self.options.get("t_step") is None:
            raise ConfigError(
                "effect 'step' needs t_step (a time, e.g. step:t_step=13.9h) or a search (ttl diagnose searches it)"
            )

        ts = float(self.options["t_step"])  # seconds (read with its unit)
        h = (data.t >= ts).astype(float)
        return [
            Column(f"step.{m}.{a}.{s}", [Part(link, h * data.witness(m, a), delayed, (m, a), h)], "m/rad", 1e-3)
            for m, a, s, link, delayed in self.coefficient_placements()
        ]
