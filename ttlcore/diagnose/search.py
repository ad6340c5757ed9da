"""Searched nonlinear parameters of any effect: profile chi^2 over them, marginal evidence.

An effect declares the options the diagnosis may search (:attr:`ttlcore.effects.base.Effect.searched`,
``option -> (low, high, scale)``); left unset, :func:`profile_search` finds them against a
fitted model and returns a :class:`SearchResult` (the effect at the estimates, estimates,
intervals, delta chi^2, log Bayes factors at the best point and marginalised).  One
mechanism - chi^2 profiled over every linear parameter on a grid, refined locally, the
evidence marginalised over the searched range - with an evaluator chosen by the kind of
column:

- filters on fixed base columns (:attr:`ttlcore.effects.columns.Column.response`, e.g.
  ``fd-coupling``): a point costs a few products over frequency bins (the base columns'
  cross-products with the model's columns, the data and each other, and their
  readout-noise responses, computed once per search); a grid (30 points per decade for a
  frequency, 5 quality factors), Nelder-Mead from the two best points, then a Nelder-Mead
  refinement with the columns the fit uses (the base series filtered in time, then
  windowed);
- the step time of ``step`` (:func:`step_time_search`): the step columns are ``H(t - t_s)``
  times the TDI of the TTL regressors, so a point recomputes one segment's spectra (the
  exact TDI of the step patched in where the delays straddle it); a 1-h grid, a 15-min
  grid around the best, golden section to 0.05 s, the profile's secondary maxima one to
  four light travel times away;
- the time offsets of the shifted-witness effects ``timing-offset`` and ``ltt-error``
  (declared ``offset.<group>``, one per group; :func:`offset_search`): a shift is a phase
  of the whitened spectra, a grid of spacing ``1 / (8 f_max)`` over ``+-shift_span`` and
  Brent's method, groups in turn, the given offsets held; each group's interval from the
  curvature of its profile (the others held), the marginal evidence by the Laplace rule
  below.  They are searched where a model's columns are built
  (:func:`ttlcore.diagnose.fitting.expand_linearised`: they need the fitted linear
  coefficients), not before the fit (``Effect.unresolved()`` leaves them out);
- the period of a ``vary=cycle`` witness effect: the unmodulated witness's TDI (once)
  times the modulation at each point, the estimate scored with the exact columns;
- anything else (a plugin whose columns change with the parameter, a cycle on a filtered
  coupling): the columns built at each point - correct but slower, a coarser grid.

Then (filters, generic and offsets): a 1-sigma interval from the curvature of the profile
log-likelihood ``l = delta_chi2 / 2`` in the scaled parameters (relative for ``log``), and
the evidence marginalised over the searched parameters under a uniform prior in the scaled
parameters over the declared range (Laplace around the optimum:
``log B = log B(best) + d/2 log 2 pi + 1/2 log det Sigma - log V``), never above the
evidence at the best point; for the offsets ``Sigma`` is diagonal, each group's variance
with the others held.  For the step time, the marginal is the grid average (uniform prior
over the coarse grid).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from scipy import fft as sp_fft
from scipy import optimize, special
from scipy.optimize import minimize_scalar

from ..effects.base import Effect
from ..effects.column_tdi import columns_tdi, effect_input_from_telemetry
from ..effects.columns import names_only_input
from ..effects.coupling import LinearTTL, Step
from ..effects.filters import filter_transform, readout_noise_factor
from ..effects.shifted import OFFSET_OPTION
from ..errors import ConfigError
from ..estimate.spectra import psd_scale
from ..tdi.combinations import MICHELSON, aet, build
from ..tdi.data import history_samples, lowpass_taps
from .columns import (
    ColumnSet,
    base_column,
    concat,
    effect_columns,
    eiv_products,
    eiv_weights,
    filtered_spectra,
    ttl_columns,
)
from .evidence import (
    Evidence,
    added_evidence,
    evidence_from_normal,
    log_bayes_factor,
    stable_solve,
)
from .model_fit import ModelFit, as_real, gram, gram_x, rhs

log = logging.getLogger(__name__)

#: The log Bayes factor a search gives a point where the columns are collinear with the model's.
COLLINEAR = -1e300


@dataclass(frozen=True)
class SearchResult:
    """Outcome of a profile search.

    Attributes
    ----------
    effect : Effect
        The effect with the searched options set to their estimates.
    estimates : dict
        Parameter -> estimate.
    intervals : dict
        Parameter -> (low, high), one sigma from the profile's curvature (empty when not
        measured).
    delta_chi2 : float
        Profiled chi^2 gain at the estimate (over ``kappa``).
    log_bayes_factor_best, log_bayes_factor : float
        At the estimate, and marginalised over the searched parameters.
    n_evaluations : int
    grid : list
        ``(parameters, value)`` of the grid points.
    evidence : Evidence or None
        The evidence at the estimate when the search computed it with columns more exact
        than those :func:`ttlcore.diagnose.columns.effect_columns` gives (the step time).
    gains : dict
        Per searched parameter, the chi^2 gain of its estimate against zero, the others at
        their estimates (offsets).
    theta : dict
        Column -> linear parameter at the optimum (offsets).
    """

    effect: Effect
    estimates: dict
    intervals: dict
    delta_chi2: float
    log_bayes_factor_best: float
    log_bayes_factor: float
    n_evaluations: int
    grid: list = field(default_factory=list, repr=False)
    evidence: Evidence | None = field(default=None, repr=False)
    gains: dict = field(default_factory=dict)
    theta: dict = field(default_factory=dict, repr=False)

    def to_json(self) -> dict:
        return {
            "estimates": {k: float(v) for k, v in self.estimates.items()},
            "intervals": {k: [float(a), float(b)] for k, (a, b) in self.intervals.items()},
            "delta_chi2": float(self.delta_chi2),
            "log_bayes_factor_best": float(self.log_bayes_factor_best),
            "log_bayes_factor_marginal": float(self.log_bayes_factor),
            "evaluations": int(self.n_evaluations),
        }


def _scaled(ranges, names):
    lo = np.array([ranges[k][0] for k in names], dtype=float)
    hi = np.array([ranges[k][1] for k in names], dtype=float)
    log_ = np.array([ranges[k][2] == "log" for k in names])
    fwd = lambda v: np.where(log_, np.log(np.maximum(v, 1e-300)), v)  # noqa: E731
    back = lambda x: np.where(log_, np.exp(x), x)  # noqa: E731
    return fwd(lo), fwd(hi), fwd, back, log_


def search_ranges(data, effect) -> dict:
    """The declared ranges, frequencies (``f0``, ``fc``, names starting with ``f``) clipped
    to the diagnosis band widened by a third of an octave, periods (names starting with
    ``period``) to twice the analysed span, the offsets of shifted-witness effects (names
    starting with ``offset.``) to ``+-settings.shift_span``."""
    out = {}
    idx = np.flatnonzero(data.mask)
    span = (idx[-1] - idx[0]) / data.fs
    for k, (lo, hi, scale) in effect.searched.items():
        if k.startswith("f"):
            lo, hi = max(lo, data.f[0] / 1.26), min(hi, data.f[-1] * 1.26)
        if k.startswith("period"):
            hi = min(hi, 2 * span)
        if k.startswith(OFFSET_OPTION):
            lo, hi = max(lo, -float(data.settings.shift_span)), min(hi, float(data.settings.shift_span))
        if lo >= hi:
            raise ConfigError(f"effect {effect.name!r}: the range of {k} does not fit these data")
        out[k] = (float(lo), float(hi), scale)
    return out


class _Spectral:
    """Per-bin products of the base columns of a filtered effect (built once per search)."""

    def __init__(self, model: ModelFit, cols):
        data = self.data = model.data
        bases: list[ColumnSet] = []
        for c in cols:
            b = base_column(data, c)
            if b.names[0] not in [x.names[0] for x in bases]:
                bases.append(b)
        self.bases = bases
        self.base_names = [b.names[0] for b in bases]
        B = concat(*bases)
        wM = model.columns.w  # (S, m, 3, P)
        wMconj = wM.conj()
        del wM
        U = B.w  # (S, m, 3, nb)
        Uconj = U.conj()
        self.PM = np.einsum("smcp,smcb->mpb", wMconj, U)
        self.Pud = np.einsum("smcb,smc->mb", Uconj, data.wd)
        self.Puu = np.einsum("smcb,smce->mbe", Uconj, U)
        del U, Uconj
        # errors-in-variables: readout-noise responses per DWS channel; only the channels
        # of the base columns add to their products with the model's columns and each other
        parts_of = model.columns.eiv + B.eiv
        touched = {ch for parts in B.eiv for ch, *_ in parts}
        resp: dict = {}
        for i, parts in enumerate(parts_of):
            for ch, link, extra, factor in parts:
                if ch not in touched:
                    continue
                r = resp.setdefault(ch, np.zeros((data.f.size, 3, len(parts_of)), dtype=complex))
                r[:, :, i] += data.store.eiv_response(data, link, extra) * readout_noise_factor(data.f, factor)
        W = eiv_weights(data, model.columns, B)
        P = len(model.columns)
        self.eMB = np.zeros((data.f.size, P, len(bases)))
        self.eBB = np.zeros((data.f.size, len(bases), len(bases)), dtype=complex)
        for r in resp.values():
            self.eMB = self.eMB + np.einsum("mcp,mcb->mpb", r[:, :, :P].conj(), r[:, :, P:]) * W[:P, P:][None]
            self.eBB = self.eBB + np.einsum("mcb,mce->mbe", r[:, :, P:].conj(), r[:, :, P:]) * W[P:, P:][None]
        self.wMc = np.ascontiguousarray(wMconj.reshape(-1, wMconj.shape[-1]).T)  # (P, S m 3)
        self.wdc = data.wd.reshape(-1).conj()
        self._cache: dict = {}
        self._transforms: dict = {}
        self.NM = model.normal[0].sum(axis=(0, 1)) - model.eiv_term.sum(axis=0)
        self.bM = model.normal[1].sum(axis=(0, 1))
        self.thM = np.linalg.solve(self.NM, self.bM)

    def _products(self, idx) -> tuple:
        """The per-bin products of the bases ``idx`` (fixed during a search), taken once:
        ``(N_MB, N_BB, b_B)`` with the readout-noise terms subtracted, the model's whitened
        columns conjugated as a matrix (S m 3, P) for the exact path."""
        key = tuple(idx)
        if key not in self._cache:
            i = list(idx)
            NMB = np.ascontiguousarray((self.PM[:, :, i] - self.eMB[:, :, i]).transpose(2, 1, 0))  # (k, P, m)
            NBB = np.ascontiguousarray(self.Puu[:, i][:, :, i] - self.eBB[:, i][:, :, i])  # (m, k, k)
            eMB = np.ascontiguousarray(self.eMB[:, :, i].transpose(2, 1, 0))  # (k, P, m)
            eBB = np.ascontiguousarray(self.eBB[:, i][:, :, i])
            self._cache[key] = (NMB, NBB, np.ascontiguousarray(self.Pud[:, i].T), eMB, eBB)
        return self._cache[key]

    def evaluate(self, cols, idx, exact: bool = False) -> tuple[float, float]:
        """Evidence of the columns ``cols`` (only their responses and prior scales are
        used) on the bases ``idx``.  Fast: the filters applied to the base columns' segment
        spectra (products over bins only); ``exact``: the base series filtered in time and
        then windowed (:func:`ttlcore.diagnose.columns.filtered_spectra`, as the fit)."""
        data = self.data
        R = np.stack(
            [
                np.ones(data.f.size, complex) if c.response is None else np.asarray(c.response(data.f), complex)
                for c in cols
            ],
            axis=1,
        )  # (m, k)
        Rc = R.conj()
        NMB, NBB, Pud, eMB, eBB = self._products(idx)
        k = R.shape[1]
        if exact:
            eMK = np.stack([(eMB[j] @ R[:, j]).real for j in range(k)], axis=1)
            eKK = np.einsum("mj,mjk,mk->jk", Rc, eBB, R).real
            wK = self._exact_spectra(cols, idx)  # (S m 3, k)
            NMK = (self.wMc @ wK).real - eMK
            NKK = (wK.conj().T @ wK).real - eKK
            bK = (wK.T @ self.wdc).real
        else:
            RT = np.ascontiguousarray(R.T)  # (k, m): the same products as with the strided columns
            NMK = np.stack([(NMB[j] @ RT[j]).real for j in range(k)], axis=1)
            NKK = np.einsum("mj,mjk,mk->jk", Rc, NBB, R).real
            bK = np.einsum("km,mk->k", Pud, Rc).real
        P = self.NM.shape[0]
        N = np.block([[self.NM, NMK], [NMK.T, NKK]])
        b = np.r_[self.bM, bK]
        th = stable_solve(N, b)
        if th is None:  # collinear: no gain (a finite value keeps the simplex well defined)
            return 0.0, COLLINEAR
        kappa = data.kappa
        dchi2 = 2 * (b @ th - self.bM @ self.thM) / kappa
        A = 2 * (NKK - NMK.T @ np.linalg.solve(self.NM, NMK)) / kappa
        lbf = log_bayes_factor(A, th[P:], np.array([c.prior_scale for c in cols]))
        return float(dchi2), float(lbf)

    def _exact_spectra(self, cols, idx) -> np.ndarray:
        """Whitened spectra (S m 3, k) of the columns filtered in time (as the fit's), each
        base's series transformed once for all its columns."""
        data = self.data
        out = np.empty((self.wMc.shape[1], len(cols)), dtype=complex)
        for i in dict.fromkeys(idx):
            js = [j for j, ii in enumerate(idx) if ii == i]
            if i not in self._transforms:  # the base series' transform, once per search
                self._transforms[i] = filter_transform(self.bases[i].series[:, 0], data.fs)
            w, _ = filtered_spectra(data, self.bases[i], [cols[j].response for j in js], self._transforms[i])
            out[:, js] = w.reshape(-1, len(js))
        return out


def _generic_evaluator(model: ModelFit, effect_at):
    """Evidence of an effect whose columns change with its parameters: built at each point
    (not cached)."""

    def evaluate(params):
        eff = effect_at(params)
        C = model.ttl_coefficients()
        cs = effect_columns(model.data, eff, C if eff.needs_coefficients else None, cache=False)
        ev = added_evidence(model, cs)
        return float(ev.delta_chi2), float(ev.log_bayes_factor)

    return evaluate


def _modulated_evaluator(model: ModelFit, effect, effect_at):
    """Evidence of a ``vary=cycle`` effect without filters (a witness effect) at a period:
    its columns are the unmodulated witness columns (exact TDI, computed once) times
    ``sin``/``cos`` of the decimated time - ``TDI(m w) = m TDI(w)`` up to the ~70 s the TDI
    delays span (a relative error ``2 pi 70 s / period``: 0.12 at 1 h, 0.015 at 8 h), enough
    to locate the period; the estimate is then scored with the exact columns.  None when
    the effect is not of that kind."""
    data = model.data
    plain = effect.with_options(vary="none", period=None)
    inp = effect_input_from_telemetry(data.tm)
    cols = plain.columns(inp)
    if any(c.response is not None for c in cols) or plain.needs_coefficients:
        return None
    bases = [base_column(data, c) for c in cols]
    base_series = []
    for b in bases:
        if b.series is None:
            raise ValueError(f"{b.names[0]}: the base column's series are needed")
        base_series.append(b.series[:, 0])
    t_dec = data.t0 + np.arange(data.mask.size) / data.fs
    t_ref = inp.t_ref if effect.options.get("t_ref") is None else float(effect.options["t_ref"])
    names_only = names_only_input()

    def evaluate(x):
        eff = effect_at(x)
        phase = 2 * np.pi * (t_dec - t_ref) / float(eff.options["period"])
        mods = (np.sin(phase), np.cos(phase))
        named = eff.columns(names_only)
        series = np.stack([bs * m for bs in base_series for m in mods], axis=1)
        k = series.shape[1]
        w = data.whiten(data.spectra(series))
        cs = ColumnSet(
            tuple(c.name for c in named),
            np.stack([np.ascontiguousarray(w[..., j]) for j in range(k)]).view(np.float64),
            data.noise_key,
            tuple(c.unit for c in named),
            tuple(c.prior_scale for c in named),
            tuple(b.eiv[0] for b in bases for _ in mods),
            tuple(m if b.eiv[0] else None for b in bases for m in mods),
        )
        ev = added_evidence(model, cs)
        return float(ev.delta_chi2), float(ev.log_bayes_factor)

    return evaluate


def profile_search(model: ModelFit, effect, coefficients=None) -> SearchResult:
    """Search the unset :attr:`~ttlcore.effects.base.Effect.searched` options of
    ``effect`` against ``model`` (see the module docstring): the step time by
    :func:`step_time_search`, the open offsets of a shifted-witness effect
    (:meth:`~ttlcore.effects.shifted._Linearised.open_offsets`) by :func:`offset_search`
    against the model's columns, filters and other parameters by a grid and local
    refinement.

    An effect with its own search (a method ``profile_search(model, coefficients)``, for a
    plugin's effect) is searched by it; a glitch goes to
    :func:`ttlcore.diagnose.glitches.glitch_search` (:func:`ttlcore.diagnose.glitches.effect_search`).

    Raises ConfigError when the data have no telemetry and the columns need DWS series."""
    own = getattr(effect, "profile_search", None)
    if callable(own):
        return own(model, coefficients)
    if hasattr(effect, "shifted_members"):
        return offset_search(model, effect)
    names = effect.unresolved()
    if not names:
        raise ConfigError(f"effect {effect.name!r}: nothing to search")
    if isinstance(effect, Step):
        return step_time_search(model, effect)
    data = model.data
    if data.tm is None:
        raise ConfigError(f"effect {effect.name!r}: searching {', '.join(names)} needs the telemetry")
    ranges = search_ranges(data, effect)
    lo, hi, fwd, back, is_log = _scaled(ranges, names)

    def effect_at(x):
        v = back(np.clip(np.asarray(x, dtype=float), lo, hi))
        return effect.with_options(**{k: float(f"{float(val):.6g}") for k, val in zip(names, v)})

    mid = effect_at(0.5 * (lo + hi))
    cols0 = mid.columns(effect_input_from_telemetry(data.tm, coefficients))
    spectral = (
        all(c.response is not None for c in cols0)
        and not mid.needs_coefficients
        and not any(k.startswith("period") for k in names)
    )
    modulated = None
    if spectral:
        sp = _Spectral(model, cols0)
        idx = [sp.base_names.index(base_column(data, c).names[0]) for c in cols0]
        names_only = names_only_input()
        # the responses of the columns at x: built on the names-only input (no series)
        evaluate = lambda x: sp.evaluate(effect_at(x).columns(names_only), idx)  # noqa: E731
        exact = lambda x: sp.evaluate(effect_at(x).columns(names_only), idx, exact=True)  # noqa: E731
        per_decade = 30
    else:
        modulated = _modulated_evaluator(model, effect, effect_at) if names == ["period"] else None
        evaluate = modulated or _generic_evaluator(model, effect_at)
        per_decade = 12 if modulated else 6

    def memoised(function):
        """``function`` of the scaled parameters, clipped to the range, evaluated once per point."""
        memo: dict = {}

        def call(x):
            key = tuple(np.round(np.clip(x, lo, hi), 9))
            if key not in memo:
                memo[key] = function(np.array(key))
            return memo[key]

        call.memo = memo  # type: ignore[attr-defined]  # the cache, read by the callers
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
    if spectral and all(score(x)[1] == COLLINEAR for x in grid) and exact(best_x)[1] == COLLINEAR:
        # e.g. a coupling placed as a TTL witness: its constant combination is the model's
        # column at every pole, so no refinement can find evidence
        raise ConfigError(
            f"effect {effect.name!r}: columns collinear with the model's at every grid point: no evidence"
        )
    # local refinement from the best few grid points (the profile may have several maxima)
    for start in grid[order[:2]]:
        res = optimize.minimize(
            lambda x: -score(x)[0],
            start,
            method="Nelder-Mead",
            options={"xatol": 1e-3, "fatol": 1e-2, "maxfev": 100 * len(names)},
        )
        if -res.fun > best:
            best, best_x = -res.fun, np.clip(res.x, lo, hi)
    if spectral:
        # the fast products miss the filter's ringing across the segment tapers: refine
        # with the columns the fit uses (filtered in time, then windowed)
        exact_score = memoised(exact)
        res = optimize.minimize(
            lambda x: -exact_score(x)[0],
            best_x,
            method="Nelder-Mead",
            options={
                "xatol": 1e-3,
                "fatol": 1e-2,
                "maxfev": 30 * len(names),
                "initial_simplex": np.vstack([best_x, best_x + 0.01 * np.eye(len(names))]),
            },
        )
        best_x = np.clip(res.x, lo, hi)
        dchi2, lbf_best = exact_score(best_x)
        n_exact = len(exact_score.memo)
    elif modulated:
        # the estimate scored with the exact columns (the modulated TDI only located it)
        exact_score = memoised(_generic_evaluator(model, effect_at))
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
        ok = bool(np.all(np.linalg.eigvalsh(H) > 0))
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
    return SearchResult(
        found,
        {k: float(found.options[k]) for k in names},
        intervals,
        float(dchi2),
        float(lbf_best),
        marg,
        len(score.memo) + n_exact,
        grid=[(list(map(float, back(x))), float(v)) for x, v in zip(grid, values)],
    )


# ---------------------------------------------------------------------------
# The step time
# ---------------------------------------------------------------------------


def step_time_search(model: ModelFit, step: Step | None = None) -> SearchResult:
    """Search the step time of ``step`` against ``model``: step columns approximated as
    ``H(t - t_s)`` times the TDI of the TTL regressors (exact but for the ~70 s the TDI
    delays span, which :func:`_step_correction` patches in from the telemetry), Bayes factor
    marginalised over the coarse grid (uniform prior); the evidence at the best time is
    :attr:`SearchResult.evidence`."""
    data = model.data
    s = data.settings
    step = step or Step()
    base = [f"{m}.{a}.{sd}" for m in step.mosas for a in step.angles for sd in step.sides]
    if not all(n in data.regressor_names for n in base):
        raise ConfigError(f"effect 'step': the TDI data lack the regressors {base[:2]}...")
    M = model.columns
    Bcs = ttl_columns(data).select(base)
    G_MB = gram(data, M, Bcs)  # (S, G, P, k)
    G_BB = gram(data, Bcs, Bcs)
    N_MM, b_M = model.normal
    b_B = rhs(data, Bcs)
    XM = M.x
    # errors-in-variables of the step columns H(t - t_s) x witness: one segment's products
    # times the taper-weighted share of each segment after t_s (tail sums over the samples)
    nM, nK = len(M), len(base)
    E_products = eiv_products(data, M, Bcs)
    W_MM = eiv_weights(data, M)
    t_flat = np.concatenate([data.t0 + (s0 + np.arange(data.L)) / data.fs for s0 in data.starts])
    w2 = data.w2.reshape(-1)
    prof = np.stack(
        [w2 if m is None else w2 * np.concatenate([m[s0 : s0 + data.L] for s0 in data.starts]) for m in M.modulation]
        + [w2]
    )
    tail = np.concatenate([np.cumsum(prof[:, ::-1], axis=1)[:, ::-1], np.zeros((nM + 1, 1))], axis=1)

    def eiv_at(ts):
        j = int(np.searchsorted(t_flat, ts))  # the first sample at or after t_s
        W = np.empty((nM + nK, nM + nK))
        W[:nM, :nM] = W_MM
        W[:nM, nM:] = tail[:nM, j][:, None]
        W[nM:, :nM] = tail[:nM, j][None, :]
        W[nM:, nM:] = tail[nM, j]
        return E_products * W[None]

    idx = np.flatnonzero(data.mask)
    # a step closer to the ends than half a coarse step is nearly collinear with the TTL
    # columns themselves: search inside
    t_lo = data.t0 + idx[0] / data.fs + s.step_grid / 2
    t_hi = data.t0 + (idx[-1] + 1) / data.fs - s.step_grid / 2
    stack = np.nan_to_num(np.stack([data.regressor_series[:, data.regressor_names.index(n)] for n in base], axis=1))
    names = [f"step.{n}" for n in base]
    # evaluate_at(ts) is piecewise constant in ts: it reads ts only through comparisons with
    # the decimated sample times (the step columns, their readout noise), the segments'
    # starts and, for the correction, the telemetry's sample times; one evaluation per
    # cell of those grids (the same numbers: the golden section ends inside one cell, and
    # the scan and the light-travel-time multiples meet cells already evaluated)
    t_dec = data.t0 + np.arange(data.mask.size) / data.fs  # as evaluate_at, eiv_at, _step_correction
    memo: dict = {}

    def cell(ts) -> tuple:
        return (
            int(np.searchsorted(data.seg_t0, ts, side="right")),
            int(np.searchsorted(t_dec, ts)),
            _correction_cell(data, ts),
        )

    def evaluate_at(ts) -> Evidence:
        key = cell(ts)
        if key not in memo:
            memo[key] = _evaluate_at(ts)
        return memo[key]

    def _evaluate_at(ts) -> Evidence:
        j = int(np.searchsorted(data.seg_t0, ts, side="right") - 1)
        after = np.arange(len(data.starts)) > j
        N_MK = np.where(after[:, None, None, None], G_MB, 0.0)
        N_KK = np.where(after[:, None, None, None], G_BB, 0.0)
        b_K = np.where(after[:, None, None], b_B, 0.0)
        if 0 <= j < len(data.starts):
            s0 = data.starts[j]
            h = (data.t0 + (s0 + np.arange(data.L)) / data.fs >= ts).astype(float)
            wm = data.win * data.mask[s0 : s0 + data.L]  # the taper on the valid samples (mask: 0 or 1)
            seg = stack[:, :, s0 : s0 + data.L] * h  # a new array: patched in place
            corr = _step_correction(data, ts, base)
            if corr is not None:  # exact TDI of the step near t_s (the delays straddle it)
                k0, c = corr
                lo, hi = max(k0 - s0, 0), min(k0 - s0 + c.shape[-1], data.L)
                if hi > lo:
                    seg[:, :, lo:hi] += c[:, :, lo - (k0 - s0) : hi - (k0 - s0)]
            # spectra of segment j only: segment_fft(seg * m, fs, win * m) with m in {0, 1}
            # (the same products), the taper applied in place, only the analysis bins scaled
            seg *= wm
            X = sp_fft.rfft(seg, axis=-1, workers=None)
            del seg
            X = psd_scale(data.fs, wm) * X[:, :, data.bins]
            wK = np.matmul(data.Lh, np.moveaxis(X, 2, 0))[None]  # (1, m, 3, k)
            XK = as_real(wK)
            N_MK[j] = gram_x(XM[:, j : j + 1], XK, data.slices)[0]
            N_KK[j] = gram_x(XK, XK, data.slices)[0]
            b_K[j] = gram_x(XK, data.wd[j : j + 1][None].view(np.float64), data.slices)[0, ..., 0]
        return evidence_from_normal(model, N_MM, N_MK, N_KK, b_M, b_K, names, np.full(len(base), 1e-3), eiv_at(ts))

    coarse = np.arange(t_lo + s.step_grid / 2, t_hi, s.step_grid)
    if coarse.size == 0:
        coarse = np.array([0.5 * (t_lo + t_hi)])
    results = [(ts, evaluate_at(ts)) for ts in coarse]
    lbfs = np.array([r.log_bayes_factor for _, r in results])
    best = coarse[int(np.nanargmax(lbfs))]
    fine = np.arange(best - s.step_grid + s.step_refine, best + s.step_grid, s.step_refine)
    fine = fine[(fine > t_lo) & (fine < t_hi)]
    results += [(ts, evaluate_at(ts)) for ts in fine if not np.any(np.isclose(ts, coarse))]
    all_lbf = np.array([r.log_bayes_factor for _, r in results])
    ts_best, ev = results[int(np.nanargmax(all_lbf))]
    # golden-section search of the maximum within one fine step either side, to 0.05 s
    a, b = max(ts_best - s.step_refine, t_lo), min(ts_best + s.step_refine, t_hi)
    ratio = (math.sqrt(5) - 1) / 2
    c, d = b - ratio * (b - a), a + ratio * (b - a)
    ec, ed = evaluate_at(c), evaluate_at(d)
    while b - a > 0.05:  # a step between two samples: the profile is flat within 0.25 s
        if np.nan_to_num(ec.delta_chi2, nan=-np.inf) >= np.nan_to_num(ed.delta_chi2, nan=-np.inf):
            b, d, ed = d, c, ec
            c = b - ratio * (b - a)
            ec = evaluate_at(c)
        else:
            a, c, ec = c, d, ed
            d = a + ratio * (b - a)
            ed = evaluate_at(d)
    for ts, e in ((c, ec), (d, ed)):
        results.append((ts, e))
        if e.log_bayes_factor > ev.log_bayes_factor:
            ts_best, ev = ts, e
    # the profile has secondary maxima one or more light travel times from the true step
    # (the TDI terms see the step delayed): try those, then refine around the best
    tau = float(np.mean(data.ltt_mean))
    for k in (-4, -3, -2, -1, 1, 2, 3, 4):
        ts = ts_best + k * tau
        if t_lo < ts < t_hi:
            e = evaluate_at(ts)
            results.append((ts, e))
            if e.log_bayes_factor > ev.log_bayes_factor:
                ts_best, ev = ts, e
    for ts in ts_best + np.arange(-2.0, 2.01, 0.25):
        if t_lo < ts < t_hi:
            e = evaluate_at(ts)
            results.append((ts, e))
            if e.log_bayes_factor > ev.log_bayes_factor:
                ts_best, ev = ts, e
    good = lbfs[np.isfinite(lbfs)]
    marg = float(special.logsumexp(good) - math.log(len(good))) if good.size else float("nan")
    found = step.with_options(t_step=round(float(ts_best), 3))
    log.debug("step time search: %.3f s, delta chi2 %.1f", ts_best, ev.delta_chi2)
    return SearchResult(
        found,
        {"t_step": float(ts_best)},
        {},
        float(ev.delta_chi2),
        float(ev.log_bayes_factor),
        marg,
        len(results),
        grid=[([float(t)], float(e.log_bayes_factor)) for t, e in results],
        evidence=ev,
    )


def _correction_stretch(data, ts: float) -> tuple[int, int, np.ndarray, int]:
    """The telemetry samples ``[a, b)`` around ``t_s`` over which :func:`_step_correction`
    computes the exact TDI of the step, the FIR taps of the decimation and the delays'
    history [samples]."""
    tm, fs = data.tm, data.tm.fs
    taps = lowpass_taps(fs) if data.decimation > 1 else np.ones(1)
    hist = history_samples(fs, float(np.max(tm.ltt)))
    i_ts = int(np.floor((ts - tm.t0) * fs))
    return max(i_ts - hist - 8, 0), min(i_ts + hist + taps.size + 8, tm.size), taps, hist


def _correction_cell(data, ts: float) -> tuple | None:
    """What :func:`_step_correction` reads of ``t_s``: its stretch of telemetry and the
    number of the stretch's samples before ``t_s`` (None without telemetry)."""
    if data.tm is None:
        return None
    a, b, _, _ = _correction_stretch(data, ts)
    t = (data.tm.t0 + a / data.tm.fs) + np.arange(b - a) / data.tm.fs  # as the stretch's EffectInput.t
    return a, b, int(np.count_nonzero(t < ts))


def _step_correction(data, ts: float, base: list) -> tuple | None:
    """``TDI(H(t - t_s) w) - H(t - t_s) TDI(w)`` for the TTL witnesses ``base``, decimated:
    non-zero only where the TDI delays straddle ``t_s`` (about 70 s, spread by the
    anti-alias filter), computed exactly on a short stretch of telemetry around ``t_s``
    (:func:`_correction_stretch`).

    Returns ``(first decimated sample index, array (3, k, n))`` or None without telemetry.
    """
    if data.tm is None:
        return None
    tm, fs = data.tm, data.tm.fs
    a, b, taps, hist = _correction_stretch(data, ts)
    sub = tm.slice(a, b)
    inp = effect_input_from_telemetry(sub)
    step = (inp.t >= ts).astype(float)
    by_name = {c.name: c for c in LinearTTL().columns(inp)}
    cols = [by_name[n] for n in base]
    for c in cols:
        for p in c.parts:
            p.series = p.series * step
    built = build(MICHELSON, sub.ltt, fs, order=data.settings.order, delay_order=data.settings.delay_order)
    exact = aet(columns_tdi(cols, built))  # (3, k, b - a); NaN where delays leave the stretch
    # before t_s - 8 s the step column is exactly zero (NaN only where the delays leave
    # the stretch), and so is the signal before the stretch
    exact = np.nan_to_num(exact)
    exact[..., : hist + 4] = 0.0
    # causal FIR then decimation on the global sample grid, as TDIData.decimated: output i
    # of the local convolution is global sample a + i; keep those inside the stretch
    full = np.apply_along_axis(lambda x: np.convolve(x, taps)[: b - a], -1, exact)
    first = (-a) % data.decimation
    dec = full[..., first :: data.decimation]
    k0 = (a + first) // data.decimation  # decimated index of global sample a + first
    n = dec.shape[-1]
    t_dec = data.t0 + (k0 + np.arange(n)) / data.fs
    idx = [data.regressor_names.index(nm) for nm in base]
    modulated = data.regressor_series[:, idx, k0 : k0 + n] * (t_dec >= ts)
    return k0, dec - np.nan_to_num(modulated)


# ---------------------------------------------------------------------------
# Time offsets of the shifted-witness effects
# ---------------------------------------------------------------------------


def offset_search(model: ModelFit, effect, passes: int = 4) -> SearchResult:
    """Profile-likelihood search of the open offsets of a shifted-witness effect.

    The exact model of ``timing-offset`` and ``ltt-error`` replaces the witnesses of the
    coefficients of group ``g`` (:meth:`~ttlcore.effects.shifted._Linearised.shifted_members`) by
    the same witnesses shifted by ``s delta_g`` (``s`` =
    :attr:`~ttlcore.effects.shifted._Linearised.d1_sign`).  A shift is the phase
    ``exp(2 pi i f s delta_g)`` of the whitened spectra (TDI commutes with it up to the
    arms' rate of change, ~1e-8; the segment taper changes by ``delta / T`` ~ 1e-4), so
    the chi^2 profiled over the linear parameters ``theta`` of the model's columns,

        Q(delta) = dd - b(delta)^T [N(delta) - E]^-1 b(delta),     chi2 = 2 Q / kappa,

    is cheap to evaluate for many offsets.  Each open group's offset (option
    ``offset.<group>`` unset, :meth:`~ttlcore.effects.shifted._Linearised.open_offsets`) is
    scanned on a grid of spacing ``1 / (8 f_max)`` over its range
    (:func:`search_ranges`: ``+-settings.shift_span``) with the other groups held, the best
    point refined by bounded Brent minimisation; groups are visited in turn (coordinate
    descent) until no offset moves by more than 1 ms, at most ``passes`` rounds.  Groups
    whose offset is given are held at it.

    Then, per open group with the others held at their estimates (one group at a time: a
    conditional interval, which the groups' weak correlation makes close to the marginal
    one), the 1-sigma interval from the curvature of the profile at the optimum,
    ``sigma^2 = kappa / Q''`` (a central difference with a step of about sigma); and the
    evidence: at the optimum, ``log B = delta_chi2 / 2 - 1/2 [log det(N - E)(delta) - log
    det(N - E)(0)]`` against the open offsets at zero (the shifted model has the same
    linear parameters as the unshifted one, flat prior on them), marginalised over a
    uniform prior on each open offset's range by Laplace's rule,
    ``+ sum_g [1/2 log 2 pi + log sigma_g - log(high_g - low_g)]`` (the groups' profile
    integrated on the grid where its curvature is not positive), never above the value at
    the optimum.

    Parameters
    ----------
    model : ModelFit
        The model without the effect; its columns must hold the shifted coefficients'
        (its normal equations and errors-in-variables term are the unshifted ones).
    effect : ttlcore.effects.shifted._Linearised
        ``timing-offset``, ``ltt-error`` or a plugin with the same interface.

    Returns
    -------
    SearchResult
        ``effect`` with the open offsets set to the estimates (6 significant digits);
        ``estimates``, ``intervals``: option ``offset.<group>`` -> offset [s] at the profile
        optimum, and its 1-sigma interval; ``gains``: option -> chi^2 gain (over ``kappa``)
        of the group's offset against zero, the others at their optimum; ``delta_chi2``:
        the joint gain of the open offsets against zero; ``theta``: column -> linear
        parameter at the optimum.

    Raises ConfigError when the effect has no open offset or the model lacks the columns.
    """
    data, columns = model.data, model.columns
    option = {g: f"{OFFSET_OPTION}{g}" for g in effect.shifted_members()}
    open_groups = effect.open_offsets()
    if not open_groups:
        raise ConfigError(f"effect {effect.name!r}: every offset is given; nothing to search")
    ranges = search_ranges(data, effect)
    names = list(columns.names)
    members = {
        g: [names.index(n) for n in mem] for g, mem in effect.shifted_members().items() if all(n in names for n in mem)
    }
    held = {g: v for g, v in effect.fixed_offsets().items() if g in members}
    searched = [g for g in open_groups if g in members]
    if not searched:
        raise ConfigError(f"effect {effect.name!r}: the model lacks the linear-ttl columns its offsets shift")
    P = len(names)
    X = columns.w  # (S, m, 3, P)
    S, m = X.shape[:2]
    X = np.ascontiguousarray(X.transpose(1, 0, 2, 3)).reshape(m, S * 3, P)
    d = np.ascontiguousarray(data.wd.transpose(1, 0, 2)).reshape(m, S * 3)
    w = 2 * np.pi * data.f * float(effect.d1_sign)  # phase [rad] per second of offset
    E = model.eiv_term.sum(axis=0)
    dd = float(data.dd.sum())
    delta = {g: held.get(g, 0.0) for g in members}
    step = 1.0 / (8.0 * data.f[-1])
    grids = {g: np.arange(ranges[option[g]][0], ranges[option[g]][1] + 0.5 * step, step) for g in searched}
    n_eval = 0
    # a shift is a phase per bin and column: the normal equations at any offsets are
    # phase-weighted sums over bins of the products of each group's columns with all the
    # columns and the data, taken once here; at zero offsets they are the model's
    N0 = model.normal[0].sum(axis=(0, 1))
    b0 = model.normal[1].sum(axis=(0, 1))
    QX, Qd = {}, {}
    for g, J in members.items():
        XJh = np.ascontiguousarray(np.swapaxes(X[:, :, J], 1, 2).conj())  # (m, |J|, S 3)
        QX[g] = np.matmul(XJh, X)  # (m, |J|, P)
        Qd[g] = np.matmul(XJh, d[:, :, None])[..., 0]  # (m, |J|)
    del X, d
    # the columns' classes: 0 unshifted, 1 + i the i-th group's
    groups = list(members)
    cls = np.zeros(P, dtype=int)
    for i, g in enumerate(groups):
        cls[members[g]] = i + 1

    def phases(col):
        """``exp(i w c)`` per bin and class (m, 1 + groups) at the offsets ``col`` [s]."""
        return np.exp(1j * np.outer(w, np.r_[0.0, [col[members[g][0]] for g in groups]]))

    def normal_at(col):
        """``(N, b)`` with the columns shifted by ``col`` [s] (the groups' columns only)."""
        N, b = N0.copy(), b0.copy()
        if not col.any():
            return N, b
        T = phases(col)
        for i, (h, J) in enumerate(members.items()):
            rel = T * T[:, i + 1].conj()[:, None]  # exp(i w (c_u - c_h))
            rows = np.einsum("mjp,mp->jp", QX[h], rel[:, cls]).real
            N[J, :] = rows
            N[:, J] = rows.T
            b[J] = (T[:, i + 1].conj() @ Qd[h]).real
        return N, b

    def columns_at(offsets):
        """Per column, the offset [s] of its group in ``offsets`` (0 for unshifted columns)."""
        col = np.zeros(P)
        for h, idx in members.items():
            col[idx] = offsets[h]
        return col

    def profile(g):
        """Q(delta_g) on an array of offsets, the other groups at ``delta``."""
        J = members[g]
        R = [i for i in range(P) if i not in J]
        col = columns_at({h: (0.0 if h == g else delta[h]) for h in members})
        N, b = normal_at(col)
        N = N - E
        ph = phases(col)[:, cls[R]]  # exp(i w c_R)
        Q = np.concatenate([(QX[g][:, :, R] * ph[:, None, :]).reshape(m, -1), Qd[g]], axis=1)  # (m, |J| (|R| + 1))
        QQ = np.concatenate([Q.real, Q.imag], axis=0)  # Re(exp(-i x w) Q) = cos(x w) Re Q + sin(x w) Im Q
        del Q

        def q(x):
            nonlocal n_eval
            x = np.atleast_1d(np.asarray(x, dtype=float))
            n_eval += x.size
            xw = np.outer(x, w)
            A = np.concatenate([np.cos(xw), np.sin(xw)], axis=1) @ QQ  # (K, |J| (|R| + 1))
            NJR = A[:, : len(J) * len(R)].reshape(-1, len(J), len(R))
            Nk = np.broadcast_to(N, (x.size, P, P)).copy()
            bk = np.broadcast_to(b, (x.size, P)).copy()
            Nk[:, np.ix_(J, R)[0], np.ix_(J, R)[1]] = NJR
            Nk[:, np.ix_(R, J)[0], np.ix_(R, J)[1]] = np.swapaxes(NJR, 1, 2)
            bk[:, J] = A[:, len(J) * len(R) :]
            th = np.linalg.solve(Nk, bk[..., None])[..., 0]
            return dd - np.einsum("kp,kp->k", bk, th), th

        return q

    gain, theta, moved = {}, None, np.inf
    profiles: dict = {}
    for _ in range(passes):
        moved = 0.0
        for g in searched:
            q = profile(g)
            Qg, _ = q(grids[g])
            profiles[g] = Qg
            x0 = float(grids[g][int(np.argmin(Qg))])
            lo, hi = ranges[option[g]][:2]
            res = minimize_scalar(
                lambda x, q=q: float(q(x)[0][0]),
                bounds=(max(x0 - step, lo), min(x0 + step, hi)),
                method="bounded",
                options={"xatol": 1e-4},
            )
            best = float(res.x) if res.fun <= Qg.min() else x0
            moved = max(moved, abs(best - delta[g]))
            delta[g] = best
            (q0, q1), th = q(np.array([0.0, best]))
            gain[g], theta = 2.0 * (q0 - q1) / data.kappa, th[1]
        if moved < 1e-3:  # the gains of this pass hold: no other offset moved since
            break
    # the gains (if the last pass moved an offset) and the curvature, each group with the
    # others at their estimates
    sigma = {}
    for g in searched:
        q = profile(g)
        if moved >= 1e-3:
            (q0, q1), th = q(np.array([0.0, delta[g]]))
            gain[g], theta = 2.0 * (q0 - q1) / data.kappa, th[1]
        sigma[g] = _offset_sigma(q, delta[g], data.kappa, step)
    # the joint gain and the evidence against the open offsets at zero (the given ones held)
    logdet, q_at = [], []
    for offsets in ({g: held.get(g, 0.0) for g in members}, delta):
        N, b = normal_at(columns_at(offsets))
        N = N - E
        q_at.append(dd - b @ np.linalg.solve(N, b))
        logdet.append(np.linalg.slogdet(N)[1])
    dchi2 = 2.0 * (q_at[0] - q_at[1]) / data.kappa
    lbf_best = 0.5 * dchi2 - 0.5 * (logdet[1] - logdet[0])
    marg = lbf_best
    for g in searched:
        lo, hi = ranges[option[g]][:2]
        if np.isfinite(sigma[g]):
            marg += 0.5 * math.log(2 * math.pi) + math.log(sigma[g]) - math.log(hi - lo)
        else:  # a flat or multimodal profile: its likelihood averaged over the grid
            marg += float(
                special.logsumexp(-(profiles[g] - profiles[g].min()) / data.kappa) - math.log(profiles[g].size)
            )
    marg = float(min(marg, lbf_best))
    log.debug("offset search %s: %s", effect.name, {g: round(v, 4) for g, v in delta.items()})
    est = {option[g]: float(delta[g]) for g in searched}
    found = effect.with_options(**{k: float(f"{v:.6g}") for k, v in est.items()})
    intervals = {option[g]: (delta[g] - sigma[g], delta[g] + sigma[g]) for g in searched if np.isfinite(sigma[g])}
    return SearchResult(
        found,
        est,
        intervals,
        float(dchi2),
        float(lbf_best),
        marg,
        n_eval,
        gains={option[g]: float(v) for g, v in gain.items()},
        theta=dict(zip(names, theta)) if theta is not None else {},
    )


def _offset_sigma(q, x0: float, kappa: float, grid_step: float) -> float:
    """One sigma [s] of an offset from the curvature of the profile ``q`` (``Q``, chi^2 =
    ``2 Q / kappa``) at its optimum ``x0``: ``sigma^2 = kappa / Q''``, by a central
    difference with a step of a hundredth of the grid's, then again with a step of the
    sigma found (the profile is quadratic over a sigma; rounding in ``Q`` matters for much
    smaller steps).  NaN where the curvature is not positive (a flat profile)."""
    h = grid_step / 100.0
    sigma = float("nan")
    for _ in range(2):
        (qm, q0, qp), _ = q(np.array([x0 - h, x0, x0 + h]))
        curv = (qp - 2.0 * q0 + qm) / h**2
        if not curv > 0:
            return float("nan")
        sigma = math.sqrt(kappa / curv)
        h = min(max(sigma, 1e-7), grid_step)
    return sigma
