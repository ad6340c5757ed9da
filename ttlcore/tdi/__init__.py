"""Time-delay interferometry: fractional delays, second-generation combinations, the TDI of the
data and of the 24 TTL regressors.

``interpolation`` (Lagrange delays), ``combinations`` (X2, Y2, Z2, A, E, T as values built into
callables), ``engine`` (the one TDI evaluator: series placed on links, in blocks with their
history), ``regressors`` (DWS witnesses placed on their links) and ``data`` (TDI of telemetry,
batch and streaming).
"""

__all__ = ["combinations", "data", "engine", "interpolation", "regressors"]
