"""The sigma-honesty tests of a fit against the truth (ttlcore.estimate.pulls), against draws."""

import numpy as np
import pytest
from scipy import stats

from ttlcore.estimate.pulls import pull_rms_range, pull_summary


def _correlated(n: int = 24, seed: int = 3) -> np.ndarray:
    """A covariance with strong correlations (a few common modes, as TDI sums of coefficients
    make) and sigmas spread over a decade [m/rad]."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, 4))
    corr = A @ A.T + 0.3 * np.eye(n)
    d = 1.0 / np.sqrt(np.diag(corr))
    sig = 1e-5 * 10 ** rng.uniform(0, 1, n)
    return (corr * np.outer(d, d)) * np.outer(sig, sig)


def test_the_range_is_chi2_n_over_n_without_correlations():
    lo, hi = pull_rms_range(np.eye(24))
    q = stats.chi2.ppf([0.025, 0.975], 24) / 24
    # 100,000 draws: the 2.5 % point to ~0.3 % (1 sigma); 1 %
    np.testing.assert_allclose([lo, hi], np.sqrt(q), rtol=0.01)


def test_the_range_with_correlations_matches_draws():
    """20,000 draws of honest errors: the 2.5 % and 97.5 % points of their pull RMS against
    the range drawn from the correlation matrix's eigenvalues (a different route: whole
    correlated vectors against independent chi^2_1 weighted by eigenvalues).  The 2.5 %
    point of 20,000 draws is known to ~1 % (its binomial error through the density there):
    2.5 %.  The range is much wider than ``chi^2_24 / 24``'s: correlations matter."""
    cov = _correlated()
    sig = np.sqrt(np.diag(cov))
    rng = np.random.default_rng(4)
    e = rng.multivariate_normal(np.zeros(24), cov, size=20000)
    drawn = np.quantile(np.sqrt(np.mean((e / sig) ** 2, axis=1)), [0.025, 0.975])
    lo, hi = pull_rms_range(cov / np.outer(sig, sig))
    np.testing.assert_allclose([lo, hi], drawn, rtol=0.025)
    assert hi - lo > 2 * np.diff(np.sqrt(stats.chi2.ppf([0.025, 0.975], 24) / 24))[0]


def test_honest_errors_pass_and_understated_sigmas_fail():
    """2,000 fits with honest covariance: the errors' chi^2 p-value is uniform (5.0 % below
    0.05, +-1 % at 2 sigma of a binomial of 2,000); the same errors with sigmas claimed 2x
    too small fail at p < 0.01 nearly always (chi^2 = 4 chi^2_24: 99 %)."""
    cov = _correlated(seed=5)
    rng = np.random.default_rng(6)
    truth = rng.normal(0, 2e-3, 24)
    draws = rng.multivariate_normal(np.zeros(24), cov, size=2000)
    honest = [pull_summary(truth + e, cov, truth, with_range=False) for e in draws]
    below = np.mean([s.p_value < 0.05 for s in honest])
    assert abs(below - 0.05) < 0.01, below
    # with the range (0.3 s each): 10 draws, ~93 % expected honest (0.01 <= p <= 0.99, in range;
    # 7 or more of 10: binomial tail 3e-3)
    assert sum(pull_summary(truth + e, cov, truth).honest for e in draws[:10]) >= 7
    short = [pull_summary(truth + e, cov / 2.0**2, truth, with_range=False) for e in draws[:200]]
    assert np.mean([s.p_value < 0.01 for s in short]) > 0.95
    s = honest[0]
    assert s.n == 24 and s.max_abs_error == pytest.approx(np.max(np.abs(draws[0])))
    assert s.pull_rms_range is None and s.to_json()["pull_rms_range"] is None
    full = pull_summary(truth + draws[0], cov, truth)
    assert full.to_json()["pull_rms_range"] == list(full.pull_rms_range)


def test_unknown_truth_is_left_out_and_bad_shapes_are_refused():
    cov = _correlated(seed=7)
    C = np.zeros(24)
    truth = np.full(24, 1e-5)
    truth[3] = np.nan
    assert pull_summary(C, cov, truth).n == 23
    with pytest.raises(ValueError, match="shapes"):
        pull_summary(C[:5], cov, truth)
    with pytest.raises(ValueError, match="no coefficient"):
        pull_summary(C, cov, np.full(24, np.nan))
