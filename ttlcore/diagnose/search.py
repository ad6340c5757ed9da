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

import numpy as np
from scipy import optimize, special

from ..effects.column_tdi import effect_input_from_telemetry
from ..effects.columns import names_only_input
from ..effects.filters import filter_transform, readout_noise_factor
from ..effects.step import Step
from ..errors import ConfigError
from .columns import (
    ColumnSet,
    base_column,
    concat,
    effect_columns,
    eiv_weights,
    filtered_spectra,
)
from .evidence import (
    added_evidence,
    log_bayes_factor,
    stable_solve,
)
from .model_fit import ModelFit
from .offset_search import offset_search
from .search_result import COLLINEAR, SearchResult, search_ranges
from .step_search import step_time_search

log = logging.getLogger(__name__)


def _scaled(ranges, names):
    lo = np.array([ranges[k][0] for k in names], dtype=float)
    hi = np.array([ranges[k][1] for k in names], dtype=float)
    log_ = np.array([ranges[k][2] == "log" for k in names])
    fwd = lambda v: np.where(log_, np.log(np.maximum(v, 1e-300)), v)  # noqa: E731
    back = lambda x: np.where(log_, np.exp(x), x)  # noqa: E731
    return fwd(lo), fwd(hi), fwd, back, log_


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
        self.Pud = np.einsum("smcb,smc->mb", Uconj, data.noise.wd)
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
                r = resp.setdefault(ch, np.zeros((data.grid.f.size, 3, len(parts_of)), dtype=complex))
                r[:, :, i] += data.context.store.eiv_response(data, link, extra) * readout_noise_factor(
                    data.grid.f, factor
                )
        W = eiv_weights(data, model.columns, B)
        P = len(model.columns)
        self.eMB = np.zeros((data.grid.f.size, P, len(bases)))
        self.eBB = np.zeros((data.grid.f.size, len(bases), len(bases)), dtype=complex)
        for r in resp.values():
            self.eMB = self.eMB + np.einsum("mcp,mcb->mpb", r[:, :, :P].conj(), r[:, :, P:]) * W[:P, P:][None]
            self.eBB = self.eBB + np.einsum("mcb,mce->mbe", r[:, :, P:].conj(), r[:, :, P:]) * W[P:, P:][None]
        self.wMc = np.ascontiguousarray(wMconj.reshape(-1, wMconj.shape[-1]).T)  # (P, S m 3)
        self.wdc = data.noise.wd.reshape(-1).conj()
        self._cache: dict = {}
        self._transforms: dict = {}
        self.NM = model.normal[0].sum(axis=(0, 1)) - model.eiv_term.sum(axis=0)
        self.bM = model.normal[1].sum(axis=(0, 1))
        self.thM = np.linalg.solve(self.NM, self.bM)

    def _products(self, idx) -> tuple:
        """The per-bin products of the bases ``idx`` (fixed during a search), taken once:
        for the fast path, those of each distinct base (``u`` in order of first use, and
        the column -> base map ``inv``): ``N_MB`` (u, P, m), ``N_BB`` (u, u, m) and ``b_B``
        (u, m) with the readout-noise terms subtracted; for the exact path, the readout-noise
        terms of each column (k, P, m) and (m, k, k)."""
        key = tuple(idx)
        if key not in self._cache:
            u = list(dict.fromkeys(idx))
            inv = np.array([u.index(i) for i in idx])
            NMB = np.ascontiguousarray((self.PM[:, :, u] - self.eMB[:, :, u]).transpose(2, 1, 0))  # (u, P, m)
            NBB = np.ascontiguousarray((self.Puu[:, u][:, :, u] - self.eBB[:, u][:, :, u]).transpose(1, 2, 0))
            Pud = np.ascontiguousarray(self.Pud[:, u].T)  # (u, m)
            i = list(idx)
            eMB = np.ascontiguousarray(self.eMB[:, :, i].transpose(2, 1, 0))  # (k, P, m)
            eBB = np.ascontiguousarray(self.eBB[:, i][:, :, i])
            self._cache[key] = (inv, NMB, NBB, Pud, eMB, eBB)
        return self._cache[key]

    def evaluate(self, cols, idx, exact: bool = False) -> tuple[float, float]:
        """Evidence of the columns ``cols`` (only their responses and prior scales are
        used) on the bases ``idx``.  Fast: the filters applied to the base columns' segment
        spectra (products over bins only); ``exact``: the base series filtered in time and
        then windowed (:func:`ttlcore.diagnose.columns.filtered_spectra`, as the fit)."""
        data = self.data
        RT = np.stack(
            [
                np.ones(data.grid.f.size, complex)
                if c.response is None
                else np.asarray(c.response(data.grid.f), complex)
                for c in cols
            ]
        )  # (k, m)
        RTc = RT.conj()
        inv, NMB, NBB, Pud, eMB, eBB = self._products(idx)
        k = RT.shape[0]
        if exact:
            eMK = np.stack([(eMB[j] @ RT[j]).real for j in range(k)], axis=1)
            eKK = np.einsum("jm,mjk,km->jk", RTc, eBB, RT).real
            wK = self._exact_spectra(cols, idx)  # (S m 3, k)
            NMK = (self.wMc @ wK).real - eMK
            NKK = (wK.conj().T @ wK).real - eKK
            bK = (wK.T @ self.wdc).real
        else:
            # products over bins, each base's (P, m) products read once for all its columns
            # (the three of a resonance's basis share one base)
            NMK = np.empty((NMB.shape[1], k))
            NKK = np.empty((k, k))
            bK = np.empty(k)
            of = [np.flatnonzero(inv == a) for a in range(len(NMB))]
            for a, ja in enumerate(of):
                NMK[:, ja] = (NMB[a] @ RT[ja].T).real
                bK[ja] = (RTc[ja] @ Pud[a]).real
                for b, jb in enumerate(of):
                    NKK[np.ix_(ja, jb)] = ((RTc[ja] * NBB[a, b]) @ RT[jb].T).real
        P = self.NM.shape[0]
        N = np.block([[self.NM, NMK], [NMK.T, NKK]])
        b = np.r_[self.bM, bK]
        th = stable_solve(N, b)
        if th is None:  # collinear: no gain (a finite value keeps the simplex well defined)
            return 0.0, COLLINEAR
        kappa = data.grid.kappa
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
                self._transforms[i] = filter_transform(self.bases[i].series[:, 0], data.grid.fs)
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
    inp = effect_input_from_telemetry(data.context.tm)
    cols = plain.columns(inp)
    if any(c.response is not None for c in cols) or plain.needs_coefficients:
        return None
    bases = [base_column(data, c) for c in cols]
    base_series = []
    for b in bases:
        if b.series is None:
            raise ValueError(f"{b.names[0]}: the base column's series are needed")
        base_series.append(b.series[:, 0])
    t_dec = data.grid.t0 + np.arange(data.grid.mask.size) / data.grid.fs
    t_ref = inp.t_ref if effect.options.get("t_ref") is None else float(effect.options["t_ref"])
    names_only = names_only_input()

    def evaluate(x):
        eff = effect_at(x)
        phase = 2 * np.pi * (t_dec - t_ref) / float(eff.options["period"])
        mods = (np.sin(phase), np.cos(phase))
        named = eff.columns(names_only)
        series = np.stack([bs * m for bs in base_series for m in mods], axis=1)
        k = series.shape[1]
        w = data.noise.whiten(data.grid.spectra(series))
        cs = ColumnSet(
            tuple(c.name for c in named),
            np.stack([np.ascontiguousarray(w[..., j]) for j in range(k)]).view(np.float64),
            data.noise.key,
            tuple(c.unit for c in named),
            tuple(c.prior_scale for c in named),
            tuple(b.eiv[0] for b in bases for _ in mods),
            tuple(m if b.eiv[0] else None for b in bases for m in mods),
        )
        ev = added_evidence(model, cs)
        return float(ev.delta_chi2), float(ev.log_bayes_factor)

    return evaluate


def profile_search(model: ModelFit, effect, coefficients=None, *, screen: bool = False) -> SearchResult:
    """Search the unset :attr:`~ttlcore.effects.base.Effect.searched` options of
    ``effect`` against ``model`` (see the module docstring): the step time by
    :func:`step_time_search`, the open offsets of a shifted-witness effect
    (:meth:`~ttlcore.effects.shifted._Linearised.open_offsets`) by :func:`offset_search`
    against the model's columns, filters and other parameters by a grid and local
    refinement.

    An effect with its own search (a method ``profile_search(model, coefficients)``, for a
    plugin's effect) is searched by it; a glitch goes to
    :func:`ttlcore.diagnose.glitches.glitch_search` (:func:`ttlcore.diagnose.glitches.effect_search`).

    ``screen``: a candidate's search (:func:`ttlcore.diagnose.candidates.score`), whose
    local refinements are skipped where they cannot make it significant (a filter's exact
    refinement, :data:`REFINE_MARGIN`; a step time below the coarse grid,
    :func:`step_time_search`); a model's effect is always refined.

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
        return step_time_search(model, effect, screen=screen)
    data = model.data
    if data.context.tm is None:
        raise ConfigError(f"effect {effect.name!r}: searching {', '.join(names)} needs the telemetry")
    return _grid_search(model, effect, names, coefficients, screen)


def _grid_search(model: ModelFit, effect, names: list[str], coefficients, screen: bool = False) -> SearchResult:
    """The options ``names`` of ``effect`` searched against ``model`` on a grid refined
    locally, with the evaluator the kind of column allows (:func:`profile_search`)."""
    ranges = search_ranges(model.data, effect)
    lo, hi, fwd, back, is_log = _scaled(ranges, names)
    effect_at = _effect_at(effect, names, lo, hi, back)
    spectral, evaluate, exact, modulated, per_decade = _evaluators(
        model, effect, names, effect_at, 0.5 * (lo + hi), coefficients
    )
    score = _memoised(evaluate, lo, hi)
    grid = _search_grid(lo, hi, is_log, spectral, per_decade)
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
        threshold = model.data.context.settings.log_bf_threshold

        def worth(x, lbf):  # could a refinement make the marginal evidence significant
            return _laplace_evidence(score, x, lo, hi, lbf, grid)[1] + REFINE_MARGIN >= threshold

        best_x, dchi2, lbf_best, n_exact = _refine_exact(exact, best_x, lo, hi, worth if screen else None)
    elif modulated:
        # the estimate scored with the exact columns (the modulated TDI only located it)
        exact_score = _memoised(_generic_evaluator(model, effect_at), lo, hi)
        dchi2, lbf_best = exact_score(best_x)
        n_exact = len(exact_score.memo)
    else:
        n_exact = 0
        dchi2, lbf_best = score(best_x)
    sig, marg = _laplace_evidence(score, best_x, lo, hi, lbf_best, grid)
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


def _effect_at(effect, names: list[str], lo: np.ndarray, hi: np.ndarray, back):
    """``effect_at(x)``: ``effect`` with the options ``names`` at the scaled parameters ``x``
    (clipped to ``[lo, hi]``, 6 significant digits)."""

    def effect_at(x):
        v = back(np.clip(np.asarray(x, dtype=float), lo, hi))
        return effect.with_options(**{k: float(f"{float(val):.6g}") for k, val in zip(names, v)})

    return effect_at


def _evaluators(model: ModelFit, effect, names: list[str], effect_at, mid_x: np.ndarray, coefficients):
    """The evaluators of a point of the search, chosen by the kind of column (of the effect
    at the scaled parameters ``mid_x``, the middle of the range).

    Returns
    -------
    spectral : bool
        Filters on fixed base columns (the fast products of :class:`_Spectral`).
    evaluate : callable
        Scaled parameters -> ``(delta_chi2, log Bayes factor)``.
    exact : callable or None
        For filters, the same with the columns the fit uses.
    modulated : callable or None
        The period of a ``vary=cycle`` witness effect's evaluator (``evaluate`` then).
    per_decade : int
        Grid points per decade of a log-scaled first parameter.
    """
    data = model.data
    mid = effect_at(mid_x)
    cols0 = mid.columns(effect_input_from_telemetry(data.context.tm, coefficients))
    spectral = (
        all(c.response is not None for c in cols0)
        and not mid.needs_coefficients
        and not any(k.startswith("period") for k in names)
    )
    if spectral:
        sp = _Spectral(model, cols0)
        idx = [sp.base_names.index(base_column(data, c).names[0]) for c in cols0]
        names_only = names_only_input()
        # the responses of the columns at x: built on the names-only input (no series)
        evaluate = lambda x: sp.evaluate(effect_at(x).columns(names_only), idx)  # noqa: E731
        exact = lambda x: sp.evaluate(effect_at(x).columns(names_only), idx, exact=True)  # noqa: E731
        return True, evaluate, exact, None, 30
    modulated = _modulated_evaluator(model, effect, effect_at) if names == ["period"] else None
    return False, modulated or _generic_evaluator(model, effect_at), None, modulated, 12 if modulated else 6


def _memoised(function, lo: np.ndarray, hi: np.ndarray):
    """``function`` of the scaled parameters, clipped to the range ``[lo, hi]``, evaluated
    once per point (the cache is the call's attribute ``memo``, read by the callers)."""
    memo: dict = {}

    def call(x):
        key = tuple(np.round(np.clip(x, lo, hi), 9))
        if key not in memo:
            memo[key] = function(np.array(key))
        return memo[key]

    call.memo = memo  # type: ignore[attr-defined]  # the cache, read by the callers
    return call


def _search_grid(lo: np.ndarray, hi: np.ndarray, is_log, spectral: bool, per_decade: int) -> np.ndarray:
    """The grid of scaled parameters (points, parameters): the first parameter
    ``per_decade`` points per decade (at least 8) if log-scaled, else 24; a quality factor
    of filters 5 (0.5 .. 300), other parameters 5 for filters, else 4."""
    axes = []
    for j in range(len(lo)):
        span = (hi[j] - lo[j]) / (math.log(10) if is_log[j] else 1.0)
        if j == 0:
            n = max(8, int(per_decade * span) + 1) if is_log[j] else 24
        elif spectral and is_log[j]:  # a quality factor: 0.5 .. 300 in five steps
            n = 5
        else:
            n = 5 if spectral else 4
        axes.append(np.linspace(lo[j], hi[j], n))
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(lo))


#: The exact refinement of a filter's search (:func:`_refine_exact`) is skipped when the
#: marginal log Bayes factor at the fast optimum (exact evidence there, the fast profile's
#: Occam factor) is this far below the significance threshold: a refinement from there
#: lifted log B at the optimum by 0-7 (the mission week's window 76..99, 2026-11-28:
#: -4.3 -> -1.7 for a resonance of 32.eta, 0 to 2.6 elsewhere; a q = 300 resonance of noise
#: on 6 h, tests/ttlcore/diagnose/test_search.py: -12.5 -> -5.5, marginal -12.5 -> -14.3).
#: Its 30-60 exact evaluations (0.15 s each for a day, three columns) were most of a live
#: diagnosis' candidate phase, spent on candidates no refinement could make significant
#: (docs/diagnostics.md, "Searched parameters"; docs/operations.md, the mission week's sixth run).
REFINE_MARGIN = 10.0


def _refine_exact(exact, best_x: np.ndarray, lo: np.ndarray, hi: np.ndarray, worth=None):
    """Nelder-Mead refinement from ``best_x`` with the columns the fit uses (``exact``): the
    fast products miss the filter's ringing across the segment tapers (filtered in time,
    then windowed).  Not refined when ``worth(best_x, log_bf)`` (the exact log Bayes factor
    at ``best_x``) is false: the point is then the fast profile's optimum, scored exactly.

    Returns the refined point, its delta chi^2 and log Bayes factor, and the number of
    exact evaluations.
    """
    d = len(best_x)
    exact_score = _memoised(exact, lo, hi)
    dchi2, lbf_best = exact_score(best_x)
    if worth is not None and not worth(best_x, lbf_best):
        return np.clip(best_x, lo, hi), dchi2, lbf_best, 1
    res = optimize.minimize(
        lambda x: -exact_score(x)[0],
        best_x,
        method="Nelder-Mead",
        options={
            "xatol": 1e-3,
            "fatol": 1e-2,
            "maxfev": 30 * d,
            "initial_simplex": np.vstack([best_x, best_x + 0.01 * np.eye(d)]),
        },
    )
    best_x = np.clip(res.x, lo, hi)
    dchi2, lbf_best = exact_score(best_x)
    return best_x, dchi2, lbf_best, len(exact_score.memo)


def _laplace_evidence(score, best_x: np.ndarray, lo: np.ndarray, hi: np.ndarray, lbf_best, grid: np.ndarray):
    """The 1-sigma errors of the scaled parameters and the marginal log Bayes factor.

    The curvature of ``l = delta_chi2 / 2`` in the scaled parameters at ``best_x`` (the
    fast profile ``score`` for filters: its shape near the optimum is the exact one's to a
    few per cent) gives the covariance; the evidence is Laplace's around the optimum under a
    uniform prior over ``[lo, hi]``, or the grid average where the curvature is not
    positive definite (NaN errors then); never above ``lbf_best``.
    """
    d = len(best_x)
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
    return sig, float(min(marg, lbf_best))
