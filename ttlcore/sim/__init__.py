"""The eta-level mission simulator and what it draws on.

``simulator`` (the mission), ``noise`` (stationary Gaussian noise of any ASD, random access),
``noise_models`` (the analytic ASDs), ``orbits`` (light travel times), ``coefficients``
(TTL coefficient sets and their time variation), ``injection`` (effects injected for tests)
and ``spec`` (a simulation described by the options of ``ttl simulate``).
"""

__all__ = ["coefficients", "injection", "noise", "noise_models", "orbits", "simulator", "spec"]
