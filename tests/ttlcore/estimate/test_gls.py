"""The GLS engine (ttlcore.estimate.gls): its solution against a direct least-squares solve,
its covariance against the scatter of estimates, and the errors-in-variables term against
the attenuation bias it removes (analytic: a regressor read with noise of variance s2 per
complex bin has E[N] = N_true + n s2 I)."""

import warnings

import numpy as np
import pytest

from ttlcore.estimate.gls import NormalEquations, inverse, sandwich, sigma_ratio, solve


def normal_equations(X: np.ndarray, y: np.ndarray, E: np.ndarray | None = None) -> NormalEquations:
    """One band's statistics of whitened complex columns X (n, P) and data y (n,)."""
    P = X.shape[1]
    N = np.real(X.conj().T @ X)[None]
    b = np.real(X.conj().T @ y)[None]
    dd = np.array([np.real(np.vdot(y, y))])
    E = np.zeros((1, P, P)) if E is None else E[None]
    return NormalEquations(
        tuple(f"c{k}" for k in range(P)), np.array([1e-3, 1.0]), N, b, dd, E, np.array([len(y)]), nchan=1
    )


def complex_normal(rng, *shape, var=1.0):
    return np.sqrt(var / 2) * (rng.standard_normal(shape) + 1j * rng.standard_normal(shape))


def test_solution_equals_least_squares_and_covariance_is_the_scatter():
    rng = np.random.default_rng(1)
    n, P = 400, 5
    X = complex_normal(rng, n, P)
    theta_true = rng.standard_normal(P)
    estimates = []
    for trial in range(400):
        y = X @ theta_true + complex_normal(rng, n)  # unit-variance complex noise: whitened
        theta, cov = solve(normal_equations(X, y), eiv=False)
        if trial == 0:
            # the same minimiser of |y - X theta|^2 over real theta, by the real stacking
            A = np.concatenate([X.real, X.imag])
            direct = np.linalg.lstsq(A, np.concatenate([y.real, y.imag]), rcond=None)[0]
            np.testing.assert_allclose(theta, direct, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(cov, cov.T, rtol=0, atol=0)
        estimates.append(theta)
    scatter = np.cov(np.array(estimates).T)
    # Cov = (2 N)^-1 for complex noise of unit variance (E|n|^2 = 1: 1/2 per real part); the
    # sample covariance of 400 draws is within ~3 sqrt(2/400) = 21 % on its diagonal
    np.testing.assert_allclose(np.diag(scatter), np.diag(cov), rtol=0.25)


def test_errors_in_variables_removes_the_attenuation_bias():
    rng = np.random.default_rng(2)
    n, P, s2 = 2000, 3, 0.5  # readout noise variance per complex bin, half the signal's
    X = complex_normal(rng, n, P)
    theta_true = np.array([1.0, -0.5, 0.25])
    E = n * s2 * np.eye(P)  # E[Re U^H U] for U of variance s2 per element
    plain, corrected = [], []
    for _ in range(200):
        X_read = X + complex_normal(rng, n, P, var=s2)
        y = X @ theta_true + complex_normal(rng, n)
        neq = normal_equations(X_read, y, E)
        plain.append(solve(neq, eiv=False)[0])
        corrected.append(solve(neq, eiv=True)[0])
    # least squares shrinks by 1 / (1 + s2) = 2/3 (|X|^2 = 1 per element); the corrected
    # estimate is unbiased: mean of 200 within ~4 standard errors (~0.01 each)
    np.testing.assert_allclose(np.mean(plain, axis=0), theta_true / (1 + s2), atol=0.02)
    np.testing.assert_allclose(np.mean(corrected, axis=0), theta_true, atol=0.02)


def test_band_sums_are_additive():
    rng = np.random.default_rng(3)
    X, y = complex_normal(rng, 300, 4), complex_normal(rng, 300)
    a, b = normal_equations(X[:100], y[:100]), normal_equations(X[100:], y[100:])
    whole = normal_equations(X, y)
    total = a + b
    np.testing.assert_allclose(total.N, whole.N, rtol=1e-12)
    np.testing.assert_allclose((total - b).b, a.b, rtol=1e-9, atol=1e-12)
    assert total.nbins[0] == 300 and total.dof_per_band()[0] == 600
    C = solve(whole, eiv=False)[0]
    # chi^2 at the optimum: 2 (dd - b^T C), the whitened residual power
    r = y - X @ C
    assert whole.chi2_per_band(C)[0] == pytest.approx(2 * np.real(np.vdot(r, r)), rel=1e-9)


def test_a_regressor_without_information_is_fixed_at_zero_and_the_rest_unchanged():
    """A column that is zero over the whole window (a glitch's column before its time in a
    rolling window) has no information: coefficient 0, infinite variance, and the other
    coefficients and their covariance those of the model without it (to round-off)."""
    rng = np.random.default_rng(3)
    n, p = 400, 4
    X = rng.standard_normal((n, p))
    y = X @ np.array([1.0, -2.0, 0.5, 3.0]) + rng.standard_normal(n)
    X0 = np.column_stack([X[:, :2], np.zeros(n), X[:, 2:]])
    names = ("a", "b", "dead", "c", "d")
    full = NormalEquations(
        names,
        np.array([0.0, 1.0]),
        (X0.T @ X0)[None],
        (X0.T @ y)[None],
        np.array([y @ y]),
        np.zeros((1, 5, 5)),
        np.array([n]),
        1,
    )
    C, cov = solve(full, eiv=False)
    assert C[2] == 0.0 and np.isinf(cov[2, 2]) and np.all(cov[2, [0, 1, 3, 4]] == 0)
    ref = np.linalg.solve(X.T @ X, X.T @ y)
    keep = [0, 1, 3, 4]
    np.testing.assert_allclose(C[keep], ref, rtol=1e-12)
    np.testing.assert_allclose(cov[np.ix_(keep, keep)], np.linalg.inv(2 * X.T @ X), rtol=1e-12)


def test_collinear_regressors_are_undetermined_and_the_rest_unchanged():
    """Two identical columns (glitches on one test mass after their times: both a constant
    velocity step) leave their split undetermined: both get infinite variance, and the other
    coefficients are those of the model without them when the data hold nothing of them."""
    rng = np.random.default_rng(4)
    n = 400
    X = rng.standard_normal((n, 3))
    y = X @ np.array([1.0, -2.0, 0.5]) + rng.standard_normal(n)
    g = np.zeros(n)
    g[:5] = 1e-3 * rng.standard_normal(5)  # a column nearly without information ...
    X0 = np.column_stack([X, g, g])  # ... twice: collinear
    C, cov = solve(normal_equations(X0.astype(complex), y.astype(complex)), eiv=False)
    assert np.all(np.isinf(np.diag(cov)[3:])) and np.all(C[3:] == 0.0)
    np.testing.assert_allclose(C[:3], np.linalg.solve(X.T @ X, X.T @ y), rtol=1e-12)


def test_a_regressor_known_worse_than_its_prior_is_set_apart():
    """A column with a trace of information (a model's glitch whose FFT segments were all left
    out: only the velocity step after it remains, nearly cancelled by TDI) is fitted at a
    noise-driven value of any size; with prior scales, one whose standard deviation exceeds
    its prior's (analytic: sigma = 1 / sqrt(2 |g|^2) for an orthogonal column) is set apart -
    coefficient 0, infinite variance, the others those of the model without it - and a
    determined one keeps the plain solve's numbers exactly."""
    rng = np.random.default_rng(5)
    n = 400
    X = rng.standard_normal((n, 3))
    y = X @ np.array([1.0, -2.0, 0.5]) + rng.standard_normal(n)
    g = np.zeros(n)
    g[-3:] = 1e-4  # |g|^2 = 3e-8: sigma ~ 4e3 in the column's unit
    X0 = np.column_stack([X, g])
    neq = normal_equations(X0.astype(complex), y.astype(complex))
    plain, plain_cov = solve(neq, eiv=False)
    assert np.sqrt(plain_cov[3, 3]) > 1e3 and plain[3] != 0.0
    C, cov = solve(neq, eiv=False, prior_scale=np.array([np.inf, np.inf, np.inf, 1.0]))
    assert C[3] == 0.0 and np.isinf(cov[3, 3])
    np.testing.assert_allclose(C[:3], np.linalg.solve(X.T @ X, X.T @ y), rtol=1e-12)
    # a prior scale above the standard deviation: the plain solve, to the bit
    C2, cov2 = solve(neq, eiv=False, prior_scale=np.array([np.inf, np.inf, np.inf, 1e6]))
    assert np.array_equal(C2, plain) and np.array_equal(cov2, plain_cov)


def test_sigma_ratio_leaves_out_the_undetermined_parameters():
    """The robust-to-model sigma ratio of a normal matrix with one empty regressor: the
    median over the determined ones, by hand (N diagonal, so sandwich = M_kk / N_kk^2 and
    the ratio of parameter k is sqrt(M_kk / N_kk)); no warning from the inf/inf of the
    empty one (it used to give NaN and an 'invalid value' RuntimeWarning)."""
    N = np.diag([4.0, 1.0, 9.0, 0.0])
    M = np.diag([16.0, 4.0, 9.0, 0.0])
    cov_model = inverse(N)
    cov_robust = sandwich(N, M)
    assert np.isinf(cov_model[3, 3]) and np.isinf(cov_robust[3, 3])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ratio = sigma_ratio(cov_robust, cov_model)
    assert ratio == pytest.approx(np.median([2.0, 2.0, 1.0]), rel=1e-12)
    assert np.isnan(sigma_ratio(np.diag([np.inf]), np.diag([np.inf])))
