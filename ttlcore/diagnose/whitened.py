"""The whitened data of a diagnosis: small immutable values built once, and a per-run context.

:class:`WhitenedData` holds what every fit, candidate and search of a diagnosis works on
(docs/diagnostics.md, "The loop"), as four parts of one concept each:

* :class:`AnalysisGrid`: the segments and bins - the decimation to 2 Hz, the 6-hour
  Tukey-windowed segments (a quarter of shorter data), the analysis bins (band and arm
  notches) and the bands of the adequacy test;
* :class:`MeasuredTDI`: the A, E, T TDI of the data and of the TTL regressors (input rate,
  decimated, band spectra), the mean light travel times and the DWS readout noise;
* :class:`Whitening`: the noise CSD ``S(f)``, its whitening ``L^H`` (``S^-1 = L L^H``) and
  the whitened data spectra ``L^H d``;
* :class:`DiagnosisContext`: the settings, telemetry and effect plugins of the run, and its
  column cache.

The first three are built by :func:`whiten_telemetry` or :func:`whiten_tdi` and never
change: :meth:`WhitenedData.with_noise` returns a new value with another :class:`Whitening`
(the fitted noise levels, the DWS readout noise of a drifting model) and the same grid, TDI
and context.

Regressor columns are computed from it by :mod:`ttlcore.diagnose.columns` (pure functions
of the effect and its parameters); their cache (:class:`ttlcore.diagnose.columns.ColumnStore`)
is the per-run state of the context, shared on purpose by the values derived from one another
with :meth:`~WhitenedData.with_noise`, its keys immutable (the effect's spelling, the
coefficients it was built with, the noise model's digest), so that no trial fit can change
what another fit sees.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from types import EllipsisType
from typing import TYPE_CHECKING

import numpy as np

from ..conventions import COEFFICIENT_NAMES
from ..effects.column_tdi import TelemetryRegressors, effect_input_from_telemetry, tdi_in_blocks
from ..effects.linear_ttl import LinearTTL
from ..effects.registry import available_effects
from ..errors import ConfigError
from ..estimate.fit import (
    DWS_ASD,
    FitSettings,
    SegmentSpectra,
    default_band_edges,
    dws_asd_from_config,
    fit_spectra,
    notch_mask,
    variance_factor,
)
from ..estimate.spectra import segment_fft, window
from ..tdi.combinations import AET, aet
from ..tdi.data import TDIData, lowpass_decimate, lowpass_taps
from .adequacy import instrument_noise_csd, merged_band_edges
from .columns import ColumnStore, read_only, regressor_columns
from .settings import DiagnoseSettings

if TYPE_CHECKING:
    from ..effects.base import Effect
    from ..io.telemetry import Telemetry
    from .noise_model import NoiseModel


def band_slices(band_index: np.ndarray, G: int) -> tuple[tuple[int, int], ...]:
    """Contiguous bin ranges of the bands (frequencies ascend, so bands are contiguous)."""
    out = []
    for g in range(G):
        idx = np.flatnonzero(band_index == g)
        out.append((int(idx[0]), int(idx[-1]) + 1) if idx.size else (0, 0))
    return tuple(out)


def fft_length(n: int) -> int:
    """The largest length ``<= n`` whose prime factors are 2, 3, 5 and 7.

    Every search of a diagnosis transforms segments of the default length again and again;
    at a length with a large prime factor the transform costs several times more (a day's
    quarter at 2 Hz, 43012 = 4 x 10753 samples: 1.2 ms against 0.19 ms for 43008 =
    2^11 x 3 x 7), and near such lengths these numbers are a few samples apart.
    ``scipy.fft.prev_fast_len`` gives lengths with factors 2, 3, 5 (``real=True``: 41472
    for 43012, 3.6 % shorter) or 2 to 11 (``real=False``), not this set."""
    best, p2 = 1, 1
    while p2 <= n:
        p3 = p2
        while p3 <= n:
            p5 = p3
            while p5 <= n:
                p7 = p5
                while p7 <= n:
                    best = max(best, p7)
                    p7 *= 7
                p5 *= 5
            p3 *= 3
        p2 *= 2
    return best


def whitening(csd: np.ndarray) -> np.ndarray:
    """``L^H`` (m, 3, 3) with ``S^-1 = L L^H`` (Cholesky of the inverse CSD)."""
    return np.conj(np.swapaxes(np.linalg.cholesky(np.linalg.inv(csd)), -1, -2))


def noise_digest(csd: np.ndarray) -> str:
    """A digest of a noise CSD: the cache key of spectra whitened with it."""
    return hashlib.blake2b(np.ascontiguousarray(csd).tobytes(), digest_size=16).hexdigest()


@dataclass(frozen=True, eq=False)
class AnalysisGrid:
    """The segments and bins of a diagnosis: where and at which frequencies it looks.

    Attributes
    ----------
    decimation : int
        Decimation factor from the input rate ``fs_in`` [Hz] (first time ``t0_in`` [s]).
    fs, t0 : float
        Rate [Hz] and first time [s] of the decimated series.
    mask : ndarray (n,) of bool
        Valid decimated samples (the TDI delays' start-up and a 120-s margin removed).
    L : int
        Segment length (decimated samples).
    starts : tuple of int
        First samples of the segments (decimated); ``seg_t0`` their times [s] (S,).
    seg_duration : float
        Segment length [s].
    win : ndarray (L,)
        Segment taper.
    f, bins : ndarray (m,)
        Analysis frequencies [Hz] and their indices in the segment's rfft grid.
    edges : ndarray (G + 1,)
        Band edges [Hz] of the adequacy test; ``G`` the number of bands.
    band_index : ndarray (m,) of int
        Band of each bin; ``slices`` the bin range ``(first, stop)`` of each band.
    kappa : float
        Variance factor of the tapered segments (:func:`ttlcore.estimate.fit.variance_factor`).
    w2 : ndarray (S, L)
        Each segment's normalised squared taper (weights of modulation products).
    """

    decimation: int
    fs_in: float
    t0_in: float
    fs: float
    t0: float
    mask: np.ndarray
    L: int
    starts: tuple[int, ...]
    seg_t0: np.ndarray
    seg_duration: float
    win: np.ndarray
    f: np.ndarray
    bins: np.ndarray
    edges: np.ndarray
    G: int
    band_index: np.ndarray
    slices: tuple[tuple[int, int], ...]
    kappa: float
    w2: np.ndarray

    def __post_init__(self) -> None:
        read_only(*(v for v in vars(self).values() if isinstance(v, np.ndarray)))

    def segment_kappa(self) -> np.ndarray:
        """The variance factor of each segment (S,): :attr:`kappa` for all of them here; a
        gated segment's own in :class:`ttlcore.diagnose.gating.GatedGrid`."""
        return np.full(len(self.starts), self.kappa)

    def spectra(self, x: np.ndarray) -> np.ndarray:
        """(3, k, n) decimated series -> band spectra (S, m, 3, k), masked like the data."""
        return self.spectra_of(x)

    def segments_over(self, a: int, b: int) -> range:
        """The segments that hold any of the decimated samples ``a .. b - 1`` (a range)."""
        hit = [i for i, s0 in enumerate(self.starts) if s0 < b and s0 + self.L > a]
        return range(hit[0], hit[-1] + 1) if hit else range(0)

    def spectra_of(self, x: np.ndarray, offset: int = 0, segments: range | None = None) -> np.ndarray:
        """Band spectra (len(segments), m, 3, k) of the ``segments`` (default all) of a
        (3, k, n) decimated series whose first sample is the decimated sample ``offset``
        (zero outside it): a stretch's spectra (a glitch's template) where it is not zero,
        the same numbers as :meth:`spectra` of the series placed at full length."""
        idx = range(len(self.starts)) if segments is None else segments
        out = np.empty((len(idx), self.f.size, x.shape[0], x.shape[1]), dtype=complex)
        for j, i in enumerate(idx):
            s0 = self.starts[i]
            a, b = max(s0 - offset, 0), max(min(s0 + self.L - offset, x.shape[-1]), 0)
            seg = x[:, :, a:b]
            if not seg.any():  # a stretch's column (a glitch's template) is zero in most segments
                out[j] = 0.0
                continue
            if b - a < self.L:  # the segment reaches past the stretch: zeros there
                full = np.zeros(x.shape[:2] + (self.L,))
                full[:, :, a + offset - s0 : b + offset - s0] = seg
                seg = full
            m = self.mask[s0 : s0 + self.L]
            bad = ~np.isfinite(seg) & m
            seg = np.where(m, np.nan_to_num(seg), 0.0)
            if bad.any():
                raise ConfigError("a regressor column is not finite inside the analysed span")
            _, X = segment_fft(seg, self.fs, self.win * m, workers=None)
            out[j] = np.moveaxis(X[:, :, self.bins], 2, 0)
        return out

    def decimate(self, xyz: np.ndarray, is_aet: bool = False) -> np.ndarray:
        """XYZ (or A, E, T) TDI of columns (3, k, n_in) -> decimated A, E, T (3, k, n), the
        data's anti-alias filter (:meth:`ttlcore.tdi.data.TDIData.decimated`; FFT threads:
        the calling thread's default, one in the candidates' threads)."""
        a = xyz if is_aet else aet(xyz)
        if self.decimation == 1:
            return a
        return lowpass_decimate([a], lowpass_taps(self.fs_in), self.decimation, workers=None)[0]


@dataclass(frozen=True, eq=False)
class MeasuredTDI:
    """The TDI of a diagnosis' data and of its TTL regressors, before any whitening.

    Attributes
    ----------
    td_in : TDIData
        A, E, T TDI of the data at the input rate, and of the regressors unless
        ``rebuild`` is set (then ``td_in.names`` is empty: :meth:`input_regressors`).
    data_series : ndarray (3, n)
        Decimated A, E, T of the data; ``d`` their band spectra (S, m, 3).
    regressor_series : ndarray (3, k, n)
        Decimated A, E, T of the TDI regressors, named ``regressor_names`` (their whitened
        spectra are :func:`ttlcore.diagnose.columns.ttl_columns`); ``ttl_names`` those of them
        that are linear TTL coefficients (the 24 of telemetry).
    ltt_mean : ndarray (6,)
        Mean light travel times [s], LINKS order.
    dws_asd : float
        DWS readout noise [rad/sqrt(Hz)].
    rebuild : TelemetryRegressors or None
        Builds the input-rate regressors again from the telemetry (:func:`whiten_telemetry`,
        which does not keep them: a day's 24 at 4 Hz are 199 MB, held through a whole
        diagnosis for the few that use them); None: ``td_in`` holds them.
    """

    td_in: TDIData
    data_series: np.ndarray
    d: np.ndarray
    regressor_names: tuple[str, ...]
    regressor_series: np.ndarray
    ttl_names: tuple[str, ...]
    ltt_mean: np.ndarray
    dws_asd: float
    rebuild: TelemetryRegressors | None = None

    def __post_init__(self) -> None:
        read_only(self.data_series, self.d, self.regressor_series, self.ltt_mean)

    def input_regressors(self, names: Iterable[str]) -> np.ndarray:
        """A, E, T (3, k, n_in) of the named TDI regressors at the input rate (the derivative
        and shifted columns and the effects' predictions start from them): ``td_in``'s, or
        built again from the telemetry by ``rebuild`` (1.7 s of CPU for a day's 24, 0.06 s a
        regressor; the same numbers, the same code path)."""
        names = tuple(names)
        if self.rebuild is not None:
            return self.rebuild(names)
        return self.td_in.regressors[:, [self.td_in.names.index(n) for n in names]]

    def input_combination(self, names: Iterable[str], weights) -> np.ndarray:
        """A, E, T (3, n_in) of ``sum_k weights_k R_k`` over the named regressors at the input
        rate: by ``rebuild``, the TDI of the weighted witnesses (one column's, not k)."""
        names = tuple(names)
        w = np.asarray(weights, dtype=float)
        if self.rebuild is not None:
            return self.rebuild(names, w)[:, 0]
        return np.einsum("k,ckn->cn", w, self.input_regressors(names))


@dataclass(frozen=True, eq=False)
class Whitening:
    """A noise model on the analysis bins and the data whitened with it.

    Attributes
    ----------
    csd : ndarray (m, 3, 3)
        Noise CSD of A, E, T [1/Hz].
    Lh : ndarray (m, 3, 3)
        Its whitening ``L^H`` (``S^-1 = L L^H``).
    key : str
        Digest of ``csd``: the cache key of spectra whitened with it.
    wd : ndarray (S, m, 3)
        Whitened data spectra ``L^H d``.
    dd : ndarray (S, G)
        Their power per segment and band.
    parameters : NoiseModel or None
        The fitted secondary-noise levels the CSD comes from
        (:class:`ttlcore.diagnose.noise_model.NoiseModel`), None for the fixed model.
    """

    csd: np.ndarray
    Lh: np.ndarray
    key: str
    wd: np.ndarray
    dd: np.ndarray
    parameters: NoiseModel | None = None

    def __post_init__(self) -> None:
        read_only(self.csd, self.Lh, self.wd, self.dd)

    def whiten(self, X: np.ndarray) -> np.ndarray:
        """``L^H X`` for spectra (S, m, 3, k)."""
        return np.matmul(self.Lh, X)


@dataclass(eq=False)
class DiagnosisContext:
    """The per-run context of a diagnosis: its inputs other than the data, and its column cache.

    Not a value (compared by identity): one per run (``ttl diagnose``, a refit; a new one for
    gated data), shared by reference by every :class:`WhitenedData` derived from the first
    one with :meth:`WhitenedData.with_noise`, so that columns built under one noise model are
    reused (transformed) under the next.  The cache is the only state a diagnosis keeps
    between fits: its keys are immutable (module docstring), its column sets are values, an
    entry is only ever replaced by its transform to another noise model.

    Attributes
    ----------
    settings : DiagnoseSettings
    tm : Telemetry or None
        The telemetry (every effect available), None for TDI outputs only.
    effect_modules : tuple of str
        Plugin modules (paths or dotted names); ``registry`` the effects available
        (name -> class, :func:`ttlcore.effects.registry.available_effects`).
    store : ColumnStore
        The column cache (:mod:`ttlcore.diagnose.columns`).
    """

    settings: DiagnoseSettings
    tm: Telemetry | None
    effect_modules: tuple[str, ...]
    registry: Mapping[str, type[Effect]]
    store: ColumnStore = field(default_factory=ColumnStore, repr=False)


@dataclass(frozen=True, eq=False)
class WhitenedData:
    """What every fit, candidate and search of a diagnosis works on (module docstring).

    Attributes
    ----------
    grid : AnalysisGrid
        Segments, bins and bands.
    tdi : MeasuredTDI
        The data's and the regressors' TDI, series and spectra.
    noise : Whitening
        The noise model and the data whitened with it.
    context : DiagnosisContext
        Settings, telemetry, plugins and column cache of the run (shared, see there).
    """

    grid: AnalysisGrid
    tdi: MeasuredTDI
    noise: Whitening
    context: DiagnosisContext

    def with_noise(self, csd: np.ndarray, noise_parameters: NoiseModel | None | EllipsisType = ...) -> WhitenedData:
        """The same data under another noise CSD (m, 3, 3): a new value sharing the grid, the
        TDI and the context (``self`` is left as it is); ``noise_parameters`` (default: kept)
        the fitted levels it comes from."""
        Lh = whitening(csd)
        M = Lh @ np.linalg.inv(self.noise.Lh)
        wd = np.einsum("mij,smj->smi", M, self.noise.wd)
        dd = np.empty_like(self.noise.dd)
        for g, (a, b) in enumerate(self.grid.slices):
            dd[:, g] = np.sum(np.abs(wd[:, a:b]) ** 2, axis=(1, 2))
        noise = Whitening(
            csd=csd,
            Lh=Lh,
            key=noise_digest(csd),
            wd=wd,
            dd=dd,
            parameters=self.noise.parameters if isinstance(noise_parameters, EllipsisType) else noise_parameters,
        )
        return replace(self, noise=noise)


def whiten_tdi(
    td: TDIData,
    settings: DiagnoseSettings | None = None,
    tm: Telemetry | None = None,
    effect_modules: Iterable[str] = (),
    dws_asd: float | None = None,
    rebuild: TelemetryRegressors | None = None,
) -> WhitenedData:
    """Build the :class:`WhitenedData` of TDI outputs (with the telemetry they come from,
    when there is one; with ``rebuild``, the input-rate regressors are not kept but built
    again from it when asked for, :meth:`MeasuredTDI.input_regressors`).

    The noise model is the instrument's (:func:`ttlcore.diagnose.adequacy.instrument_noise_csd`):
    secondary noises plus the DWS readout noise through a first estimate of the linear
    coefficients (the first pass of the standard GLS fit of the TTL columns, used for nothing else).
    """
    s = settings or DiagnoseSettings()
    dws = float(dws_asd if dws_asd is not None else (s.dws_asd if s.dws_asd is not None else DWS_ASD))
    ltt_mean = np.asarray(td.ltt_mean, dtype=float)
    tda = td.to_aet()
    del td  # with rebuild, the input-rate regressors go once decimated (the caller hands td over)
    factor = max(1, int(round(tda.fs / 2.0)))
    dec = tda.decimated(factor) if factor > 1 else tda
    grid = _analysis_grid(dec, tda, ltt_mean, s)
    d = grid.spectra(dec.data[:, None, :])[..., 0]
    R = grid.spectra(dec.regressors)
    if rebuild is not None:
        tda = replace(tda, regressors=np.empty((3, 0, tda.size)), names=())
    tdi = MeasuredTDI(
        td_in=tda,
        data_series=dec.data,
        d=d,
        regressor_names=tuple(dec.names),
        regressor_series=dec.regressors,
        ttl_names=tuple(nm for nm in dec.names if nm in COEFFICIENT_NAMES),
        ltt_mean=ltt_mean,
        dws_asd=dws,
        rebuild=rebuild,
    )
    C0 = _first_coefficients(grid, d, R, tdi, s, dws)
    csd = instrument_noise_csd(grid.f, ltt_mean, C0, dws)
    Lh = whitening(csd)
    wd = np.matmul(Lh, d[..., None])[..., 0]  # (S, m, 3)
    dd = np.zeros((len(grid.starts), grid.G))
    for g in range(grid.G):
        dd[:, g] = np.sum(np.abs(wd[:, grid.band_index == g]) ** 2, axis=(1, 2))
    modules = tuple(effect_modules)
    data = WhitenedData(
        grid=grid,
        tdi=tdi,
        noise=Whitening(csd=csd, Lh=Lh, key=noise_digest(csd), wd=wd, dd=dd),
        context=DiagnosisContext(settings=s, tm=tm, effect_modules=modules, registry=available_effects(modules)),
    )
    data.context.store.put(("regressors",), data, regressor_columns(data, R))
    return data


#: FFT segments keeping less than this share of their taper's power (under the data's gaps,
#: or a gate) are left out: a short remnant of a segment leaks the red noise below the band
#: into it through the gap's edges or the gate's ramps (4-h simulated day, 58-min segments,
#: a 55-min gate: keeping a remnant of 0.3 read chi2/dof 1.43 and pull RMS 2.49; leaving it
#: out, 0.993 and 0.88).
MIN_KEPT = 0.6


def _analysis_grid(dec: TDIData, tda: TDIData, ltt_mean: np.ndarray, s: DiagnoseSettings) -> AnalysisGrid:
    """The segments and frequency bins of the diagnosis on the decimated TDI ``dec`` (of the
    A, E, T outputs ``tda``): the valid samples less a 120-s margin at either end, segments
    of ``s.segment_duration`` (default a quarter of the span, at most 6 h, shortened to a
    fast FFT length), the band's bins less the notches, and the analysis bands.

    Raises ConfigError when the data are too short.
    """
    factor = max(1, int(round(tda.fs / 2.0)))
    fs, t0, n = dec.fs, dec.t0, dec.size
    ok = np.isfinite(dec.data).all(axis=0) & np.isfinite(dec.regressors).all(axis=(0, 1))
    idx = np.flatnonzero(ok)
    if idx.size < 2:
        raise ConfigError("no valid TDI samples (data too short for the TDI delays)")
    margin = int(round(120 * fs))  # room for the extra delays and derivative stencils of effects
    lo, hi = idx[0] + margin, idx[-1] + 1 - margin
    mask = np.zeros(n, dtype=bool)
    mask[lo:hi] = True
    mask &= ok
    span = (hi - lo) / fs
    seg = s.segment_duration or min(21600.0, np.floor(span / 4))
    if seg * fs < 256:
        raise ConfigError(f"data too short for a diagnosis ({span:.0f} s of valid TDI)")
    step = int(round(seg * fs))
    # segments start every ``step`` samples; the default length is shortened to one the FFT
    # handles fast, the last few samples of each segment left out (the segments stay where
    # they were: the tapers move by those few samples only)
    L = step if s.segment_duration else fft_length(step)
    starts = tuple(range(lo, hi - step + 1, step))
    if not starts:
        raise ConfigError(f"no FFT segment of {seg:g} s fits in {span:.0f} s of valid TDI")
    win = window(s.window, L)
    # a segment of a gap (missing data) holding less than MIN_KEPT of its taper's power is
    # left out, as the gated data leave it out (ttlcore.diagnose.gating): one with no data
    # at all has no spectrum (a 7-h gap in a 25-h live window, 6-h segments)
    full = float(np.sum(win**2))
    starts = tuple(s0 for s0 in starts if float(np.sum((win * mask[s0 : s0 + L]) ** 2)) >= MIN_KEPT * full)
    if not starts:
        raise ConfigError(f"no FFT segment of {seg:g} s holds {MIN_KEPT:.0%} of its data: the data are mostly gaps")
    seg_t0 = np.array([t0 + s0 / fs for s0 in starts])
    f = np.fft.rfftfreq(L, 1 / fs)
    sel = (f >= s.band[0]) & (f <= s.band[1])
    keep = np.zeros_like(sel)
    keep[sel] = notch_mask(f[sel], ltt_mean)
    bins = np.flatnonzero(keep)
    f = f[bins]
    edges = merged_band_edges(f, default_band_edges(s.band, s.n_bands), 6 * len(starts), s.min_band_dof)
    G = len(edges) - 1
    band_index = np.clip(np.searchsorted(edges, f, side="right") - 1, 0, G - 1)
    w2 = np.stack([(win * mask[s0 : s0 + L]) ** 2 for s0 in starts])
    return AnalysisGrid(
        decimation=factor,
        fs_in=tda.fs,
        t0_in=tda.t0,
        fs=fs,
        t0=t0,
        mask=mask,
        L=L,
        starts=starts,
        seg_t0=seg_t0,
        seg_duration=L / fs,
        win=win,
        f=f,
        bins=bins,
        edges=edges,
        G=G,
        band_index=band_index,
        slices=band_slices(band_index, G),
        kappa=variance_factor(s.window, 4096, 0.0),
        w2=w2 / w2.sum(axis=1, keepdims=True),
    )


def _first_coefficients(
    grid: AnalysisGrid, d: np.ndarray, R: np.ndarray, tdi: MeasuredTDI, s: DiagnoseSettings, dws: float
):
    """A first estimate of the 24 linear coefficients (None unless the TDI hold all 24
    regressors) from the segment spectra ``d`` of the data and ``R`` of the regressors.

    The first GLS pass, under the analytic secondary-noise CSD (no re-estimation of the
    CSD from the residual): C0 only sets the DWS readout-noise term, which it needs to a
    few per cent; the ten passes of the standard fit moved the diagnosis' coefficients by
    1e-3 sigma and chi^2/dof by 6e-7 (bench day with a witness, 1 day) and cost 40 % of a
    window refit, which the live fitter makes every segment.
    """
    if len(tdi.ttl_names) != len(COEFFICIENT_NAMES):
        return None
    sp = [SegmentSpectra(t, grid.seg_duration, grid.f, d[i], R[i]) for i, t in enumerate(grid.seg_t0)]
    res, _ = fit_spectra(
        sp,
        tdi.ltt_mean,
        FitSettings(band=s.band, notch=False, dws_asd=dws, iterations=0, robust_covariance=False, n_bands=s.n_bands),
        names=tdi.regressor_names,
    )
    return res.coefficients[[tdi.regressor_names.index(nm) for nm in COEFFICIENT_NAMES]]


def without_missing_ends(tm: Telemetry) -> Telemetry:
    """``tm`` from its first to its last sample where every series (eta, both DWS angles)
    is finite: missing data at either end are no gap between data, and are cut off
    (``t0`` moved with them).

    A live window that begins inside a long gap holds hours of NaN before its data: the
    blind week's window 120..143 began with the last 4 h of a 7-h gap, and its analysis read
    an "event" 8-23 min after the data began (T share 83 %, SNR 17000) that the same data
    without those hours do not have (reproduced from the recording; advised as two 430-s
    glitches).  A file that starts or ends with a gap is read the same way."""
    ok = np.isfinite(tm.eta).all(axis=0) & np.isfinite(tm.dws_phi).all(axis=0) & np.isfinite(tm.dws_eta).all(axis=0)
    idx = np.flatnonzero(ok)
    if idx.size == 0 or (idx[0] == 0 and idx[-1] == tm.size - 1):
        return tm
    a, b = int(idx[0]), int(idx[-1]) + 1
    return replace(
        tm,
        t0=float(tm.t0) + a / float(tm.fs),
        eta=tm.eta[:, a:b],
        dws_phi=tm.dws_phi[:, a:b],
        dws_eta=tm.dws_eta[:, a:b],
        ltt=tm.ltt[:, a:b],
    )


def whiten_telemetry(
    tm: Telemetry, settings: DiagnoseSettings | None = None, effect_modules: Iterable[str] = ()
) -> WhitenedData:
    """:class:`WhitenedData` of a :class:`~ttlcore.io.telemetry.Telemetry` (ours or
    lisainstrument's): every effect available.  TDI in blocks
    (:func:`ttlcore.effects.column_tdi.tdi_in_blocks`): the interpolation taps of a day would
    hold ~4 GB.  The input-rate regressors are not kept (:class:`TelemetryRegressors`)."""
    s = settings or DiagnoseSettings()
    tm = without_missing_ends(tm)
    data, regs = tdi_in_blocks(
        tm.ltt,
        tm.fs,
        LinearTTL().columns(effect_input_from_telemetry(tm)),
        tm.eta,
        order=s.order,
        delay_order=s.delay_order,
    )
    # A, E, T in place, one column at a time (TDIData.to_aet held X2, Y2, Z2 and A, E, T of a
    # day at once: 2 x 207 MB), handed over (whiten_tdi lets them go once decimated)
    data = aet(data)  # its own array: a view would hold the regressors' with it
    for k in range(regs.shape[1]):
        regs[:, k] = aet(regs[:, k])
    ltt_mean = np.nanmean(np.asarray(tm.ltt), axis=-1)
    handed = [TDIData(float(tm.t0), float(tm.fs), AET, data, regs, COEFFICIENT_NAMES, ltt_mean)]
    del data, regs
    dws = s.dws_asd if s.dws_asd is not None else dws_asd_from_config(tm.config)
    rebuild = TelemetryRegressors(tm, s.order, s.delay_order)
    return whiten_tdi(handed.pop(), s, tm=tm, effect_modules=effect_modules, dws_asd=dws, rebuild=rebuild)
