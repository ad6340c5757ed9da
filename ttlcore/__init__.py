"""ttlcore: the science of tilt-to-length (TTL) noise subtraction for LISA.

Plain functions and small dataclasses, numpy arrays in and out, usable from a notebook::

    from ttlcore.simulator import SimulationConfig, simulate
    tm, truth = simulate(SimulationConfig(duration=6 * 3600, orbit="keplerian"))

Conventions (indices, units, signs) are those of ``PHYSICS.md`` and live in
:mod:`ttlcore.conventions`.
"""

__version__ = "0.1.0"
