"""``second-order``: squares and products of the angles coupling into the length readout."""

from __future__ import annotations

from ..conventions import (
    ANGLES,
    MOSAS,
    C,
)
from ..tdi.regressors import witness_placement as placement
from .base import Effect, split_list
from .columns import Column, Part


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
