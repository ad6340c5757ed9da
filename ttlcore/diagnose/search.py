"""Searched nonlinear parameters of any effect: profile chi^2 over them, marginal evidence.

An effect declares the options the diagnosis may search (:attr:`ttlcore.diagnose.effects.Effect.searched`,
``option -> (low, high, scale)``); left unset, :func:`profile_search` finds them against a
fitted model:

1. the chi^2 of the model plus the effect, profiled over every linear parameter, on a grid
   (log-spaced for ``scale="log"``; 40 points per decade for one parameter, a 40-per-decade
   by 5 grid for two), clipped to the diagnosis band for frequencies;
2. local refinement from the best grid point (Nelder-Mead in the scaled parameters);
3. the estimate with a 1-sigma interval from the curvature of the profile log-likelihood
   ``l = delta_chi2 / 2`` (in the scaled parameters: relative for ``log``);
4. the evidence marginalised over the searched parameters under a uniform prior in the
   scaled parameters over the declared range (Laplace's method around the optimum:
   ``log B = log B(best) + d/2 log 2 pi + 1/2 log det Sigma - log V``), never above the
   evidence at the best point.

For effects whose columns are filters applied to fixed base columns
(:attr:`ttlcore.diagnose.effects.Column.response`, e.g. ``fd-coupling``), a point costs a few
products over frequency bins: the base columns' cross-products with the model's columns,
the data and each other (and their readout-noise responses) are computed once per search.
Other effects (a plugin whose columns change with the parameter) are evaluated by building
their columns at each point - correct but slower; their grid is coarser.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, special

from ..errors import ConfigError
from .effects import effect_input_from_telemetry, names_only_input, readout_noise_factor
from .evidence import log_bayes_factor

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SearchResult:
    """Outcome of :func:`profile_search`.

    Attributes
    ----------
    effect : Effect
        The effect with the searched options set to their estimates.
    estimates : dict
        Option -> estimate.
    intervals : dict
        Option -> (low, high), one sigma from the profile's curvature.
    delta_chi2 : float
        Profiled chi^2 gain at the estimate (over ``kappa``).
    log_bayes_factor_best, log_bayes_factor : float
        At the estimate, and marginalised over the searched parameters.
    n_evaluations : int
    """

    effect: object
    estimates: dict
    intervals: dict
    delta_chi2: float
    log_bayes_factor_best: float
    log_bayes_factor: float
    n_evaluations: int
    grid: list = field(default_factory=list, repr=False)

    def to_json(self) -> dict:
        return {"estimates": {k: float(v) for k, v in self.estimates.items()},
                "intervals": {k: [float(a), float(b)] for k, (a, b) in self.intervals.items()},
                "delta_chi2": float(self.delta_chi2), "log_bayes_factor_best": float(self.log_bayes_factor_best),
                "log_bayes_factor_marginal": float(self.log_bayes_factor), "evaluations": int(self.n_evaluations)}


def _scaled(ranges, names):
    lo = np.array([ranges[k][0] for k in names], dtype=float)
    hi = np.array([ranges[k][1] for k in names], dtype=float)
    log_ = np.array([ranges[k][2] == "log" for k in names])
    fwd = lambda v: np.where(log_, np.log(np.maximum(v, 1e-300)), v)  # noqa: E731
    back = lambda x: np.where(log_, np.exp(x), x)  # noqa: E731
    return fwd(lo), fwd(hi), fwd, back, log_


def search_ranges(dg, effect) -> dict:
    """The declared ranges, frequencies (``f0``, ``fc``, names starting with ``f``) clipped
    to the diagnosis band widened by a third of an octave."""
    out = {}
    for k, (lo, hi, scale) in effect.searched.items():
        if k.startswith("f"):
            lo, hi = max(lo, dg.f[0] / 1.26), min(hi, dg.f[-1] * 1.26)
        out[k] = (float(lo), float(hi), scale)
    return out


class _Spectral:
    """Per-bin products of the base columns of a filtered effect (built once per search)."""

    def __init__(self, dg, model, cols):

        self.dg = dg
        M = list(model.names)
        self.bases = []
        for c in cols:
            b = dg.base_column(c)
            if b not in self.bases:
                self.bases.append(b)
        wM = self.wM = dg._w(M)  # (S, m, 3, P)
        U = dg._w(self.bases)  # (S, m, 3, nb)
        self.PM = np.einsum("smcp,smcb->mpb", wM.conj(), U)
        self.Pud = np.einsum("smcb,smc->mb", U.conj(), dg.wd)
        self.Puu = np.einsum("smcb,smce->mbe", U.conj(), U)
        # errors-in-variables: readout-noise responses per DWS channel
        names = M + self.bases
        resp: dict = {}
        for i, n in enumerate(names):
            for ch, link, extra, *shift in dg.eiv_parts.get(n, ()):
                r = resp.setdefault(ch, np.zeros((dg.f.size, 3, len(names)), dtype=complex))
                r[:, :, i] += dg._eiv_response(link, extra) * readout_noise_factor(dg.f, shift[0] if shift else 0.0)
        W = dg.eiv_weights(names)
        P = len(M)
        self.eMB = np.zeros((dg.f.size, P, len(self.bases)))
        self.eBB = np.zeros((dg.f.size, len(self.bases), len(self.bases)), dtype=complex)
        for r in resp.values():
            self.eMB = self.eMB + np.einsum("mcp,mcb->mpb", r[:, :, :P].conj(), r[:, :, P:]) * W[:P, P:][None]
            self.eBB = self.eBB + np.einsum("mcb,mce->mbe", r[:, :, P:].conj(), r[:, :, P:]) * W[P:, P:][None]
        self.NM = model.normal[0].sum(axis=(0, 1)) - model.eiv_term.sum(axis=0)
        self.bM = model.normal[1].sum(axis=(0, 1))
        self.thM = np.linalg.solve(self.NM, self.bM)

    def evaluate(self, cols, idx, exact: bool = False) -> tuple[float, float]:
        """Evidence of the columns ``cols`` (only their responses and prior scales are
        used) on the bases ``idx``.  Fast: the filters applied to the base columns' segment
        spectra (products over bins only); ``exact``: the base series filtered in time and
        then windowed (:meth:`ttlcore.diagnose.diagnoser.Diagnoser.filtered_spectra`, as the fit)."""

        dg = self.dg
        R = np.stack([np.ones(dg.f.size, complex) if c.response is None else np.asarray(c.response(dg.f), complex)
                      for c in cols], axis=1)  # (m, k)
        eMK = np.einsum("mpk,mk->pk", self.eMB[:, :, idx], R).real
        eKK = np.einsum("mj,mjk,mk->jk", R.conj(), self.eBB[:, idx][:, :, idx], R).real
        if exact:
            wK = np.concatenate([dg.filtered_spectra(self.bases[i], [c.response])[0] for c, i in zip(cols, idx)], axis=-1)
            NMK = np.einsum("smcp,smck->pk", self.wM.conj(), wK).real - eMK
            NKK = np.einsum("smcj,smck->jk", wK.conj(), wK).real - eKK
            bK = np.einsum("smck,smc->k", wK.conj(), dg.wd).real
        else:
            NMK = np.einsum("mpk,mk->pk", self.PM[:, :, idx], R).real - eMK
            NKK = np.einsum("mj,mjk,mk->jk", R.conj(), self.Puu[:, idx][:, :, idx], R).real - eKK
            bK = np.einsum("mk,mk->k", R.conj(), self.Pud[:, idx]).real
        P = self.NM.shape[0]
        N = np.block([[self.NM, NMK], [NMK.T, NKK]])
        b = np.r_[self.bM, bK]
        th = stable_solve(N, b)
        if th is None:  # collinear: no gain (a finite value keeps the simplex well defined)
            return 0.0, -1e300
        kappa = dg.kappa
        dchi2 = 2 * (b @ th - self.bM @ self.thM) / kappa
        A = 2 * (NKK - NMK.T @ np.linalg.solve(self.NM, NMK)) / kappa
        lbf = log_bayes_factor(A, th[P:], np.array([c.prior_scale for c in cols]))
        return float(dchi2), float(lbf)


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


def _generic_evaluator(dg, model, effect_at):
    """Evidence of an effect whose columns change with its parameters: built at each point."""
    def evaluate(params):
        eff = effect_at(params)
        with dg._columns_kept():
            C = model.ttl_coefficients()
            names = dg.effect_columns(eff, C if eff.needs_coefficients else None, keep_series=False)
            ev = dg.evaluate(model, names)
        return float(ev["delta_chi2"]), float(ev["log_bayes_factor"])
    return evaluate


def profile_search(dg, model, effect, coefficients=None) -> SearchResult:
    """Search the unset :attr:`~ttlcore.diagnose.effects.Effect.searched` options of ``effect``
    against ``model`` (a :class:`ttlcore.diagnose.diagnoser.ModelFit`); see the module docstring.

    Raises ConfigError when the diagnoser has no telemetry (the columns need DWS series)."""

    names = effect.unresolved()
    if not names:
        raise ConfigError(f"effect {effect.name!r}: nothing to search")
    if dg.tm is None:
        raise ConfigError(f"effect {effect.name!r}: searching {', '.join(names)} needs the telemetry")
    ranges = search_ranges(dg, effect)
    lo, hi, fwd, back, is_log = _scaled(ranges, names)

    def effect_at(x):
        v = back(np.clip(np.asarray(x, dtype=float), lo, hi))
        return effect.with_options(**{k: float(f"{float(val):.6g}") for k, val in zip(names, v)})


    data = effect_input_from_telemetry(dg.tm, coefficients)
    mid = effect_at(0.5 * (lo + hi))
    cols0 = mid.columns(data)
    spectral = all(c.response is not None for c in cols0) and not mid.needs_coefficients
    if spectral:
        sp = _Spectral(dg, model, cols0)
        idx = [sp.bases.index(dg.base_column(c)) for c in cols0]
        names_only = names_only_input()
        # the responses of the columns at x: built on the names-only input (no series)
        evaluate = lambda x: sp.evaluate(effect_at(x).columns(names_only), idx)  # noqa: E731
        exact = lambda x: sp.evaluate(effect_at(x).columns(names_only), idx, exact=True)  # noqa: E731
        per_decade = 30
    else:
        gen = _generic_evaluator(dg, model, effect_at)
        evaluate = gen
        per_decade = 6
    def memoised(function):
        """``function`` of the scaled parameters, clipped to the range, evaluated once per point."""
        memo: dict = {}

        def call(x):
            key = tuple(np.round(np.clip(x, lo, hi), 9))
            if key not in memo:
                memo[key] = function(np.array(key))
            return memo[key]

        call.memo = memo
        return call

    score = memoised(evaluate)

    axes = []
    for j in range(len(names)):
        span = (hi[j] - lo[j]) / (math.log(10) if is_log[j] else 1.0)
        if j == 0:
            n = max(8, int(per_decade * span) + 1) if is_log[j] else 24
        elif spectral and is_log[j]:  # a quality factor: 0.5 .. 300 in five steps
            n = 5
        else:
            n = 5 if spectral else 4
        axes.append(np.linspace(lo[j], hi[j], n))
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(names))
    values = np.array([score(x)[0] for x in grid])
    order = np.argsort(-np.nan_to_num(values, nan=-np.inf))
    best_x, best = grid[order[0]], values[order[0]]
    # local refinement from the best few grid points (the profile may have several maxima)
    for start in grid[order[:2]]:
        res = optimize.minimize(lambda x: -score(x)[0], start, method="Nelder-Mead",
                                options={"xatol": 1e-3, "fatol": 1e-2, "maxfev": 100 * len(names)})
        if -res.fun > best:
            best, best_x = -res.fun, np.clip(res.x, lo, hi)
    if spectral:
        # the fast products miss the filter's ringing across the segment tapers: refine
        # with the columns the fit uses (filtered in time, then windowed)
        exact_score = memoised(exact)

        res = optimize.minimize(lambda x: -exact_score(x)[0], best_x, method="Nelder-Mead",
                                options={"xatol": 1e-3, "fatol": 1e-2, "maxfev": 30 * len(names),
                                         "initial_simplex": np.vstack([best_x, best_x + 0.01 * np.eye(len(names))])})
        best_x = np.clip(res.x, lo, hi)
        dchi2, lbf_best = exact_score(best_x)
        n_exact = len(exact_score.memo)
    else:
        n_exact = 0
        dchi2, lbf_best = score(best_x)
    # curvature of l = delta_chi2 / 2 in the scaled parameters (the fast profile for
    # filters: its shape near the optimum is the exact one's to a few per cent)
    d = len(names)
    h = 1e-3 * np.maximum(hi - lo, 1e-12)
    H = np.zeros((d, d))
    for i in range(d):
        for j in range(i, d):
            ei, ej = np.eye(d)[i] * h[i], np.eye(d)[j] * h[j]
            fpp = score(best_x + ei + ej)[0] / 2
            fpm = score(best_x + ei - ej)[0] / 2
            fmp = score(best_x - ei + ej)[0] / 2
            fmm = score(best_x - ei - ej)[0] / 2
            H[i, j] = H[j, i] = -(fpp - fpm - fmp + fmm) / (4 * h[i] * h[j])
    try:
        cov = np.linalg.inv(H)
        ok = np.all(np.linalg.eigvalsh(H) > 0)
    except np.linalg.LinAlgError:
        cov, ok = np.full((d, d), np.nan), False
    sig = np.sqrt(np.abs(np.diag(cov))) if ok else np.full(d, np.nan)
    volume = float(np.prod(hi - lo))
    if ok:
        marg = lbf_best + 0.5 * d * math.log(2 * math.pi) + 0.5 * math.log(np.linalg.det(cov)) - math.log(volume)
    else:  # the grid average (uniform prior over the grid)
        lb = np.array([score(x)[1] for x in grid])
        marg = float(special.logsumexp(lb) - math.log(lb.size))
    marg = float(min(marg, lbf_best))
    est = back(best_x)
    intervals = {}
    for j, k in enumerate(names):
        a, b = best_x[j] - sig[j], best_x[j] + sig[j]
        intervals[k] = (float(np.exp(a)), float(np.exp(b))) if is_log[j] else (float(a), float(b))
    found = effect_at(best_x)
    log.debug("profile search %s: %s, delta chi2 %.1f", effect.name, dict(zip(names, est)), dchi2)
    return SearchResult(found, {k: float(found.options[k]) for k in names}, intervals, float(dchi2),
                        float(lbf_best), marg, len(score.memo) + n_exact, grid=[(list(map(float, back(x))), float(v))
                                                               for x, v in zip(grid, values)])
