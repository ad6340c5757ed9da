"""The named effects of the coupling coefficients: the linear TTL and its variations.

``linear-ttl`` (the 24 coefficients), ``drift`` (coefficients drifting linearly in time),
``step`` (a coefficient step), ``cross-coupling`` (the neighbouring MOSA's jitter) and
``second-order`` (squares and products of the angles); docs/diagnostics.md.
"""

from __future__ import annotations

import numpy as np

from ..conventions import (
    ANGLES,
    DAY,
    MOSAS,
    SIDES,
    C,
)
from ..errors import ConfigError
from ..tdi.regressors import witness_placement as placement
from .base import Effect, split_list
from .columns import Column, Part


def partner(mosa: str) -> str:
    """The other MOSA on the same spacecraft (``12`` <-> ``13``, ``23`` <-> ``21``, ``31`` <-> ``32``)."""
    i = mosa[0]
    return next(m for m in MOSAS if m[0] == i and m != mosa)


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
        cols = []
        for m in self.mosas:
            for a in self.angles:
                for s in self.sides:
                    link, delayed = placement(m, s)
                    cols.append(
                        Column(
                            f"drift.{m}.{a}.{s}",
                            [Part(link, tau * data.witness(m, a), delayed, (m, a), tau)],
                            "m/rad/day",
                            1e-3,
                        )
                    )
        return cols


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
        cols = []
        for m in self.mosas:
            for a in self.angles:
                for s in self.sides:
                    link, delayed = placement(m, s)
                    cols.append(
                        Column(
                            f"step.{m}.{a}.{s}", [Part(link, h * data.witness(m, a), delayed, (m, a), h)], "m/rad", 1e-3
                        )
                    )
        return cols


class CrossCoupling(Effect):
    name = "cross-coupling"
    title = "jitter of the neighbouring MOSA on the same spacecraft"
    physics = (
        "Stray light, the shared optical bench or mechanical coupling let the angle of the other MOSA on "
        "the same spacecraft (12 <-> 13, 23 <-> 21, 31 <-> 32) couple into a MOSA's received (rx) or "
        "transmitted (tx) beam path. Distinguishable from the linear TTL only through the MOSA jitter "
        "(the spacecraft jitter is common to both MOSAs). Rx side only: a channel on both sides "
        "of both MOSAs forms, with the linear rx and tx terms, the pattern of a laser's frequency noise "
        "(-1 on the two undelayed links of its spacecraft, +1 delayed on the two links it feeds), "
        "which TDI cancels - the tx cross terms are absorbed by the linear coefficients."
    )
    parameters = {"mosas": "all", "angles": "all", "sides": "rx"}

    def __init__(self, **options):
        super().__init__(**options)
        if set(self.sides) == {"rx", "tx"}:
            raise ConfigError(
                "effect 'cross-coupling': sides rx and tx together are unobservable with the linear TTL "
                "(they form a laser-noise pattern TDI cancels); use sides=rx or sides=tx"
            )

    def columns(self, data):
        cols = []
        for m in self.mosas:
            for a in self.angles:
                for s in self.sides:
                    link, delayed = placement(m, s)
                    cols.append(
                        Column(
                            f"cross.{m}.{a}.{s}",
                            [Part(link, data.witness(partner(m), a), delayed, (partner(m), a))],
                            "m/rad",
                            1e-3,
                        )
                    )
        return cols


class SecondOrder(Effect):
    name = "second-order"
    title = "second-order angle terms (squares and products, static offsets)"
    physics = (
        "The path length depends quadratically on the angles near the optimal alignment: "
        "l = C1 a + K (a + a0)(b + b0) for a, b in {phi, eta}. Differentiated, K (a' b + a b') adds to "
        "eta; the static offsets a0, b0 only add K (a0 b' + b0 a'), absorbed by the linear "
        "coefficients (which then differ from the linear-only truth by K a0, K b0). "
        "Angles are the running integral of the DWS velocities."
    )
    parameters = {"mosas": "all", "sides": "rx", "terms": "phiphi,etaeta,phieta", "offset_phi": 0.0, "offset_eta": 0.0}
    units = {"offset_phi": "rad", "offset_eta": "rad"}
    TERMS = ("phiphi", "etaeta", "phieta")
    integrates_angles = True

    @property
    def terms(self) -> tuple:
        return split_list(self.options.get("terms"), self.TERMS, "effect 'second-order' terms")

    def columns(self, data):
        ang = dict(zip(ANGLES, data.angles))
        off = {"phi": float(self.options["offset_phi"]), "eta": float(self.options["offset_eta"])}
        cols = []
        for m in self.mosas:
            k = MOSAS.index(m)
            for term in self.terms:
                a, b = term[:3], term[3:]
                x, y = ang[a][k] + off[a], ang[b][k] + off[b]
                dx, dy = data.velocity(a)[k], data.velocity(b)[k]
                series = -(dx * y + x * dy) / C
                for s in self.sides:
                    link, delayed = placement(m, s)
                    cols.append(Column(f"quad.{m}.{term}.{s}", [Part(link, series, delayed)], "m/rad^2", 1e3))
        return cols
