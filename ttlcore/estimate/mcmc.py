"""MCMC (emcee) over the likelihood of the GLS fit, optionally with free noise levels
(docs/physics.md, fit and subtraction).

Likelihood
----------
The GLS fit (:mod:`ttlcore.estimate.fit`) reduces the data to sufficient statistics per frequency
band ``g`` (:class:`~ttlcore.estimate.fit.NormalEquations`): the whitened residual power

    Q_g(C) = C^T N'_g C - 2 C^T b_g + dd_g,        N'_g = N_g - E_g  (E_g only with eiv),

and the coefficient log-likelihood

    log L(C) = -(1 / kappa) sum_g Q_g(C),

where ``kappa`` (``FitResult.extra["variance_factor"]``) accounts for the correlation of
neighbouring frequency bins introduced by the window.  Under a flat prior the posterior is
exactly Gaussian with mean ``C = N'^-1 b`` and covariance ``kappa (2 N')^-1``
(``N' = sum_g N'_g``, ``b = sum_g b_g``): the GLS estimate and its model-based covariance.

Noise levels (what GLS cannot do): with a free scale ``lambda_g`` of the noise CSD in each
band, every complex bin of ``nchan`` channels contributes ``-nchan log lambda_g`` to the
complex-Gaussian log-likelihood, so

    log L(C, lambda) = sum_g [ -Q_g(C) / (kappa lambda_g) - (nchan nbins_g / kappa) log lambda_g ].

The priors are flat in ``C`` and in ``s_g = log lambda_g``.  For fixed ``C`` the posterior
of ``lambda_g`` is inverse-gamma with shape ``n_g / kappa`` and scale ``Q_g(C) / kappa``
(``n_g = nchan nbins_g``): its mode in ``s_g`` is ``Q_g / n_g = chi2_g / dof_g`` and its
relative width ``sqrt(kappa / n_g)``.

Sampler
-------
emcee's ensemble sampler with the differential-evolution move (for a Gaussian target its
autocorrelation time is about 3 times the dimension, against about 8 times for the
stretch move) runs in whitened coordinates ``z``:

    x = x0 + L z,       x = (C, s),      L L^T = Sigma,

with ``x0`` the posterior mode and ``Sigma`` the inverse of the negative Hessian of
``log L`` there (the Laplace approximation; without noise levels exactly the GLS
covariance), so the target is (close to) the isotropic unit Gaussian.  The walkers start
from draws of that Gaussian.  The log-probability is vectorised over walkers and uses the
centred form

    Q_g(x0_C + delta) = Q_g(x0_C) + 2 delta^T (N'_g x0_C - b_g) + delta^T N'_g delta,

cheap (``P x P`` per band) and free of the cancellation in ``C^T N C - 2 C^T b + dd``.
The chain runs in chunks until it is longer than ``n_autocorr`` times the largest
integrated autocorrelation time (emcee's estimator on the natural parameters); then a
burn-in of 3 tau is discarded and the chain thinned by tau / 2.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import emcee
import numpy as np
from scipy import fft as sp_fft

from ..conventions import COEFFICIENT_NAMES
from .fit import FitResult, FitSettings, NormalEquations, SegmentSpectra, fit_spectra

log = logging.getLogger(__name__)

#: Burn-in discarded, in autocorrelation times.
BURN_IN_TAU = 3.0
#: Thinning of the returned samples, in autocorrelation times.
THIN_TAU = 0.5
#: Steps per walker kept in memory while sampling: beyond, every other stored step is
#: dropped (stride doubled).  The chain is 50 tau long, so the stored stride stays near
#: tau / 20, fine for the autocorrelation estimate (``stride * tau_thinned ~ tau``) and for
#: the tau / 2 thinning of the output, and memory and estimation cost stay bounded.
STORE_CAP = 1024


@dataclass
class McmcResult:
    """Posterior samples and their diagnostics.

    Attributes
    ----------
    names : tuple of str
        Parameter names: the coefficients, then ``noise_level.<g>`` per sampled band.
    samples : ndarray, shape (n, P [+ G])
        Burnt-in, thinned samples: coefficients [m/rad], then noise scales ``lambda_g``.
    coefficients : ndarray, shape (P,)
        Posterior mean of the coefficients [m/rad].
    covariance : ndarray, shape (P, P)
        Sample covariance of the coefficients [m^2/rad^2].
    autocorr_time : ndarray, shape (P [+ G],)
        Integrated autocorrelation time of each parameter (coefficients, ``log lambda_g``)
        [steps].
    n_independent : float
        ``nwalkers (n_steps - burn-in) / max(autocorr_time)``.
    acceptance_fraction : float
        Mean over walkers.
    n_steps : int
        Steps per walker, burn-in included.
    converged : bool
        ``n_steps >= n_autocorr * max(autocorr_time)``.
    noise_levels : ndarray (G,) or None
        Posterior mean of ``lambda_g`` (NaN for bands without bins); None if not sampled.
    noise_levels_std : ndarray (G,) or None
        Posterior standard deviation of ``lambda_g``.
    log_prob : ndarray, shape (n,)
        Log-posterior of each sample (up to a constant).
    nwalkers : int
    wall_time : float
        [s].
    """

    names: tuple
    samples: np.ndarray
    coefficients: np.ndarray
    covariance: np.ndarray
    autocorr_time: np.ndarray
    n_independent: float
    acceptance_fraction: float
    n_steps: int
    converged: bool
    noise_levels: np.ndarray | None
    noise_levels_std: np.ndarray | None
    log_prob: np.ndarray
    nwalkers: int = 0
    wall_time: float = float("nan")

    @property
    def sigma(self) -> np.ndarray:
        """Posterior standard deviations of the coefficients [m/rad]."""
        return np.sqrt(np.diag(self.covariance))


# ---------------------------------------------------------------------------
# Posterior
# ---------------------------------------------------------------------------


class _Posterior:
    """Vectorised log-posterior in whitened coordinates (see the module docstring)."""

    #: origin and Cholesky factor of the whitened coordinates (:meth:`set_whitening`, before any use)
    x0: np.ndarray
    L: np.ndarray

    def __init__(self, neq: NormalEquations, eiv: bool, kappa: float, bands: np.ndarray | None):
        self.Np = neq.N - (neq.E if eiv else 0.0)  # (G, P, P)
        self.b = np.asarray(neq.b, dtype=float)
        self.dd = np.asarray(neq.dd, dtype=float)
        self.kappa = float(kappa)
        self.P = self.b.shape[1]
        self.bands = bands  # indices of bands with a free noise level, or None
        self.n = neq.nchan * np.asarray(neq.nbins, dtype=float)

    @property
    def ndim(self) -> int:
        return self.P + (0 if self.bands is None else len(self.bands))

    # -- natural parameters ------------------------------------------------
    def Q(self, C: np.ndarray) -> np.ndarray:
        """``Q_g(C)`` for every band, C of shape (P,) -> (G,)."""
        return np.einsum("p,gpq,q->g", C, self.Np, C) - 2 * self.b @ C + self.dd

    def log_prob_x(self, x: np.ndarray) -> float:
        """Log-posterior at natural parameters ``x = (C, s)`` (not vectorised)."""
        q = self.Q(x[: self.P])
        if self.bands is None:
            return float(-q.sum() / self.kappa)
        s = x[self.P :]
        g = self.bands
        return float(-(q.sum() - q[g].sum()) / self.kappa - np.sum(q[g] * np.exp(-s) + self.n[g] * s) / self.kappa)

    def mode(self, max_iter: int = 200, tol: float = 1e-12) -> np.ndarray:
        """Posterior mode: ``C = N'^-1 b``; with noise levels, alternate ``lambda_g = Q_g / n_g``
        and ``C = (sum_g N'_g / lambda_g)^-1 sum_g b_g / lambda_g`` (profile likelihood)."""
        lam = np.ones(len(self.b))
        C = np.linalg.solve(self.Np.sum(0), self.b.sum(0))
        if self.bands is None:
            return C
        g = self.bands
        for _ in range(max_iter):
            q = self.Q(C)
            if np.any(q[g] <= 0):
                raise ValueError("residual power Q_g <= 0 in a band: noise levels are not identifiable")
            lam_new = lam.copy()
            lam_new[g] = q[g] / self.n[g]
            C_new = np.linalg.solve(np.einsum("gpq,g->pq", self.Np, 1 / lam_new), (self.b / lam_new[:, None]).sum(0))
            done = np.max(np.abs(np.log(lam_new[g] / lam[g]))) < tol
            C, lam = C_new, lam_new
            if done:
                break
        return np.concatenate([C, np.log(lam[g])])

    def precision(self, x: np.ndarray) -> np.ndarray:
        """Negative Hessian of the log-posterior at ``x``.

        ``-d2/dC2 = (2 / kappa) sum_g N'_g / lambda_g``; with noise levels
        ``-d2/dC ds_g = -(2 / kappa) (N'_g C - b_g) / lambda_g`` and
        ``-d2/ds_g2 = Q_g(C) / (kappa lambda_g)``.
        """
        P = self.P
        C = x[:P]
        lam = np.ones(len(self.b))
        if self.bands is not None:
            lam[self.bands] = np.exp(x[P:])
        H = np.zeros((self.ndim, self.ndim))
        H[:P, :P] = 2 / self.kappa * np.einsum("gpq,g->pq", self.Np, 1 / lam)
        if self.bands is not None:
            g = self.bands
            grad = 2 * (np.einsum("gpq,q->gp", self.Np[g], C) - self.b[g])  # dQ_g/dC
            H[:P, P:] = -(grad / lam[g][:, None]).T / self.kappa
            H[P:, :P] = H[:P, P:].T
            H[P:, P:] = np.diag(self.Q(C)[g] / (self.kappa * lam[g]))
        return 0.5 * (H + H.T)

    # -- whitened coordinates ----------------------------------------------
    def set_whitening(self, x0: np.ndarray, cov: np.ndarray) -> None:
        self.x0 = np.asarray(x0, dtype=float)
        try:
            self.L = np.linalg.cholesky(cov)
        except np.linalg.LinAlgError as exc:
            raise ValueError(
                "whitening covariance is not positive definite (N - E not positive definite? try eiv=False)"
            ) from exc
        C0 = self.x0[: self.P]
        self.q0 = self.Q(C0)  # (G,)
        self.grad0 = 2 * (np.einsum("gpq,q->gp", self.Np, C0) - self.b)  # (G, P)
        self.LC = self.L[: self.P]  # (P, D)

    def to_natural(self, z: np.ndarray) -> np.ndarray:
        """``x = x0 + L z`` for z of shape (..., D)."""
        return self.x0 + z @ self.L.T

    def __call__(self, z: np.ndarray) -> np.ndarray:
        """Log-posterior of walkers ``z`` (W, D) -> (W,)."""
        z = np.atleast_2d(z)
        delta = z @ self.LC.T  # (W, P)
        quad = np.einsum("wgq,wq->wg", np.tensordot(delta, self.Np, axes=([1], [1])), delta)
        q = self.q0 + delta @ self.grad0.T + quad  # (W, G)
        if self.bands is None:
            return -q.sum(axis=1) / self.kappa
        g = self.bands
        s = self.x0[self.P :] + z @ self.L[self.P :].T  # (W, Gs)
        fixed = (q.sum(axis=1) - q[:, g].sum(axis=1)) / self.kappa
        lp = -fixed - np.sum(q[:, g] * np.exp(-s) + self.n[g] * s, axis=1) / self.kappa
        # Q_g must stay positive for a proper noise-level posterior (N'_g may be indefinite)
        return np.where(np.all(q[:, g] > 0, axis=1), lp, -np.inf)


# ---------------------------------------------------------------------------
# Sampling
# ---------------------------------------------------------------------------


def sample(
    neq: NormalEquations,
    *,
    eiv: bool = True,
    kappa: float = 1.0,
    noise_levels: bool = False,
    start: np.ndarray | None = None,
    scale: np.ndarray | None = None,
    nwalkers: int | None = None,
    n_autocorr: float = 50,
    max_steps: int = 200_000,
    seed: int = 0,
    progress: Callable[[int, float, float], None] | None = None,
) -> McmcResult:
    """Sample the posterior of the coefficients (and noise levels) given normal equations.

    ``log L(C) = -(1/kappa) sum_g Q_g(C)`` or, with ``noise_levels``,
    ``sum_g [-Q_g(C) / (kappa lambda_g) - (nchan nbins_g / kappa) log lambda_g]``, flat
    priors in ``C`` and ``log lambda_g`` (see the module docstring).

    Parameters
    ----------
    neq : NormalEquations
        Sufficient statistics (e.g. ``internals["normal_equations"]`` of
        :func:`ttlcore.estimate.fit.fit_spectra`).
    eiv : bool
        Subtract the errors-in-variables term ``E_g`` from ``N_g``.
    kappa : float
        Variance factor of the window (``FitResult.extra["variance_factor"]``).
    noise_levels : bool
        Sample one noise scale ``lambda_g`` per band holding bins.
    start : ndarray (D,), optional
        Centre of the whitening, natural parameters ``(C, log lambda_g)``; default the
        posterior mode.
    scale : ndarray (D, D), optional
        Covariance used for whitening; default the Laplace approximation at ``start``.
    nwalkers : int, optional
        Default ``4 D`` (even).
    n_autocorr : float
        Run until the chain is at least this many autocorrelation times long.
    max_steps : int
        Upper bound on steps per walker (``converged`` is False if reached first).
    seed : int
        Seeds both the walkers' start and emcee's generator: same seed, same samples.
    progress : callable, optional
        Called after every chunk as ``progress(n_steps, max_tau, n_target)``.

    Returns
    -------
    McmcResult
    """
    t_start = time.perf_counter()
    P, G = neq.b.shape[1], neq.b.shape[0]
    bands = np.flatnonzero(np.asarray(neq.nbins) > 0) if noise_levels else None
    post = _Posterior(neq, eiv, kappa, bands)
    D = post.ndim
    x0 = post.mode() if start is None else np.asarray(start, dtype=float)
    if x0.shape != (D,):
        raise ValueError(f"start must have shape ({D},), got {x0.shape}")
    if scale is None:
        scale = np.linalg.inv(post.precision(x0))
        scale = 0.5 * (scale + scale.T)
    post.set_whitening(x0, np.asarray(scale, dtype=float))

    W = _walkers(nwalkers, D)
    rng = np.random.default_rng(seed)
    sampler = emcee.EnsembleSampler(W, D, post, moves=emcee.moves.DEMove(), vectorize=True)
    sampler.random_state = np.random.RandomState(seed).get_state()
    state = emcee.State(rng.standard_normal((W, D)))

    zs, lps, stride, n_steps, accepted, tau = _run_chains(sampler, state, post, n_autocorr, max_steps, progress)
    tau_max = float(np.max(tau))
    converged = bool(n_steps >= n_autocorr * tau_max)
    if not converged:
        log.warning(
            "mcmc: not converged after %d steps (max tau %.1f, needs %.0f)", n_steps, tau_max, n_autocorr * tau_max
        )
    burn = BURN_IN_TAU * tau_max
    xs, lp_flat = _thinned(post, zs, lps, (n_steps, stride), burn, tau_max)

    C_samples = xs[:, :P]
    mean = C_samples.mean(axis=0)
    cov = np.cov(C_samples, rowvar=False)
    names = tuple(neq.names)
    lam_mean = lam_std = None
    samples = xs.copy()
    if bands is not None:
        lam = np.exp(xs[:, P:])
        samples[:, P:] = lam
        lam_mean, lam_std = np.full(G, np.nan), np.full(G, np.nan)
        lam_mean[bands], lam_std[bands] = lam.mean(axis=0), lam.std(axis=0, ddof=1)
        names = names + tuple(f"noise_level.{g}" for g in bands)
    n_independent = float(W * max(n_steps - burn, 0) / tau_max)
    wall = time.perf_counter() - t_start
    acc = float(np.mean(accepted / n_steps))
    log.info(
        "mcmc: %d walkers x %d steps, max tau %.1f, %.0f independent samples, acceptance %.2f, %.1f s",
        W,
        n_steps,
        tau_max,
        n_independent,
        acc,
        wall,
    )
    return McmcResult(
        names=names,
        samples=samples,
        coefficients=mean,
        covariance=0.5 * (cov + cov.T),
        autocorr_time=tau,
        n_independent=n_independent,
        acceptance_fraction=acc,
        n_steps=int(n_steps),
        converged=converged,
        noise_levels=lam_mean,
        noise_levels_std=lam_std,
        log_prob=lp_flat,
        nwalkers=W,
        wall_time=wall,
    )


def _walkers(nwalkers: int | None, D: int) -> int:
    """The number of walkers: ``nwalkers`` (default ``4 D``) made even; ValueError below ``2 D``."""
    W = int(nwalkers or 4 * D)
    W += W % 2
    if W < 2 * D:
        raise ValueError(f"need at least 2 * ndim = {2 * D} walkers, got {W}")
    return W


def _run_chains(sampler, state, post, n_autocorr: float, max_steps: int, progress) -> tuple:
    """Run ``sampler`` from ``state`` in chunks until the chain is ``n_autocorr``
    autocorrelation times long or ``max_steps`` steps, keeping every ``stride``-th step (the
    stride doubled whenever more than ``STORE_CAP`` steps are stored).

    Returns
    -------
    tuple
        The stored whitened positions ``(steps, W, D)`` and log probabilities, the stride,
        the number of steps, the acceptances per walker and the integrated
        autocorrelation times [steps] of the natural parameters.
    """
    D = post.ndim
    W = sampler.nwalkers
    stride = 1  # storage stride [steps]
    kept_z, kept_lp = [], []
    n_steps, accepted = 0, np.zeros(W)
    chunk = min(max(500, 40 * D), max_steps)
    tau = np.full(D, np.inf)
    while True:
        state = sampler.run_mcmc(state, chunk, progress=False)
        z, lp = sampler.get_chain(), sampler.get_log_prob()
        accepted += sampler.backend.accepted
        steps = n_steps + 1 + np.arange(chunk)  # global step number of each row
        keep = steps % stride == 0
        kept_z.append(z[keep])
        kept_lp.append(lp[keep])
        n_steps += chunk
        sampler.reset()
        zs, lps = np.concatenate(kept_z), np.concatenate(kept_lp)
        while zs.shape[0] > STORE_CAP:  # bound memory: keep every other stored step
            sel = _stored_steps(n_steps, stride, zs.shape[0]) % (2 * stride) == 0
            zs, lps, stride = zs[sel], lps[sel], 2 * stride
        kept_z, kept_lp = [zs], [lps]
        xs = post.to_natural(zs)
        tau = stride * integrated_time(xs)
        target = n_autocorr * float(np.max(tau))
        log.debug("mcmc: %d steps, max tau %.1f, target %.0f", n_steps, np.max(tau), target)
        if progress is not None:
            progress(n_steps, float(np.max(tau)), target)
        if n_steps >= target or n_steps >= max_steps:
            break
        chunk = int(min(max(1.2 * target - n_steps, 200), max_steps - n_steps))
    return kept_z[0], kept_lp[0], stride, n_steps, accepted, tau


def _thinned(post, zs: np.ndarray, lps: np.ndarray, counts: tuple, burn: float, tau_max: float) -> tuple:
    """The stored steps after the burn-in ``burn`` [steps], thinned to one every
    ``THIN_TAU`` autocorrelation times (at least the last step), as natural parameters
    ``(samples, D)`` with their log probabilities; ``counts`` is ``(steps run, stride)``."""
    n_steps, stride = counts
    steps = _stored_steps(n_steps, stride, zs.shape[0])
    thin = max(stride, int(round(THIN_TAU * tau_max / stride)) * stride)
    sel = (steps > burn) & ((steps - steps[-1]) % thin == 0)
    if not np.any(sel):
        sel = steps == steps[-1]
    xs = post.to_natural(zs[sel]).reshape(-1, post.ndim)
    return xs, lps[sel].reshape(-1)


def integrated_time(x: np.ndarray, c: float = 5.0) -> np.ndarray:
    """Integrated autocorrelation time of each parameter of a chain ``x`` (steps, walkers, D).

    The estimator of ``emcee.autocorr.integrated_time(x, c=c, tol=0)`` (Sokal's automatic
    window), vectorised over walkers and parameters: the normalised autocorrelation
    function ``rho(t)`` of every walker is averaged over walkers, and

        tau = 1 + 2 sum_{t=1}^{M} rho(t),     M the smallest with M >= c tau(M).
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[0]
    nfft = sp_fft.next_fast_len(2 * n - 1, real=True)  # zero padding: linear, not circular
    y = np.ascontiguousarray(np.moveaxis(x - x.mean(axis=0), 0, -1))  # (W, D, n)
    f = sp_fft.rfft(y, n=nfft, axis=-1, workers=-1)
    acf = sp_fft.irfft(f.real**2 + f.imag**2, n=nfft, axis=-1, workers=-1)[..., :n]
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = np.nan_to_num(acf / acf[..., :1]).mean(axis=0).T  # (n, D)
    taus = 2.0 * np.cumsum(rho, axis=0) - 1.0
    m = np.arange(n)[:, None] < c * taus
    window = np.where(m.all(axis=0), n - 1, np.argmin(m, axis=0))
    return taus[window, np.arange(x.shape[2])]


def _stored_steps(n_steps: int, stride: int, count: int) -> np.ndarray:
    """Global step numbers of the ``count`` stored rows: the multiples of ``stride`` up to
    ``n_steps``."""
    last = n_steps - n_steps % stride
    return last - stride * np.arange(count)[::-1]


# ---------------------------------------------------------------------------
# Fit
# ---------------------------------------------------------------------------


def fit_mcmc(
    spectra: list[SegmentSpectra],
    ltt_mean,
    settings: FitSettings | None = None,
    names=COEFFICIENT_NAMES,
    *,
    noise_levels: bool = False,
    seed: int = 0,
    n_autocorr: float = 50,
    nwalkers: int | None = None,
    max_steps: int = 200_000,
    progress: Callable[[int, float, float], None] | None = None,
) -> tuple[FitResult, dict]:
    """MCMC fit of the coefficients: GLS first (noise weights, normal equations), then
    :func:`sample` over the same likelihood.

    Returns
    -------
    FitResult
        ``method="mcmc"``, ``coefficients`` the posterior mean, ``covariance`` the sample
        covariance, ``chi2`` from the GLS normal equations at the posterior mean; ``extra``
        holds ``autocorr_time``, ``n_independent``, ``acceptance_fraction``, ``n_steps``,
        ``converged``, ``nwalkers``, ``noise_levels`` (mean, std, band edges; if sampled),
        ``gls_coefficients``, ``gls_sigma_model_based`` and ``variance_factor``.
    dict
        The GLS internals (``normal_equations``, ``weights``, ``noise_csd``) plus
        ``gls`` (its :class:`FitResult`) and ``mcmc`` (the :class:`McmcResult`).
    """
    s = settings or FitSettings()
    gls, internals = fit_spectra(spectra, ltt_mean, s, names)
    neq = internals["normal_equations"]
    kappa = float(gls.extra.get("variance_factor", 1.0))
    eiv = bool(s.eiv)
    mc = sample(
        neq,
        eiv=eiv,
        kappa=kappa,
        noise_levels=noise_levels,
        nwalkers=nwalkers,
        n_autocorr=n_autocorr,
        max_steps=max_steps,
        seed=seed,
        progress=progress,
    )
    chi2 = neq.chi2_per_band(mc.coefficients, eiv=eiv)
    dof_bands = neq.dof_per_band().astype(float)
    res = FitResult(
        names=tuple(names),
        coefficients=mc.coefficients,
        covariance=mc.covariance,
        chi2=float(chi2.sum()),
        dof=float(dof_bands.sum() - len(names)),
        band=tuple(s.band),
        method="mcmc",
        eiv=eiv,
        iterations=gls.iterations,
        converged=bool(gls.converged and mc.converged),
        band_edges=neq.band_edges,
        chi2_per_band=chi2,
        dof_per_band=dof_bands,
        t_start=gls.t_start,
        t_stop=gls.t_stop,
        n_segments=gls.n_segments,
    )
    res.extra.update(
        {
            "autocorr_time": dict(zip(mc.names, map(float, mc.autocorr_time))),
            "n_independent": mc.n_independent,
            "acceptance_fraction": mc.acceptance_fraction,
            "n_steps": mc.n_steps,
            "nwalkers": mc.nwalkers,
            "converged": mc.converged,
            "variance_factor": kappa,
            "gls_coefficients": dict(zip(names, map(float, gls.coefficients))),
            "gls_sigma_model_based": dict(
                zip(names, map(float, np.sqrt(np.diag(gls.extra["covariance_model_based"]))))
            ),
        }
    )
    if mc.noise_levels is not None and mc.noise_levels_std is not None:
        res.extra["noise_levels"] = {
            "band_edges": list(map(float, neq.band_edges)),
            "mean": [None if not np.isfinite(v) else float(v) for v in mc.noise_levels],
            "std": [None if not np.isfinite(v) else float(v) for v in mc.noise_levels_std],
        }
    internals = dict(internals, gls=gls, mcmc=mc)
    return res, internals
