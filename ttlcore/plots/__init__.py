"""Figures (matplotlib): the batch analysis's paper-style figures and the diagnosis figure.
Imported only where figures are drawn.
"""

__all__ = ["batch", "diagnosis"]
