"""``cross-coupling``: the jitter of the neighbouring MOSA on the same spacecraft."""

from __future__ import annotations

from ..conventions import (
    MOSAS,
)
from ..errors import ConfigError
from .base import Effect
from .columns import Column, Part


def partner(mosa: str) -> str:
    """The other MOSA on the same spacecraft (``12`` <-> ``13``, ``23`` <-> ``21``, ``31`` <-> ``32``)."""
    i = mosa[0]
    return next(m for m in MOSAS if m[0] == i and m != mosa)


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
        return [
            Column(
                f"cross.{m}.{a}.{s}", [Part(link, data.witness(partner(m), a), delayed, (partner(m), a))], "m/rad", 1e-3
            )
            for m, a, s, link, delayed in self.coefficient_placements()
        ]
