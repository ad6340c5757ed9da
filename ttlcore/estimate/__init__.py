"""Estimation: spectra, the noise CSD models, the GLS fit with errors in variables, the rolling
fit, the emcee sampler, the subtraction and the batch analysis of a file.
"""

__all__ = ['analyze', 'fit', 'mcmc', 'noise_psd', 'rolling', 'spectra', 'subtraction']
