"""The engine of the diagnosis (ttlcore.diagnose.model_fit.solve) on a tiny synthetic problem,
against numpy.linalg.lstsq on the whitened system built here another way.

The problem: S = 2 segments, m = 24 bins in G = 2 bands, A, E, T, three real parameters, a
random Hermitian positive-definite noise CSD per bin, columns without errors in variables.
The engine whitens with ``L^H`` (``S^-1 = L L^H``, Cholesky of the inverse CSD); the
reference whitens with ``C^-1`` (``S = C C^H``, Cholesky of the CSD itself): a different
matrix, the same ``W^H W = S^-1``, so the same GLS.  The GLS of real parameters on complex
spectra is the least-squares fit of the real and imaginary parts stacked.

The values are built directly from the small parts of a
:class:`~ttlcore.diagnose.whitened.WhitenedData` (no telemetry, no TDI).
"""

import numpy as np
import pytest

from ttlcore.diagnose.columns import ColumnSet
from ttlcore.diagnose.model_fit import solve
from ttlcore.diagnose.settings import DiagnoseSettings
from ttlcore.diagnose.whitened import (
    AnalysisGrid,
    DiagnosisContext,
    MeasuredTDI,
    WhitenedData,
    Whitening,
    noise_digest,
    whitening,
)
from ttlcore.tdi.data import TDIData

S, M, P, L = 2, 24, 3, 48
KAPPA = 1.25  # any variance factor: the covariance scales with it


def _problem(seed: int = 11):
    rng = np.random.default_rng(seed)
    f = np.linspace(0.01, 0.2, M)
    # a random Hermitian positive-definite CSD per bin (well conditioned: identity + a small part)
    B = rng.normal(size=(M, 3, 3)) + 1j * rng.normal(size=(M, 3, 3))
    csd = 1e-3 * (np.eye(3) + 0.3 * B @ np.conj(np.swapaxes(B, -1, -2)))
    R = rng.normal(size=(S, M, 3, P)) + 1j * rng.normal(size=(S, M, 3, P))  # raw column spectra
    theta_true = np.array([0.5, -1.5, 2.0])
    noise = np.linalg.cholesky(csd) @ (rng.normal(size=(S, M, 3, 1)) + 1j * rng.normal(size=(S, M, 3, 1)))
    d = R @ theta_true + noise[..., 0]  # raw data spectra (S, m, 3)
    return f, csd, R, d


def _whitened_data(f, csd, d) -> WhitenedData:
    G = 2
    band_index = np.repeat(np.arange(G), M // G)
    grid = AnalysisGrid(
        decimation=1,
        fs_in=1.0,
        t0_in=0.0,
        fs=1.0,
        t0=0.0,
        mask=np.ones(S * L, dtype=bool),
        L=L,
        starts=tuple(range(0, S * L, L)),
        seg_t0=np.arange(S) * float(L),
        seg_duration=float(L),
        win=np.ones(L),
        f=f,
        bins=np.arange(M),
        edges=np.array([f[0], f[M // G], f[-1] + 1e-3]),
        G=G,
        band_index=band_index,
        slices=((0, M // G), (M // G, M)),
        kappa=KAPPA,
        w2=np.full((S, L), 1.0 / L),
    )
    tdi = MeasuredTDI(
        td_in=TDIData(0.0, 1.0, ("A", "E", "T"), np.zeros((3, S * L)), np.zeros((3, 0, S * L)), names=()),
        data_series=np.zeros((3, S * L)),
        d=d,
        regressor_names=(),
        regressor_series=np.zeros((3, 0, S * L)),
        ttl_names=(),
        ltt_mean=np.full(6, 8.3),
        dws_asd=0.0,
    )
    Lh = whitening(csd)
    wd = np.matmul(Lh, d[..., None])[..., 0]
    dd = np.stack([np.sum(np.abs(wd[:, a:b]) ** 2, axis=(1, 2)) for a, b in grid.slices], axis=1)
    noise = Whitening(csd=csd, Lh=Lh, key=noise_digest(csd), wd=wd, dd=dd)
    context = DiagnosisContext(settings=DiagnoseSettings(), tm=None, effect_modules=(), registry={})
    return WhitenedData(grid=grid, tdi=tdi, noise=noise, context=context)


def _columns(data: WhitenedData, R) -> ColumnSet:
    w = data.noise.whiten(R)  # (S, m, 3, P)
    x = np.stack([np.ascontiguousarray(w[..., k]) for k in range(P)]).view(np.float64)
    return ColumnSet(("a", "b", "c"), x, data.noise.key, ("",) * P, (1.0,) * P, ((),) * P, (None,) * P)


def _reference_system(csd, R, d):
    """The whitened system with ``W = C^-1``, ``S = C C^H``: rows (s, m, channel), real and
    imaginary parts stacked."""
    W = np.linalg.inv(np.linalg.cholesky(csd))  # (m, 3, 3)
    A = np.matmul(W, R)  # (S, m, 3, P)
    y = np.matmul(W, d[..., None])[..., 0]  # (S, m, 3)
    return A, y


def test_solve_is_the_least_squares_fit_of_the_whitened_system():
    f, csd, R, d = _problem()
    data = _whitened_data(f, csd, d)
    fit = solve(data, _columns(data, R))
    A, y = _reference_system(csd, R, d)
    Ar = np.concatenate([A.real.reshape(-1, P), A.imag.reshape(-1, P)])
    yr = np.concatenate([y.real.reshape(-1), y.imag.reshape(-1)])
    theta, *_ = np.linalg.lstsq(Ar, yr, rcond=None)
    # a 3-parameter problem of condition ~10 in double precision: both solutions agree to
    # ~1e-14; 1e-10 leaves room for the different factorisations (Cholesky of S vs of S^-1)
    np.testing.assert_allclose(fit.theta, theta, rtol=1e-10, atol=0)
    # chi2 = 2 Q = 2 |W (d - R theta)|^2 per segment and band (the spectra's normalisation of
    # ttlcore.estimate: E|w|^2 = 1/2 per real component), and Cov = kappa (2 A^T A)^-1
    r = y - A @ theta
    chi2 = np.stack([2 * np.sum(np.abs(r[:, a:b]) ** 2, axis=(1, 2)) for a, b in data.grid.slices], axis=1)
    np.testing.assert_allclose(fit.chi2_seg_band, chi2, rtol=1e-10)
    np.testing.assert_allclose(fit.covariance, KAPPA * np.linalg.inv(2 * Ar.T @ Ar), rtol=1e-10)
    # the whitened residual differs by a unitary matrix per bin: the same power per bin
    np.testing.assert_allclose(
        np.sum(np.abs(fit.residual_w) ** 2, axis=-1), np.sum(np.abs(r) ** 2, axis=-1), rtol=1e-10
    )


def test_with_noise_leaves_the_value_and_changes_the_whitening_only():
    f, csd, R, d = _problem(seed=12)
    data = _whitened_data(f, csd, d)
    scaled = data.with_noise(4.0 * csd)
    assert scaled.grid is data.grid and scaled.tdi is data.tdi and scaled.context is data.context
    assert scaled.noise.key != data.noise.key
    # a CSD scaled by 4: whitened spectra halved, power per band divided by 4, exactly
    np.testing.assert_allclose(scaled.noise.wd, data.noise.wd / 2, rtol=1e-12)
    np.testing.assert_allclose(scaled.noise.dd, data.noise.dd / 4, rtol=1e-12)
    with pytest.raises(ValueError):
        data.noise.wd[0, 0, 0] = 0.0  # read-only: a trial cannot change another fit's input


def test_robust_covariance_is_the_sandwich_of_the_whitened_system():
    """The sandwich against one built from the stacked real system: per bin, the score is the
    sum over its rows (3 channels, real and imaginary parts) of ``a_row * residual_row`` (the
    same per bin whatever unitary whitening: the engine's ``L^H`` or the reference's ``C^-1``)."""
    f, csd, R, d = _problem(seed=13)
    data = _whitened_data(f, csd, d)
    fit = solve(data, _columns(data, R))
    A, y = _reference_system(csd, R, d)
    r = y - A @ fit.theta  # (S, m, 3)
    g = np.einsum("smcp,smc->smp", A.real, r.real) + np.einsum("smcp,smc->smp", A.imag, r.imag)
    Mref = np.einsum("smp,smq->pq", g, g)
    Ar = np.concatenate([A.real.reshape(-1, P), A.imag.reshape(-1, P)])
    Ninv = np.linalg.inv(Ar.T @ Ar)
    # the same sums in another order: round-off only
    np.testing.assert_allclose(fit.robust_covariance, KAPPA * Ninv @ Mref @ Ninv, rtol=1e-10)
    np.testing.assert_allclose(fit.robust_sigma, np.sqrt(np.diag(fit.robust_covariance)), rtol=1e-12)
    with pytest.raises(ValueError):
        fit.robust_covariance[0, 0] = 0.0  # read-only, as the fit's other arrays


def _scatter_and_sigmas(segment_scale, seed):
    """400 draws of the tiny problem with the noise of each segment scaled by
    ``segment_scale`` against the noise model's (drawn at the spectra's normalisation:
    ``E|w|^2 = 1/2`` per real component): the estimates' scatter times ``sqrt(kappa)`` (the
    covariance carries the variance factor, the draws do not) and the RMS of the model-based
    and robust sigmas."""
    f, csd, R, _ = _problem(seed=14)
    rng = np.random.default_rng(seed)
    theta_true = np.array([0.5, -1.5, 2.0])
    Lc = np.linalg.cholesky(csd)
    scale = np.asarray(segment_scale, dtype=float)[:, None, None]
    thetas, model_sigma, robust_sigma = [], [], []
    for _ in range(400):
        z = (rng.normal(size=(S, M, 3, 1)) + 1j * rng.normal(size=(S, M, 3, 1))) / np.sqrt(2)
        d = R @ theta_true + scale * (Lc @ z)[..., 0]
        data = _whitened_data(f, csd, d)
        fit = solve(data, _columns(data, R))
        thetas.append(fit.theta)
        model_sigma.append(fit.sigma)
        robust_sigma.append(fit.robust_sigma)
    rms = lambda x: np.sqrt(np.mean(np.square(x), axis=0))  # noqa: E731
    return np.std(thetas, axis=0) * np.sqrt(KAPPA), rms(model_sigma), rms(robust_sigma)


def test_robust_sigma_follows_the_scatter_where_the_noise_model_is_short():
    """Monte Carlo, 400 draws each.  Noise as modelled: both sigmas follow the estimates'
    scatter.  The noise of segment 0 three times the model's (an excess the model does not
    know, as the tail of a glitch): the model-based sigma stays at the noise model's (too
    small by ~2.2: the variance is 9x in half the data), the robust one follows the scatter.
    Tolerances: the scatter of 400 draws is known to ~3.5 % (1 sigma) and the sandwich of 48
    bins and 3 parameters is biased low by ~P / n: 20 % covers both."""
    scatter, model, robust = _scatter_and_sigmas([1.0, 1.0], seed=15)
    np.testing.assert_allclose(model, scatter, rtol=0.2)
    np.testing.assert_allclose(robust, scatter, rtol=0.2)
    scatter, model, robust = _scatter_and_sigmas([3.0, 1.0], seed=16)
    np.testing.assert_allclose(robust, scatter, rtol=0.2)
    assert np.all(model < 0.6 * scatter), (model, scatter)
