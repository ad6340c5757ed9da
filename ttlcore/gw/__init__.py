"""Gravitational-wave sources and the paper's scenarios.

``response`` (the link response to a plane wave), ``sources`` (verification binaries, MBHBs,
background, galaxy), ``galaxy``, ``sgwb``, ``mbhb`` (the models), ``injection`` (sources added
to the simulated links) and ``scenarios`` (the paper's cases with and without GW).
"""

__all__ = ["galaxy", "injection", "mbhb", "response", "scenarios", "sgwb", "sources"]
