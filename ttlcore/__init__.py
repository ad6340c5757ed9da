"""ttlcore: the science of tilt-to-length (TTL) noise subtraction for LISA.

Plain functions and small dataclasses, numpy arrays in and out, usable from a notebook::

    import ttlcore
    tm, truth = ttlcore.simulate(ttlcore.SimulationConfig(duration=6 * 3600, orbit="keplerian"))
    td = ttlcore.compute_tdi(tm)                 # X2, Y2, Z2 of eta and of the 24 regressors
    fit, _ = ttlcore.fit_tdi(td)                 # GLS with errors in variables
    fit.coefficients, fit.sigma                  # m/rad

The sub-packages follow the data flow: :mod:`ttlcore.io` (files) -> :mod:`ttlcore.sim`
(simulated telemetry) -> :mod:`ttlcore.tdi` (TDI of the data and the regressors) ->
:mod:`ttlcore.estimate` (spectra, fit, subtraction) -> :mod:`ttlcore.diagnose` (the model
against the measurement); :mod:`ttlcore.gw` holds the gravitational-wave sources,
:mod:`ttlcore.plots` the figures and :mod:`ttlcore.cli` the science commands of ``ttl``.
Conventions (indices, units, signs: ``docs/physics.md``) live in :mod:`ttlcore.conventions`.
"""

__version__ = "0.1.0"

from .conventions import COEFFICIENT_NAMES, LINKS, MOSAS
from .diagnose.diagnoser import diagnose, refit, text_report
from .diagnose.effects import make_effects
from .errors import ConfigError, TelemetryError, TTLError
from .estimate.fit import FitResult, FitSettings, fit_tdi
from .estimate.rolling import RollingFit
from .estimate.subtraction import residual_aet, subtract
from .io.telemetry import Telemetry, write_telemetry
from .io.reader import read_telemetry
from .io.truth import Truth, read_truth
from .sim.simulator import SimulationConfig, simulate
from .tdi.data import TDIData, compute_tdi

__all__ = [
    "COEFFICIENT_NAMES", "LINKS", "MOSAS",
    "Telemetry", "read_telemetry", "write_telemetry", "Truth", "read_truth",
    "SimulationConfig", "simulate",
    "TDIData", "compute_tdi",
    "FitSettings", "FitResult", "fit_tdi", "RollingFit", "subtract", "residual_aet",
    "diagnose", "refit", "text_report", "make_effects",
    "TTLError", "TelemetryError", "ConfigError",
]
