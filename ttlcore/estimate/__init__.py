"""Estimation: spectra, the noise CSD models, the GLS fit with errors in variables, the rolling
fit, the emcee sampler, the subtraction and what a monitor of the subtraction computes
(noise curves of a segment, the truth over a fit's window).  The batch analysis of a file
(``ttl analyze``) is :mod:`ttlcore.app.analysis`.

::

    from ttlcore.estimate import FitSettings, fit_tdi, residual_aet
"""

from .fit import FitResult, FitSettings, dws_asd_from_config, fit_tdi
from .mcmc import fit_mcmc
from .rolling import RollingFit
from .subtraction import residual_aet, subtract

__all__ = [
    "FitResult",
    "FitSettings",
    "RollingFit",
    "dws_asd_from_config",
    "fit_mcmc",
    "fit_tdi",
    "residual_aet",
    "subtract",
]
