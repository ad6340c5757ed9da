"""``timing-offset``: the DWS of a spacecraft time-stamped late against the phasemeter."""

from __future__ import annotations

from ..conventions import (
    COEFFICIENT_NAMES,
    MOSAS,
    local_spacecraft,
)
from ..errors import ConfigError
from .shifted import ShiftInjection, _Linearised, _offset_parameters


class TimingOffset(_Linearised):
    name = "timing-offset"
    title = "timing offset between DWS and phasemeter readouts"
    physics = (
        "The DWS samples of a spacecraft are time-stamped delta late with respect to the phasemeter "
        "(a processing latency, a misaligned data stream): the length readout holds C DWS(t + delta). "
        "To second order C [w + delta w' + delta^2/2 w''], with the fitted C."
    )
    parameters = {"per": "sc", **_offset_parameters(["sc1", "sc2", "sc3", *MOSAS, "all"])}

    def _groups(self):
        per = self.options.get("per", "sc")
        if per not in ("sc", "mosa", "global"):
            raise ConfigError("effect 'timing-offset' per: expected sc, mosa or global")
        groups: dict = {}
        for cname in COEFFICIENT_NAMES:
            m = cname.split(".")[0]
            key = {"sc": f"sc{local_spacecraft(m)}", "mosa": m, "global": "all"}[per]
            groups.setdefault(key, []).append(cname)
        return groups

    def injection(self, values, name=None):
        return ShiftInjection(self, values, name)
