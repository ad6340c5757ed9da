"""``witness``: a witness series (a DWS angle, its derivative, a product of angles) coupled
into a link with a constant gain, placed by source, link and delay.
"""

from __future__ import annotations

from ..conventions import (
    ANGLES,
)
from ..errors import ConfigError
from .columns import Column, Part
from .filters import derivative_response
from .placed import _int_option, _Placed


class WitnessEffect(_Placed):
    name = "witness"
    title = "a witness series of the library, fitted with one coefficient each"
    physics = (
        "Any series of the witness library (ttlcore.witnesses: a DWS channel on any link, undelayed or "
        "delayed by one or two light travel times, its time derivative, a product of angles) can couple "
        "into the data with a constant coefficient. The column is the series placed on the link through "
        "the exact time-varying TDI delays; a plain DWS channel carries its readout noise into the "
        "errors-in-variables term."
    )
    parameters = {
        "source": None,
        "link": None,
        "delay": 0,
        "derivative": 0,
        "mosas": None,
        "angles": "all",
        "sides": "rx",
        "links": "all",
        "vary": "none",
        "t_ref": None,
        "t_step": None,
        "period": None,
    }
    units = {"delay": "count", "derivative": "count", "t_ref": "s", "t_step": "s", "period": "s"}

    def columns(self, data):
        der = _int_option(self, "derivative", (0, 1))
        cols = []
        for src, link, n in self.placements():
            if der and src.split(".")[1] not in ANGLES:
                raise ConfigError(f"effect 'witness' source {src!r}: products have no derivative option")
            for suffix, mod in self.modulations(data):
                series, channel, unit = self._series(data, src, mod)
                label = self._label(("d/dt:" if der else "") + self.placement_label(src, link, n), suffix)
                prior = {"m/rad": 1e-3, "m/rad^2": 1e3}[unit]
                # the time derivative as the filter 2 pi i f: its readout noise follows exactly
                cols.append(
                    Column(
                        f"witness.{label}",
                        [Part(link, series, n, channel, mod)],
                        "m s/rad" if der else unit,
                        prior * 10 if der else prior,
                        response=derivative_response if der else None,
                    )
                )
        return cols
