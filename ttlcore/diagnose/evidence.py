"""Evidence for adding parameters to a linear-Gaussian model: a small typed result.

Used by the diagnosis to rank candidate effects (docs/diagnostics.md, "Exact
linear-Gaussian Bayes factor"), by the searches to score effects with nonlinear
parameters, and by the report of a model change.

For a candidate with columns ``K`` added to the model columns ``M`` (:func:`added_evidence`):

- ``delta_chi2 = chi2_M - chi2_{M+K}`` at the GLS optima, divided by the variance factor
  ``kappa`` of the tapered segments (:func:`ttlcore.estimate.fit.variance_factor`), distributed as
  chi^2 with ``|K|`` degrees of freedom if the effect is absent;
- the exact log Bayes factor of the linear-Gaussian model with a flat prior on the model
  coefficients and a zero-mean Gaussian prior of standard deviation ``prior_scale`` on each
  new parameter (:func:`log_bayes_factor`);
- where the gain is: per band and per segment.

Models that are not nested (a shifted-witness effect moved TTL columns) are compared by
Laplace's method (:func:`laplace_evidence`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from .columns import ColumnSet, eiv, rewhitened
from .model_fit import ModelFit, gram, parameter_name, rhs, total_offset

__all__ = [
    "Evidence",
    "log_bayes_factor",
    "added_evidence",
    "evidence_from_normal",
    "laplace_evidence",
    "change",
    "stable_solve",
]


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
    q2 = beta @ A @ np.linalg.solve(np.eye(k) + (d**2)[:, None] * A, beta)
    return float(-0.5 * logdet + 0.5 * (q1 - q2))


def stable_solve(N: np.ndarray, b: np.ndarray, max_condition: float = 1e12) -> np.ndarray | None:
    """``N^-1 b`` for a symmetric normal matrix, with Jacobi scaling (columns of very
    different norms: a filter basis far from its pole); None when the scaled matrix is not
    positive definite or its condition number exceeds ``max_condition`` (columns nearly
    collinear: no evidence can be read from them)."""
    d = np.sqrt(np.abs(np.diag(N)))
    if not np.all(d > 0):
        return None
    Ns = N / d[:, None] / d[None, :]
    w = np.linalg.eigvalsh(Ns)
    if w[0] <= 0 or w[-1] / w[0] > max_condition:
        return None
    return np.linalg.solve(Ns, b / d) / d


@dataclass(frozen=True)
class Evidence:
    """Evidence for adding parameters to a model.

    Attributes
    ----------
    delta_chi2 : float
        chi^2 gain over ``kappa``.
    log_bayes_factor : float
        Exact (or Laplace, or marginalised over searched parameters) log Bayes factor.
    n_parameters : int
        Linear parameters added.
    names : tuple
        Their columns.
    beta, sigma : ndarray
        Their estimates and standard deviations (the model's parameters marginalised).
    band_delta, segment_delta : ndarray or None
        chi^2 gain (over ``kappa``) per band (G,) and per segment (S,).
    delta_bic : float or None
        Change of the Bayesian information criterion (searched parameters counted).
    """

    delta_chi2: float
    log_bayes_factor: float
    n_parameters: int
    names: tuple
    beta: np.ndarray
    sigma: np.ndarray
    band_delta: np.ndarray | None = None
    segment_delta: np.ndarray | None = None
    delta_bic: float | None = None


def evidence_from_normal(model: ModelFit, N_MM, N_MK, N_KK, b_M, b_K, names, priors, E_full) -> Evidence:
    """Evidence for the columns ``names`` added to ``model`` from the per-segment, per-band
    normal equations and the errors-in-variables term ``E_full`` (G, P + k, P + k) of all
    the columns: the candidates' readout noise correlates with the model's where they
    share a DWS channel, and left out, that correlation would pass for a signal."""
    kappa = model.data.grid.kappa
    P, k = N_MM.shape[-1], N_KK.shape[-1]
    full = np.zeros(N_MM.shape[:2] + (P + k, P + k))
    full[..., :P, :P] = N_MM
    full[..., :P, P:] = N_MK
    full[..., P:, :P] = np.swapaxes(N_MK, -1, -2)
    full[..., P:, P:] = N_KK
    bb = np.concatenate([b_M, b_K], axis=-1)
    Nt = full.sum(axis=(0, 1)) - E_full.sum(axis=0)
    bt = bb.sum(axis=(0, 1))
    th = stable_solve(Nt, bt)
    if th is None:
        raise ConfigError(f"columns {list(names)[:2]} are (nearly) collinear with the model's: no evidence")
    NM = Nt[:P, :P]
    thM = np.linalg.solve(NM, bt[:P])
    dchi2 = 2 * (bt @ th - bt[:P] @ thM) / kappa
    # Schur complement: precision of the new parameters with the model's marginalised
    Sch = Nt[P:, P:] - Nt[P:, :P] @ np.linalg.solve(NM, Nt[:P, P:])
    A = 2 * Sch / kappa
    beta = th[P:]
    lbf = log_bayes_factor(A, beta, np.asarray(priors, dtype=float))
    # where: per band and per segment (chi2 with the plain N, as the adequacy)
    thM_full = np.r_[thM, np.zeros(k)]
    dd = model.dd
    chi2_before = 2 * (np.einsum("p,sgpq,q->sg", thM_full, full, thM_full) - 2 * bb @ thM_full + dd)
    chi2_after = 2 * (np.einsum("p,sgpq,q->sg", th, full, th) - 2 * bb @ th + dd)
    try:
        var = np.diag(np.linalg.inv(A))
    except np.linalg.LinAlgError:
        var = np.full(k, np.nan)
    return Evidence(
        float(dchi2),
        lbf,
        k,
        tuple(names),
        beta,
        np.sqrt(np.abs(var)),
        (chi2_before - chi2_after).sum(axis=0) / kappa,
        (chi2_before - chi2_after).sum(axis=1) / kappa,
    )


def added_evidence(model: ModelFit, cand: ColumnSet, priors=None) -> Evidence:
    """Evidence for adding the columns ``cand`` (whitened like ``model``'s) to ``model``."""
    data = model.data
    M = model.columns
    N_MM, b_M = model.normal
    return evidence_from_normal(
        model,
        N_MM,
        gram(data, M, cand),
        gram(data, cand, cand),
        b_M,
        rhs(data, cand),
        cand.names,
        cand.priors if priors is None else priors,
        eiv(data, M, cand),
    )


def laplace_evidence(base: ModelFit, model: ModelFit) -> tuple[float, float]:
    """``(delta_chi2, log B)`` of ``model`` against ``base`` when they are not nested (a
    shifted-witness effect moved some TTL columns; nested pairs: :func:`added_evidence`,
    exact).

    ``delta_chi2 = 2 (Q_base - Q_model) / kappa`` at the optima; the log Bayes factor by
    Laplace's method on ``log L = -Q / kappa``: with a flat prior on the parameters both
    models share (by :func:`~ttlcore.diagnose.model_fit.parameter_name`) and the Gaussian
    prior ``N(0, prior_scale)`` on each new one, evaluated at its estimate (offsets:
    expansion point plus ``d1``),

        log B = -(Q_model - Q_base) / kappa - 1/2 [log det H_model - log det H_base]
                + sum_new [1/2 log 2 pi + log N(theta_k; 0, prior_k)],

    ``H = 2 (N - E) / kappa`` the Hessians.  For a nested pair whose new parameters lie
    well inside their prior this equals :func:`log_bayes_factor`."""
    kappa = base.data.grid.kappa

    def logdet(fit):
        H = 2 * (fit.normal[0].sum(axis=(0, 1)) - fit.eiv_term.sum(axis=0)) / kappa
        sign, value = np.linalg.slogdet(H)
        return value if sign > 0 else float("nan")

    shared = set(base.parameter_names)
    lbf = -(model.q_min - base.q_min) / kappa - 0.5 * (logdet(model) - logdet(base))
    for n, v, p in zip(model.names, model.theta, model.columns.priors):
        if parameter_name(n) in shared:
            continue
        lbf += -np.log(float(p)) - 0.5 * (total_offset(n, v, model.expansion) / float(p)) ** 2
    return float(2 * (base.q_min - model.q_min) / kappa), float(lbf)


def change(base: ModelFit, model: ModelFit) -> Evidence | None:
    """Evidence for ``model`` against ``base``: exact (:func:`added_evidence`) when
    ``base``'s columns are among ``model``'s, Laplace (:func:`laplace_evidence`) when a
    shifted-witness effect moved TTL columns; None when ``model`` adds nothing."""
    added = [n for n in model.names if n not in base.names]
    if not added:
        return None
    if set(base.names) <= set(model.names):
        return added_evidence(base, rewhitened(model.columns.select(added), model.data.noise.Lh, base.data))
    dchi2, lbf = laplace_evidence(base, model)
    new = [i for i, n in enumerate(model.names) if parameter_name(n) not in set(base.parameter_names)]
    return Evidence(
        dchi2,
        lbf,
        len(new),
        tuple(model.names[i] for i in new),
        np.array([total_offset(model.names[i], model.theta[i], model.expansion) for i in new]),
        model.sigma[new],
    )
