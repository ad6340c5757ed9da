"""Figures (matplotlib, imported inside the functions): the batch analysis's paper-style
figures (``batch``), the diagnosis figures (``diagnosis``, ``transients``) and those of the
paper's scenarios (``scenarios``).
"""

from .batch import plot_asd_x, plot_coefficients
from .diagnosis import plot_residual_vs_noise, plot_witness_coherence
from .transients import plot_time_frequency

__all__ = [
    "plot_asd_x",
    "plot_coefficients",
    "plot_residual_vs_noise",
    "plot_time_frequency",
    "plot_witness_coherence",
]
