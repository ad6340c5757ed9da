"""The class of a diagnosis' excess (docs/diagnostics.md, "Signals, glitches, gaps and
changing noise"): each event of the time-frequency map (:mod:`ttlcore.diagnose.transients`)
classified with its evidence (T's share against what a link or test-mass signal would put
there, coherence with the witnesses, duration, band, track), the quiet tiles against the
noise model, the class of the excess as a whole, and the TTL fit's robustness to a signal
(:func:`transient_report`, the report's ``transients``).
"""

from __future__ import annotations

import logging

import numpy as np
from scipy import stats

from ..conventions import LINKS
from ..effects.gate import GATE_TAPER, gate
from ..errors import ConfigError
from ..estimate.spectra import segment_fft, window
from ..tdi.combinations import AET_MATRIX, MICHELSON, link_responses
from .candidates import rescore
from .columns import effect_columns
from .event_class import _f, classify, event_json
from .fitting import fit_resolved
from .onsets import data_end, onset_events, reclassify_onsets
from .transients import (
    CHANNELS,
    COHERENT_FRACTION,
    MAP_ALPHA,
    NOT_AN_EFFECT,
    T_SHARE_FRACTION,
    T_SHARE_INSTRUMENTAL,
    TILE_DURATION,
    Event,
    TimeFrequencyMap,
    data_gaps,
    find_events,
    kept_like,
    residual_map,
    tile_p_value,
)

log = logging.getLogger(__name__)


def witness_coherence(
    residual,
    witnesses,
    fs: float,
    tf: TimeFrequencyMap,
    event: Event,
    f_psd,
    psd,
    t0: float,
    keep=None,
    alpha: float = MAP_ALPHA,
) -> dict:
    """How much of ``event``'s excess the witnesses explain (module docstring).

    Parameters
    ----------
    residual : ndarray (3, n)
        A, E, T residual series.
    witnesses : ndarray (3, k, n)
        A, E, T of the ``k`` witness series (the 24 TTL regressors) on the same samples.
    f_psd, psd : ndarray (m,), (m, 3)
        The channels' noise PSD (as :func:`time_frequency_map`).

    Returns
    -------
    dict
        ``delta_chi2`` of the regression, ``expected`` (``2 k G_e`` on noise),
        ``explained_fraction`` of the event's excess, ``p_value``, ``coherent``.
    """
    x = np.asarray(residual, dtype=float)
    W = np.asarray(witnesses, dtype=float)
    L = int(round(tf.duration * fs))
    f = np.fft.rfftfreq(L, 1 / fs)
    sel = (f >= tf.edges[0]) & (f <= tf.edges[-1])
    if keep is not None:  # the notches, found over the whole band as for the map
        sel[sel] = keep(f[sel])
    sel &= (f >= event.f_lo) & (f < event.f_hi)
    if not sel.any() or W.shape[1] == 0:
        return {"delta_chi2": 0.0, "expected": 0.0, "explained_fraction": 0.0, "p_value": 1.0, "coherent": False}
    fb = f[sel]
    S = np.stack(
        [np.exp(np.interp(np.log(fb), np.log(f_psd), np.log(np.maximum(psd[:, c], 1e-300)))) for c in range(3)]
    )
    sq = np.sqrt(S)
    win = window("hann", L)
    bands = np.clip(np.searchsorted(tf.edges, fb, side="right") - 1, 0, len(tf.edges) - 2)
    ys, Xs = [], []  # whitened per channel
    sl = np.asarray(event.slices)
    peak = sl[int(np.argmin(np.abs(tf.t_mid[sl] - event.t_peak)))]
    for i in sl[(sl - peak) % 2 == 0]:  # independent tiles, the loudest among them
        s0 = int(round((tf.t_start[i] - t0) * fs))
        _, Y = segment_fft(np.nan_to_num(x[:, s0 : s0 + L]), fs, win, workers=None)
        _, X = segment_fft(np.nan_to_num(W[:, :, s0 : s0 + L]), fs, win, workers=None)
        ys.append(Y[:, sel] / sq)  # (3, nb)
        Xs.append(X[:, :, sel] / sq[:, None, :])  # (3, k, nb)
    y = np.stack(ys).reshape(-1)  # (ns, 3, nb) -> N complex rows
    X = np.moveaxis(np.stack(Xs), 2, -1).reshape(-1, np.shape(W)[1])  # (N, k)
    N, k = X.shape
    if N <= 2 * k:
        return {"delta_chi2": 0.0, "expected": 0.0, "explained_fraction": 0.0, "p_value": 1.0, "coherent": False}
    beta, *_ = np.linalg.lstsq(X, y, rcond=None)
    dchi2 = 2 * float(np.sum(np.abs(X @ beta) ** 2))
    total = 2 * float(np.sum(np.abs(y) ** 2))
    # a k-dimensional projection of a residual independent of the witnesses takes k / N of
    # its power, whatever that power is (signal or noise): the chance expectation
    expected = total * k / N
    F = (dchi2 / (2 * k)) / max((total - dchi2) / (2 * (N - k)), 1e-300)
    p = float(stats.f.sf(F, 2 * k / tf.kappa, 2 * (N - k) / tf.kappa))
    # the event's excess in the bands regressed (the same independent tiles)
    exc = max(sum(event.band_excess[g] for g in np.unique(bands)), 1e-300)
    frac = float(np.clip((dchi2 - expected) / exc, 0.0, 1.0))
    return {
        "delta_chi2": dchi2,
        "expected": expected,
        "explained_fraction": frac,
        "p_value": p,
        "coherent": bool(frac >= COHERENT_FRACTION and p < alpha),
    }


def instrumental_t_share(f, noise_csd, ltt_mean, f_lo: float, f_hi: float, slope: float = -2.0) -> float:
    """The smallest whitened T share of a signal on one link (the OMS placement, ``eta_ij``)
    or one test mass (``eta_ij`` and ``D_ji eta_ji``) in ``[f_lo, f_hi)``:

        share = sum_f |x_T|^2 / S_TT / sum_f sum_c |x_c|^2 / S_cc,

    ``x_c`` the response of channel ``c`` to the placement (static mean arms,
    :func:`ttlcore.tdi.combinations.link_responses`) times a signal spectrum ``f^slope``
    (default ``f^-2`` in power: a velocity step, the shape of a glitch, in fractional
    frequency), ``S`` the diagnosis' noise CSD.  Under a noise made of independent link
    noises of one kind, the shares of the links add up to a third (each channel's noise is
    the sum over links); where the test-mass noise dominates A and E but not T (a few mHz)
    a test-mass signal's share falls to a few per cent, still far above a
    gravitational wave's (0.1 % for a merger at 3-20 mHz)."""
    f = np.asarray(f, dtype=float)
    sel = (f >= f_lo) & (f < f_hi)
    if not sel.any():
        return float("nan")
    fb = f[sel]
    S = np.real(np.einsum("mii->mi", np.asarray(noise_csd)[sel]))  # (m, 3)
    ltt = np.asarray(ltt_mean, dtype=float)
    h = np.stack([link_responses(c, fb, ltt) for c in MICHELSON])
    h = np.einsum("ia,alm->lmi", AET_MATRIX, h)  # (6 links, m, 3)
    rev = [LINKS.index(k[::-1]) for k in LINKS]
    g = np.stack([h[k] + h[rev[k]] * np.exp(-2j * np.pi * fb * ltt[rev[k]])[:, None] for k in range(6)])
    w = fb**slope
    shares = []
    for x in np.concatenate([h, g]):
        p = np.abs(x) ** 2 / S * w[:, None]  # (m, 3)
        tot = p.sum()
        if tot > 0:
            shares.append(float(p[:, 2].sum() / tot))
    return float(min(shares)) if shares else float("nan")


# ---------------------------------------------------------------------------
# the diagnosis' use: the model's residual, the quiet hours, the class of the excess
# ---------------------------------------------------------------------------


def gated_ttl_fit(data, spans, names=None) -> dict:
    """The linear TTL coefficients with and without the data in ``spans`` [s].

    A plain GLS of the data's A, E, T on the 24 TTL regressors under the diagnosis' noise
    model (whitened segment spectra, ``theta = (W^H W)^-1 W^H w``, sigma from
    ``kappa (2 Re W^H W)^-1``), once on all data and once with data and regressors
    multiplied by :func:`gate` (the span and a 300-s cosine taper each side, as lisa-gap
    smooths a gap).  The errors-in-variables term of the diagnosis' fit is left out of
    both, so the difference measures what the gated hours pull (in sigma of the full fit).

    Parameters
    ----------
    data : WhitenedData
    spans : list of (start, stop)
        Times [s] to leave out.

    Returns
    -------
    dict
        ``names``, ``full``, ``gated``, ``sigma_full``, ``sigma_gated`` (m/rad),
        ``shift_sigma`` ((gated - full) / sigma_full), ``max_abs_shift_sigma``, ``spans``.
    """
    names = list(names or data.tdi.ttl_names or data.tdi.regressor_names)
    cols = [list(data.tdi.regressor_names).index(n) for n in names]
    y = np.asarray(data.tdi.data_series, dtype=float)
    g = gate(y.shape[-1], data.grid.fs, data.grid.t0, spans)
    out = {}
    for label, w in (("full", None), ("gated", g)):
        yy = y if w is None else y * w
        Y = data.noise.whiten(data.grid.spectra(yy[:, None, :]))[..., 0]  # (S, m, 3)
        X = _whitened_columns(data, cols, w)  # (S, m, 3, P)
        Xf = X.reshape(-1, X.shape[-1])
        A = 2 * np.real(Xf.conj().T @ Xf)
        b = 2 * np.real(Xf.conj().T @ Y.reshape(-1))
        theta = np.linalg.solve(A, b)
        sigma = np.sqrt(np.diag(np.linalg.inv(A)) * data.grid.kappa)
        out[label] = (theta, sigma)
        del X, Xf
    shift = (out["gated"][0] - out["full"][0]) / out["full"][1]
    return {
        "names": names,
        "full": out["full"][0].tolist(),
        "gated": out["gated"][0].tolist(),
        "sigma_full": out["full"][1].tolist(),
        "sigma_gated": out["gated"][1].tolist(),
        "shift_sigma": shift.tolist(),
        "max_abs_shift_sigma": float(np.max(np.abs(shift))),
        "spans": [[float(a), float(b)] for a, b in spans],
    }


#: Regressor columns transformed at a time by :func:`_whitened_columns`.
COLUMN_BLOCK = 6


def _whitened_columns(data, cols: list[int], w: np.ndarray | None) -> np.ndarray:
    """Whitened segment spectra (S, m, 3, len(cols)) of the decimated regressors ``cols``
    times the gate ``w`` (None: not gated), :data:`COLUMN_BLOCK` columns at a time.

    The same numbers as transforming them all at once, without a copy of the day's
    regressors and another of them gated (2 x 100 MB for a day, at the diagnosis' peak:
    the transient phase calls this once per event and per gate it weighs)."""
    series = data.tdi.regressor_series
    out: np.ndarray | None = None
    for k0 in range(0, len(cols), COLUMN_BLOCK):
        block = cols[k0 : k0 + COLUMN_BLOCK]
        x = np.asarray(series[:, block], dtype=float)
        X = data.noise.whiten(data.grid.spectra(x if w is None else x * w))
        if out is None:
            out = np.empty(X.shape[:3] + (len(cols),), dtype=complex)
        out[..., k0 : k0 + len(block)] = X
    assert out is not None, "no regressor column"
    return out


def model_residual(model) -> np.ndarray:
    """The model's residual series (3, n): decimated A, E, T of the data minus the fitted
    columns (``ModelFit.columns.series``; when the fit kept no series, the series the
    column store holds for the model's effects (:func:`stored_residual`), else the model
    refitted with them, :func:`ttlcore.diagnose.fitting.fit_resolved`)."""
    data = model.data
    if model.columns.series is None:  # a fitted model keeps its whitened columns only
        resid = stored_residual(model)
        if resid is not None:
            return resid
        model = fit_resolved(data, list(model.effects), None, True)
    return data.tdi.data_series - np.einsum("p,cpn->cn", model.theta, model.columns.series)


def stored_residual(model) -> np.ndarray | None:
    """The residual of :func:`model_residual` from the series of the model's columns the
    column store holds (:func:`~ttlcore.diagnose.columns.effect_columns`, built with the
    model's fit), column by column, with the model's own coefficients; None for a model with
    a linearised effect (refitted instead).  The refit gave the same coefficients, but held
    a second copy of the columns and series (a day's gated model: 0.18 GB at the peak)."""
    effects = list(model.effects)
    if any(e.needs_coefficients for e in effects):
        return None
    series = {}
    for e in effects:  # a name in several sets: the last set's (as the fit assembles them)
        cs = effect_columns(model.data, e, keep_series=True)
        if cs.series is None:
            return None
        series.update({n: cs.series[:, i] for i, n in enumerate(cs.names)})  # views
    if any(n not in series for n in model.columns.names):
        return None
    resid = np.array(model.data.tdi.data_series, dtype=float)
    for n, theta in zip(model.columns.names, model.theta, strict=True):
        resid -= theta * series[n]
    return resid


def quiet_adequacy(tf: TimeFrequencyMap, events, alpha: float, spans=()) -> dict:
    """The residual of the tiles outside every event (and every ``(start, stop)`` of
    ``spans`` [s]: gated hours with their tapers) against the noise model itself (not the
    background): chi2/dof per band over independent tiles (every other one), A, E, T
    summed; ``fails`` when a band fails at ``alpha`` (divided by the bands)."""
    n_t = tf.chi2.shape[1]
    busy = np.zeros(n_t, dtype=bool)
    for e in events:
        lo, hi = min(e.slices), max(e.slices)
        busy[max(0, lo - 1) : hi + 2] = True  # the tiles overlapping an event's
    t_mid = tf.t_mid
    for a, b in spans:
        busy |= (t_mid + tf.duration / 2 > a) & (t_mid - tf.duration / 2 < b)
    idx = np.flatnonzero(tf.valid & ~busy)
    idx = idx[(idx - (idx[0] if idx.size else 0)) % 2 == 0]
    G = tf.chi2.shape[2]
    if idx.size == 0:
        return {
            "tiles": 0,
            "hours": 0.0,
            "chi2_dof": None,
            "band_chi2_dof": [None] * G,
            "fails": False,
            "excess_chi2_full_span": None,
        }
    chi2 = tf.chi2[:, idx].sum(axis=(0, 1))
    dof = 3 * tf.dof * idx.size
    p = tile_p_value(chi2, dof, 1.0, tf.kappa, tf.tolerance)
    ch = tf.chi2[:, idx].sum(axis=(1, 2))
    ch_dof = tf.dof.sum() * idx.size
    ex = np.maximum(ch - ch_dof, 0.0)
    # the excess beyond the tolerance the quiet tiles' level would give over the whole span
    # (a tile of length T holds dof 2 n_b per channel and band; the span T_s / T tiles' worth),
    # in the units of the candidates' explained fraction (divided by the segments' kappa
    # there, by the caller)
    n_span = (tf.valid.sum() + 1) / 2.0
    full = float(np.sum(np.maximum(chi2 / dof - (1 + tf.tolerance), 0.0) * 3 * tf.dof * n_span))
    return {
        "tiles": int(idx.size),
        "hours": float(idx.size * tf.duration / 3600),
        "chi2_dof": float(chi2.sum() / dof.sum()),
        "band_chi2_dof": [float(x) for x in chi2 / dof],
        "channel_chi2_dof": {c: float(ch[i] / ch_dof) for i, c in enumerate(CHANNELS)},
        "t_share": float(ex[2] / ex.sum()) if ex.sum() > 0 else None,
        "excess_chi2_full_span": full,
        "fails": bool((p < alpha / G).any()),
    }


def gap_of(t_start: float, t_stop: float, gaps, hop: float) -> tuple[float, float] | None:
    """The run of missing data ``(a, b)`` [s] among ``gaps`` that an event over ``[t_start,
    t_stop]`` [s] overlaps, its ramps included (or None).

    A gap is gated with cosine ramps of :data:`~ttlcore.effects.gate.GATE_TAPER` each side:
    the data there are the gap's, and an event within a ramp and a tile's ``hop`` of its edge
    is that edge, not a transient of the instrument.  (Missing data at the ends of the data
    are cut off before: :func:`ttlcore.diagnose.whitened.without_missing_ends`.)"""
    margin = GATE_TAPER + hop
    return next(((a, b) for a, b in gaps if a - margin < t_stop and b + margin > t_start), None)


def classified_events(data, resid: np.ndarray, tf: TimeFrequencyMap, events, gaps, alpha: float) -> list[dict]:
    """The report entries of the map's ``events`` (loudest first): each with its coherence
    with the witnesses, the run of missing data it overlaps (its ramps included,
    :func:`gap_of`), T's expected share, its class and evidence
    (:func:`ttlcore.diagnose.event_class.classify`); those that last to the data's end are
    onsets (:func:`ttlcore.diagnose.onsets.reclassify_onsets`)."""
    grid = data.grid
    psd = np.real(np.einsum("mii->mi", data.noise.csd))
    keep = kept_like(grid.f, 1.0 / grid.seg_duration, 1.0 / tf.duration)
    out = []
    for e in events:
        coh = witness_coherence(resid, data.tdi.regressor_series, grid.fs, tf, e, grid.f, psd, grid.t0, keep, alpha)
        gap = gap_of(e.t_start, e.t_stop, gaps, tf.hop)
        expected = instrumental_t_share(grid.f, data.noise.csd, data.tdi.ltt_mean, e.f_lo, e.f_hi)
        e = Event(
            **{
                **e.__dict__,
                "coherence": coh,
                "gap": gap,
                "t_share_expected": expected if np.isfinite(expected) else None,
            }
        )
        out.append(event_json(e, *classify(e)))
    reclassify_onsets(out, data_end(data), tf.duration, tf.hop)
    return out


def transient_report(
    model, report: dict | None = None, tile: float = TILE_DURATION, alpha: float = MAP_ALPHA, refit=None, onsets=None
) -> dict:
    """The ``transients`` part of a diagnosis report (docs/diagnostics.md): the
    time-frequency map of the model's residual, its events with their class and evidence,
    the missing data, the quiet tiles against the noise model, the class of the excess as
    a whole (``classification``) and, when the excess is a signal or a defect of the data,
    the TTL fit's robustness to it (:func:`gated_ttl_fit`).

    ``report`` (the diagnosis' report so far: adequacy, candidates) decides between a
    missing coupling and an unexplained stationary excess when the quiet tiles fail.
    The key ``_map`` holds the :class:`TimeFrequencyMap` (for the figure; the diagnosis moves
    it to :attr:`~ttlcore.diagnose.diagnosis.Diagnosis.transient_map`), ``_residual`` the model's residual
    series (3, n) (the diagnosis scores the transients' glitches and gates on it,
    :func:`ttlcore.diagnose.transient_advice.transient_actions`, and drops it).

    ``refit(spans)``, optional, returns the model refitted with ``spans`` [s] gated (or
    None): when events read as signals or defects of the data (:data:`NOT_AN_EFFECT`) or
    data are missing, the quiet tiles are then read on that fit's residual, so that what a
    loud signal pulls the linear fit by is not taken for excess in every hour (``quiet.gated``);
    ``_gated`` holds that fit.  Events that last to the data's end are onsets
    (:func:`ttlcore.diagnose.onsets.reclassify_onsets`); ``onsets(events)``, optional, scores
    their candidates into ``report`` before the excess is classed.
    """
    data = model.data
    grid = data.grid
    s = data.context.settings
    resid = model_residual(model)
    tf = residual_map(data, resid, tile)
    band = (max(s.band[0], 3.0 / tile), s.band[1])
    # a gated span reads as zeros: not missing data, the model's choice
    spans = getattr(data.grid, "gate_spans", ())
    gaps = [
        (a, b)
        for a, b in data_gaps(data.tdi.data_series, grid.fs, grid.t0, grid.mask)
        if not any(lo - 1.0 <= a and b <= hi + 1.0 for lo, hi in spans)
    ]
    events = find_events(tf, alpha)
    out_events = classified_events(data, resid, tf, events, gaps, alpha)
    classes = [e["class"] for e in out_events]
    if onsets is not None and onset_events(out_events):
        onsets(out_events)
    signal_spans = [(e["t_start"] - tf.hop, e["t_stop"] + tf.hop) for e in out_events if e["class"] in NOT_AN_EFFECT]
    signal_spans += [(a, b) for a, b in gaps if not any(x[0] <= a and b <= x[1] for x in signal_spans)]
    # a loud signal pulls the linear fit, whose mis-subtracted TTL noise is then in every
    # quiet tile: the quiet tiles are read on the model refitted with the signals gated
    gated = refit(signal_spans) if refit is not None and signal_spans else None
    if gated is not None:
        quiet_tf = residual_map(gated.data, model_residual(gated), tile)
        busy = [(a - GATE_TAPER, b + GATE_TAPER) for a, b in signal_spans]
        quiet = quiet_adequacy(quiet_tf, events, alpha, busy)
        quiet["gated"] = True
        segments = (gated.time_table or {}).get("segments", [])  # its adequacy: what gating gives
        quiet["gated_model_fails"] = bool(np.any(gated.bands.fails) or any(r.get("fails") for r in segments))
        quiet["gated_model_chi2_dof"] = float(gated.chi2_dof)
    else:
        quiet = quiet_adequacy(tf, events, alpha)
    fb = [(b["f_lo"], b["f_hi"]) for b in ((report or {}).get("adequacy") or {}).get("bands", []) if b.get("fails")]
    lo, hi = (min(a for a, _ in fb), max(b for _, b in fb)) if fb else tuple(band)
    expected = instrumental_t_share(grid.f, data.noise.csd, data.tdi.ltt_mean, lo, hi)
    quiet["t_share_expected"] = float(expected) if np.isfinite(expected) else None
    if (
        quiet.get("gated")
        and quiet.get("fails")
        and any(c in NOT_AN_EFFECT for c in classes)
        and not at_lower_bound(((report or {}).get("adequacy") or {}).get("noise_model") or {})
    ):  # only where excess_classification weighs it: a candidate scored again costs seconds
        quiet["best_delta_chi2_gated"] = _best_on_gated(report or {}, gated)
        quiet["best_gated_spec"] = next(
            (c["spec"] for c in (report or {}).get("candidates") or [] if c.get("significant")), None
        )
    verdict = excess_classification(report or {}, out_events, quiet, gaps)
    robust = None
    if signal_spans and data.tdi.regressor_series is not None:
        robust = gated_ttl_fit(data, signal_spans, model.data.tdi.ttl_names or None)
        robust["model"] = model.ttl_coefficients().tolist()
    summary = []
    for ev in out_events:
        summary.append(
            f"{ev['class']}: {ev['t_start'] / 3600:.2f}-{ev['t_stop'] / 3600:.2f} h, {_f(ev['f_lo'])}-{_f(ev['f_hi'])} "
            f"in {', '.join(ev['channels']) or '-'} (T share {100 * ev['t_share']:.1f} %, track {ev['track_kind']}, "
            f"SNR {ev['snr']:.0f})"
        )
    for a, b in gaps:
        summary.append(f"missing data {a / 3600:.2f}-{b / 3600:.2f} h")
    if robust is not None:
        summary.append(
            f"TTL fit without those hours: largest coefficient shift {robust['max_abs_shift_sigma']:.2f} sigma"
        )
    return {
        "tile_duration": tf.duration,
        "hop": tf.hop,
        "alpha": alpha,
        "t_share_threshold": T_SHARE_INSTRUMENTAL,
        "events": out_events,
        "gaps": [[a, b] for a, b in gaps],
        "quiet": quiet,
        "classification": verdict,
        "robustness": robust,
        "summary": summary,
        "map": tf.to_json(),
        "_map": tf,
        "_residual": resid,
        "_gated": gated,
    }


def at_lower_bound(noise_model: dict) -> list[str]:
    """The secondary-noise levels of a report's ``noise_model`` at the lower bound of their
    allowed range (to 1e-6)."""
    params, bounds = noise_model.get("parameters") or {}, noise_model.get("bounds") or {}
    return [k for k, v in params.items() if k in bounds and v["psd_scale"] <= bounds[k][0] * (1 + 1e-6)]


def _best_on_gated(report: dict, gated) -> float | None:
    """delta chi^2 of the report's best significant candidate added to the ``gated`` model
    (the signals' hours gated): what it explains of the quiet data, not of a merger it can
    also take.  None when there is none, or it cannot be scored there."""
    best = next((c for c in report.get("candidates") or [] if c.get("significant")), None)
    if best is None or gated is None:
        return None
    try:
        ev = rescore(gated, best)
    except ConfigError as exc:
        log.info("best candidate not scored on the gated model: %s", exc)
        return None
    log.info("best candidate %s on the gated model: delta chi2 %.1f", best["cli_spec"], ev.delta_chi2)
    return float(ev.delta_chi2)


def excess_classification(report: dict, events: list, quiet: dict, gaps=()) -> dict:
    """The class of the model's excess as a whole, with its evidence.

    - no failure and no event: ``"none"``;
    - every event a signal or a defect of the data (:data:`NOT_AN_EFFECT`) and the quiet
      tiles consistent with the noise model: the loudest event's class (``signal``: no
      effect is recommended); no event but missing data (``gaps``) and the quiet tiles
      consistent, or read on the model with the gaps gated and that model passing its
      adequacy (``quiet.gated_model_fails`` False): ``"gap"``;
    - otherwise the excess is in the quiet tiles too (or coherent with the witnesses):
      ``"missing-coupling"`` when an event is witness-coherent or the best candidate
      explains at least half of the excess; ``"gravitational-wave"`` (``signal``) when T
      carries less than a third of the share a link or test-mass signal would have in the
      failing bands (:func:`instrumental_t_share`) of the quiet tiles' excess (a long-lived
      source in band over the whole span); else ``"stationary-excess"`` (nothing named
      explains it).
    """
    ad = report.get("adequacy") or {}
    fails = bool(ad.get("fails")) or bool(events)
    cands = report.get("candidates") or []
    best = next((c for c in cands if c.get("significant")), None)
    ev = []
    if quiet.get("chi2_dof") is not None:
        ev.append(
            f"tiles outside the events ({quiet['hours']:.1f} h): chi2/dof {quiet['chi2_dof']:.3f} against the "
            f"noise model, {'failing' if quiet['fails'] else 'consistent'}"
        )
    if not fails:
        return {"class": "none", "signal": False, "classes": [], "evidence": ev}
    kinds = [e["class"] for e in events]
    # a gap-only day: the quiet tiles consistent, or, read with the gaps gated, failing while
    # the gated model itself passes (900-s tiles of a lisainstrument day read chi2/dof 1.040
    # where its adequacy reads 1.000, gaps or not: the tiles' failure is not the gaps')
    gated_passes = quiet.get("gated") and quiet.get("gated_model_fails") is False
    if not events and gaps and (not quiet.get("fails") or gated_passes):
        return {
            "class": "gap",
            "signal": True,
            "classes": ["gap"],
            "evidence": ev
            + [
                "missing data "
                + ", ".join(f"{a / 3600:.2f}-{b / 3600:.2f} h" for a, b in gaps)
                + "; no transient outside it"
                + (f"; gated, the model passes (chi2/dof {quiet['gated_model_chi2_dof']:.3f})" if gated_passes else "")
            ],
        }
    if events and all(k in NOT_AN_EFFECT for k in kinds) and not quiet.get("fails"):
        return {
            "class": kinds[0],
            "signal": True,
            "classes": sorted(set(kinds)),
            "evidence": ev + [f"{len(events)} event(s): " + ", ".join(kinds)] + events[0]["evidence"],
        }
    frac = best.get("explained_fraction", 0.0) if best is not None else 0.0
    outside = quiet.get("excess_chi2_full_span")
    if (
        best is not None
        and quiet.get("fails")
        and outside
        and quiet.get("gated")
        and not at_lower_bound(ad.get("noise_model") or {})
        and any(k in NOT_AN_EFFECT for k in kinds)
    ):
        # signals beside a stationary excess: the share of the excess outside them decides,
        # when the quiet tiles were read with the signals gated (else what a merger pulls the
        # fit by is in every quiet tile, and a candidate fitted to the merger "explained" it:
        # a live window with a merger adopted second-order); not when a noise level sits at
        # its lower bound: less noise than the instrument has, a level whose bins a signal
        # took, and the quiet excess is the levels' misfit as much as anything (a 14-h live
        # window with 10 h of a chirp gated: tm_acc at 0.25, and second-order "explained" 66 %
        # of the 3.8 quiet hours' excess; a missing coupling pushes levels to their upper bounds)
        # (the candidate scored on the gated model: on the full data it takes the signals too)
        kappa = float(ad.get("variance_factor") or 1.0)
        taken = quiet.get("best_delta_chi2_gated")
        taken = best.get("delta_chi2", 0.0) if taken is None else taken
        frac = float(min(1.0, max(taken, 0.0) / (outside / kappa)))
    if "missing-coupling" in kinds or frac >= 0.5:
        if best is not None:
            ev.append(
                f"the best candidate, {best['cli_spec']}, explains {100 * frac:.0f} % of the excess"
                + (" outside the transients" if frac != best.get("explained_fraction") else "")
            )
        return {"class": "missing-coupling", "signal": False, "classes": sorted(set(kinds)), "evidence": ev}
    share = quiet.get("t_share")
    expected = quiet.get("t_share_expected")
    thr = T_SHARE_INSTRUMENTAL if expected is None else T_SHARE_FRACTION * expected
    if quiet.get("fails") and share is not None and share < thr:
        # in every hour, T nearly empty, nothing named explains it: a long-lived signal (an
        # inspiral in band over the whole span, binaries), not a coupling (a link signal
        # puts 1/6 to 1/2 of its whitened excess into T)
        ev.append(
            f"stationary in time, T carries {100 * share:.1f} % of the excess outside any transient "
            f"(threshold {100 * thr:.2g} %): a long-lived gravitational-wave signal"
        )
        if best is not None:
            ev.append(f"the best candidate, {best['cli_spec']}, explains {100 * best['explained_fraction']:.0f} %")
        return {
            "class": "gravitational-wave",
            "signal": True,
            "classes": sorted(set(kinds) | {"gravitational-wave"}),
            "evidence": ev,
        }
    return {"class": "stationary-excess", "signal": False, "classes": sorted(set(kinds)), "evidence": ev}
