"""Time-delay interferometry: fractional delays, second-generation combinations, the TDI of the
data and of the 24 TTL regressors.

``interpolation`` (Lagrange delays), ``combinations`` (X2, Y2, Z2, A, E, T as values built into
callables), ``engine`` (the one TDI evaluator: series placed on links, in blocks with their
history), ``regressors`` (DWS witnesses placed on their links) and ``data`` (TDI of telemetry,
batch and streaming).

::

    from ttlcore.tdi import aet, compute_tdi
    td = compute_tdi(tm)                   # X2, Y2, Z2 of eta and of the 24 regressors
    a, e, t = aet(td.data)

The names below are imported on first use, so that a light module under this package does not
import the engine and scipy.
"""

from .._lazy import lazy_face

#: name -> module it lives in
_EXPORTS = {
    "TDIData": "data",
    "TDIStream": "data",
    "compute_tdi": "data",
    "AET": "combinations",
    "MICHELSON": "combinations",
    "Combination": "combinations",
    "aet": "combinations",
    "build": "combinations",
    "timeshift": "interpolation",
    "regressor_responses": "regressors",
    "ttl_witnesses": "regressors",
}
__getattr__, __dir__ = lazy_face(__name__, _EXPORTS, globals())

__all__ = list(_EXPORTS)
