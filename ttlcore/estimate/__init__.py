"""Estimation: spectra, the noise CSD models, the GLS fit with errors in variables, the rolling
fit, the emcee sampler, the subtraction, the batch analysis of a file and what a monitor of
the subtraction computes (noise curves of a segment, the truth over a fit's window).
"""

__all__ = ["analyze", "fit", "mcmc", "monitoring", "noise_psd", "rolling", "spectra", "subtraction"]
