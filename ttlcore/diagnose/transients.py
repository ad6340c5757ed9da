"""Transients in the residual: excess localised in time, and what it looks like.

docs/diagnostics.md, "Signals, glitches, gaps and changing noise".  The adequacy test says
*that* the model fails in a band and an hour; this module says *what the excess looks
like*, so that a gravitational wave, a glitch, a gap or a change of the noise level is not
read as a missing coupling.

**Time-frequency map.**  The residual of the model (A, E, T, fractional frequency) is cut
into Hann-windowed tiles of ``tile`` seconds (default 900 s) overlapping by half, each
PSD-normalised (:func:`ttlcore.estimate.spectra.segment_fft`, ``E|X|^2 = S``), and each
channel is divided by its own noise PSD ``S_cc(f)`` (the diagonal of the diagnosis' noise
model).  Per tile, channel ``c`` and log-spaced band ``b`` (third-octave bands merged until
each holds ``MIN_TILE_DOF`` degrees of freedom per channel),

    chi2[c, t, b] = 2 sum_{f in b} |X_c(t, f)|^2 / S_cc(f),     dof[b] = 2 n_b,

is chi^2 with ``dof`` degrees of freedom under the noise model; the bins of one Hann tile
are correlated, which inflates its variance by ``kappa``
(:func:`ttlcore.estimate.fit.variance_factor`, 1.94 for Hann), so ``chi2 / kappa`` is
compared with chi^2 of ``dof / kappa`` degrees of freedom (Satterthwaite), as the per-hour
adequacy test does.

**Background.**  A transient is an excess *against the rest of the data*: each channel and
band has a background level ``B[c, b]``, the median over the tiles of ``chi2/dof`` divided
by the median of ``chi^2_k / k`` (``k = dof``; Wilson-Hilferty, ``(1 - 2 / (9 k))^3``), and
never below 1 (the noise model).  A stationary excess (a missing
coupling, a wrong noise level) raises ``B`` and is not a transient; a loud hour does not
move a median.

**Detection.**  A tile is *hot* when ``chi2 / (B (1 + tol) kappa)`` has p < ``alpha /
n_tests`` (Bonferroni over every tile and channel and every tile's broadband sum, so that a
day of noise raises a false event with probability ``alpha``, default 1e-3); a slice is hot
when one of its tiles or its broadband sum (all bands of one channel) is.  Contiguous hot
slices form the core of an event, which grows over the neighbouring slices whose sum over
the core's significant bands (A, E, T) has p < ``alpha`` (hysteresis: the weak start of a
chirp belongs to it).  An *event* has: start and stop (the first and last hot slice's centre -+ half a
hop), the channels that carry it (a channel whose most significant tile or broadband sum in
the event passes the same threshold), its band (the bands whose summed excess over the
event is significant at ``alpha`` per band), its time-frequency track (per hot slice the
band with the largest excess in A + E, and the excess-weighted mean log frequency), and
``t_share``: the fraction of the event's whitened excess power that T carries.

**T as a null channel.**  Noises enter the six links independently; whitened by the noise
model, a signal on one link puts between a sixth and a half of its excess power in T where
link noises dominate every channel (a third on average: the links share each channel's
noise; ``tests/ttlcore/diagnose/test_transients.py`` computes it from the link responses),
and a test-mass signal at a few mHz, where the test-mass noise dominates A and E but not
T, a few per cent (2.7 % measured for a glitch on test mass 21 at 3-11 mHz).  A
gravitational wave at the low frequencies of a merger leaves T nearly empty (T is the
Sagnac-type null stream; 0.1 % for MBHB2 at 3-21 mHz).  :func:`instrumental_t_share`
computes, for the event's band and the diagnosis' noise CSD, the smallest share any single
link or test mass would give (a velocity-step spectrum); the event is instrumental when its
T share reaches a third of that (``T_SHARE_FRACTION``), gravitational-wave-like below.

**Witness coherence.**  Over an event's independent tiles (every other one) and band, the
whitened residual tiles (A, E, T, each over its own noise PSD) are regressed on the
whitened tiles of the 24 TTL regressors (every DWS channel on its rx and tx placements,
through TDI), one complex coefficient per regressor (a coupling with a gain and a phase):
``delta chi2 = 2 |X beta|^2``.  A projection on ``k`` directions of ``N`` complex rows takes
``k / N`` of the power of a residual independent of the witnesses, signal or noise, so
``delta chi2 - (k / N) chi2_total`` is the excess the witnesses explain; its significance
is the F test ``(delta chi2 / 2k) / ((chi2_total - delta chi2) / 2(N - k))`` (degrees of
freedom divided by ``kappa``).  ``coherent`` when the witnesses explain at least
``COHERENT_FRACTION`` (0.5) of the event's excess in those bands with p < alpha.

**Classes** (:func:`classify`), first match: ``gap`` (the event overlaps missing data:
runs of zeros or NaN in the data); ``missing-coupling`` (witness-coherent);
``noise-change`` (at least ``NOISE_CHANGE_HOURS`` long and broadband: excess significant in
at least ``BROADBAND_FRACTION`` of the bands, T carrying its share); ``gravitational-wave``
(A or E carry it, T share below the instrumental threshold, not coherent, its track not
falling: a merger's 900-s tiles read chirp, stationary or, with its leakage, irregular);
``glitch`` (T share at least the threshold,
shorter than ``NOISE_CHANGE_HOURS``); otherwise ``unclassified``.  Each class comes with the
evidence (numbers) that decided it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from ..estimate.fit import variance_factor
from ..estimate.spectra import segment_fft, window
from .adequacy import merged_band_edges, third_octave_edges

log = logging.getLogger(__name__)

CHANNELS = ("A", "E", "T")
#: Tile length [s] of the time-frequency map (hop: half of it).
TILE_DURATION = 900.0
#: Degrees of freedom per channel a tile's band must hold (bands merged up to it): two
#: bins, so that a 900-s tile still resolves the track of a merger at a few mHz.
MIN_TILE_DOF = 4
#: False-alarm probability of the whole map (Bonferroni over its tests).
MAP_ALPHA = 1e-3
#: Whitened excess share of T above which an event is instrumental when the noise model
#: gives no expectation (:func:`instrumental_t_share` gives one in the diagnosis).
T_SHARE_INSTRUMENTAL = 0.1
#: An event is instrumental when T carries at least this fraction of the smallest share a
#: signal on one link or one test mass would give it (:func:`instrumental_t_share`).
T_SHARE_FRACTION = 1.0 / 3.0
#: Share of an event's excess the witnesses must explain for it to be a missing coupling.
COHERENT_FRACTION = 0.5
#: An event at least this long [h] and broadband is a change of the noise level.
NOISE_CHANGE_HOURS = 2.0
#: Share of the bands whose excess must be significant for "broadband".
BROADBAND_FRACTION = 0.6
#: A track whose frequency rises by at least this factor over the event is a chirp; one
#: that stays within it (both ways) is stationary.
CHIRP_RATIO = 1.5
#: Shortest run of zeros or NaN [s] taken as missing data.
MIN_GAP = 10.0

CLASSES = ("gravitational-wave", "glitch", "missing-coupling", "noise-change", "gap", "unclassified")
#: The classes that are signals or data defects, for which no effect is recommended.
NOT_AN_EFFECT = ("gravitational-wave", "glitch", "noise-change", "gap")


@dataclass(frozen=True)
class TimeFrequencyMap:
    """Whitened residual power per channel, time tile and band.

    Attributes
    ----------
    t_start : ndarray (n_t,)
        Start of each tile [s].
    duration, hop : float
        Tile length and hop [s].
    edges : ndarray (n_f + 1,)
        Band edges [Hz].
    chi2 : ndarray (3, n_t, n_f)
        ``2 sum |X_c|^2 / S_cc`` per channel (A, E, T), tile and band.
    dof : ndarray (n_f,)
        Degrees of freedom of one channel, tile and band (``2 n_b``).
    kappa : float
        Variance factor of the bins of one Hann tile.
    background : ndarray (3, n_f)
        The background level ``B`` (module docstring), at least 1.
    tolerance : float
        Relative tolerance of the noise model.
    valid : ndarray (n_t,) of bool
        Tiles fully inside the analysed span.
    """

    t_start: np.ndarray
    duration: float
    hop: float
    edges: np.ndarray
    chi2: np.ndarray
    dof: np.ndarray
    kappa: float
    background: np.ndarray
    tolerance: float
    valid: np.ndarray

    @property
    def t_mid(self) -> np.ndarray:
        return self.t_start + 0.5 * self.duration

    @property
    def ratio(self) -> np.ndarray:
        """chi2/dof over the background, (3, n_t, n_f): 1 for noise."""
        return self.chi2 / (self.dof[None, None, :] * self.background[:, None, :])

    def excess(self) -> np.ndarray:
        """chi2 beyond the background's expectation ``B dof`` (3, n_t, n_f)."""
        return self.chi2 - self.background[:, None, :] * self.dof[None, None, :]

    def tile_p(self) -> np.ndarray:
        """p-value of every tile (3, n_t, n_f) against ``B (1 + tol)``."""
        return tile_p_value(self.chi2, self.dof[None, None, :], self.background[:, None, :], self.kappa, self.tolerance)

    def broadband_p(self) -> np.ndarray:
        """p-value of every tile's sum over bands, per channel (3, n_t)."""
        bd = self.background[:, None, :] * self.dof[None, None, :]
        return tile_p_value(
            self.chi2.sum(axis=2), self.dof.sum(), bd.sum(axis=2) / self.dof.sum(), self.kappa, self.tolerance
        )

    def to_json(self) -> dict:
        return {
            "tile_duration": self.duration,
            "hop": self.hop,
            "t_start": [float(x) for x in self.t_start],
            "edges": [float(x) for x in self.edges],
            "dof": [float(x) for x in self.dof],
            "kappa": self.kappa,
            "background": {c: [float(x) for x in self.background[i]] for i, c in enumerate(CHANNELS)},
        }


def tile_p_value(chi2, dof, level, kappa, tol):
    """Upper-tail p of ``chi2`` against a noise level ``level (1 + tol)`` with bins
    correlated by ``kappa`` (Satterthwaite, as :func:`ttlcore.diagnose.adequacy.p_value`)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return stats.chi2.sf(np.asarray(chi2) / (np.asarray(level) * (1 + tol) * kappa), np.asarray(dof) / kappa)


def median_factor(k) -> np.ndarray:
    """Median of ``chi^2_k / k`` (Wilson-Hilferty): ``(1 - 2 / (9 k))^3``."""
    k = np.asarray(k, dtype=float)
    return (1 - 2 / (9 * k)) ** 3


def time_frequency_map(
    residual,
    fs: float,
    t0: float,
    f_psd,
    psd,
    band,
    *,
    tile: float = TILE_DURATION,
    valid=None,
    keep=None,
    tolerance: float = 0.02,
    min_dof: int = MIN_TILE_DOF,
) -> TimeFrequencyMap:
    """The time-frequency map of the module docstring.

    Parameters
    ----------
    residual : ndarray (3, n)
        A, E, T residual series (any unit; ``psd`` in the same unit squared per Hz).
    fs, t0 : float
        Rate [Hz] and time of the first sample [s].
    f_psd, psd : ndarray (m,), ndarray (m, 3)
        The noise model's PSD of each channel at ``f_psd`` [Hz], interpolated (linearly in
        log-log) to each tile's bins.
    band : tuple
        Frequencies [Hz] analysed.
    tile : float
        Tile length [s] (hop: half).
    valid : ndarray (n,) of bool, optional
        Samples inside the analysed span (tiles must lie within it).
    keep : callable, optional
        ``keep(f) -> bool mask`` of the bins to use (the notches of the TDI response).
    tolerance : float
        Relative tolerance of the noise model.
    """
    x = np.asarray(residual, dtype=float)
    L = int(round(tile * fs))
    hop = max(1, L // 2)
    if valid is None:
        valid = np.isfinite(x).all(axis=0)
    idx = np.flatnonzero(valid)
    if idx.size < L:
        raise ValueError(f"the analysed span ({idx.size / fs:.0f} s) is shorter than one tile ({tile:.0f} s)")
    lo, hi = int(idx[0]), int(idx[-1]) + 1
    starts = np.arange(lo, hi - L + 1, hop)
    f = np.fft.rfftfreq(L, 1 / fs)
    sel = (f >= band[0]) & (f <= band[1])
    if keep is not None:
        sel[sel] = keep(f[sel])
    fb = f[sel]
    S = np.stack(
        [np.exp(np.interp(np.log(fb), np.log(f_psd), np.log(np.maximum(psd[:, c], 1e-300)))) for c in range(3)]
    )  # (3, nb)
    edges = merged_band_edges(fb, third_octave_edges(band), 2, min_dof)
    bidx = np.clip(np.searchsorted(edges, fb, side="right") - 1, 0, len(edges) - 2)
    G = len(edges) - 1
    win = window("hann", L)
    chi2 = np.zeros((3, starts.size, G))
    ok = np.zeros(starts.size, dtype=bool)
    for k, s0 in enumerate(starts):
        seg = x[:, s0 : s0 + L]
        ok[k] = bool(valid[s0 : s0 + L].all())
        _, X = segment_fft(np.nan_to_num(seg), fs, win, workers=None)
        z = 2 * np.abs(X[:, sel]) ** 2 / S
        for c in range(3):
            chi2[c, k] = np.bincount(bidx, weights=z[c], minlength=G)
    dof = 2.0 * np.bincount(bidx, minlength=G)
    kappa = variance_factor("hann", min(L, 4096), 0.0)
    use = ok if ok.any() else np.ones_like(ok)
    med = np.median(chi2[:, use], axis=1) / dof[None, :]
    # the median of chi2/dof: the bins' correlation inflates the variance, not the mean; the
    # median of a sum of a few correlated exponentials stays close to chi^2 with dof degrees
    background = np.maximum(med / median_factor(dof)[None, :], 1.0)
    return TimeFrequencyMap(t0 + starts / fs, L / fs, hop / fs, edges, chi2, dof, kappa, background, tolerance, ok)


def data_gaps(series, fs: float, t0: float, valid=None, min_gap: float = MIN_GAP) -> list[tuple[float, float]]:
    """Runs of missing data [s]: samples that are NaN in a channel or exactly zero in every
    channel of ``series`` (3, n) for at least ``min_gap`` seconds, between the first and
    the last sample of ``valid`` (the analysed span)."""
    x = np.asarray(series)
    bad = ~np.isfinite(x).all(axis=0) | (x == 0).all(axis=0)
    if valid is not None:
        idx = np.flatnonzero(valid)
        inside = np.zeros_like(bad)
        if idx.size:
            inside[idx[0] : idx[-1] + 1] = True
        bad &= inside
    out: list[tuple[float, float]] = []
    d = np.diff(np.concatenate([[0], bad.astype(np.int8), [0]]))
    for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)):
        if (b - a) / fs >= min_gap:
            out.append((t0 + a / fs, t0 + b / fs))
    return out


@dataclass(frozen=True)
class Event:
    """One transient (module docstring); times [s], frequencies [Hz]."""

    t_start: float
    t_stop: float
    t_peak: float
    slices: tuple  # indices of its hot tiles in the map
    channels: tuple  # channels that carry it
    channel_p: dict  # channel -> smallest tile/broadband p (times the tests made)
    f_lo: float
    f_hi: float
    band_excess: tuple  # per band of the map: summed excess chi2 (A+E+T) over the event
    significant_bands: tuple  # indices of the bands whose excess is significant
    track: tuple  # ((t_mid, f_peak, f_mean), ...) per hot slice
    excess: dict  # channel -> excess chi2 over the event
    t_share: float
    snr: float  # sqrt of the total excess chi2 (A+E+T): a rough matched-filter SNR
    track_kind: str  # "chirp", "stationary", "falling", "irregular" or "single"
    coherence: dict = field(default_factory=dict)  # witness coherence (witness_coherence)
    gap: tuple | None = None  # (start, stop) of missing data it overlaps
    #: the smallest T share a signal on one link or one test mass would have in the event's
    #: band under the noise model (:func:`instrumental_t_share`); None: T_SHARE_INSTRUMENTAL
    t_share_expected: float | None = None

    @property
    def t_share_threshold(self) -> float:
        """T share separating a gravitational wave from an instrumental signal: a third of
        :attr:`t_share_expected`, or :data:`T_SHARE_INSTRUMENTAL` without it."""
        return T_SHARE_INSTRUMENTAL if self.t_share_expected is None else T_SHARE_FRACTION * self.t_share_expected

    @property
    def duration(self) -> float:
        return self.t_stop - self.t_start


def find_events(tf: TimeFrequencyMap, alpha: float = MAP_ALPHA) -> list[Event]:
    """The events of the module docstring, loudest first."""
    n_c, n_t, G = tf.chi2.shape
    if n_t == 0:
        return []
    n_tests = n_c * n_t * (G + 1)
    thr = alpha / n_tests
    pt = np.where(tf.valid[None, :, None], tf.tile_p(), 1.0)
    pb = np.where(tf.valid[None, :], tf.broadband_p(), 1.0)
    hot = (pt < thr).any(axis=(0, 2)) | (pb < thr).any(axis=0)
    ex = tf.excess()
    # cores: contiguous hot tiles; then each core grows (hysteresis) over the neighbouring
    # tiles whose sum over the core's significant bands (A, E, T) has p < alpha: the weak
    # start of a chirp or the tail of a ringing glitch belong to the event, not to the quiet
    # tiles
    member = np.zeros(n_t, dtype=bool)
    k = 0
    while k < n_t:
        if not hot[k]:
            k += 1
            continue
        j = k
        while j + 1 < n_t and hot[j + 1]:
            j += 1
        core = _event(tf, np.arange(k, j + 1), pt, pb, ex, n_tests, alpha)
        bands = np.arange(min(core.significant_bands), max(core.significant_bands) + 1)
        level = (tf.background[:, bands] * tf.dof[None, bands]).sum()
        dof = 3 * tf.dof[bands].sum()

        def weak(i, bands=bands, dof=dof, level=level):
            return (
                bool(tf.valid[i])
                and tile_p_value(tf.chi2[:, i][:, bands].sum(), dof, level / dof, tf.kappa, tf.tolerance) < alpha
            )

        lo, hi = k, j
        while lo - 1 >= 0 and weak(lo - 1):
            lo -= 1
        while hi + 1 < n_t and weak(hi + 1):
            hi += 1
        member[lo : hi + 1] = True
        k = j + 1
    events = []
    k = 0
    while k < n_t:
        if not member[k]:
            k += 1
            continue
        j = k
        while j + 1 < n_t and member[j + 1]:
            j += 1
        events.append(_event(tf, np.arange(k, j + 1), pt, pb, ex, n_tests, alpha))
        k = j + 1
    events.sort(key=lambda e: -e.snr)
    return events


def _event(tf, sl, pt, pb, ex, n_tests, alpha) -> Event:
    G = tf.chi2.shape[2]
    centres = tf.t_mid[sl]
    # channels: the smallest p of a tile or broadband sum in the event, Bonferroni over the map
    ch_p = {c: float(min(pt[i, sl].min(), pb[i, sl].min()) * n_tests) for i, c in enumerate(CHANNELS)}
    carries = tuple(c for c in CHANNELS if ch_p[c] < alpha)
    # independent slices only (every other one: the tiles overlap by half), the loudest among
    # them, for sums
    peak = sl[int(np.argmax(np.maximum(ex[:, sl], 0).sum(axis=(0, 2))))]
    ind = sl[(sl - peak) % 2 == 0]
    exc = ex[:, ind].sum(axis=1)  # (3, G)
    bg_dof = tf.background * tf.dof[None, :]
    band_chi2 = tf.chi2[:, ind].sum(axis=(0, 1))
    band_level = (bg_dof.sum(axis=0)) * ind.size
    band_p = tile_p_value(
        band_chi2, 3 * tf.dof * ind.size, band_level / (3 * tf.dof * ind.size), tf.kappa, tf.tolerance
    )
    sig = np.flatnonzero(band_p < alpha / G)
    if sig.size == 0:
        sig = np.array([int(np.argmax(exc.sum(axis=0)))])
    f_lo, f_hi = float(tf.edges[sig.min()]), float(tf.edges[sig.max() + 1])
    # track: per slice, among its significant tiles (p < alpha per tile, A + E summed), the
    # band with the most excess and the excess-weighted mean log frequency; T alone where
    # A and E have none
    fc = np.sqrt(tf.edges[:-1] * tf.edges[1:])
    bg = tf.background * tf.dof[None, :]
    track = []
    for i in sl:
        for chans in ((0, 1), (0, 1, 2)):
            ch = list(chans)
            p_ae = tile_p_value(
                tf.chi2[ch, i].sum(axis=0),
                len(ch) * tf.dof,
                bg[ch].sum(axis=0) / (len(ch) * tf.dof),
                tf.kappa,
                tf.tolerance,
            )
            e = np.where(p_ae < alpha, np.maximum(ex[ch, i].sum(axis=0), 0.0), 0.0)
            if e.sum() > 0:
                break
        if e.sum() <= 0:
            continue
        track.append(
            (float(tf.t_mid[i]), float(fc[int(np.argmax(e))]), float(np.exp(np.sum(e * np.log(fc)) / e.sum())))
        )
    exc_c = np.maximum(exc.sum(axis=1), 0.0)
    total = float(exc_c.sum())
    t_share = float(exc_c[2] / total) if total > 0 else 0.0
    return Event(
        t_start=float(centres[0] - 0.5 * tf.hop),
        t_stop=float(centres[-1] + 0.5 * tf.hop),
        t_peak=float(tf.t_mid[peak]),
        slices=tuple(int(i) for i in sl),
        channels=carries,
        channel_p=ch_p,
        f_lo=f_lo,
        f_hi=f_hi,
        band_excess=tuple(float(x) for x in exc.sum(axis=0)),
        significant_bands=tuple(int(g) for g in sig),
        track=tuple(track),
        excess={c: float(exc_c[i]) for i, c in enumerate(CHANNELS)},
        t_share=t_share,
        snr=float(np.sqrt(total)),
        track_kind=track_kind([t for t, _, _ in track], [m for _, _, m in track]),
    )


def track_kind(t, f, ratio: float = CHIRP_RATIO) -> str:
    """``"chirp"`` when the excess-weighted frequency ``f`` rises over the event by at
    least ``ratio`` (from the first third of the track to its last third, means of log f)
    and ends at its highest; ``"falling"`` when it falls by as much; ``"stationary"`` when
    every point stays within ``ratio`` of the track's median; ``"single"`` for one point;
    else ``"irregular"``."""
    f = np.asarray(f, dtype=float)
    if f.size <= 1:
        return "single"
    lf = np.log(f)
    n3 = max(1, f.size // 3)
    rise = float(np.exp(lf[-n3:].mean() - lf[:n3].mean()))
    if rise >= ratio:
        return "chirp"
    if rise <= 1 / ratio:
        return "falling"
    if np.all(np.abs(lf - np.median(lf)) <= np.log(ratio)):
        return "stationary"
    return "irregular"


def kept_like(f_kept, df_fine: float, df_tile: float, lobe: float = 2.0):
    """``keep(f)`` for a tile's bins: those whose Hann main lobe (``+-lobe`` tile bins of
    width ``df_tile``) holds only kept fine bins (spacing ``df_fine``) of ``f_kept``, the
    diagnosis' analysis bins (the notches of the TDI response and the band already
    applied).  Bins that only half-avoid a notch leak its excess (measured on a 12-h
    simulated day, quiet tiles of 900 s: chi2/dof 1.072 keeping bins with half of their
    width clear, 1.007 with the main lobe clear, 1.002 with three bins either side)."""
    fk = np.sort(np.asarray(f_kept, dtype=float))

    def keep(f):
        f = np.asarray(f, dtype=float)
        n = np.searchsorted(fk, f + lobe * df_tile) - np.searchsorted(fk, f - lobe * df_tile)
        return n >= 0.99 * 2 * lobe * df_tile / df_fine

    return keep


def residual_map(data, residual, tile: float = TILE_DURATION) -> TimeFrequencyMap:
    """The time-frequency map (:func:`time_frequency_map`) of a residual (3, n) of ``data``
    (:class:`~ttlcore.diagnose.whitened.WhitenedData`) under its noise model: the diagonal of
    its noise CSD, its analysis bins (:func:`kept_like`), its band from ``3 / tile`` (the
    Hann main lobe clear of zero frequency), its valid samples and tolerance."""
    grid = data.grid
    s = data.context.settings
    psd = np.real(np.einsum("mii->mi", data.noise.csd))
    keep = kept_like(grid.f, 1.0 / grid.seg_duration, 1.0 / tile)
    band = (max(s.band[0], 3.0 / tile), s.band[1])
    return time_frequency_map(
        residual,
        grid.fs,
        grid.t0,
        grid.f,
        psd,
        band,
        tile=tile,
        valid=grid.mask,
        keep=keep,
        tolerance=s.tolerance,
    )


def event_excess(tf: TimeFrequencyMap, t_start: float, t_stop: float, background=None) -> float:
    """Excess chi^2 ``sum (chi2 - B dof)`` over A, E, T, the bands and the tiles of ``tf``
    centred in ``[t_start, t_stop]`` (``background`` ``B``: ``tf``'s, or another map's, so
    that a residual before and after a change is measured against one level)."""
    B = tf.background if background is None else background
    sl = (tf.t_mid >= t_start - 1e-6) & (tf.t_mid <= t_stop + 1e-6) & tf.valid
    return float(np.sum(tf.chi2[:, sl] - B[:, None, :] * tf.dof[None, None, :]))
