"""The glitch search: the time, damping and test mass of a glitch against a fitted model.

The effect (:class:`ttlcore.effects.glitch.Glitch`: the LISA Pathfinder shapelet, docs/diagnostics.md,
"Glitches and gates") is defined below the diagnosis; its unset time ``t``, damping ``beta``
and placement (test mass or link) are searched here (:func:`glitch_search`), each template
the exact TDI of its parts on a stretch of telemetry (:func:`glitch_series`).
:func:`effect_search` is the search of any effect's unset parameters: the glitch's here,
the others' by :func:`ttlcore.diagnose.search.profile_search`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator

import numpy as np
from scipy import fft as sp_fft
from scipy import optimize

from ..conventions import C
from ..effects.column_tdi import effect_input_from_telemetry, tdi_in_blocks
from ..effects.columns import Column, Part
from ..effects.glitch import (
    BETA_GRID,
    BETA_RANGE,
    GLITCH_PRIOR,
    PLACEMENTS,
    Glitch,
    _parse_span,
    glitch_velocity,
    placement_parts,
)
from ..errors import ConfigError
from ..tdi.data import history_samples
from .columns import ColumnSet
from .evidence import added_evidence
from .search import profile_search
from .search_result import COLLINEAR, SearchResult
from .whitened import AnalysisGrid

log = logging.getLogger(__name__)


def glitch_series(data, where, t_glitch: float, beta: float) -> np.ndarray:
    """Decimated A, E, T (3, n) of a unit glitch (``dv = 1 m/s``) placed ``where`` at
    ``t_glitch`` with damping ``beta`` - (3, k, n) for a list of ``k`` placements: the
    exact TDI of its parts computed on a stretch of telemetry from the delays' history
    before ``t_glitch`` to ``12 beta + 300 s`` after it (beyond, TDI cancels the velocity
    step that stays, to ``13 exp(-12)``), zero elsewhere (:func:`glitch_stretch`)."""
    many = not isinstance(where, str)
    k0, x = glitch_stretch(data, list(where) if many else [where], t_glitch, beta)
    out = np.zeros((3, x.shape[1], data.grid.mask.size))
    out[:, :, k0 : k0 + x.shape[-1]] = x
    return out if many else out[:, 0]


def glitch_stretch(data, wheres: list, t_glitch: float, beta: float) -> tuple[int, np.ndarray]:
    """``(k0, x)``: the decimated A, E, T (3, k, n') of unit glitches at the ``k`` placements
    ``wheres`` on the stretch of :func:`glitch_series` where they are not zero, from the
    decimated sample ``k0``.  The stretch starts on a multiple of the decimation factor, so
    that its decimated samples are the data's; on gated data the series is gated once
    placed.  (A day's full-length series of twelve placements are 50 MB, made and
    transformed for every template of a glitch search.)"""
    tm = data.context.tm
    if tm is None:
        raise ConfigError("effect 'glitch' needs the telemetry")
    fs = float(tm.fs)
    dec = int(data.grid.decimation)
    hist = history_samples(fs, float(np.nanmax(tm.ltt)))
    i0 = int(math.floor((t_glitch - float(tm.t0)) * fs))
    a = max(i0 - hist - 16, 0)
    a -= a % dec
    b = min(max(i0, 0) + hist + int((12.0 * beta + 300.0) * fs), tm.size)
    n_dec = data.grid.mask.size
    if b <= a + hist:
        return 0, np.zeros((3, len(wheres), 0))
    sub = tm.slice(a, b)
    inp = effect_input_from_telemetry(sub)
    v = glitch_velocity(inp.t, t_glitch, beta) / C
    cols = [Column(w, [Part(link, factor * v, n) for link, n, factor in placement_parts(w)]) for w in wheres]
    _, xyz = tdi_in_blocks(
        sub.ltt, fs, cols, order=data.context.settings.order, delay_order=data.context.settings.delay_order
    )
    # (3, k, m): global decimated samples a / dec + j, ungated (a stretch), gated once placed
    x = AnalysisGrid.decimate(data.grid, np.nan_to_num(xyz))
    k0 = a // dec
    m = max(min(x.shape[-1], n_dec - k0), 0)
    x = x[:, :, :m]
    g = getattr(data.grid, "gate", None)
    if g is not None:
        x = x * g[k0 : k0 + m]
    return k0, x


def glitch_spectra(data, where, t_glitch: float, beta: float) -> np.ndarray:
    """Whitened segment spectra (S, m, 3) of a unit glitch (:func:`glitch_series`); (S, m,
    3, k) for a list of placements."""
    many = not isinstance(where, str)
    first, w = glitch_spectra_of(data, list(where) if many else [where], t_glitch, beta)
    out = np.zeros((len(data.grid.starts),) + w.shape[1:], dtype=complex)
    out[first : first + w.shape[0]] = w
    return out if many else out[..., 0]


def glitch_spectra_of(data, wheres: list, t_glitch: float, beta: float) -> tuple[int, np.ndarray]:
    """``(first, G)``: the whitened spectra (s, m, 3, k) of unit glitches at the placements
    ``wheres`` (:func:`glitch_stretch`) in the ``s`` segments from ``first`` that their
    stretch reaches (zero in the others: neither transformed nor whitened)."""
    k0, x = glitch_stretch(data, wheres, t_glitch, beta)
    segments = data.grid.segments_over(k0, k0 + x.shape[-1])
    if not len(segments):
        segments = range(1)  # nowhere in the segments: one segment of zeros
    return segments.start, data.noise.whiten(data.grid.spectra_of(x, k0, segments))


#: A template whose part the model's columns do not explain (``D`` of :class:`_Scanner`) is
#: below this share of its norm holds no information of its own (a glitch in FFT segments
#: gated out or left out: a zero column, or one collinear with the model's): its gain is 0.
#: Before, ``0 / 1e-300`` there could be the best of the scan, at a time with no data.
DEGENERATE = 1e-9
#: Bytes of the template-model products :class:`_Scanner` holds at once (a few templates').
PRODUCTS_BYTES = 24e6


class _Scanner:
    """Profile of a glitch's time against a fitted model, for templates.

    Adding one column ``g`` to the model ``M`` (fitted: residual ``r``, normal matrix with
    errors in variables ``N_MM - E``) gains

        delta chi2 = 2 c^2 / (D kappa),  c = Re sum conj(g) r,
        D = Re sum |g|^2 - n^T (N_MM - E)^-1 n,  n = Re sum conj(g) M,

    (the glitch column carries no readout noise).  A template moved by ``tau`` is the
    phase ``exp(-2 pi i f tau)`` of its spectra (inside one segment, away from the taper),
    so ``c`` and ``n`` at every shift by a sample of the decimated grid are one inverse FFT
    of their per-bin products over the segment's frequency grid (``n`` matters: a glitch
    already in the model, near in time, is correlated with the template).  The model's columns and
    residual are arranged once per search (:meth:`products` then costs a batched product
    per template)."""

    def __init__(self, model):
        self.data = model.data
        S, m = model.residual_w.shape[:2]
        self.r = np.ascontiguousarray(model.residual_w.transpose(1, 0, 2)).reshape(m, S * 3)
        x = model.columns.x.view(complex)  # (P, S, m, 3)
        self.M = np.ascontiguousarray(x.transpose(2, 1, 3, 0)).reshape(m, S * 3, -1)  # (m, S 3, P)
        NM = model.normal[0].sum(axis=(0, 1)) - model.eiv_term.sum(axis=0)
        self.NMinv = np.linalg.inv(NM)

    def products(self, G: np.ndarray, first: int = 0) -> list[tuple]:
        """``(p (m,), q (m, P), |g|^2)`` per template of ``G`` (s, m, 3, k), the spectra of
        the segments ``first .. first + s - 1`` (zero in the others,
        :func:`glitch_spectra_of`): the per-bin products ``sum conj(g) r``, ``sum conj(g)
        M``.  Over those segments only: the others add zeros (a day's four segments, a
        template in one or two of them; the same numbers to rounding)."""
        S, m, _, k = G.shape
        j0, j1 = 3 * first, 3 * (first + S)
        Gc = np.ascontiguousarray(G.conj().transpose(1, 3, 0, 2)).reshape(m, k, S * 3)
        p = np.einsum("mkj,mj->mk", Gc, self.r[:, j0:j1])
        q = np.matmul(Gc, self.M[:, j0:j1])  # (m, k, P)
        ngg = np.sum(np.abs(G) ** 2, axis=(0, 1, 2))
        return [(p[:, j], q[:, j], float(ngg[j])) for j in range(k)]

    def each_product(self, G: np.ndarray, first: int = 0) -> Iterator[tuple]:
        """:meth:`products` one template after the other, computed for a few templates at a
        time (their ``q`` about :data:`PRODUCTS_BYTES`): twelve placements' ``q`` at once
        were 90 MB of a day's diagnosis, twice over while the next piece's were computed."""
        m, k = G.shape[1], G.shape[-1]
        step = max(1, int(PRODUCTS_BYTES // (16 * m * max(1, self.M.shape[-1]))))
        for j0 in range(0, k, step):
            yield from self.products(G[..., j0 : j0 + step], first)

    def shifts(self, prods, max_shift: float) -> tuple[np.ndarray, np.ndarray]:
        """``(tau [s], delta chi2)`` of one template's products on the decimated grid,
        ``|tau| <= max_shift``."""
        data = self.data
        grid = data.grid
        p, q, ngg = prods
        L = grid.L
        kmax = int(max_shift * grid.fs) + 1
        if grid.bins[0] > 0 and 2 * grid.bins[-1] < L:  # Re sum_f x(f) exp(2 pi i f k / fs): half an irfft
            half = np.zeros((1 + q.shape[1], L // 2 + 1), dtype=complex)
            half[0, grid.bins] = p
            half[1:, grid.bins] = q.T
            z = sp_fft.irfft(half, n=L, axis=1)
            z *= L / 2
        else:
            full = np.zeros((1 + q.shape[1], L), dtype=complex)
            full[0, grid.bins] = p
            full[1:, grid.bins] = q.T
            z = np.fft.ifft(full, axis=1).real * L
        k = np.r_[np.arange(-min(kmax, L // 2 - 1), 0), np.arange(0, min(kmax, L // 2) + 1)]
        c = z[0, k]
        n = z[1:, k]  # (P, K)
        D = ngg - np.einsum("pk,pk->k", n, self.NMinv @ n)
        return k / grid.fs, np.where(D > DEGENERATE * ngg, 2.0 * c**2 / (np.maximum(D, 1e-300) * grid.kappa), 0.0)

    def at(self, prods, tau: float) -> float:
        """delta chi2 of one template's products at a shift ``tau`` [s] (any real value)."""
        p, q, ngg = prods
        ph = np.exp(2j * np.pi * self.data.grid.f * tau)
        c = float(np.real(np.sum(p * ph)))
        n = np.real(ph @ q)
        D = ngg - n @ self.NMinv @ n
        return 2.0 * c**2 / (max(D, 1e-300) * self.data.grid.kappa) if D > DEGENERATE * ngg else 0.0


def _pieces(data, lo: float, hi: float) -> list[tuple[float, float, float]]:
    """``[lo, hi]`` cut at the segment boundaries: ``(t_ref, a, b)`` per piece, the
    template's reference time the piece's centre."""
    bounds = sorted({float(t) for t in data.grid.seg_t0} | {float(data.grid.seg_t0[-1] + data.grid.seg_duration)})
    cuts = [lo] + [t for t in bounds if lo < t < hi] + [hi]
    return [(0.5 * (a + b), a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]


def glitch_search(model, effect: Glitch) -> SearchResult:
    """Profile-likelihood search of a glitch's unset time, damping and placement.

    For each placement (``tm`` or ``link`` given: that one; otherwise the six test masses
    and the six links, :data:`PLACEMENTS`) and each damping of :data:`BETA_GRID` (or the
    given one), a template at the centre of each piece of the searched span (``span``, the
    analysed data without it; cut at the segments' boundaries) is scanned over every shift
    by a decimated sample (:class:`_Scanner`); the best (placement, damping, time) is refined
    by Brent's method in ``log beta`` (templates rebuilt exactly at the time found, the
    time rescanned +-60 s) and in time (the phase formula).  The estimate is scored with
    its exact template (:func:`ttlcore.diagnose.evidence.added_evidence`).

    The marginal evidence: Laplace's rule over time and ``log beta`` (the curvatures of the
    profile), a uniform prior over the span and the damping range, and ``1 / n`` for the
    ``n`` placements tried; never above the evidence at the estimate.
    """
    data = model.data
    if data.context.tm is None:
        raise ConfigError("effect 'glitch': the search needs the telemetry")
    idx = np.flatnonzero(data.grid.mask)
    t_lo, t_hi = data.grid.t0 + idx[0] / data.grid.fs, data.grid.t0 + idx[-1] / data.grid.fs
    span = _parse_span(effect.options.get("span"))
    if effect.options.get("t") is not None:
        t_fixed = float(effect.options["t"])
        lo = hi = t_fixed
    else:
        lo, hi = span if span is not None else (t_lo, t_hi)
        lo, hi = max(lo, t_lo), min(hi, t_hi)
        if hi <= lo:
            raise ConfigError(f"effect 'glitch': the searched span {span} is outside the analysed data")
    places = [effect.where] if effect.where else list(PLACEMENTS)
    betas = [float(effect.options["beta"])] if effect.options.get("beta") is not None else list(BETA_GRID)
    n_eval = 0
    scanner = _Scanner(model)
    best: tuple = (-np.inf, None, None, None)  # (dchi2, where, beta, t)
    grid = []
    for t_ref, a, b in _pieces(data, lo, hi) if hi > lo else [(lo, lo, lo)]:
        half = max(t_ref - a, b - t_ref)
        for beta in betas:
            # every placement in one TDI
            products = scanner.each_product(*glitch_spectra_of(data, places, t_ref, beta)[::-1])
            for where, place_products in zip(places, products, strict=True):
                tau, dchi2 = scanner.shifts(place_products, half)
                inside = (t_ref + tau >= a) & (t_ref + tau <= b)
                n_eval += int(inside.sum())
                j = int(np.argmax(np.where(inside, dchi2, -np.inf)))
                grid.append(([where, beta, float(t_ref + tau[j])], float(dchi2[j])))
                if dchi2[j] > best[0]:
                    best = (float(dchi2[j]), where, beta, float(t_ref + tau[j]))
    _, where, beta, t_best = best
    fixed_t = effect.options.get("t") is not None

    def refine_time(beta_):
        """Best time [s] and delta chi2 near ``t_best`` for a damping (exact template there)."""
        nonlocal n_eval
        pr = scanner.products(*glitch_spectra_of(data, [where], t_best, beta_)[::-1])[0]
        if fixed_t:
            n_eval += 1
            return t_best, scanner.at(pr, 0.0), pr
        tau, dchi2 = scanner.shifts(pr, 60.0)
        j = int(np.argmax(dchi2))
        res = optimize.minimize_scalar(
            lambda x: -scanner.at(pr, x),
            bounds=(tau[j] - 1.0 / data.grid.fs, tau[j] + 1.0 / data.grid.fs),
            method="bounded",
            options={"xatol": 1e-3},
        )
        n_eval += tau.size + res.nfev
        x, val = (float(res.x), -float(res.fun)) if -res.fun >= dchi2[j] else (float(tau[j]), float(dchi2[j]))
        return t_best + x, val, pr

    if effect.options.get("beta") is None:
        lb = math.log(beta)
        step = math.log(BETA_GRID[1] / BETA_GRID[0])
        res = optimize.minimize_scalar(
            lambda x: -refine_time(math.exp(x))[1],
            bounds=(max(lb - step, math.log(BETA_RANGE[0])), min(lb + step, math.log(BETA_RANGE[1]))),
            method="bounded",
            options={"xatol": 2e-3},
        )
        beta = float(math.exp(res.x))
    t_best, _, _ = refine_time(beta)
    found = effect.with_options(
        t=round(t_best, 2),
        beta=float(f"{beta:.4g}"),
        span=None,
        **({} if effect.where else {("tm" if where.startswith("tm") else "link"): where[-2:]}),
    )
    g = glitch_spectra(data, where, t_best, beta)
    try:
        ev = _evidence(model, found, g)
    except ConfigError as exc:  # no template holds information of its own: nothing found
        log.info("glitch search over %.0f-%.0f s: %s", lo, hi, exc)
        return SearchResult(found, {"t": float(t_best), "beta": float(beta)}, {}, 0.0, COLLINEAR, COLLINEAR, n_eval)
    # curvatures of l = delta chi2 / 2 in time and log beta (the others at the estimate)
    sig_t = sig_lb = float("nan")
    if not fixed_t:
        pr = scanner.products(g[..., None])[0]
        h = 0.25 / data.grid.fs
        curv = -(scanner.at(pr, h) - 2 * scanner.at(pr, 0.0) + scanner.at(pr, -h)) / (2 * h * h)
        sig_t = 1.0 / math.sqrt(curv) if curv > 0 else float("nan")
    if effect.options.get("beta") is None:
        h = 0.05
        prods = [
            scanner.products(*glitch_spectra_of(data, [where], t_best, beta * math.exp(x))[::-1])[0]
            for x in (-h, 0.0, h)
        ]
        vals = [scanner.at(pr, 0.0) for pr in prods]
        curv = -(vals[0] - 2 * vals[1] + vals[2]) / (2 * h * h)
        sig_lb = 1.0 / math.sqrt(curv) if curv > 0 else float("nan")
    marg = ev.log_bayes_factor - math.log(len(places))
    if not fixed_t:
        marg += (
            (0.5 * math.log(2 * math.pi) + math.log(sig_t) - math.log(max(hi - lo, 1e-9)))
            if np.isfinite(sig_t)
            else -math.log(max((hi - lo) * data.grid.fs, 1.0))
        )
    if effect.options.get("beta") is None:
        width = math.log(BETA_RANGE[1] / BETA_RANGE[0])
        marg += (
            (0.5 * math.log(2 * math.pi) + math.log(sig_lb) - math.log(width))
            if np.isfinite(sig_lb)
            else -math.log(len(BETA_GRID))
        )
    marg = float(min(marg, ev.log_bayes_factor))
    est = {"t": float(t_best), "beta": float(beta)}
    intervals = {}
    if np.isfinite(sig_t):
        intervals["t"] = (t_best - sig_t, t_best + sig_t)
    if np.isfinite(sig_lb):
        intervals["beta"] = (beta * math.exp(-sig_lb), beta * math.exp(sig_lb))
    log.info("glitch search: %s at %.1f s, beta %.3g s, delta chi2 %.1f", where, t_best, beta, ev.delta_chi2)
    return SearchResult(
        found,
        est,
        intervals,
        float(ev.delta_chi2),
        float(ev.log_bayes_factor),
        marg,
        n_eval,
        grid=grid,
        evidence=ev,
        theta={found.column_name(): float(ev.beta[0])},
    )


def glitch_columns(data, effect: Glitch, g: np.ndarray | None = None) -> ColumnSet:
    """The whitened column of a resolved glitch (its exact template on a stretch,
    :func:`glitch_spectra`)."""
    if g is None:
        g = glitch_spectra(data, effect.where, float(effect.options["t"]), float(effect.options["beta"]))
    x = np.ascontiguousarray(g)[None].view(np.float64)
    return ColumnSet((effect.column_name(),), x, data.noise.key, ("m/s",), (GLITCH_PRIOR,), ((),), (None,))


def _evidence(model, effect: Glitch, g: np.ndarray):
    return added_evidence(model, glitch_columns(model.data, effect, g))


def effect_search(model, effect, coefficients=None, *, screen: bool = False) -> SearchResult:
    """The search of ``effect``'s unset parameters against ``model``: a glitch's by
    :func:`glitch_search` (its own evaluator, templates on stretches), any other's by
    :func:`ttlcore.diagnose.search.profile_search` (``screen``: a candidate's search)."""
    if isinstance(effect, Glitch):
        return glitch_search(model, effect)
    return profile_search(model, effect, coefficients, screen=screen)
