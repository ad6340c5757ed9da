"""Evidence for adding parameters to a linear-Gaussian model: the exact log Bayes factor.

Used by the diagnosis to rank candidate effects (docs/diagnostics.md, "Which effect is
missing") and by the profile search to score searched effects.
"""

from __future__ import annotations

import numpy as np

__all__ = ["log_bayes_factor"]


def log_bayes_factor(A: np.ndarray, beta: np.ndarray, prior_scale: np.ndarray) -> float:
    """Exact log Bayes factor of adding parameters ``beta`` to a linear-Gaussian model.

    With the other parameters marginalised under a flat prior, the likelihood of the new
    parameters is Gaussian with precision ``A`` (the Schur complement of the Fisher matrix)
    around ``beta``; with the prior ``N(0, D)``, ``D = diag(prior_scale^2)``,

        log B = -1/2 log det(I + D^1/2 A D^1/2)
                + 1/2 [beta^T A beta - beta^T A (I + D A)^-1 beta].

    ``beta^T A beta`` is the delta chi^2.  Positive values favour the larger model.
    """
    d = np.asarray(prior_scale, dtype=float)
    k = beta.size
    M = np.eye(k) + d[:, None] * A * d[None, :]
    sign, logdet = np.linalg.slogdet(M)
    if sign <= 0:
        return float("nan")
    q1 = beta @ A @ beta
    q2 = beta @ A @ np.linalg.solve(np.eye(k) + (d ** 2)[:, None] * A, beta)
    return float(-0.5 * logdet + 0.5 * (q1 - q2))
