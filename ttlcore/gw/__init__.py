"""Gravitational-wave sources: signal generators the simulator injects into the links.

``response`` (the link response to a plane wave), ``sources`` (verification binaries),
``galaxy`` (the galactic population), ``sgwb`` (a stochastic background), ``mbhb`` (massive
black-hole binaries) and ``injection`` (the sources as simulator injections, ``--gw``).
They sit on the simulator's floor (they use its orbits and noise streams, and it rebuilds
them from their descriptions); the paper's scenarios that run them are
:mod:`ttlcore.app.scenarios`.

::

    from ttlcore.gw import parse_gw_spec
    injections = parse_gw_spec("vb", t0=0.0, duration=86400.0, seed=1)
"""

from .injection import injection_from_description, parse_gw_spec
from .response import link_response

__all__ = ["injection_from_description", "link_response", "parse_gw_spec"]
