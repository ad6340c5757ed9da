"""MCMC over the GLS likelihood (ttlcore.estimate.mcmc) against independent sources: the analytic
Gaussian posterior of a linear model, simulated complex-Gaussian data with known noise
levels, the GLS fit on simulated LISA data, and emcee's own autocorrelation estimator.

Monte-Carlo tolerances: with ``n_ind`` independent samples (about 5000 here: 96 walkers
times 50 autocorrelation times, less the burn-in) a posterior mean is known to
``sigma / sqrt(n_ind) ~ 0.015 sigma`` and a standard deviation to ``1 / sqrt(2 n_ind) ~ 1 %``;
the maximum over 24 parameters stays below about 3 of those.  The 0.1 sigma and 10 %
tolerances are therefore more than 5 Monte-Carlo standard errors, loose enough never to
flake and tight enough to catch a wrong factor of kappa, of 2, or a missing E term.
"""

import json
import logging

import emcee
import numpy as np
import pytest

from ttlcore.estimate.fit import (
    FitSettings,
    NormalEquations,
    SegmentSpectra,
    accumulate,
    default_band_edges,
    fit_tdi,
)
from ttlcore.estimate.mcmc import McmcResult, fit_mcmc, integrated_time, sample
from ttlcore.sim.simulator import SimulationConfig, simulate
from ttlcore.tdi.data import compute_tdi

P, G = 24, 8
NAMES = tuple(f"c{k}" for k in range(P))


def linear_problem(seed: int, kappa: float = 1.0):
    """Normal equations of a random, well-conditioned linear-Gaussian problem with
    coefficient scales of ~1e-3 (m/rad-like) and correlated columns, plus a small
    positive errors-in-variables term; returns (neq, analytic mean, analytic covariance)."""
    rng = np.random.default_rng(seed)
    scale = np.diag(1e3 * rng.uniform(0.5, 2.0, P))  # coefficients ~1e-3
    mix = np.eye(P) + 0.3 * rng.standard_normal((P, P)) / np.sqrt(P)  # correlated columns
    A = rng.standard_normal((G, 300, P)) @ mix @ scale
    N = np.einsum("gkp,gkq->gpq", A, A)
    B = rng.standard_normal((G, 30, P)) @ scale
    E = 0.2 * np.einsum("gkp,gkq->gpq", B, B)
    c_true = 1e-3 * rng.uniform(-2, 2, P)
    b = np.einsum("gpq,q->gp", N - E, c_true) + np.einsum("gkp,gk->gp", A, rng.standard_normal((G, 300)))
    neq = NormalEquations(NAMES, default_band_edges(), N, b, np.full(G, 1e5), E, np.full(G, 1000), 3)
    Np = (N - E).sum(axis=0)
    mean = np.linalg.solve(Np, b.sum(axis=0))
    cov = kappa * np.linalg.inv(2 * Np)
    return neq, mean, cov


def test_linear_gaussian_posterior_matches_analytic():
    # Flat prior, log L = -(1/kappa) sum_g Q_g: the posterior is exactly N((N-E)^-1 b, kappa (2(N-E))^-1).
    kappa = 1.7
    neq, mean, cov = linear_problem(1, kappa)
    res = sample(neq, eiv=True, kappa=kappa, seed=3)
    assert isinstance(res, McmcResult)
    sig = np.sqrt(np.diag(cov))
    assert res.converged and res.n_steps >= 50 * np.max(res.autocorr_time)
    assert res.n_independent > 2000
    assert np.max(np.abs(res.coefficients - mean) / sig) < 0.1
    assert np.max(np.abs(res.sigma / sig - 1)) < 0.10
    # correlations (MC error (1 - rho^2) / sqrt(n_ind) ~ 0.015)
    corr = cov / np.outer(sig, sig)
    assert np.max(np.abs(res.covariance / np.outer(res.sigma, res.sigma) - corr)) < 0.08
    assert res.samples.shape[1] == P and res.samples.shape[0] == res.log_prob.shape[0]
    assert 0.15 < res.acceptance_fraction < 0.5
    assert res.noise_levels is None
    # without the EIV term the posterior is centred on N^-1 b instead: the sampler uses E
    mean_no_e = np.linalg.solve(neq.N.sum(0), neq.b.sum(0))
    assert np.max(np.abs(mean_no_e - mean) / sig) > 1.0


def complex_gaussian_problem(seed: int, lam_true: np.ndarray, bins_per_band: int = 1000):
    """Complex-Gaussian data ``d = R C + n``, ``n ~ CN(0, lambda_g I)`` in band g, reduced
    with :func:`ttlcore.estimate.fit.accumulate` and unit weights (so the likelihood is exactly the
    model's, kappa = 1)."""
    rng = np.random.default_rng(seed)
    edges = default_band_edges()
    m = G * bins_per_band
    # bins_per_band log-spaced frequencies inside each band
    f = np.concatenate([np.geomspace(lo, hi, bins_per_band + 2)[1:-1] for lo, hi in zip(edges[:-1], edges[1:])])
    band = np.repeat(np.arange(G), bins_per_band)

    def cn(*shape):
        return (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) / np.sqrt(2)

    R = 1e3 * cn(m, 3, P)
    c_true = 1e-3 * rng.uniform(-2, 2, P)
    d = R @ c_true + np.sqrt(lam_true[band])[:, None] * cn(m, 3)
    sp = SegmentSpectra(t0=0.0, duration=1.0, f=f, d=d, R=R)
    neq = accumulate([sp], np.broadcast_to(np.eye(3), (m, 3, 3)), edges, NAMES)
    assert np.all(neq.nbins == bins_per_band)
    return neq, c_true


def test_noise_levels_recovered_on_data_with_known_noise():
    # Each band's noise scale is known; its posterior (inverse-gamma like, relative width
    # 1 / sqrt(3 * 1000 - 2) = 1.8 %) must contain it, and its width must be the analytic one.
    lam_true = np.array([0.5, 0.8, 1.0, 1.0, 1.2, 2.0, 1.0, 0.9])
    neq, c_true = complex_gaussian_problem(4, lam_true)
    res = sample(neq, eiv=False, kappa=1.0, noise_levels=True, seed=1)
    assert res.converged
    assert res.samples.shape[1] == P + G and res.names[P:] == tuple(f"noise_level.{g}" for g in range(G))
    n_g = 3 * neq.nbins
    rel_width = 1 / np.sqrt(n_g - 2.0)
    pull = (res.noise_levels - lam_true) / res.noise_levels_std
    assert np.max(np.abs(pull)) < 3.5, pull  # 8 bands: |pull| > 3.5 has probability 0.4 %
    assert np.max(np.abs(res.noise_levels / lam_true - 1)) < 0.065  # "a few percent": 3.5 x 1.8 %
    assert np.max(np.abs(res.noise_levels_std / res.noise_levels / rel_width - 1)) < 0.10
    # coefficients: chi^2 of the truth against the posterior, 24 dof (p(> 55) ~ 3e-4)
    err = res.coefficients - c_true
    assert err @ np.linalg.solve(res.covariance, err) < 55
    # coefficient covariance = (2 sum_g N_g / lambda_g)^-1 at the noise levels (their
    # uncertainty, 1.8 %, barely widens it)
    cov = np.linalg.inv(2 * np.einsum("gpq,g->pq", neq.N, 1 / res.noise_levels))
    assert np.max(np.abs(res.sigma / np.sqrt(np.diag(cov)) - 1)) < 0.10


def test_same_seed_same_samples():
    neq, _, _ = linear_problem(2)
    calls = []
    a = sample(neq, seed=7, n_autocorr=10, progress=lambda *args: calls.append(args))
    assert calls and calls[-1][0] == a.n_steps and calls[-1][0] >= calls[-1][2]  # (steps, max tau, target)
    b = sample(neq, seed=7, n_autocorr=10)
    c = sample(neq, seed=8, n_autocorr=10)
    assert np.array_equal(a.samples, b.samples) and np.array_equal(a.log_prob, b.log_prob)
    assert a.n_steps == b.n_steps and np.array_equal(a.autocorr_time, b.autocorr_time)
    assert not np.array_equal(a.samples[: len(c.samples)], c.samples[: len(a.samples)])


def test_not_converged_when_max_steps_too_small(caplog):
    neq, _, _ = linear_problem(3)
    with caplog.at_level(logging.WARNING, logger="ttlcore.estimate.mcmc"):
        res = sample(neq, seed=0, max_steps=300)
    assert not res.converged and res.n_steps == 300
    assert "not converged" in caplog.text


def test_autocorrelation_time_matches_emcee_and_ar1():
    # AR(1) chains x_t = a x_{t-1} + e_t have tau = (1 + a) / (1 - a) = 19 for a = 0.9.
    rng = np.random.default_rng(0)
    a, n = 0.9, 4000
    e = rng.standard_normal((n, 32, 3))
    x = np.empty_like(e)
    x[0] = e[0] / np.sqrt(1 - a * a)
    for t in range(1, n):
        x[t] = a * x[t - 1] + e[t]
    ours = integrated_time(x)
    ref = emcee.autocorr.integrated_time(x, tol=0)
    assert np.allclose(ours, ref, rtol=1e-10)
    assert np.allclose(ours, (1 + a) / (1 - a), rtol=0.1)


# ---------------------------------------------------------------------------
# Simulated LISA data: against the GLS fit
# ---------------------------------------------------------------------------


def batch_standard_error(x: np.ndarray, nwalkers: int, n_batches: int = 16) -> np.ndarray:
    """Standard error of the mean of samples ``x`` (steps * walkers, D), stored step-major,
    from the scatter of the means of ``n_batches`` runs of consecutive steps."""
    x = x.reshape(-1, nwalkers, x.shape[-1])
    k = x.shape[0] // n_batches
    means = x[: k * n_batches].reshape(n_batches, k * nwalkers, -1).mean(axis=1)
    return means.std(axis=0, ddof=1) / np.sqrt(n_batches)


@pytest.fixture(scope="module")
def six_hours():
    tm, _ = simulate(SimulationConfig(duration=6 * 3600, orbit="unequal", seed=11))
    td = compute_tdi(tm)
    settings = FitSettings(segment_duration=3600)
    gls, internals = fit_tdi(td, settings)
    return td, settings, gls, internals["spectra"]


def test_mcmc_agrees_with_gls_on_simulated_data(six_hours):
    # Same likelihood: posterior mean = GLS estimate, covariance = GLS model-based covariance
    # kappa (2 (N - E))^-1 (not the robust sandwich one, which the likelihood does not know).
    td, settings, gls, spectra = six_hours
    res, internals = fit_mcmc(spectra, td.ltt_mean, settings, td.names, seed=5)
    assert res.method == "mcmc" and res.names == gls.names
    sig = np.sqrt(np.diag(np.asarray(gls.extra["covariance_model_based"])))
    assert np.max(np.abs(res.coefficients - gls.coefficients) / sig) < 0.1
    assert np.max(np.abs(res.sigma / sig - 1)) < 0.10
    assert res.extra["converged"] is True and res.converged
    assert res.extra["n_independent"] > 2000
    assert res.extra["n_steps"] >= 50 * max(res.extra["autocorr_time"].values())
    assert np.allclose(list(res.extra["gls_coefficients"].values()), gls.coefficients)
    # chi^2 at the posterior mean: the GLS minimum plus 2 d^T (N - E) d = kappa |d / sigma|^2 for
    # the Monte-Carlo offset d, about 24 kappa / n_independent ~ 0.005
    assert res.chi2 >= gls.chi2 * (1 - 1e-12) and res.chi2 - gls.chi2 < 0.1
    assert internals["mcmc"].noise_levels is None
    json.dumps(res.to_json())  # serialisable as fit.json


def test_noise_levels_on_simulated_data_match_gls_chi2_per_band(six_hours):
    # The GLS's final weights are the residual CSD smoothed over +-2.2 mHz; what is left per
    # band is chi2_g / dof_g, about 0.5 to 1 here rather than 1 (measured: the analytic
    # noise model gives 0.94-1.01 in the mid bands, a +-2 bin smoothing 0.95-0.98; a wide
    # running mean over a steep or notched spectrum overestimates the noise, most in the
    # lowest band where +-2.2 mHz is comparable to f).  lambda_g measures exactly that:
    # given C its posterior mode is Q_g(C) / n_g = chi2_g / dof_g; the posterior mean
    # differs by the inverse-gamma mode-to-mean offset (kappa / n_g) and by the small
    # coefficient shift the noise levels bring, both well below a quarter of the posterior
    # width sqrt(kappa / n_g).
    td, settings, gls, spectra = six_hours
    res, internals = fit_mcmc(spectra, td.ltt_mean, settings, td.names, noise_levels=True, seed=6)
    mc = internals["mcmc"]
    neq = internals["normal_equations"]
    kappa = res.extra["variance_factor"]
    assert mc.converged
    n_g = neq.nchan * neq.nbins
    chi2_dof = gls.chi2_per_band / gls.dof_per_band
    width = np.sqrt(kappa / n_g)
    assert np.all(np.abs(mc.noise_levels / chi2_dof - 1) < 0.25 * width), (mc.noise_levels, chi2_dof)
    # inverse-gamma width (shape n_g / kappa): relative std 1 / sqrt(n_g / kappa - 2)
    assert np.max(np.abs(mc.noise_levels_std / mc.noise_levels * np.sqrt(n_g / kappa - 2) - 1)) < 0.10
    # Rao-Blackwell: E[lambda_g] = E_C[Q_g(C)] / (n_g - kappa) exactly (lambda_g | C is
    # inverse-gamma with shape n_g / kappa and scale Q_g(C) / kappa).  Monte-Carlo error of
    # the mean difference from 16 batches of consecutive steps (which, unlike
    # std / sqrt(n_independent), includes the correlation between walkers): |t_15| < 5.
    C = mc.samples[:, :24]
    Q = np.einsum("np,gpq,nq->ng", C, neq.N - neq.E, C) - 2 * C @ neq.b.T + neq.dd
    diff = mc.samples[:, 24:] - Q / (n_g - kappa)
    assert np.all(np.abs(diff.mean(axis=0)) < 5 * batch_standard_error(diff, mc.nwalkers))
    assert res.extra["noise_levels"]["mean"] == pytest.approx(list(mc.noise_levels))
    json.dumps(res.to_json())
