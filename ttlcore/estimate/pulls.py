"""A fit against the truth: are its sigmas honest?

A simulation knows the true coefficients ``C_true``; a fit gives ``C`` with covariance
``Sigma``.  Two numbers say whether the errors ``e = C - C_true`` are as large as the sigmas
claim:

* the **pull RMS**, ``sqrt(mean((e_k / sigma_k)^2))``, the number the project's acceptance
  lists quote.  Its spread is wide: the 24 coefficients are correlated (a TDI channel
  sees sums and differences of them), so for honest sigmas ``pull_rms^2`` is a weighted sum
  ``(1/n) sum_i lambda_i chi^2_1`` with ``lambda_i`` the eigenvalues of the correlation matrix,
  not ``chi^2_n / n``.  On a lisainstrument day its central 95 % runs from about 0.64 to 1.42
  (measured from a live fit's covariance), so one day's 1.3 says little;
* the **errors' chi^2**, ``e^T Sigma^-1 e``, which is ``chi^2_n`` for honest sigmas
  whatever the correlations: its p-value is the test.

:func:`pull_summary` gives both, with the pull RMS's honest range from the fit's own
correlations (drawn from the eigenvalues of the fit's correlation matrix; checked against
draws of whole error vectors in ``tests/ttlcore/estimate/test_pulls.py``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import stats

__all__ = ["PullSummary", "pull_summary"]


@dataclass(frozen=True)
class PullSummary:
    """A fit's errors against the truth, and whether its sigmas are honest.

    Attributes
    ----------
    n : int
        Coefficients compared (those with a finite truth, value and sigma).
    max_abs_error : float
        ``max |C - C_true|`` [m/rad].
    pull_rms : float
        ``sqrt(mean((e / sigma)^2))``.
    pull_rms_range : (float, float) or None
        The central 95 % of the pull RMS for honest sigmas with the fit's correlations
        (None when not asked for).
    chi2 : float
        ``e^T Sigma^-1 e`` (``chi^2_n`` for honest sigmas).
    p_value : float
        ``P(chi^2_n >= chi2)``: small when the errors are larger than the covariance claims.
    """

    n: int
    max_abs_error: float
    pull_rms: float
    pull_rms_range: tuple[float, float] | None
    chi2: float
    p_value: float

    @property
    def verdict(self) -> str:
        """``"too small"`` (the sigmas understate the errors: the errors' chi^2 at p < 0.01,
        or the pull RMS above its 95 % range), ``"too large"`` (they overstate them: chi^2
        at p > 0.99, or the pull RMS below its range) or ``"honest"``."""
        lo, hi = self.pull_rms_range if self.pull_rms_range is not None else (0.0, np.inf)
        if self.p_value < 0.01 or self.pull_rms > hi:
            return "too small"
        if self.p_value > 0.99 or self.pull_rms < lo:
            return "too large"
        return "honest"

    @property
    def honest(self) -> bool:
        return self.verdict == "honest"

    def to_json(self) -> dict:
        out = asdict(self)
        out["pull_rms_range"] = None if self.pull_rms_range is None else list(self.pull_rms_range)
        out["verdict"] = self.verdict
        return out


#: Draws of the weighted chi^2 sum behind :func:`pull_rms_range` (its 2.5 % point to ~0.3 %).
DRAWS = 100_000


def pull_rms_range(correlation: np.ndarray, level: float = 0.95) -> tuple[float, float]:
    """Central ``level`` interval of the pull RMS for honest sigmas.

    ``pull_rms^2 = (1/n) z^T z`` with ``z ~ N(0, R)`` (``R`` the correlation matrix) is
    ``(1/n) sum_i lambda_i chi^2_1`` (``lambda_i`` the eigenvalues of ``R``; for ``R = I``
    it is ``chi^2_n / n``).  Its quantiles are taken from :data:`DRAWS` draws of that sum,
    with a fixed seed: the same covariance always gives the same range.
    """
    R = np.asarray(correlation, dtype=float)
    lam = np.clip(np.linalg.eigvalsh(R), 0.0, None)
    rng = np.random.default_rng(20261128)
    q = rng.chisquare(1.0, size=(DRAWS, lam.size)) @ lam / R.shape[0]
    lo, hi = np.quantile(q, [(1 - level) / 2, (1 + level) / 2])
    return float(np.sqrt(lo)), float(np.sqrt(hi))


def pull_summary(coefficients, covariance, truth, with_range: bool = True) -> PullSummary:
    """Errors of a fit against the truth, and the tests of its sigmas (module docstring).

    Parameters
    ----------
    coefficients : array_like (n,)
        Fitted coefficients [m/rad].
    covariance : array_like (n, n)
        Their covariance [m^2/rad^2].
    truth : array_like (n,)
        True coefficients [m/rad] over the fit's window (NaN: not known, left out).
    with_range : bool
        Compute the pull RMS's honest range (:func:`pull_rms_range`, ~0.3 s).

    Returns
    -------
    PullSummary

    Raises
    ------
    ValueError
        If the shapes disagree or no coefficient has a finite truth, value and sigma.
    """
    C = np.asarray(coefficients, dtype=float)
    cov = np.asarray(covariance, dtype=float)
    t = np.asarray(truth, dtype=float)
    if C.ndim != 1 or t.shape != C.shape or cov.shape != (C.size, C.size):
        raise ValueError(f"shapes disagree: coefficients {C.shape}, covariance {cov.shape}, truth {t.shape}")
    sigma = np.sqrt(np.diag(cov))
    ok = np.isfinite(C) & np.isfinite(t) & np.isfinite(sigma) & (sigma > 0)
    if not ok.any():
        raise ValueError("no coefficient with a finite truth, value and sigma")
    e, s, cv = (C - t)[ok], sigma[ok], cov[np.ix_(ok, ok)]
    chi2 = float(e @ np.linalg.solve(cv, e))
    return PullSummary(
        n=int(ok.sum()),
        max_abs_error=float(np.max(np.abs(e))),
        pull_rms=float(np.sqrt(np.mean((e / s) ** 2))),
        pull_rms_range=pull_rms_range(cv / np.outer(s, s)) if with_range else None,
        chi2=chi2,
        p_value=float(stats.chi2.sf(chi2, e.size)),
    )
