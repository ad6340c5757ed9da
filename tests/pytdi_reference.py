"""pytdi's natural usage as an independent TDI reference for tests and bench/tdi.py.

Each of X2_ETA, Y2_ETA, Z2_ETA is built once (its default delay order 5) and evaluated with
its default order 31 and ``unit="phase"`` (``D x(t) = x(t - tau(t))``, docs/physics.md) on
the data and on each TTL regressor's witness placed on its link, with the scalar 0 on the
five other links; Tx witnesses are first delayed with ``pytdi.dsp.timeshift`` (order 31), as
the simulator forms them.
"""

from __future__ import annotations

import numpy as np
from pytdi.dsp import timeshift
from pytdi.michelson import X2_ETA, Y2_ETA, Z2_ETA

from ttlcore.conventions import COEFFICIENT_NAMES, LINKS
from ttlcore.tdi.regressors import ttl_witnesses


def pytdi_natural(tm) -> tuple[np.ndarray, np.ndarray]:
    """X2, Y2, Z2 of telemetry ``tm``'s ``eta`` (3, n) and of its 24 regressors (3, 24, n);
    pytdi pads before the data with zeros where ttlcore gives NaN."""
    delays = {f"d_{l}": tm.ltt[k] for k, l in enumerate(LINKS)}
    built = [c.build(delays, tm.fs) for c in (X2_ETA, Y2_ETA, Z2_ETA)]
    data = np.stack([b({f"eta_{l}": tm.eta[k] for k, l in enumerate(LINKS)}, unit="phase") for b in built])
    witnesses, index = ttl_witnesses(tm.dws_phi, tm.dws_eta)
    regs = np.zeros((3, len(COEFFICIENT_NAMES), tm.size))
    for (link, extra), w in witnesses.items():
        for row, k in zip(w, index[(link, extra)]):
            if extra:
                row = timeshift(row, -tm.ltt[LINKS.index(extra[0])] * tm.fs, 31)
            meas = {f"eta_{l}": (row if l == link else 0.0) for l in LINKS}
            for c, b in enumerate(built):
                regs[c, k] = b(meas, unit="phase")
    return data, regs
