"""The step time of ``step`` searched (:func:`step_time_search`): the step columns are
``H(t - t_s)`` times the TDI of the TTL regressors, so a point recomputes one segment's
spectra (the exact TDI of the step patched in where the delays straddle it); a 1-h grid, a
15-min grid around the best, golden section to 0.05 s, the profile's secondary maxima one
to four light travel times away, every 0.25-s cell within 2 s of the best until it stays (docs/diagnostics.md; :mod:`ttlcore.diagnose.search`)."""

from __future__ import annotations

import logging
import math

import numpy as np
from scipy import fft as sp_fft
from scipy import special

from ..effects.column_tdi import columns_tdi, effect_input_from_telemetry
from ..effects.linear_ttl import LinearTTL
from ..effects.step import Step
from ..errors import ConfigError
from ..estimate.spectra import psd_scale
from ..tdi.combinations import MICHELSON, aet, build
from ..tdi.data import history_samples, lowpass_taps
from .columns import (
    eiv_products,
    eiv_weights,
    ttl_columns,
)
from .evidence import (
    Evidence,
    evidence_from_normal,
)
from .model_fit import ModelFit, as_real, gram, gram_x, rhs
from .search_result import SearchResult

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------
# The step time
# ---------------------------------------------------------------------------


def step_time_search(model: ModelFit, step: Step | None = None, *, screen: bool = False) -> SearchResult:
    """Search the step time of ``step`` against ``model``: step columns approximated as
    ``H(t - t_s)`` times the TDI of the TTL regressors (exact but for the ~70 s the TDI
    delays span, which :func:`_step_correction` patches in from the telemetry), Bayes factor
    marginalised over the coarse grid (uniform prior); the evidence at the best time is
    :attr:`SearchResult.evidence`.

    ``screen``: a candidate's search (:func:`ttlcore.diagnose.candidates.score`): when the
    marginal log Bayes factor of the coarse grid is below the significance threshold, the
    time is not refined below the coarse grid - the refinement cannot change that evidence,
    so the candidate stays insignificant, and it is most of the search (3-4 s of a day's)."""
    data = model.data
    grid = data.grid
    s = data.context.settings
    step = step or Step()
    base = [f"{m}.{a}.{sd}" for m in step.mosas for a in step.angles for sd in step.sides]
    if not all(n in data.tdi.regressor_names for n in base):
        raise ConfigError(f"effect 'step': the TDI data lack the regressors {base[:2]}...")
    evaluate_at = _StepProfile(model, base)
    idx = np.flatnonzero(grid.mask)
    # a step closer to the ends than half a coarse step is nearly collinear with the TTL
    # columns themselves: search inside
    t_lo = grid.t0 + idx[0] / grid.fs + s.step_grid / 2
    t_hi = grid.t0 + (idx[-1] + 1) / grid.fs - s.step_grid / 2
    coarse = np.arange(t_lo + s.step_grid / 2, t_hi, s.step_grid)
    if coarse.size == 0:
        coarse = np.array([0.5 * (t_lo + t_hi)])
    results = [(ts, evaluate_at(ts)) for ts in coarse]
    lbfs = np.array([r.log_bayes_factor for _, r in results])
    good = lbfs[np.isfinite(lbfs)]
    marg = float(special.logsumexp(good) - math.log(len(good))) if good.size else float("nan")
    k = int(np.nanargmax(lbfs))
    best = coarse[k]
    if screen and not marg >= s.log_bf_threshold:
        return _step_result(step, best, results[k][1], marg, results)
    fine = np.arange(best - s.step_grid + s.step_refine, best + s.step_grid, s.step_refine)
    fine = fine[(fine > t_lo) & (fine < t_hi)]
    results += [(ts, evaluate_at(ts)) for ts in fine if not np.any(np.isclose(ts, coarse))]
    all_lbf = np.array([r.log_bayes_factor for _, r in results])
    ts_best, ev = results[int(np.nanargmax(all_lbf))]
    ts_best, ev = _golden_section(evaluate_at, results, ts_best, ev, (t_lo, t_hi), s.step_refine)
    # the profile has secondary maxima one or more light travel times from the true step
    # (the TDI terms see the step delayed): try those, then refine around the best
    tau = float(np.mean(data.tdi.ltt_mean))
    for k in (-4, -3, -2, -1, 1, 2, 3, 4):
        ts_best, ev = _try_times(evaluate_at, results, [ts_best + k * tau], ts_best, ev, (t_lo, t_hi))
    # a scan of every 0.25-s cell within 2 s of the best, again around a new best until
    # the best stays (the profile is jagged from cell to cell: a day's step of 0.01 mm/rad
    # had a secondary maximum 1.74 s early, only 540 below the true cell's log Bayes
    # factor; one scan around an earlier best missed the true cell by 0.25 s)
    for _ in range(8):
        centre = ts_best
        ts_best, ev = _try_times(evaluate_at, results, centre + np.arange(-2.0, 2.01, 0.25), ts_best, ev, (t_lo, t_hi))
        if ts_best == centre:
            break
    return _step_result(step, ts_best, ev, marg, results)


def _step_result(step: Step, ts_best: float, ev: Evidence, marg: float, results: list) -> SearchResult:
    """The search's result: the step at ``ts_best`` [s] with its evidence ``ev``, the
    marginal log Bayes factor ``marg`` and every point evaluated (``results``)."""
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


def _golden_section(evaluate_at, results: list, ts_best, ev: Evidence, bounds: tuple, refine: float):
    """Golden-section search of the maximum within one fine step ``refine`` [s] either side
    of ``ts_best`` [s] (inside ``bounds``), to 0.05 s; its last two points join ``results``.

    Returns the best time [s] and its evidence, the given ones if no point beats them.
    """
    a, b = max(ts_best - refine, bounds[0]), min(ts_best + refine, bounds[1])
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
    return ts_best, ev


def _try_times(evaluate_at, results: list, times, ts_best, ev: Evidence, bounds: tuple):
    """The step times ``times`` [s] strictly inside ``bounds`` evaluated in turn (joining
    ``results``); returns the best time [s] and its evidence, ``ts_best`` and ``ev`` unless
    one beats them."""
    for ts in times:
        if bounds[0] < ts < bounds[1]:
            e = evaluate_at(ts)
            results.append((ts, e))
            if e.log_bayes_factor > ev.log_bayes_factor:
                ts_best, ev = ts, e
    return ts_best, ev


class _StepProfile:
    """The evidence of the step columns ``H(t - t_s)`` times the TDI of the TTL regressors
    ``base`` against ``model``, at any step time: ``profile(ts) -> Evidence``.

    The normal equations of the step columns are the regressors' per segment, zero before
    the segment holding ``t_s`` and recomputed for it (the exact TDI of the step patched in
    where the delays straddle it, :func:`_step_correction`); the errors-in-variables term
    is one segment's products times the taper-weighted share of each segment after ``t_s``
    (tail sums over the samples).

    A call is piecewise constant in ``t_s``: it reads ``t_s`` only through comparisons with
    the decimated sample times (the step columns, their readout noise), the segments'
    starts and, for the correction, the telemetry's sample times; one evaluation per cell
    of those grids (the same numbers: the golden section ends inside one cell, and the
    scan and the light-travel-time multiples meet cells already evaluated).
    """

    def __init__(self, model: ModelFit, base: list[str]):
        data = model.data
        grid = data.grid
        self.model, self.data, self.base = model, data, base
        M = model.columns
        Bcs = ttl_columns(data).select(base)
        self.G_MB = gram(data, M, Bcs)  # (S, G, P, k)
        self.G_BB = gram(data, Bcs, Bcs)
        self.N_MM, self.b_M = model.normal
        self.b_B = rhs(data, Bcs)
        self.XM = M.x
        # errors-in-variables of the step columns H(t - t_s) x witness: one segment's products
        # times the taper-weighted share of each segment after t_s (tail sums over the samples)
        nM = len(M)
        self.nM, self.nK = nM, len(base)
        self.E_products = eiv_products(data, M, Bcs)
        self.W_MM = eiv_weights(data, M)
        self.t_flat = np.concatenate([grid.t0 + (s0 + np.arange(grid.L)) / grid.fs for s0 in grid.starts])
        w2 = grid.w2.reshape(-1)
        prof = np.stack(
            [
                w2 if m is None else w2 * np.concatenate([m[s0 : s0 + grid.L] for s0 in grid.starts])
                for m in M.modulation
            ]
            + [w2]
        )
        self.tail = np.concatenate([np.cumsum(prof[:, ::-1], axis=1)[:, ::-1], np.zeros((nM + 1, 1))], axis=1)
        self.stack = np.nan_to_num(  # the stack's own array, converted in place (a day: 0.1 GB)
            np.stack([data.tdi.regressor_series[:, data.tdi.regressor_names.index(n)] for n in base], axis=1),
            copy=False,
        )
        self.names = [f"step.{n}" for n in base]
        self.t_dec = grid.t0 + np.arange(grid.mask.size) / grid.fs  # as _evaluate, eiv_at, _step_correction
        self.memo: dict = {}

    def eiv_at(self, ts: float) -> np.ndarray:
        """The errors-in-variables term of the model's and the step columns at step time ``ts`` [s]."""
        nM, nK, tail = self.nM, self.nK, self.tail
        j = int(np.searchsorted(self.t_flat, ts))  # the first sample at or after t_s
        W = np.empty((nM + nK, nM + nK))
        W[:nM, :nM] = self.W_MM
        W[:nM, nM:] = tail[:nM, j][:, None]
        W[nM:, :nM] = tail[:nM, j][None, :]
        W[nM:, nM:] = tail[nM, j]
        return self.E_products * W[None]

    def cell(self, ts: float) -> tuple:
        """The cell of ``ts`` [s] in the grids a call reads it through."""
        return (
            int(np.searchsorted(self.data.grid.seg_t0, ts, side="right")),
            int(np.searchsorted(self.t_dec, ts)),
            _correction_cell(self.data, ts),
        )

    def __call__(self, ts: float) -> Evidence:
        key = self.cell(ts)
        if key not in self.memo:
            self.memo[key] = self._evaluate(ts)
        return self.memo[key]

    def _evaluate(self, ts: float) -> Evidence:
        grid = self.data.grid
        j = int(np.searchsorted(grid.seg_t0, ts, side="right") - 1)
        after = np.arange(len(grid.starts)) > j
        N_MK = np.where(after[:, None, None, None], self.G_MB, 0.0)
        N_KK = np.where(after[:, None, None, None], self.G_BB, 0.0)
        b_K = np.where(after[:, None, None], self.b_B, 0.0)
        if 0 <= j < len(grid.starts):
            XK = self._segment_columns(ts, j)
            N_MK[j] = gram_x(self.XM[:, j : j + 1], XK, grid.slices)[0]
            N_KK[j] = gram_x(XK, XK, grid.slices)[0]
            b_K[j] = gram_x(XK, self.data.noise.wd[j : j + 1][None].view(np.float64), grid.slices)[0, ..., 0]
        return evidence_from_normal(
            self.model, self.N_MM, N_MK, N_KK, self.b_M, b_K, self.names, np.full(len(self.base), 1e-3), self.eiv_at(ts)
        )

    def _segment_columns(self, ts: float, j: int) -> np.ndarray:
        """The whitened step columns of segment ``j``, which holds ``ts`` [s] (real view)."""
        data, grid = self.data, self.data.grid
        s0 = grid.starts[j]
        h = (grid.t0 + (s0 + np.arange(grid.L)) / grid.fs >= ts).astype(float)
        wm = grid.win * grid.mask[s0 : s0 + grid.L]  # the taper on the valid samples (mask: 0 or 1)
        seg = self.stack[:, :, s0 : s0 + grid.L] * h  # a new array: patched in place
        corr = _step_correction(data, ts, self.base)
        if corr is not None:  # exact TDI of the step near t_s (the delays straddle it)
            k0, c = corr
            lo, hi = max(k0 - s0, 0), min(k0 - s0 + c.shape[-1], grid.L)
            if hi > lo:
                seg[:, :, lo:hi] += c[:, :, lo - (k0 - s0) : hi - (k0 - s0)]
        # spectra of segment j only: segment_fft(seg * m, fs, win * m) with m in {0, 1}
        # (the same products), the taper applied in place, only the analysis bins scaled
        seg *= wm
        X = sp_fft.rfft(seg, axis=-1, workers=None)
        del seg
        X = psd_scale(grid.fs, wm) * X[:, :, grid.bins]
        wK = np.matmul(data.noise.Lh, np.moveaxis(X, 2, 0))[None]  # (1, m, 3, k)
        return as_real(wK)


def _correction_stretch(data, ts: float) -> tuple[int, int, np.ndarray, int]:
    """The telemetry samples ``[a, b)`` around ``t_s`` over which :func:`_step_correction`
    computes the exact TDI of the step, the FIR taps of the decimation and the delays'
    history [samples]."""
    tm, fs = data.context.tm, data.context.tm.fs
    taps = lowpass_taps(fs) if data.grid.decimation > 1 else np.ones(1)
    hist = history_samples(fs, float(np.max(tm.ltt)))
    i_ts = int(np.floor((ts - tm.t0) * fs))
    return max(i_ts - hist - 8, 0), min(i_ts + hist + taps.size + 8, tm.size), taps, hist


def _correction_cell(data, ts: float) -> tuple | None:
    """What :func:`_step_correction` reads of ``t_s``: its stretch of telemetry and the
    number of the stretch's samples before ``t_s`` (None without telemetry)."""
    tm = data.context.tm
    if tm is None:
        return None
    a, b, _, _ = _correction_stretch(data, ts)
    t = (tm.t0 + a / tm.fs) + np.arange(b - a) / tm.fs  # as the stretch's EffectInput.t
    return a, b, int(np.count_nonzero(t < ts))


def _step_correction(data, ts: float, base: list) -> tuple | None:
    """``TDI(H(t - t_s) w) - H(t - t_s) TDI(w)`` for the TTL witnesses ``base``, decimated:
    non-zero only where the TDI delays straddle ``t_s`` (about 70 s, spread by the
    anti-alias filter), computed exactly on a short stretch of telemetry around ``t_s``
    (:func:`_correction_stretch`).

    Returns ``(first decimated sample index, array (3, k, n))`` or None without telemetry.
    """
    if data.context.tm is None:
        return None
    tm, fs = data.context.tm, data.context.tm.fs
    a, b, taps, hist = _correction_stretch(data, ts)
    sub = tm.slice(a, b)
    inp = effect_input_from_telemetry(sub)
    step = (inp.t >= ts).astype(float)
    by_name = {c.name: c for c in LinearTTL().columns(inp)}
    cols = [by_name[n] for n in base]
    for c in cols:
        for p in c.parts:
            p.series = p.series * step
    built = build(
        MICHELSON, sub.ltt, fs, order=data.context.settings.order, delay_order=data.context.settings.delay_order
    )
    exact = aet(columns_tdi(cols, built))  # (3, k, b - a); NaN where delays leave the stretch
    # before t_s - 8 s the step column is exactly zero (NaN only where the delays leave
    # the stretch), and so is the signal before the stretch
    exact = np.nan_to_num(exact)
    exact[..., : hist + 4] = 0.0
    # causal FIR then decimation on the global sample grid, as TDIData.decimated: output i
    # of the local convolution is global sample a + i; keep those inside the stretch
    full = np.apply_along_axis(lambda x: np.convolve(x, taps)[: b - a], -1, exact)
    first = (-a) % data.grid.decimation
    dec = full[..., first :: data.grid.decimation]
    k0 = (a + first) // data.grid.decimation  # decimated index of global sample a + first
    n = dec.shape[-1]
    t_dec = data.grid.t0 + (k0 + np.arange(n)) / data.grid.fs
    idx = [data.tdi.regressor_names.index(nm) for nm in base]
    modulated = data.tdi.regressor_series[:, idx, k0 : k0 + n] * (t_dec >= ts)
    return k0, dec - np.nan_to_num(modulated)
