"""The eta-level mission simulator and what it draws on.

``simulator`` (the mission), ``noise`` (stationary Gaussian noise of any ASD, random access),
``noise_models`` (the analytic ASDs), ``orbits`` (light travel times), ``coefficients``
(TTL coefficient sets and their time variation) and ``injection`` (the protocol of the
signals added to the links: the effects of :mod:`ttlcore.effects` and the GW sources of
:mod:`ttlcore.gw`).  ``ttl simulate``'s options are mapped to a configuration by
:mod:`ttlcore.cli.simulation`.

::

    from ttlcore.sim import SimulationConfig, simulate
    tm, truth = simulate(SimulationConfig(duration=4 * 3600.0, orbit="keplerian", seed=1))
"""

from .coefficients import CoefficientModel, make_coefficients
from .orbits import Orbit, make_orbit
from .simulator import NoiseSwitches, SimulationConfig, Simulator, simulate, simulate_to_file

__all__ = [
    "CoefficientModel",
    "NoiseSwitches",
    "Orbit",
    "SimulationConfig",
    "Simulator",
    "make_coefficients",
    "make_orbit",
    "simulate",
    "simulate_to_file",
]
