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
against the measurement); :mod:`ttlcore.effects` holds the model effects (fitted by the
diagnosis, injected by the simulator), :mod:`ttlcore.gw` the gravitational-wave sources,
:mod:`ttlcore.plots` the figures, :mod:`ttlcore.app` the commands' work (analysis,
reprocessing, scenarios) and :mod:`ttlcore.cli` the science commands of ``ttl``; they stand on
floors, each importing only its own and those below (``docs/architecture.md``).
Conventions (indices, units, signs: ``docs/physics.md``) live in :mod:`ttlcore.conventions`.
"""

from ._lazy import lazy_face
from ._version import __version__ as __version__  # one place for the version (re-exported)

#: where each name of the notebook API lives; imported on first use (PEP 562) so that
#: ``import ttlcore.cli...`` or ``ttlcore.conventions`` does not pull in scipy and the whole
#: science stack (``ttl --help`` must start in well under a second)
_EXPORTS = {
    "COEFFICIENT_NAMES": "conventions",
    "LINKS": "conventions",
    "MOSAS": "conventions",
    "make_effects": "effects",
    "ConfigError": "errors",
    "TelemetryError": "errors",
    "TTLError": "errors",
    "FitResult": "estimate.fit",
    "FitSettings": "estimate.fit",
    "fit_tdi": "estimate.fit",
    "RollingFit": "estimate.rolling",
    "residual_aet": "estimate.subtraction",
    "subtract": "estimate.subtraction",
    "Telemetry": "io.telemetry",
    "write_telemetry": "io.telemetry",
    "read_telemetry": "io.reader",
    "Truth": "io.truth",
    "read_truth": "io.truth",
    "SimulationConfig": "sim.simulator",
    "simulate": "sim.simulator",
    "TDIData": "tdi.data",
    "compute_tdi": "tdi.data",
}


#: the sub-packages, each with a small face of its own (``from ttlcore.diagnose import diagnose``);
#: ``ttlcore.diagnose`` is the sub-package, imported on first use like the names above
_SUBPACKAGES = ("io", "sim", "effects", "tdi", "estimate", "diagnose", "gw", "plots", "app", "cli")

__getattr__, __dir__ = lazy_face(__name__, _EXPORTS | {name: name for name in _SUBPACKAGES}, globals())

__all__ = [
    "COEFFICIENT_NAMES",
    "LINKS",
    "MOSAS",
    "Telemetry",
    "read_telemetry",
    "write_telemetry",
    "Truth",
    "read_truth",
    "SimulationConfig",
    "simulate",
    "TDIData",
    "compute_tdi",
    "FitSettings",
    "FitResult",
    "fit_tdi",
    "RollingFit",
    "subtract",
    "residual_aet",
    "make_effects",
    "TTLError",
    "TelemetryError",
    "ConfigError",
]
