"""Model against measurement: fit a model (a list of effects), test it against the
instrument noise model, rank the missing effects and the generic witnesses
(docs/diagnostics.md; ``ttl diagnose``).

Everything here is the linear-Gaussian model of :mod:`ttlcore.estimate.fit` in the frequency domain,
A, E, T jointly, with the noise CSD held *fixed* at the instrument model
(:func:`ttlcore.diagnose.adequacy.instrument_noise_csd`) - never re-estimated from the residual -
so that chi^2 values of different models are comparable and an unmodelled effect shows
as excess instead of being absorbed:

    Q(theta) = theta^T (N - E) theta - 2 theta^T b + dd,    chi2 = 2 Q,

with ``N = Re sum R^H S^-1 R``, ``b = Re sum R^H S^-1 d``, ``dd = sum d^H S^-1 d`` over the
bins of each band and segment (:class:`Gram`), ``E`` the errors-in-variables term of the TTL
regressors (:mod:`ttlcore.estimate.fit`).  For a candidate effect with columns ``K`` added to the
model columns ``M``:

- ``delta_chi2 = chi2_M - chi2_{M+K}`` at the GLS optima, divided by the variance factor
  ``kappa`` of the tapered segments (:func:`ttlcore.estimate.fit.variance_factor`), distributed as
  chi^2 with ``|K|`` degrees of freedom if the effect is absent;
- the exact log Bayes factor of the linear-Gaussian model with a flat prior on the model
  coefficients and a zero-mean Gaussian prior of standard deviation ``prior_scale`` on each
  new parameter (:func:`log_bayes_factor`);
- for effects with a searched nonlinear parameter (a step time) the Bayes factor is
  marginalised over the search grid (uniform prior) and the Bayesian information criterion
  change is reported too;
- the share of the excess it explains, ``delta_chi2 / (chi2_M - dof_M)``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import special, stats
from scipy.optimize import minimize_scalar

from ..conventions import COEFFICIENT_NAMES, LINKS, parse_duration
from ..conventions import C as SPEED_OF_LIGHT
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
from ..tdi.combinations import (
    AET_MATRIX,
    DEFAULT_DELAY_ORDER,
    MICHELSON,
    aet,
    build,
    link_responses,
)
from ..tdi.data import TDIData, history_samples, lowpass_taps
from ..tdi.interpolation import DEFAULT_ORDER, timeshift
from ..tdi.regressors import placement
from .adequacy import (
    DEFAULT_ALPHA,
    DEFAULT_TOLERANCE,
    DIAGNOSIS_BAND,
    _hz,
    band_table,
    describe_failures,
    describe_time_failures,
    instrument_noise_csd,
    merged_band_edges,
    p_value,
    third_octave_table,
)
from .effects import (
    Column,
    Effect,
    LinearTTL,
    Step,
    available_effects,
    columns_tdi,
    derivative,
    effect_input_from_telemetry,
    filtered,
    make_effects,
    names_only_input,
    readout_noise_factor,
    tdi_in_blocks,
)
from .evidence import log_bayes_factor
from .noise_model import noise_model_json, profile_noise_model
from .search import profile_search, stable_solve
from .witnesses import witness_candidates, witness_search

log = logging.getLogger(__name__)


@dataclass
class DiagnoseSettings:
    """Settings of a diagnosis.

    Attributes
    ----------
    band : tuple
        Frequency band [Hz] (default :data:`ttlcore.diagnose.adequacy.DIAGNOSIS_BAND`).
    segment_duration : float or None
        FFT segment length [s]; None: 6 h, or a quarter of shorter data.
    n_bands : int
        Log-spaced bands for the per-band tests.
    time_segment : float
        Length [s] of the time slices of the per-time adequacy (Hann-windowed residual).
    tolerance, alpha : float
        Noise-model tolerance and significance level (:mod:`ttlcore.diagnose.adequacy`).
    noise_model : str
        ``"fitted"``: the secondary-noise levels are fitted with the model
        (:mod:`ttlcore.diagnose.noise_model`, default); ``"fixed"``: the paper's levels (then a
        tolerance of 0.05 is advisable, see docs/diagnostics.md).
    log_bf_threshold : float
        A candidate is significant when its log Bayes factor exceeds this (2.3: odds 10:1)
        *and* its delta chi^2 has p < alpha.
    step_grid, step_refine : float
        Coarse and fine spacing [s] of the step-time search.
    expansion_passes, shift_span : int, float
        Gauss-Newton passes of the shifted-witness effects (``timing-offset``,
        ``ltt-error``), and the half-width [s] of the offset search that starts them.
    witnesses : bool
        Run the witness search.
    dws_asd : float or None
        DWS readout noise [rad/sqrt(Hz)]; None: from the telemetry's configuration.
    """

    band: tuple = DIAGNOSIS_BAND
    segment_duration: float | None = None
    window: str = "tukey:0.1"
    n_bands: int = 8
    time_segment: float = 3600.0
    tolerance: float = DEFAULT_TOLERANCE
    alpha: float = DEFAULT_ALPHA
    noise_model: str = "fitted"
    log_bf_threshold: float = 2.3
    step_grid: float = 3600.0
    step_refine: float = 900.0
    witnesses: bool = True
    top_witnesses: int = 5
    #: distinct top witnesses turned into candidates (witness effect; for DWS witnesses
    #: also fd-coupling with a searched pole pair and with a searched real pole)
    witness_candidates: int = 3
    #: Gauss-Newton passes of the linearised effects in a model (0: Taylor at zero only)
    expansion_passes: int = 3
    #: half-width [s] of the profile search of the offsets of ``timing-offset`` and
    #: ``ltt-error`` (:meth:`Diagnoser.shift_search`) that starts those passes
    shift_span: float = 5.0
    #: bands with fewer degrees of freedom are merged with their neighbour, so that the
    #: statistical scatter of chi2/dof in a band (sqrt(2 kappa / dof) = 0.032 at 2000) stays
    #: well inside the +-10 % a correct model must meet
    min_band_dof: int = 2000
    dws_asd: float | None = None
    order: int = DEFAULT_ORDER
    delay_order: int = DEFAULT_DELAY_ORDER


# ---------------------------------------------------------------------------
# Linear-Gaussian algebra
# ---------------------------------------------------------------------------

def _band_slices(band_index: np.ndarray, G: int) -> list[tuple[int, int]]:
    """Contiguous bin ranges of the bands (frequencies ascend, so bands are contiguous)."""
    out = []
    for g in range(G):
        idx = np.flatnonzero(band_index == g)
        out.append((int(idx[0]), int(idx[-1]) + 1) if idx.size else (0, 0))
    return out


def _as_real(w: np.ndarray) -> np.ndarray:
    """(S, m, 3, p) complex -> (p, S, m, 6) float (real and imaginary parts interleaved), so
    that ``Re sum conj(a) b`` is a real dot product."""
    return np.ascontiguousarray(np.moveaxis(w, -1, 0)).view(np.float64)


def _gram_x(XA: np.ndarray, XB: np.ndarray, slices) -> np.ndarray:
    """``Re sum conj(A) B`` per segment and band from :func:`_as_real` layouts -> (S, G, p, q)."""
    p, S = XA.shape[:2]
    q = XB.shape[0]
    out = np.zeros((S, len(slices), p, q))
    for g, (a, b) in enumerate(slices):
        if b <= a:
            continue
        A = XA[:, :, a:b].reshape(p, S, -1).transpose(1, 0, 2)
        B = XB[:, :, a:b].reshape(q, S, -1).transpose(1, 2, 0)
        out[:, g] = np.matmul(A, B)
    return out


def _gram(wA: np.ndarray, wB: np.ndarray, band_index: np.ndarray, G: int) -> np.ndarray:
    """``Re sum conj(A) B`` per segment and band: (S, m, 3, p) x (S, m, 3, q) -> (S, G, p, q)."""
    return _gram_x(_as_real(wA), _as_real(wB), _band_slices(band_index, G))


@dataclass
class ModelFit:
    """A model fitted under the fixed instrument noise model.

    Attributes
    ----------
    effects : list of Effect
    names : tuple
        Column names (the 24 TTL names first when present).
    theta : ndarray (P,)
        GLS estimates (column units: m/rad for TTL).
    covariance : ndarray (P, P)
        ``kappa (2 (N - E))^-1``.
    chi2_seg_band : ndarray (S, G)
        chi^2 per segment and band against the noise model (plain ``N``: the residual's
        DWS-noise part is in the noise model).
    dof_band : ndarray (G,)
    bands : :class:`ttlcore.diagnose.adequacy.BandTable`
    q_min : float
        ``Q`` at the optimum on the EIV-corrected likelihood (for evidences).
    """

    effects: list
    names: tuple
    theta: np.ndarray
    covariance: np.ndarray
    chi2_seg_band: np.ndarray
    dof_band: np.ndarray
    bands: object
    q_min: float
    residual_w: np.ndarray = field(repr=False, default=None)
    time_table: dict | None = None
    #: per-segment, per-band normal equations (N (S, G, P, P), b (S, G, P)) of the model
    normal: tuple | None = field(repr=False, default=None)
    #: whitened data power per segment and band
    dd: np.ndarray | None = field(repr=False, default=None)
    #: errors-in-variables term (G, P, P) of the model's columns (cached)
    eiv_term: np.ndarray | None = field(repr=False, default=None)
    #: searched nonlinear parameters of the model's effects: effect spec -> SearchResult.to_json()
    searches: dict = field(default_factory=dict)

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.abs(np.diag(self.covariance)))

    @property
    def chi2(self) -> float:
        return float(self.chi2_seg_band.sum())

    @property
    def dof(self) -> float:
        return float(self.dof_band.sum())

    @property
    def chi2_dof(self) -> float:
        return self.chi2 / self.dof

    @property
    def parameter_names(self) -> tuple:
        """The physical parameter of each column: a linear coefficient whose witness a
        shifted-witness effect moved (column ``"21.phi.tx@ltt-error.12"``) is still
        ``"21.phi.tx"``."""
        return tuple(parameter_name(n) for n in self.names)

    def ttl_coefficients(self) -> np.ndarray:
        """The 24 linear coefficients (NaN for those not in the model)."""
        return self._ttl(self.theta)

    def ttl_sigma(self) -> np.ndarray:
        return self._ttl(self.sigma)

    def _ttl(self, values) -> np.ndarray:
        out = np.full(len(COEFFICIENT_NAMES), np.nan)
        names = self.parameter_names
        for k, n in enumerate(COEFFICIENT_NAMES):
            if n in names:
                out[k] = values[names.index(n)]
        return out


def total_offset(column: str, value: float, expansion: dict) -> float:
    """The parameter of a shifted-witness effect's ``<effect>.<group>.d1`` column is the
    offset beyond its expansion point (:meth:`Diagnoser.expansion_points`): the offset is
    their sum.  Other columns: ``value``."""
    return float(value) + (float(expansion.get(column[:-3], 0.0)) if column.endswith(".d1") else 0.0)


def parameter_name(column: str) -> str:
    """The parameter a column's coefficient is: the column name up to ``@`` (shifted
    witnesses of :meth:`Diagnoser._shifted_columns` carry ``@effect.group``)."""
    return column.split("@", 1)[0]


# ---------------------------------------------------------------------------
# The engine
# ---------------------------------------------------------------------------

class Diagnoser:
    """Whitened spectra of the data and of every column of every effect, under one fixed
    noise model; fits models and evaluates candidates on them.

    Build it from telemetry (:meth:`from_telemetry`: every effect available) or from TDI
    outputs alone (:meth:`from_tdi`: the linear TTL and the effects derivable from its TDI
    regressors, ``drift`` and ``step``, by modulating them in time - exact up to the
    ~70 s span of the TDI delays).
    """

    def __init__(self, td: TDIData, settings: DiagnoseSettings | None = None, tm=None, effect_modules=(),
                 dws_asd: float | None = None):
        s = self.settings = settings or DiagnoseSettings()
        self.tm = tm
        self._have_derivatives = False
        self._expansion: dict = {}
        self.effect_modules = tuple(effect_modules)
        self.registry = available_effects(self.effect_modules)
        self.dws_asd = float(dws_asd if dws_asd is not None else (s.dws_asd if s.dws_asd is not None else DWS_ASD))
        self.ltt_mean = np.asarray(td.ltt_mean, dtype=float)
        tda = td.to_aet()
        self._td_in = tda
        factor = max(1, int(round(tda.fs / 2.0)))
        self.decimation = factor
        self.fs_in = tda.fs
        self.t0_in = tda.t0
        self.n_in = tda.size
        dec = tda.decimated(factor) if factor > 1 else tda
        self.fs = dec.fs
        self.t0 = dec.t0
        n = dec.size
        ok = np.isfinite(dec.data).all(axis=0) & np.isfinite(dec.regressors).all(axis=(0, 1))
        idx = np.flatnonzero(ok)
        if idx.size < 2:
            raise ConfigError("no valid TDI samples (data too short for the TDI delays)")
        margin = int(round(120 * self.fs))  # room for the extra delays and derivative stencils of effects
        lo, hi = idx[0] + margin, idx[-1] + 1 - margin
        self.mask = np.zeros(n, dtype=bool)
        self.mask[lo:hi] = True
        self.mask &= ok
        span = (hi - lo) / self.fs
        seg = s.segment_duration or min(21600.0, np.floor(span / 4))
        if seg * self.fs < 256:
            raise ConfigError(f"data too short for a diagnosis ({span:.0f} s of valid TDI)")
        self.L = int(round(seg * self.fs))
        self.starts = list(range(lo, hi - self.L + 1, self.L))
        if not self.starts:
            raise ConfigError(f"no FFT segment of {seg:g} s fits in {span:.0f} s of valid TDI")
        self.seg_t0 = np.array([self.t0 + s0 / self.fs for s0 in self.starts])
        self.seg_duration = self.L / self.fs
        self.win = window(s.window, self.L)
        f = np.fft.rfftfreq(self.L, 1 / self.fs)
        sel = (f >= s.band[0]) & (f <= s.band[1])
        keep = np.zeros_like(sel)
        keep[sel] = notch_mask(f[sel], self.ltt_mean)
        self.bins = np.flatnonzero(keep)
        self.f = f[self.bins]
        self.edges = merged_band_edges(self.f, default_band_edges(s.band, s.n_bands), 6 * len(self.starts), s.min_band_dof)
        self.G = len(self.edges) - 1
        self.band_index = np.clip(np.searchsorted(self.edges, self.f, side="right") - 1, 0, self.G - 1)
        self.slices = _band_slices(self.band_index, self.G)
        self._x_cache: dict = {}
        self.kappa = variance_factor(s.window, 4096, 0.0)
        self.data_series = dec.data
        self.series: dict[str, np.ndarray] = {}
        d = self._spectra(dec.data[:, None, :])[..., 0]
        R = self._spectra(dec.regressors)
        for k, name in enumerate(dec.names):
            self.series[name] = dec.regressors[:, k]
        # noise model: secondary noises + DWS noise through a first estimate of the coefficients
        # (the standard GLS fit of the TTL columns, used for nothing else)
        ttl_names = [n for n in dec.names if n in COEFFICIENT_NAMES]
        C0 = None
        if len(ttl_names) == len(COEFFICIENT_NAMES):
            sp = [SegmentSpectra(t, self.seg_duration, self.f, d[i], R[i]) for i, t in enumerate(self.seg_t0)]
            res, _ = fit_spectra(sp, self.ltt_mean, FitSettings(band=s.band, notch=False, dws_asd=self.dws_asd,
                                                                 robust_covariance=False, n_bands=s.n_bands),
                                 names=tuple(dec.names))
            C0 = res.coefficients[[dec.names.index(n) for n in COEFFICIENT_NAMES]]
        self.noise_csd = instrument_noise_csd(self.f, self.ltt_mean, C0, self.dws_asd)
        #: fitted secondary-noise levels (:func:`ttlcore.diagnose.noise_model.profile_noise_model`); None: fixed
        self.noise_parameters = None
        W = np.linalg.inv(self.noise_csd)
        self.Lh = np.conj(np.swapaxes(np.linalg.cholesky(W), -1, -2))
        self.wd = np.matmul(self.Lh, d[..., None])[..., 0]  # (S, m, 3)
        self.wcols: dict[str, np.ndarray] = {}
        self.col_info: dict[str, tuple] = {}
        self._add_columns(list(dec.names), np.matmul(self.Lh, R), [(1.0, "m/rad", 2.3e-3)] * len(dec.names))
        # errors-in-variables: the DWS channel and placement of every plain-witness column

        self._eiv_cache: dict = {}
        self.eiv_parts: dict = {}
        #: column -> slowly varying factor (decimated samples) multiplying its witnesses, and
        #: so their readout noise (drift, step); absent: 1
        self.eiv_modulation: dict = {}
        # each segment's normalised squared taper: the weight of a modulation product
        w2 = np.stack([(self.win * self.mask[s0:s0 + self.L]) ** 2 for s0 in self.starts])
        self._w2 = w2 / w2.sum(axis=1, keepdims=True)  # (S, L)
        for n in ttl_names:
            link, extra, mosa, angle = placement(n)
            self.eiv_parts[n] = [((mosa, angle), link, tuple(extra))]
        self.ttl_names = ttl_names
        self._gram_cache: dict = {}
        #: column name -> the cache key of the effect that registered it last
        self._owner: dict = {}
        self.dd = np.zeros((len(self.starts), self.G))
        for g in range(self.G):
            self.dd[:, g] = np.sum(np.abs(self.wd[:, self.band_index == g]) ** 2, axis=(1, 2))

    # --- construction ------------------------------------------------------------------

    @classmethod
    def from_telemetry(cls, tm, settings: DiagnoseSettings | None = None, effect_modules=()) -> "Diagnoser":
        """From a :class:`~ttlcore.io.telemetry.Telemetry` (ours or lisainstrument's)."""
        s = settings or DiagnoseSettings()

        # TDI in 3-h blocks (tdi_in_blocks): the interpolation taps of a day would hold ~4 GB
        data, regs = tdi_in_blocks(tm.ltt, tm.fs, LinearTTL().columns(effect_input_from_telemetry(tm)), tm.eta,
                                   order=s.order, delay_order=s.delay_order)
        td = TDIData(t0=float(tm.t0), fs=float(tm.fs), channels=tuple(c.name for c in MICHELSON), data=data,
                     regressors=regs, names=COEFFICIENT_NAMES, ltt_mean=np.nanmean(np.asarray(tm.ltt), axis=-1))
        dws = s.dws_asd if s.dws_asd is not None else dws_asd_from_config(tm.config)
        return cls(td, s, tm=tm, effect_modules=effect_modules, dws_asd=dws)

    @classmethod
    def from_tdi(cls, td: TDIData, settings: DiagnoseSettings | None = None, dws_asd: float | None = None,
                 effect_modules=()) -> "Diagnoser":
        """From TDI outputs only (no telemetry: effects needing DWS series are unavailable)."""
        return cls(td, settings, tm=None, effect_modules=effect_modules, dws_asd=dws_asd)

    # --- spectra -----------------------------------------------------------------------

    def _spectra(self, x: np.ndarray) -> np.ndarray:
        """(3, k, n_dec) decimated series -> band spectra (S, m, 3, k), masked like the data."""
        out = np.empty((len(self.starts), self.f.size, x.shape[0], x.shape[1]), dtype=complex)
        for i, s0 in enumerate(self.starts):
            seg = x[:, :, s0:s0 + self.L]
            m = self.mask[s0:s0 + self.L]
            seg = np.where(m, np.nan_to_num(seg), 0.0)
            bad = ~np.isfinite(x[:, :, s0:s0 + self.L]) & m
            if bad.any():
                raise ConfigError("a regressor column is not finite inside the analysed span")
            _, X = segment_fft(seg, self.fs, self.win * m)
            out[i] = np.moveaxis(X[:, :, self.bins], 2, 0)
        return out

    def _add_columns(self, names, wR, info):
        for k, n in enumerate(names):
            self.wcols[n] = np.ascontiguousarray(wR[..., k])
            self.col_info[n] = info[k]
        self._x_cache.clear()

    def _decimate(self, xyz: np.ndarray, is_aet: bool = False) -> np.ndarray:
        """XYZ TDI of columns (3, k, n_in) -> decimated A, E, T (3, k, n_dec), the data's filter."""
        a = xyz if is_aet else aet(xyz)
        td = TDIData(t0=self.t0_in, fs=self.fs_in, channels=("A", "E", "T"), data=np.zeros((3, a.shape[-1])),
                     regressors=a, names=tuple(f"c{k}" for k in range(a.shape[1])), ltt_mean=self.ltt_mean)
        dec = td.decimated(self.decimation) if self.decimation > 1 else td
        return dec.regressors

    def _derivatives(self):
        """Whitened spectra and decimated series of the first and second time derivatives of
        the TTL regressors' TDI (columns ``d1:<name>``, ``d2:<name>``), computed once."""
        if self._have_derivatives:
            return

        td = self._td_in
        for order in (1, 2):
            series = np.concatenate([self._decimate(derivative(td.regressors[:, j0:j0 + 8], td.fs, order), is_aet=True)
                                     for j0 in range(0, len(td.names), 8)], axis=1)
            names = [f"d{order}:{n}" for n in td.names]
            self._add_columns(names, np.matmul(self.Lh, self._spectra(series)), [(1.0, "", 1.0)] * len(names))
            for k, n in enumerate(names):
                self.series[n] = series[:, k]
        self._have_derivatives = True

    def effect_columns(self, effect: Effect, coefficients=None, keep_series: bool = False,
                       exact: bool = True) -> list[str]:
        """Compute (once) and register the columns of ``effect``; returns their names.

        ``exact=False`` (candidate ranking) builds ``drift`` and ``step`` columns by modulating
        the TDI regressors in time (``TDI(m w) = m TDI(w)`` but for the ~70 s the TDI delays
        span, a relative error ~1e-3 on a drift column), saving a TDI per column.
        Linearised effects (``timing-offset``, ``ltt-error``) always use the time derivatives
        of the TDI regressors (:meth:`ttlcore.diagnose.effects._Linearised.tdi_terms`)."""
        if hasattr(effect, "tdi_terms") and all(n in self.series for n in self.ttl_names) and len(self.ttl_names) == 24:
            if coefficients is None:
                raise ConfigError(f"effect {effect.name!r} needs the linear coefficients")
            key = (effect.name, repr(sorted(effect.options.items())), tuple(np.round(coefficients, 15)))
            if key in self._gram_cache:
                return self._gram_cache[key]
            self._derivatives()
            names, info = [], []
            for cname, unit, prior, terms in effect.tdi_terms(coefficients):
                w = sum(f * self.wcols[f"d{o}:{n}"] for n, o, f in terms)
                self.wcols[cname] = np.ascontiguousarray(w)
                self.series[cname] = sum(f * self.series[f"d{o}:{n}"] for n, o, f in terms)
                self.col_info[cname] = (1.0, unit, prior)
                names.append(cname)
            self._x_cache.clear()
            self._gram_cache[key] = names
            return names
        if not exact and effect.name in ("drift", "step") and all(
                f"{m}.{a}.{sd}" in self.series for m in effect.mosas for a in effect.angles for sd in effect.sides):
            key = ("approx", effect.name, repr(sorted(effect.options.items())))
            if key not in self._gram_cache:
                names, series, info = self._columns_from_tdi(effect)
                self._add_columns(names, np.matmul(self.Lh, self._spectra(series)), info)
                self._gram_cache[key] = names
                self._gram_cache.pop(("exact", effect.name, repr(sorted(effect.options.items())), None), None)
            return self._gram_cache[key]
        return self._exact_columns(effect, coefficients, keep_series)

    def _exact_columns(self, effect, coefficients, keep_series) -> list[str]:
        if isinstance(effect, Step) and effect.options.get("t_step") is None:
            raise ConfigError("effect 'step' needs t_step in a model (ttl diagnose reports the searched time)")
        if effect.name == "linear-ttl":
            names = [c.name for c in effect.columns(names_only_input())]
            missing = [n for n in names if n not in self.wcols]
            if missing:
                raise ConfigError(f"linear-ttl columns {missing[:3]} missing from the TDI data")
            return names
        key = ("exact", effect.name, repr(sorted(effect.options.items())), None if coefficients is None else tuple(np.round(coefficients, 12)))
        if key in self._gram_cache and any(self._owner.get(n) != key for n in self._gram_cache[key]):
            self._gram_cache.pop(key)  # another option set re-registered these names since
        if key in self._gram_cache:
            names = self._gram_cache[key]
            if keep_series:
                missing = [n for n in names if n not in self.series]
                if missing:
                    self._gram_cache.pop(key)
                    return self._exact_columns(effect, coefficients, keep_series)
            return names
        self._gram_cache.pop(("approx", effect.name, repr(sorted(effect.options.items()))), None)
        if self.tm is None:
            names, series, info = self._columns_from_tdi(effect)
        else:
            data = effect_input_from_telemetry(self.tm, coefficients)
            cols = effect.columns(data)
            if not cols:
                raise ConfigError(f"effect {effect.name!r} produced no column (check its options)")
            if any(c.response is not None for c in cols):
                names = self._filtered_columns(cols)
                self._gram_cache[key] = names
                self._owner.update(dict.fromkeys(names, key))
                return names
            names = [c.name for c in cols]
            info = [(1.0, c.unit, c.prior_scale) for c in cols]
            for c in cols:
                self._register_eiv(c)
            chunks = []
            for j0 in range(0, len(cols), 8):  # bounded memory (a day: ~70 MB per column in flight)
                _, xyz = tdi_in_blocks(self.tm.ltt, self.tm.fs, cols[j0:j0 + 8], order=self.settings.order,
                                       delay_order=self.settings.delay_order)
                chunks.append(self._decimate(xyz))
            series = np.concatenate(chunks, axis=1)
        self._add_columns(names, np.matmul(self.Lh, self._spectra(series)), info)
        if keep_series:
            for k, n in enumerate(names):
                self.series[n] = series[:, k]
        self._gram_cache[key] = names
        self._owner.update(dict.fromkeys(names, key))
        return names

    def base_column(self, column) -> str:
        """Register (once) the unfiltered column of a filtered one: its parts through the
        exact TDI, whitened spectra under ``base:<key>`` (transformed with the noise model
        like every column); returns that name.  The key is the parts' placement and source,
        so that witness and frequency-dependent candidates on one placement share it."""
        key = "base:" + (column.base or column.name.split(".", 1)[-1])
        key += "|" + ";".join(f"{p.link}/{int(p.delayed)}/{p.channel}" for p in column.parts)
        if key not in self.wcols:
            plain = Column(key, column.parts, column.unit, column.prior_scale)
            _, xyz = tdi_in_blocks(self.tm.ltt, self.tm.fs, [plain], order=self.settings.order,
                                   delay_order=self.settings.delay_order)
            series = self._decimate(xyz)
            self._add_columns([key], np.matmul(self.Lh, self._spectra(series)), [(1.0, column.unit, column.prior_scale)])
            self.series[key] = series[:, 0]
            self._register_eiv(plain)
        return key

    def filtered_spectra(self, base: str, responses) -> tuple[np.ndarray, np.ndarray]:
        """Whitened spectra (S, m, 3, k) and decimated series (3, k, n) of the registered
        column ``base`` through the filters ``responses`` (callables ``f -> complex``),
        filtered in the time domain before the segments are windowed
        (:func:`ttlcore.diagnose.effects.filtered`): multiplying the windowed segment's spectrum
        instead misses the filter's ringing across the taper, a few tens of per cent of a
        strong resonance's excess at the segment ends.  Pure: nothing is registered."""
        x = self.series[base]
        ok = np.isfinite(x)
        series = np.stack([np.where(ok, filtered(x, self.fs, r), np.nan) for r in responses], axis=1)
        return np.matmul(self.Lh, self._spectra(series)), series

    def _filtered_columns(self, cols) -> list[str]:
        """Columns carrying a frequency response: the base column (its parts through the
        exact TDI, once) filtered in time (:meth:`filtered_spectra`); the readout noise
        response is the base column's times the response (errors-in-variables term)."""
        names = []
        for c in cols:
            base = self.base_column(c)
            resp = np.ones(self.f.size, dtype=complex) if c.response is None else np.asarray(c.response(self.f), dtype=complex)
            w, series = self.filtered_spectra(base, [c.response or (lambda f: np.ones(np.shape(f)))])
            self.wcols[c.name] = np.ascontiguousarray(w[..., 0])
            self.series[c.name] = series[:, 0]
            self.col_info[c.name] = (1.0, c.unit, c.prior_scale)
            self.eiv_parts.pop(c.name, None)
            self.eiv_modulation.pop(c.name, None)
            if base in self.eiv_parts:
                self.eiv_parts[c.name] = [(ch, link, extra, resp) for ch, link, extra, *_ in self.eiv_parts[base]]
            if base in self.eiv_modulation:
                self.eiv_modulation[c.name] = self.eiv_modulation[base]
            names.append(c.name)
        self._x_cache.clear()
        return names

    def _register_eiv(self, column) -> None:
        """Errors-in-variables parts of an effect's column: plain (or slowly modulated) DWS
        witnesses carry their channel's readout noise; other columns none."""
        self.eiv_parts.pop(column.name, None)
        self.eiv_modulation.pop(column.name, None)
        parts = column.parts
        if not parts or any(p.channel is None for p in parts):
            return
        mods = [p.modulation for p in parts]
        if any(m is not None for m in mods):
            if any(m is None or not np.array_equal(m, mods[0]) for m in mods):
                return  # parts modulated differently: not modelled
            t_tm = float(self.tm.t0) + np.arange(len(mods[0])) / float(self.tm.fs)
            t_dec = self.t0 + np.arange(self.mask.size) / self.fs
            self.eiv_modulation[column.name] = np.interp(t_dec, t_tm, np.asarray(mods[0], dtype=float))
        self.eiv_parts[column.name] = [(p.channel, p.link, p.extra) for p in parts]

    def _columns_from_tdi(self, effect: Effect):
        """Drift and step columns as time-modulated TDI regressors (no telemetry)."""
        if effect.name not in ("drift", "step"):
            raise ConfigError(f"effect {effect.name!r} needs the telemetry (DWS series); these segments carry TDI only")
        t = self.t0 + np.arange(self.data_series.shape[-1]) / self.fs
        if effect.name == "drift":
            t_ref = effect.options.get("t_ref")
            t_ref = 0.5 * (t[self.mask][0] + t[self.mask][-1]) if t_ref is None else float(t_ref)
            mod, prefix, unit = (t - t_ref) / 86400.0, "drift", "m/rad/day"
        else:

            mod, prefix, unit = (t >= parse_duration(effect.options["t_step"])).astype(float), "step", "m/rad"
        names, cols = [], []
        for m in effect.mosas:
            for a in effect.angles:
                for sd in effect.sides:
                    base = f"{m}.{a}.{sd}"
                    names.append(f"{prefix}.{base}")
                    cols.append(self.series[base] * mod)
                    if base in self.eiv_parts:
                        self.eiv_parts[names[-1]] = list(self.eiv_parts[base])
                        self.eiv_modulation[names[-1]] = mod
        series = np.stack(cols, axis=1)
        return names, series, [(1.0, unit, 1e-3)] * len(names)

    # --- normal equations ------------------------------------------------------------------

    def _w(self, names) -> np.ndarray:
        return np.stack([self.wcols[n] for n in names], axis=-1)

    def _x(self, names) -> np.ndarray:
        """Real layout (p, S, m, 6) of the columns, cached for the last few name lists."""
        key = tuple(names)
        if key not in self._x_cache:
            if len(self._x_cache) > 1:  # bounded memory: a day's stack is ~100 MB per 30 columns
                self._x_cache.pop(next(iter(self._x_cache)))
            self._x_cache[key] = np.stack([self.wcols[n] for n in names]).view(np.float64)
        return self._x_cache[key]

    def gram(self, A, B) -> np.ndarray:
        return _gram_x(self._x(A), self._x(B), self.slices)

    def rhs(self, names) -> np.ndarray:
        """``b`` per segment and band, (S, G, p)."""
        return _gram_x(self._x(names), self.wd[None].view(np.float64), self.slices)[..., 0]

    def eiv(self, names) -> np.ndarray:
        """Errors-in-variables term (G, p, p) of the columns, summed over segments:
        ``E_kl = W_kl sum_ch Re sum_f U_k,ch^H U_l,ch`` (:meth:`eiv_products`, one segment)
        with ``W_kl`` the segments' taper-weighted means of the product of the columns'
        modulations (:meth:`eiv_weights`; the number of segments for unmodulated columns)."""
        return self.eiv_products(names) * self.eiv_weights(names)[None]

    def eiv_products(self, names) -> np.ndarray:
        """One segment's errors-in-variables products (G, p, p): ``Re sum_f U_k,ch^H U_l,ch``
        summed over the DWS channels ``ch``, ``U_k,ch`` the whitened response of column ``k``
        to the readout noise of channel ``ch``.  Columns whose parts are plain (or slowly
        modulated) DWS witnesses carry it: the TTL regressors, cross-coupling, drift and
        step, the TTL witnesses a shifted-witness effect moved by ``s`` seconds (response
        times ``exp(2 pi i f s)``); others, built from products of the readouts, carry none -
        their bias is second order in the small readout noise."""
        p = len(names)
        E = np.zeros((self.G, p, p))
        by_channel: dict = {}
        for i, n in enumerate(names):
            for ch, link, extra, *shift in self.eiv_parts.get(n, ()):
                by_channel.setdefault(ch, {}).setdefault(i, []).append((link, extra, shift[0] if shift else 0.0))
        for ch, cols in by_channel.items():
            idx = sorted(cols)
            U = np.stack([sum(self._eiv_response(link, extra) * readout_noise_factor(self.f, shift)
                              for link, extra, shift in cols[i]) for i in idx], axis=-1)
            for g, (a, b) in enumerate(self.slices):
                if b > a:
                    Ug = U[a:b].reshape(-1, len(idx))
                    E[g][np.ix_(idx, idx)] += np.real(Ug.conj().T @ Ug)
        return E

    def eiv_weights(self, names) -> np.ndarray:
        """``W_kl = sum_s <m_k m_l>_s`` (p, p): per segment the mean of the product of the
        columns' modulations weighted by the squared taper (the readout noise is white on the
        modulations' time scale), ``m = 1`` for unmodulated columns."""
        mods = [self.eiv_modulation.get(n) for n in names]
        W = np.full((len(names), len(names)), float(len(self.starts)))
        idx = [i for i, m in enumerate(mods) if m is not None]
        if idx:
            A = np.stack([np.stack([mods[i][s0:s0 + self.L] for s0 in self.starts]) for i in idx])  # (q, S, L)
            cross = np.einsum("qsl,sl->q", A, self._w2)  # against m = 1
            W[idx, :] = cross[:, None]
            W[:, idx] = cross[None, :]
            W[np.ix_(idx, idx)] = np.einsum("qsl,rsl,sl->qr", A, A, self._w2)
        return W

    def _eiv_response(self, link, extra) -> np.ndarray:
        """Whitened A, E, T response (m, 3) to the DWS readout noise of a witness ``-DWS/c``
        placed on ``link`` after ``extra`` delays, times the noise's ASD (velocity)."""
        key = (link, tuple(extra))
        if key not in self._eiv_cache:

            h = np.stack([link_responses(c, self.f, self.ltt_mean, tuple(extra))[LINKS.index(link)] for c in MICHELSON])
            T = (AET_MATRIX @ h).T * (-1.0 / SPEED_OF_LIGHT)  # (m, 3)
            self._eiv_cache[key] = np.matmul(self.Lh, T[..., None])[..., 0] * (2 * np.pi * self.f * self.dws_asd)[:, None]
        return self._eiv_cache[key]

    def fit(self, effects, coefficients_for_linearised=None, keep_series: bool = True, time_table: bool = True) -> ModelFit:
        """Fit a model (list of effects or specs) under the fixed noise model.

        A model whose coefficients change in time (drift, step) changes the readout noise the
        subtraction lets through: the DWS term of the noise model is then re-evaluated with
        the model's own coefficient history (time average of ``|sum C_k(t) T_k|^2``) and the
        model refitted once; the new noise model stays for what follows."""
        effects = make_effects(effects, self.effect_modules) if not all(isinstance(e, Effect) for e in effects) else list(effects)
        effects, searches = self.resolve(effects, coefficients_for_linearised)
        fit = self._fit(effects, coefficients_for_linearised, keep_series)
        fit.searches = searches
        hist = self.coefficient_history(fit)
        if hist is not None and self.dws_asd > 0:
            nm = self.noise_parameters
            self.set_noise_model(instrument_noise_csd(self.f, self.ltt_mean, hist, self.dws_asd,
                                                      secondary=None if nm is None else nm.csd(self.f)))
            fit = self._fit(effects, coefficients_for_linearised, keep_series)
        fit.searches = searches
        if time_table and all(n in self.series for n in fit.names):
            fit.time_table = self.time_adequacy(list(fit.names), fit.theta)
        return fit

    def resolve(self, effects, coefficients_for_linearised=None) -> tuple[list, dict]:
        """Effects with unset searched parameters (:attr:`ttlcore.diagnose.effects.Effect.searched`)
        replaced by the same effect at the estimates of :func:`ttlcore.diagnose.search.profile_search`,
        profiled against the model of the other effects; returns the effects and the
        searches (``cli spec -> result``)."""

        out, searches = list(effects), {}
        for i, e in enumerate(effects):
            if not e.unresolved():
                continue
            rest = [x for x in out if x is not e and not x.unresolved()]
            base = self._fit(rest, coefficients_for_linearised, False)
            res = profile_search(self, base, e, base.ttl_coefficients())
            out[i] = res.effect
            searches[res.effect.cli_spec()] = res.to_json()
        return out, searches

    def _fit(self, effects, coefficients_for_linearised, keep_series) -> ModelFit:
        names = self._model_names(effects, coefficients_for_linearised, keep_series)
        N = self.gram(names, names)  # (S, G, P, P)
        b = self.rhs(names)
        dd = self.dd
        E = self.eiv(names)
        Ntot = N.sum(axis=(0, 1)) - E.sum(axis=0)
        btot = b.sum(axis=(0, 1))
        theta = np.linalg.solve(Ntot, btot)
        cov = self.kappa * np.linalg.inv(2 * Ntot)
        cov = 0.5 * (cov + cov.T)
        chi2_sg = 2 * (np.einsum("p,sgpq,q->sg", theta, N, theta) - 2 * b @ theta + dd)
        wr = self.wd - self._w(names) @ theta
        n_noise = 0 if self.noise_parameters is None else self.noise_parameters.n_parameters
        bands = band_table(wr, self.band_index, self.edges, len(names) + n_noise, self.kappa, self.settings.tolerance,
                           self.settings.alpha)
        q_min = float(dd.sum() - btot @ theta)
        fit = ModelFit(effects, tuple(names), theta, cov, chi2_sg, bands.dof, bands, q_min, residual_w=wr)
        fit.normal = (N, b)
        fit.eiv_term = E
        fit.dd = dd
        return fit

    def coefficient_history(self, model: ModelFit, n_t: int = 97) -> np.ndarray | None:
        """The model's linear coefficients on a time grid over the data, (24, n_t), when it
        holds drift or step columns (None otherwise)."""
        vals = dict(zip(model.names, model.theta))
        if not any(n.startswith(("drift.", "step.")) for n in vals):
            return None
        idx = np.flatnonzero(self.mask)
        t = self.t0 + np.linspace(idx[0], idx[-1], n_t) / self.fs
        t_ref = 0.5 * (t[0] + t[-1])
        C = np.tile(model.ttl_coefficients()[:, None], (1, n_t))
        steps = {e.name: e for e in model.effects}
        for k, name in enumerate(COEFFICIENT_NAMES):
            if f"drift.{name}" in vals:
                ref = steps["drift"].options.get("t_ref") if "drift" in steps else None
                C[k] += vals[f"drift.{name}"] * (t - (t_ref if ref is None else float(ref))) / 86400.0
            if f"step.{name}" in vals and "step" in steps:

                C[k] += vals[f"step.{name}"] * (t >= parse_duration(steps["step"].options["t_step"]))
        return C

    def set_noise_model(self, csd: np.ndarray) -> None:
        """Replace the noise model: every whitened spectrum is transformed by
        ``L_new^H (L_old^H)^-1`` per bin (no spectra recomputed)."""
        Lh = np.conj(np.swapaxes(np.linalg.cholesky(np.linalg.inv(csd)), -1, -2))
        M = Lh @ np.linalg.inv(self.Lh)
        self.wd = np.einsum("mij,smj->smi", M, self.wd)
        for n in list(self.wcols):
            self.wcols[n] = np.ascontiguousarray(np.einsum("mij,smj->smi", M, self.wcols[n]))
        self.Lh, self.noise_csd = Lh, csd
        self._x_cache.clear()
        self._eiv_cache.clear()
        for g, (a, b) in enumerate(self.slices):
            self.dd[:, g] = np.sum(np.abs(self.wd[:, a:b]) ** 2, axis=(1, 2))

    def _model_names(self, effects, coefficients, keep_series) -> list[str]:
        names: list[str] = []
        plain = [e for e in effects if not e.needs_coefficients]
        for e in plain:
            names += [n for n in self.effect_columns(e, keep_series=keep_series) if n not in names]
        lin = [e for e in effects if e.needs_coefficients]
        if lin:
            C = coefficients
            if C is None:
                part = self.fit(plain, keep_series=False, time_table=False)
                C = part.ttl_coefficients()
                if np.isnan(C).any():
                    raise ConfigError("linearised effects (timing-offset, ltt-error) need all 24 linear-ttl coefficients in the model")
            first = list(names)
            self._expansion = {}
            for e in lin:
                names += [n for n in self.effect_columns(e, C, keep_series=keep_series) if n not in names]
            if self.settings.expansion_passes and all(n in self.series for n in self.ttl_names):
                names = self._reexpand(first, lin, names)
        return names

    def _reexpand(self, first, lin, names) -> list[str]:
        """The exact model of the linearised effects where their offsets are large.

        Each group's offset is found by :meth:`shift_search` (no Taylor expansion, so offsets
        with 2 pi f delta >> 1 at the top of the band are found).  Where it is clearly
        measured (delta chi^2 > 25) and large enough for the Taylor error to matter
        (2 pi f delta > 0.05 at the band's top), the model holds the group's TTL columns
        with their witnesses shifted by ``s delta_0`` (exact, the linear coefficients
        fitted as before) and a ``d1`` column, the derivative there: its fitted coefficient
        is the remaining offset ``delta - delta_0``, moved into ``delta_0`` by Gauss-Newton
        passes until it is below a hundredth of its sigma.  Other groups keep the Taylor
        columns ``d1``, ``d2`` at zero."""
        small = 0.05 / (2 * np.pi * self.settings.band[1])
        shifts, C, moved_names = {}, None, set()
        for e in lin:
            found, gain, theta = self.shift_search(e, first)
            if C is None:
                C = self._ttl_vector(theta)
            shifts[e.name] = {}
            for g, members in e.shifted_members().items():
                big = g in found and gain[g] > 25.0 and abs(found[g]) > small and not moved_names & set(members)
                if big:
                    moved_names |= set(members)
                    shifts[e.name][g] = found[g]
        if not moved_names:
            return names  # the Taylor columns at zero are the model
        for _ in range(max(1, self.settings.expansion_passes)):
            model = list(first)
            for e in lin:
                repl, cols = self._shifted_columns(e, C, shifts[e.name])
                model = [repl.get(n, n) for n in model] + cols
            fit, sig = self._solve_only(model)
            C = self._ttl_vector(fit)
            step = {(e.name, g): fit[f"{e.name}.{g}.d1"] for e in lin for g in shifts[e.name]}
            if all(abs(v) < 0.01 * sig[f"{e}.{g}.d1"] for (e, g), v in step.items()):
                break
            for (e, g), v in step.items():
                shifts[e][g] += v
        return model

    @staticmethod
    def _ttl_vector(values: dict) -> np.ndarray:
        """The 24 linear coefficients from a dict column -> value (shifted columns resolved)."""
        by = {parameter_name(n): v for n, v in values.items()}
        return np.array([by[n] for n in COEFFICIENT_NAMES])

    def shift_search(self, effect, names, span: float | None = None, passes: int = 4) -> tuple[dict, dict, dict]:
        """Profile-likelihood search of the offsets of a shifted-witness effect.

        The exact model of ``timing-offset`` and ``ltt-error`` replaces the witnesses of the
        coefficients of group ``g`` (:meth:`~ttlcore.diagnose.effects._Linearised.shifted_members`) by
        the same witnesses shifted by ``s delta_g`` (``s`` =
        :attr:`~ttlcore.diagnose.effects._Linearised.d1_sign`).  A shift is the phase
        ``exp(2 pi i f s delta_g)`` of the whitened spectra (TDI commutes with it up to the
        arms' rate of change, ~1e-8; the segment taper changes by ``delta / T`` ~ 1e-4), so
        the chi^2 profiled over the linear parameters ``theta`` of ``names``,

            Q(delta) = dd - b(delta)^T [N(delta) - E]^-1 b(delta),     chi2 = 2 Q,

        is cheap to evaluate for many offsets.  Each group's offset is scanned on a grid of
        spacing ``1 / (8 f_max)`` over ``[-span, span]`` with the other groups held, the best
        point refined by bounded Brent minimisation; groups are visited in turn (coordinate
        descent) until no offset moves by more than 1 ms, at most ``passes`` rounds.

        Parameters
        ----------
        effect : ttlcore.diagnose.effects._Linearised
            ``timing-offset``, ``ltt-error`` or a plugin with the same interface.
        names : list of str
            Columns of the model without the effect; must hold the shifted coefficients'.
        span : float, optional
            Half-width [s] of the search (default ``settings.shift_span``).

        Returns
        -------
        shifts : dict
            Group -> offset [s] at the profile optimum.
        delta_chi2 : dict
            Group -> chi^2 gain (over ``kappa``) of its offset against zero, the others at
            their optimum.
        theta : dict
            Column name -> linear parameter at the optimum.
        """

        span = float(self.settings.shift_span if span is None else span)
        members = {g: [names.index(n) for n in mem] for g, mem in effect.shifted_members().items()
                   if all(n in names for n in mem)}
        P = len(names)
        X = self._w(names)  # (S, m, 3, P)
        S, m = X.shape[:2]
        X = np.ascontiguousarray(X.transpose(1, 0, 2, 3)).reshape(m, S * 3, P)
        d = np.ascontiguousarray(self.wd.transpose(1, 0, 2)).reshape(m, S * 3)
        w = 2 * np.pi * self.f * float(effect.d1_sign)  # phase [rad] per second of offset
        E = self.eiv(names).sum(axis=0)
        dd = float(self.dd.sum())
        delta = {g: 0.0 for g in members}
        step = 1.0 / (8.0 * self.f[-1])
        grid = np.arange(-span, span + 0.5 * step, step)

        def profile(g):
            """Q(delta_g) on an array of offsets, the other groups at ``delta``."""
            J = members[g]
            R = [i for i in range(P) if i not in J]
            col = np.zeros(P)
            for h, idx in members.items():
                if h != g:
                    col[idx] = delta[h]
            Xs = X * np.exp(1j * w[:, None] * col[None, :])[:, None, :]
            flat = Xs.reshape(-1, P)
            N = (flat.conj().T @ flat).real - E
            b = (flat.conj().T @ d.reshape(-1)).real
            XJ = Xs[:, :, J].conj()
            Q = np.concatenate([np.einsum("mkj,mkr->mjr", XJ, Xs[:, :, R]).reshape(m, -1),
                                np.einsum("mkj,mk->mj", XJ, d)], axis=1)  # (m, |J| (|R| + 1))

            def q(x):
                x = np.atleast_1d(np.asarray(x, dtype=float))
                A = (np.exp(-1j * np.outer(x, w)) @ Q).real  # (K, |J| (|R| + 1))
                NJR = A[:, :len(J) * len(R)].reshape(-1, len(J), len(R))
                Nk = np.broadcast_to(N, (x.size, P, P)).copy()
                bk = np.broadcast_to(b, (x.size, P)).copy()
                Nk[:, np.ix_(J, R)[0], np.ix_(J, R)[1]] = NJR
                Nk[:, np.ix_(R, J)[0], np.ix_(R, J)[1]] = np.swapaxes(NJR, 1, 2)
                bk[:, J] = A[:, len(J) * len(R):]
                th = np.linalg.solve(Nk, bk[..., None])[..., 0]
                return dd - np.einsum("kp,kp->k", bk, th), th

            return q

        gain, theta, moved = {}, None, np.inf
        for _ in range(passes):
            moved = 0.0
            for g in members:
                q = profile(g)
                Qg, _ = q(grid)
                x0 = float(grid[int(np.argmin(Qg))])
                res = minimize_scalar(lambda x: float(q(x)[0][0]), bounds=(x0 - step, x0 + step),
                                      method="bounded", options={"xatol": 1e-4})
                best = float(res.x) if res.fun <= Qg.min() else x0
                moved = max(moved, abs(best - delta[g]))
                delta[g] = best
                (q0, q1), th = q(np.array([0.0, best]))
                gain[g], theta = 2.0 * (q0 - q1) / self.kappa, th[1]
            if moved < 1e-3:  # the gains of this pass hold: no other offset moved since
                break
        if moved >= 1e-3:
            for g in members:
                (q0, q1), th = profile(g)(np.array([0.0, delta[g]]))
                gain[g], theta = 2.0 * (q0 - q1) / self.kappa, th[1]
        if theta is None:
            theta = np.linalg.solve(self.gram(names, names).sum(axis=(0, 1)) - E, self.rhs(names).sum(axis=(0, 1)))
        log.debug("shift search %s: %s", effect.name, {g: round(v, 4) for g, v in delta.items()})
        return delta, gain, dict(zip(names, theta))

    def _solve_only(self, names) -> tuple[dict, dict]:
        N = self.gram(names, names).sum(axis=(0, 1)) - self.eiv(names).sum(axis=0)
        b = self.rhs(names).sum(axis=(0, 1))
        theta = np.linalg.solve(N, b)
        sig = np.sqrt(np.abs(np.diag(np.linalg.inv(2 * N))) * self.kappa)
        return dict(zip(names, theta)), dict(zip(names, sig))

    def _shifted_columns(self, effect, C, shifts: dict) -> tuple[dict, list[str]]:
        """Columns of a linearised effect expanded at ``shifts[group]`` (see :meth:`_reexpand`).

        For each group with an offset ``delta_0``: its TTL columns with the witnesses shifted,
        ``R_k(t + s delta_0)``, named ``"<coefficient>@<effect>.<group>"``, and the column
        ``<effect>.<group>.d1 = s sum_k C_k R_k'(t + s delta_0)`` (parameter: the offset
        beyond ``delta_0`` [s]).  Groups without one: the Taylor columns ``d1``, ``d2`` at
        zero.  The shifted series are built from the 4-Hz TDI regressors (TDI commutes with
        the shift up to the arms' rate of change, ~1e-8).

        Returns
        -------
        replaced : dict
            TTL column name -> the name of its shifted column.
        names : list of str
            The effect's own columns.
        """

        td = self._td_in
        sgn = float(effect.d1_sign)
        replaced, names, series_list, info = {}, [], [], []
        for g, members in effect.shifted_members().items():
            d0 = float(shifts.get(g, 0.0))
            self._expansion[(effect.name, g)] = d0
            R = np.stack([td.regressors[:, td.names.index(k)] for k in members], axis=1)  # (3, k, n)
            if d0:
                R = timeshift(R, sgn * d0 * td.fs)
                for k, cname in enumerate(members):
                    new = f"{cname}@{effect.name}.{g}"
                    replaced[cname] = new
                    names.append(new)
                    series_list.append(R[:, k])
                    info.append(self.col_info[cname])
                    self.eiv_parts[new] = [(*part, sgn * d0) for part in self.eiv_parts.get(cname, ())]
            A = np.einsum("k,ckn->cn", [float(C[COEFFICIENT_NAMES.index(k)]) for k in members], R)
            cols = {"d1": sgn * derivative(A, td.fs, 1)}
            if not d0:
                cols["d2"] = 0.5 * derivative(A, td.fs, 2)
            for kind, x in cols.items():
                n = f"{effect.name}.{g}.{kind}"
                names.append(n)
                series_list.append(x)
                info.append((1.0, {"d1": "s", "d2": "s^2"}[kind], {"d1": 0.1, "d2": 0.01}[kind]))
                self.eiv_parts.pop(n, None)
        series = self._decimate(np.stack(series_list, axis=1), is_aet=True)
        self._add_columns(names, np.matmul(self.Lh, self._spectra(series)), info)
        for k, n in enumerate(names):
            self.series[n] = series[:, k]
        return replaced, [n for n in names if "@" not in n]

    def expansion_points(self) -> dict:
        """``"effect.group" -> delta_0`` of the last Gauss-Newton expansion (the fitted
        offset is ``delta_0`` plus the group's ``d1`` coefficient)."""
        return {f"{e}.{g}": v for (e, g), v in self._expansion.items()}

    # --- adequacy in time -----------------------------------------------------------------

    def time_adequacy(self, names, theta) -> dict:
        """chi^2 of the residual in Hann-windowed slices of ``settings.time_segment`` against
        the same noise model (interpolated to the slice's frequency grid)."""
        s = self.settings
        resid = self.data_series - np.einsum("p,cpn->cn", theta, np.stack([self.series[n] for n in names], axis=1))
        L = int(round(min(s.time_segment, self.seg_duration) * self.fs))
        idx = np.flatnonzero(self.mask)
        lo, hi = idx[0], idx[-1] + 1
        f = np.fft.rfftfreq(L, 1 / self.fs)
        sel = (f >= s.band[0]) & (f <= s.band[1])
        keep = np.zeros_like(sel)
        keep[sel] = notch_mask(f[sel], self.ltt_mean)
        fb = f[keep]
        csd = np.empty((fb.size, 3, 3), dtype=complex)
        for i in range(3):  # interpolate the model CSD (smooth) from the segment grid
            for j in range(3):
                csd[:, i, j] = np.interp(fb, self.f, self.noise_csd[:, i, j].real) + 1j * np.interp(fb, self.f, self.noise_csd[:, i, j].imag)
        Lh = np.conj(np.swapaxes(np.linalg.cholesky(np.linalg.inv(csd)), -1, -2))
        bidx = np.clip(np.searchsorted(self.edges, fb, side="right") - 1, 0, self.G - 1)
        win = window("hann", L)
        kappa = variance_factor("hann", 4096, 0.0)
        rows = []
        for s0 in range(lo, hi - L + 1, L):
            seg = resid[:, s0:s0 + L]
            _, X = segment_fft(np.nan_to_num(seg), self.fs, win)
            wr = np.matmul(Lh, X[:, keep].T[..., None])[..., 0][None]
            tab = band_table(wr, bidx, self.edges, 0, kappa, s.tolerance, s.alpha)
            chi2, dof = tab.chi2.sum(), tab.dof.sum()
            rows.append({"t_start": self.t0 + s0 / self.fs, "t_stop": self.t0 + (s0 + L) / self.fs,
                         "chi2": float(chi2), "dof": float(dof), "chi2_dof": float(chi2 / dof),
                         "p_value": float(p_value(chi2, dof, kappa, s.tolerance)),
                         "band_chi2_dof": [float(x) if np.isfinite(x) else None for x in tab.chi2_dof],
                         "band_fails": [bool(x) for x in tab.fails]})
        for r in rows:
            r["fails"] = bool(r["p_value"] < s.alpha) or any(r["band_fails"])
        t0 = self.t0_in
        summary = describe_time_failures([r["t_start"] for r in rows], [r["t_stop"] for r in rows],
                                         [r["fails"] for r in rows], t0)
        return {"segment_duration": L / self.fs, "window": "hann", "variance_factor": kappa, "segments": rows,
                "summary": summary}

    # --- candidates -----------------------------------------------------------------------

    def evaluate(self, model: ModelFit, cand_names: list[str], prior=None) -> dict:
        """Evidence for adding the registered columns ``cand_names`` to ``model``."""
        M = list(model.names)
        K = list(cand_names)
        N_MM, b_M = model.normal if model.normal is not None else (self.gram(M, M), self.rhs(M))
        N_MK = self.gram(M, K)
        N_KK = self.gram(K, K)
        b_K = self.rhs(K)
        return self._evidence(model, N_MM, N_MK, N_KK, b_M, b_K, K, prior, self.eiv(M + K))

    def change(self, base: ModelFit, model: ModelFit) -> dict | None:
        """Evidence for ``model`` against ``base``: :meth:`evaluate` (exact) when ``base``'s
        columns are among ``model``'s, :meth:`compare` (Laplace) when a shifted-witness
        effect moved TTL columns; None when ``model`` adds nothing."""
        added = [n for n in model.names if n not in base.names]
        if not added:
            return None
        if set(base.names) <= set(model.names):
            return self.evaluate(base, added)
        return self.compare(base, model)

    def compare(self, base: ModelFit, model: ModelFit, expansion: dict | None = None) -> dict:
        """Evidence of ``model`` against ``base`` when they are not nested (a shifted-witness
        effect moved some TTL columns; nested pairs: :meth:`evaluate`, exact).

        ``delta_chi2 = 2 (Q_base - Q_model) / kappa`` at the optima; the log Bayes factor by
        Laplace's method on ``log L = -Q / kappa``: with a flat prior on the parameters both
        models share (by :func:`parameter_name`) and the Gaussian prior ``N(0, prior_scale)``
        on each new one, evaluated at its estimate (offsets: expansion point plus ``d1``),

            log B = -(Q_model - Q_base) / kappa - 1/2 [log det H_model - log det H_base]
                    + sum_new [1/2 log 2 pi + log N(theta_k; 0, prior_k)],

        ``H = 2 (N - E) / kappa`` the Hessians.  For a nested pair whose new parameters lie
        well inside their prior this equals :func:`log_bayes_factor`.  ``expansion``: the
        expansion points of ``model`` (default: the last fit's)."""
        def logdet(fit):
            H = 2 * (fit.normal[0].sum(axis=(0, 1)) - fit.eiv_term.sum(axis=0)) / self.kappa
            sign, value = np.linalg.slogdet(H)
            return value if sign > 0 else float("nan")

        shared = set(base.parameter_names)
        lbf = -(model.q_min - base.q_min) / self.kappa - 0.5 * (logdet(model) - logdet(base))
        expansion = self.expansion_points() if expansion is None else expansion
        for n, v in zip(model.names, model.theta):
            if parameter_name(n) in shared:
                continue
            p = float(self.col_info[n][2])
            lbf += -np.log(p) - 0.5 * (total_offset(n, v, expansion) / p) ** 2
        return {"delta_chi2": float(2 * (base.q_min - model.q_min) / self.kappa), "log_bayes_factor": float(lbf)}

    def _evidence(self, model, N_MM, N_MK, N_KK, b_M, b_K, K, prior, E_full) -> dict:
        """Evidence for the columns ``K`` added to ``model`` from the per-segment, per-band
        normal equations and the errors-in-variables term ``E_full`` (G, P + k, P + k) of all
        the columns: the candidates' readout noise correlates with the model's where they
        share a DWS channel, and left out, that correlation would pass for a signal."""
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
            raise ConfigError(f"columns {K[:2]} are (nearly) collinear with the model's: no evidence")
        NM = Nt[:P, :P]
        thM = np.linalg.solve(NM, bt[:P])
        dchi2 = 2 * (bt @ th - bt[:P] @ thM) / self.kappa
        # Schur complement: precision of the new parameters with the model's marginalised
        Sch = Nt[P:, P:] - Nt[P:, :P] @ np.linalg.solve(NM, Nt[:P, P:])
        A = 2 * Sch / self.kappa
        beta = th[P:]
        prior = np.array([self.col_info[n][2] for n in K]) if prior is None else prior
        lbf = log_bayes_factor(A, beta, prior)
        # where: per band and per segment (chi2 with the plain N, as the adequacy)
        thM_full = np.r_[thM, np.zeros(k)]
        dd = model.dd if model.dd is not None else self.dd
        chi2_before = 2 * (np.einsum("p,sgpq,q->sg", thM_full, full, thM_full) - 2 * bb @ thM_full + dd)
        chi2_after = 2 * (np.einsum("p,sgpq,q->sg", th, full, th) - 2 * bb @ th + dd)
        try:
            var = np.diag(np.linalg.inv(A))
        except np.linalg.LinAlgError:
            var = np.full(k, np.nan)
        return {"delta_chi2": float(dchi2), "log_bayes_factor": lbf, "n_parameters": k, "beta": beta,
                "sigma": np.sqrt(np.abs(var)), "band_delta": (chi2_before - chi2_after).sum(axis=0) / self.kappa,
                "segment_delta": (chi2_before - chi2_after).sum(axis=1) / self.kappa, "names": K}

    def step_search(self, model: ModelFit, step: Step | None = None) -> dict:
        """Search the step time on a grid: step columns approximated as ``H(t - t_s)`` times the
        TDI of the TTL regressors (exact but for the ~70 s the TDI delays span), Bayes factor
        marginalised over the grid; returns the best time and the evidence there."""
        s = self.settings
        step = step or Step()
        base = [f"{m}.{a}.{sd}" for m in step.mosas for a in step.angles for sd in step.sides]
        M = list(model.names)
        G_MB = self.gram(M, base)  # (S, G, P, k)
        G_BB = self.gram(base, base)
        N_MM, b_M = model.normal if model.normal is not None else (self.gram(M, M), self.rhs(M))
        b_B = self.rhs(base)
        XM = self._x(M)
        # errors-in-variables of the step columns H(t - t_s) x witness: one segment's products
        # times the taper-weighted share of each segment after t_s (tail sums over the samples)
        nM, nK = len(M), len(base)
        E_products = self.eiv_products(M + base)
        W_MM = self.eiv_weights(M)
        t_flat = np.concatenate([self.t0 + (s0 + np.arange(self.L)) / self.fs for s0 in self.starts])
        w2 = self._w2.reshape(-1)
        prof = np.stack([w2 if m is None else w2 * np.concatenate([m[s0:s0 + self.L] for s0 in self.starts])
                         for m in (self.eiv_modulation.get(n) for n in M)] + [w2])
        tail = np.concatenate([np.cumsum(prof[:, ::-1], axis=1)[:, ::-1], np.zeros((nM + 1, 1))], axis=1)

        def eiv_at(ts):
            j = int(np.searchsorted(t_flat, ts))  # the first sample at or after t_s
            W = np.empty((nM + nK, nM + nK))
            W[:nM, :nM] = W_MM
            W[:nM, nM:] = tail[:nM, j][:, None]
            W[nM:, :nM] = tail[:nM, j][None, :]
            W[nM:, nM:] = tail[nM, j]
            return E_products * W[None]

        idx = np.flatnonzero(self.mask)
        # a step closer to the ends than half a coarse step is nearly collinear with the TTL
        # columns themselves: search inside
        t_lo = self.t0 + idx[0] / self.fs + s.step_grid / 2
        t_hi = self.t0 + (idx[-1] + 1) / self.fs - s.step_grid / 2
        stack = np.nan_to_num(np.stack([self.series[n] for n in base], axis=1))  # (3, k, n)

        def evaluate_at(ts):
            j = int(np.searchsorted(self.seg_t0, ts, side="right") - 1)
            after = np.arange(len(self.starts)) > j
            N_MK = np.where(after[:, None, None, None], G_MB, 0.0)
            N_KK = np.where(after[:, None, None, None], G_BB, 0.0)
            b_K = np.where(after[:, None, None], b_B, 0.0)
            if 0 <= j < len(self.starts):
                s0 = self.starts[j]
                h = (self.t0 + (s0 + np.arange(self.L)) / self.fs >= ts).astype(float)
                m = self.mask[s0:s0 + self.L]
                seg = stack[:, :, s0:s0 + self.L] * h
                corr = self._step_correction(ts, base)
                if corr is not None:  # exact TDI of the step near t_s (the delays straddle it)
                    k0, c = corr
                    lo, hi = max(k0 - s0, 0), min(k0 - s0 + c.shape[-1], self.L)
                    if hi > lo:
                        seg = seg.copy()
                        seg[:, :, lo:hi] += c[:, :, lo - (k0 - s0):hi - (k0 - s0)]
                # spectra of segment j only
                _, X = segment_fft(seg * m, self.fs, self.win * m)
                wK = np.matmul(self.Lh, np.moveaxis(X[:, :, self.bins], 2, 0))[None]  # (1, m, 3, k)
                XK = _as_real(wK)
                N_MK[j] = _gram_x(XM[:, j:j + 1], XK, self.slices)[0]
                N_KK[j] = _gram_x(XK, XK, self.slices)[0]
                b_K[j] = _gram_x(XK, self.wd[j:j + 1][None].view(np.float64), self.slices)[0, ..., 0]
            return self._evidence(model, N_MM, N_MK, N_KK, b_M, b_K, [f"step.{n}" for n in base],
                                  np.full(len(base), 1e-3), eiv_at(ts))

        coarse = np.arange(t_lo + s.step_grid / 2, t_hi, s.step_grid)
        if coarse.size == 0:
            coarse = np.array([0.5 * (t_lo + t_hi)])
        results = [(ts, evaluate_at(ts)) for ts in coarse]
        lbfs = np.array([r["log_bayes_factor"] for _, r in results])
        best = coarse[int(np.nanargmax(lbfs))]
        fine = np.arange(best - s.step_grid + s.step_refine, best + s.step_grid, s.step_refine)
        fine = fine[(fine > t_lo) & (fine < t_hi)]
        results += [(ts, evaluate_at(ts)) for ts in fine if not np.any(np.isclose(ts, coarse))]
        all_lbf = np.array([r["log_bayes_factor"] for _, r in results])
        ts_best, ev = results[int(np.nanargmax(all_lbf))]
        # golden-section search of the maximum within one fine step either side, to 1 s
        a, b = max(ts_best - s.step_refine, t_lo), min(ts_best + s.step_refine, t_hi)
        ratio = (math.sqrt(5) - 1) / 2
        c, d = b - ratio * (b - a), a + ratio * (b - a)
        ec, ed = evaluate_at(c), evaluate_at(d)
        while b - a > 0.05:  # a step between two samples: the profile is flat within 0.25 s
            if np.nan_to_num(ec["delta_chi2"], nan=-np.inf) >= np.nan_to_num(ed["delta_chi2"], nan=-np.inf):
                b, d, ed = d, c, ec
                c = b - ratio * (b - a)
                ec = evaluate_at(c)
            else:
                a, c, ec = c, d, ed
                d = a + ratio * (b - a)
                ed = evaluate_at(d)
        for ts, e in ((c, ec), (d, ed)):
            results.append((ts, e))
            if e["log_bayes_factor"] > ev["log_bayes_factor"]:
                ts_best, ev = ts, e
        # the profile has secondary maxima one or more light travel times from the true step
        # (the TDI terms see the step delayed): try those, then refine around the best
        tau = float(np.mean(self.ltt_mean))
        for k in (-4, -3, -2, -1, 1, 2, 3, 4):
            ts = ts_best + k * tau
            if t_lo < ts < t_hi:
                e = evaluate_at(ts)
                results.append((ts, e))
                if e["log_bayes_factor"] > ev["log_bayes_factor"]:
                    ts_best, ev = ts, e
        for ts in ts_best + np.arange(-2.0, 2.01, 0.25):
            if t_lo < ts < t_hi:
                e = evaluate_at(ts)
                results.append((ts, e))
                if e["log_bayes_factor"] > ev["log_bayes_factor"]:
                    ts_best, ev = ts, e
        all_lbf = np.array([r["log_bayes_factor"] for _, r in results])
        good = lbfs[np.isfinite(lbfs)]
        marg = float(special.logsumexp(good) - math.log(len(good))) if good.size else float("nan")
        return {"t_step": float(ts_best), "evidence_at_best": ev, "log_bayes_factor_marginal": marg,
                "grid": [float(t) for t, _ in results], "grid_log_bayes_factor": [float(x) for x in all_lbf]}

    def _step_correction(self, ts: float, base: list) -> tuple | None:
        """``TDI(H(t - t_s) w) - H(t - t_s) TDI(w)`` for the TTL witnesses ``base``, decimated:
        non-zero only where the TDI delays straddle ``t_s`` (about 70 s, spread by the
        anti-alias filter), computed exactly on a short stretch of telemetry around ``t_s``.

        Returns ``(first decimated sample index, array (3, k, n))`` or None without telemetry.
        """
        if self.tm is None:
            return None

        tm, fs = self.tm, self.tm.fs
        taps = lowpass_taps(fs) if self.decimation > 1 else np.ones(1)
        hist = history_samples(fs, float(np.max(tm.ltt)))
        i_ts = int(np.floor((ts - tm.t0) * fs))
        a = max(i_ts - hist - 8, 0)
        b = min(i_ts + hist + taps.size + 8, tm.size)
        sub = tm.slice(a, b)
        data = effect_input_from_telemetry(sub)
        step = (data.t >= ts).astype(float)
        cols = {c.name: c for c in LinearTTL().columns(data)}
        cols = [cols[n] for n in base]
        for c in cols:
            for p in c.parts:
                p.series = p.series * step
        built = build(MICHELSON, sub.ltt, fs, order=self.settings.order, delay_order=self.settings.delay_order)
        exact = aet(columns_tdi(cols, built))  # (3, k, b - a); NaN where delays leave the stretch
        # before t_s - 8 s the step column is exactly zero (NaN only where the delays leave
        # the stretch), and so is the signal before the stretch
        exact = np.nan_to_num(exact)
        exact[..., : hist + 4] = 0.0
        # causal FIR then decimation on the global sample grid, as TDIData.decimated: output i
        # of the local convolution is global sample a + i; keep those inside the stretch
        full = np.apply_along_axis(lambda x: np.convolve(x, taps)[: b - a], -1, exact)
        first = (-a) % self.decimation
        dec = full[..., first::self.decimation]
        k0 = (a + first) // self.decimation  # decimated index of global sample a + first
        n = dec.shape[-1]
        t_dec = self.t0 + (k0 + np.arange(n)) / self.fs
        modulated = np.stack([self.series[nm][:, k0:k0 + n] for nm in base], axis=1) * (t_dec >= ts)
        return k0, dec - np.nan_to_num(modulated)

    def candidates(self, model: ModelFit, names=None, extra=()) -> list[dict]:
        """Try every available effect not in ``model`` and the effect instances ``extra``
        (witness effects and frequency-dependent couplings of the top witnesses,
        :func:`witness_candidates`); ranked list (best first).  Effects that need options to
        mean anything (``witness``, ``fd-coupling``) are tried through ``extra`` only."""
        s = self.settings
        in_model = {e.name for e in model.effects}
        todo = [n for n in (names or self.registry) if n not in in_model and n not in ("witness", "fd-coupling")]
        todo += list(extra)
        C = model.ttl_coefficients()
        # the excess the noise model (with its tolerance) cannot explain
        excess = float(np.sum(np.maximum(model.bands.chi2 - (1 + s.tolerance) * model.bands.dof, 0.0))) / self.kappa
        n_data = float(model.dof_band.sum())
        out = []
        in_specs = {e.spec() for e in model.effects}
        for name in todo:
            if isinstance(name, Effect):
                effect, cls, name = name, type(name), name.name
                if effect.spec() in in_specs:
                    continue
            else:
                cls = self.registry[name]
                effect = cls()
            t_start = time.monotonic()
            extra = {}
            try:
                if effect.unresolved() and not isinstance(effect, Step):

                    with self._columns_kept():
                        found = profile_search(self, model, effect, C)
                        effect = found.effect
                        cols = self.effect_columns(effect, C if effect.needs_coefficients else None, keep_series=False)
                        ev = self.evaluate(model, cols)
                    extra = {"search": found.to_json(), "log_bayes_factor_at_best": ev["log_bayes_factor"]}
                    ev["log_bayes_factor"] = found.log_bayes_factor
                    ev["delta_bic"] = ev["delta_chi2"] - (ev["n_parameters"] + len(found.estimates)) * math.log(n_data)
                elif isinstance(effect, Step) and effect.options.get("t_step") is None:
                    if not all(f"{m}.{a}.{sd}" in self.series for m in effect.mosas for a in effect.angles for sd in effect.sides):
                        continue
                    found = self.step_search(model, effect)
                    effect = Step(t_step=round(found["t_step"], 3))
                    # the evidence at the best time, with the exact step near t_s (the merely
                    # modulated columns lose much of a large step's delta chi2 there)
                    ev = dict(found["evidence_at_best"])
                    extra = {"t_step": found["t_step"], "log_bayes_factor_at_best": ev["log_bayes_factor"]}
                    ev["log_bayes_factor"] = found["log_bayes_factor_marginal"]
                    ev["delta_bic"] = ev["delta_chi2"] - (ev["n_parameters"] + 1) * math.log(n_data)
                elif name in ("witness", "fd-coupling") or any(c.startswith(("witness.", "fd.")) for c in effect.column_names()):
                    with self._columns_kept():  # trial columns leave the model's as they are
                        cols = self.effect_columns(effect, C if effect.needs_coefficients else None, keep_series=False)
                        ev = self.evaluate(model, cols)
                    ev["delta_bic"] = ev["delta_chi2"] - ev["n_parameters"] * math.log(n_data)
                else:
                    if effect.needs_coefficients and np.isnan(C).any():
                        continue
                    cols = self.effect_columns(effect, C if effect.needs_coefficients else None, keep_series=False,
                                               exact=False)
                    ev = self.evaluate(model, cols)
                    if hasattr(effect, "shifted_members") and stats.chi2.sf(max(ev["delta_chi2"], 0.0), len(cols)) < s.alpha:
                        ev, extra = self._shifted_evidence(model, effect, ev)
                    ev["delta_bic"] = ev["delta_chi2"] - ev["n_parameters"] * math.log(n_data)
            except ConfigError as exc:
                log.info("candidate %s skipped: %s", name, exc)
                continue
            k = ev["n_parameters"]
            # a searched nonlinear parameter counts as one more degree of freedom (a rough
            # allowance for the look-elsewhere effect of the search; the evidence is marginal)
            k_eff = k + len(extra.get("search", {}).get("estimates", {}))
            p = float(stats.chi2.sf(max(ev["delta_chi2"], 0.0), k_eff))
            significant = bool(p < s.alpha and ev["log_bayes_factor"] > s.log_bf_threshold)
            out.append({
                "effect": name,
                "spec": effect.spec(),
                "cli_spec": effect.cli_spec(),
                "title": cls.title,
                "physics": cls.physics,
                "n_parameters": k,
                "delta_chi2": float(ev["delta_chi2"]),
                "p_value": p,
                "log_bayes_factor": float(ev["log_bayes_factor"]),
                "delta_bic": float(ev["delta_bic"]),
                "explained_fraction": float(min(1.0, max(ev["delta_chi2"], 0.0) / excess)) if excess > 0 else 0.0,
                "significant": significant,
                "where": self._where(ev, extra),
                "parameters": _top_parameters(ev),
                "seconds": round(time.monotonic() - t_start, 2),
                **({"searched": extra} if extra else {}),
            })
        out.sort(key=lambda c: (not c["significant"], -np.nan_to_num(c["log_bayes_factor"], nan=-np.inf)))
        return out

    def _shifted_evidence(self, model: ModelFit, effect, taylor: dict) -> tuple[dict, dict]:
        """Evidence of a shifted-witness candidate with its offsets searched (the exact model
        of :meth:`_reexpand`) instead of the Taylor columns at zero, which lose most of a
        large offset's delta chi^2 where ``2 pi f delta`` nears one.  Falls back to the Taylor
        evidence when no group's offset needs the exact model."""
        if self.settings.expansion_passes == 0 or not all(n in self.series for n in self.ttl_names):
            return taylor, {}
        with self._columns_kept():  # the model's own shifted columns stay as they are
            exact = self._fit(list(model.effects) + [effect], None, False)
            expansion = self.expansion_points()
        if all("@" not in n for n in exact.names):
            return taylor, {}
        ev = self.compare(model, exact, expansion)
        new = [i for i, n in enumerate(exact.names) if parameter_name(n) not in set(model.parameter_names)]
        names = [exact.names[i] for i in new]
        beta = np.array([total_offset(exact.names[i], exact.theta[i], expansion) for i in new])
        ev.update({"n_parameters": len(new), "names": names, "beta": beta, "sigma": exact.sigma[new],
                   "band_delta": (model.chi2_seg_band - exact.chi2_seg_band).sum(axis=0) / self.kappa,
                   "segment_delta": (model.chi2_seg_band - exact.chi2_seg_band).sum(axis=1) / self.kappa})
        return ev, {"offsets": {n[:-3]: float(b) for n, b in zip(names, beta) if n.endswith(".d1")}}

    @contextlib.contextmanager
    def _columns_kept(self):
        """Restore the registered columns and expansion points on exit: a trial fit with a
        shifted-witness effect re-registers columns under names a fitted model may hold
        (``ltt-error.12.d1``, ``21.phi.tx@ltt-error.12``) with other offsets and weights."""
        kept = {a: dict(getattr(self, a)) for a in ("wcols", "series", "col_info", "eiv_parts", "eiv_modulation",
                                                     "_gram_cache", "_expansion", "_owner")}
        have_derivatives = self._have_derivatives
        try:
            yield
        finally:
            bases = [n for n in self.wcols if n.startswith("base:") and n not in kept["wcols"]]
            for a, v in kept.items():
                for n in bases if a in ("wcols", "series", "col_info", "eiv_parts", "eiv_modulation") else ():
                    if n in getattr(self, a):
                        v[n] = getattr(self, a)[n]
                setattr(self, a, v)
            self._have_derivatives = have_derivatives
            self._x_cache.clear()

    def _where(self, ev, extra) -> dict:
        bd = ev["band_delta"]
        sd = ev["segment_delta"]
        tot = max(float(np.sum(np.maximum(bd, 0))), 1e-300)
        bands = [{"f_lo": float(self.edges[g]), "f_hi": float(self.edges[g + 1]), "delta_chi2": float(bd[g]),
                  "share": float(max(bd[g], 0) / tot)} for g in range(self.G)]
        strong = [b for b in bands if b["share"] >= 0.1]
        z2 = (ev["beta"] / np.where(ev["sigma"] > 0, ev["sigma"], np.inf)) ** 2
        groups: dict = {}
        for n, z in zip(ev["names"], z2):
            parts = n.split(".")
            groups[parts[1] if len(parts) > 1 else n] = groups.get(parts[1] if len(parts) > 1 else n, 0.0) + float(z)
        links = sorted(groups.items(), key=lambda kv: -kv[1])
        ztot = max(sum(groups.values()), 1e-300)
        out = {
            "bands": bands,
            "main_bands": [[b["f_lo"], b["f_hi"]] for b in strong],
            "segments": [{"t_start": float(t), "t_stop": float(t + self.seg_duration), "delta_chi2": float(x)}
                         for t, x in zip(self.seg_t0, sd)],
            "links": [{"group": g, "z2": z, "share": z / ztot} for g, z in links[:6]],
        }
        if "t_step" in extra:
            out["t_step"] = extra["t_step"]
        if "offsets" in extra:  # searched offsets [s] of a shifted-witness effect, per group
            out["offsets"] = extra["offsets"]
        return out


def _top_parameters(ev, n: int = 6) -> list[dict]:
    beta, sig = ev["beta"], ev["sigma"]
    z = np.abs(beta) / np.where(sig > 0, sig, np.inf)
    order = np.argsort(-z)[:n]
    return [{"name": ev["names"][i], "value": float(beta[i]), "sigma": float(sig[i]), "z": float(z[i])} for i in order]


# ---------------------------------------------------------------------------
# Reports
# ---------------------------------------------------------------------------

def fine_band_table(dg: Diagnoser, model: ModelFit):
    """``model``'s adequacy in third-octave bands where the data allow it
    (:func:`ttlcore.diagnose.adequacy.third_octave_table`), its fitted parameters (linear
    and noise) counted as in its band table."""
    s = dg.settings
    n_fitted = 6 * dg.f.size * len(dg.starts) - float(model.bands.dof.sum())
    return third_octave_table(model.residual_w, dg.f, s.band, n_fitted, dg.kappa, s.tolerance, s.alpha, s.min_band_dof)


def adequacy_json(dg: Diagnoser, model: ModelFit) -> dict:
    """The ``adequacy`` part of the report for ``model``."""
    s = dg.settings
    bands = model.bands.to_json()
    summary = describe_failures(model.bands)
    fine = fine_band_table(dg, model)
    summary += [f"localised (third-octave bands): {x}" for x in describe_failures(fine)]
    nm = dg.noise_parameters
    if nm is not None and nm.at_bound:
        summary.append(f"noise level(s) {', '.join(nm.at_bound)} at the bound of their allowed range: more (or less) "
                       "noise of that shape than the instrument is known to have, or an unmodelled effect of that shape")
    time_part = model.time_table or {}
    summary += time_part.get("summary", [])
    return {
        "noise_model": noise_model_json(dg.noise_parameters),
        "tolerance": s.tolerance, "alpha": s.alpha, "variance_factor": dg.kappa,
        "band": list(map(float, s.band)), "segment_duration": dg.seg_duration, "segments": len(dg.starts),
        "chi2": model.chi2, "dof": model.dof, "chi2_dof": model.chi2_dof,
        "bands": bands, "fine_bands": fine.to_json(), "time": time_part,
        "fails": bool(any(b["fails"] for b in bands) or any(r.get("fails") for r in time_part.get("segments", []))),
        "summary": summary or ["no failure: the residual is consistent with the instrument noise model"],
    }


def coefficients_json(model: ModelFit, truth=None, expansion: dict | None = None) -> dict:
    """The fitted columns (value, sigma) and, with truth, the errors of the 24 linear ones;
    ``offsets``: the fitted offsets of linearised effects (expansion point + ``d1``)."""
    out = {"values": {n: float(v) for n, v in zip(model.parameter_names, model.theta)},
           "sigma": {n: float(v) for n, v in zip(model.parameter_names, model.sigma)}}
    offsets = {}
    for n, v, sg in zip(model.names, model.theta, model.sigma):
        if n.endswith(".d1"):
            offsets[n[:-3]] = {"value": total_offset(n, v, expansion or {}), "sigma": float(sg), "unit": "s"}
    if offsets:
        out["offsets"] = offsets
    if truth is not None:
        C, sig = model.ttl_coefficients(), model.ttl_sigma()
        err = C - np.asarray(truth, dtype=float)
        z = err / sig
        ok = np.isfinite(z)
        out["truth"] = dict(zip(COEFFICIENT_NAMES, map(float, truth)))
        out["error"] = {n: float(e) for n, e, k in zip(COEFFICIENT_NAMES, err, ok) if k}
        out["max_abs_error"] = float(np.nanmax(np.abs(err)))
        out["max_abs_error_over_sigma"] = float(np.nanmax(np.abs(z)))
        out["rms_error"] = float(np.sqrt(np.nanmean(err ** 2)))
    return out


def model_json(dg: Diagnoser, model: ModelFit, truth=None) -> dict:
    return {"effects": [e.spec() for e in model.effects], "n_parameters": len(model.names),
            "cli_effects": ",".join(e.cli_spec() for e in model.effects), "searched": dict(model.searches),
            "chi2_dof": model.chi2_dof, "adequacy": adequacy_json(dg, model),
            "coefficients": coefficients_json(model, truth, dg.expansion_points())}


def diagnose(tm, effects=("linear-ttl",), *, settings: DiagnoseSettings | None = None, effect_modules=(),
             candidates=None, truth_coefficients=None, witnesses: bool | None = None, progress=None) -> dict:
    """Full diagnosis of telemetry ``tm`` with a model (list of effect specs).

    Fits the model under the instrument noise model, tests its adequacy per band and per
    time slice, ranks every other available effect (named, entry points, ``effect_modules``)
    and the witness library.  If the model holds more than ``linear-ttl``, the linear-only
    model is fitted too and reported as ``before``, with the evidence for the change.
    ``truth_coefficients`` (24,) only adds coefficient errors; nothing else reads truth.

    Returns
    -------
    dict
        The JSON report (schema in ``docs/diagnostics.md``); the key ``"_internals"`` holds
        the :class:`Diagnoser` and fits (removed before writing).
    """
    s = settings or DiagnoseSettings()
    say = progress or (lambda msg: None)
    clock = time.monotonic()
    timings = {}

    def lap(name):
        nonlocal clock
        now = time.monotonic()
        timings[name] = round(now - clock, 3)
        clock = now

    eff = make_effects(list(effects), effect_modules)
    if not any(e.name == "linear-ttl" for e in eff):
        log.warning("model without linear-ttl: the 24 linear coefficients are not fitted")
    say("TDI and spectra")
    dg = Diagnoser.from_telemetry(tm, s, effect_modules)
    lap("tdi_and_spectra")
    say("fit")
    model = dg.fit(eff)
    if s.noise_model == "fitted":
        say("noise model")
        model = _with_noise_levels(dg, model)
    lap("fit")
    report: dict = {"model": model_json(dg, model, truth_coefficients)}
    report["adequacy"] = report["model"]["adequacy"]
    if len(eff) > 1 or eff[0].name != "linear-ttl":
        before = dg.fit(make_effects(["linear-ttl"]))
        ev = dg.change(before, model)
        report["before"] = model_json(dg, before, truth_coefficients)
        report["change"] = {
            "added": [e.spec() for e in eff if e.name != "linear-ttl"],
            "delta_chi2": None if ev is None else ev["delta_chi2"],
            "log_bayes_factor": None if ev is None else ev["log_bayes_factor"],
            "chi2_dof_before": before.chi2_dof, "chi2_dof_after": model.chi2_dof,
            "bands_before": [b["chi2_dof"] for b in report["before"]["adequacy"]["bands"]],
            "bands_after": [b["chi2_dof"] for b in report["adequacy"]["bands"]],
        }
        lap("before")
    use_witnesses = s.witnesses if witnesses is None else witnesses
    extra = []
    if use_witnesses:

        say("witness search")
        report["witnesses"] = witness_search(tm, dg, model, s.top_witnesses)
        lap("witnesses")
        extra = witness_candidates(report["witnesses"], s.witness_candidates, effect_modules)
    else:
        report["witnesses"] = None
    say("candidates")
    report["candidates"] = dg.candidates(model, candidates, extra)
    lap("candidates")
    report["recommendation"] = recommendation(report, eff, s)
    report["settings"] = {"band": list(map(float, s.band)), "n_bands": s.n_bands, "segment_duration": dg.seg_duration,
                          "time_segment": s.time_segment, "tolerance": s.tolerance, "alpha": s.alpha,
                          "log_bf_threshold": s.log_bf_threshold, "dws_asd": dg.dws_asd}
    report["timings_s"] = timings
    report["_internals"] = {"diagnoser": dg, "model": model}
    return report


def recommendation(report: dict, effects, settings: DiagnoseSettings) -> dict | None:
    """The next step: the significant candidate with the largest (marginal) log Bayes
    factor over everything tried (named effects, witness effects, frequency-dependent
    couplings, plugins), its ``--effects`` option runnable as printed (quoted when it holds
    ``;``), and whether it explains the excess (at least half of the chi^2 beyond the
    tolerance).  None when the model is adequate and nothing is significant; when nothing
    explains the excess, ``pointers`` lists what the top witnesses point at."""
    cands = report["candidates"]
    best = next((c for c in cands if c["significant"]), None)
    fails = bool(report["adequacy"]["fails"])
    if best is None and not fails:
        return None
    pointers = []
    for w in (report.get("witnesses") or {}).get("overall", [])[:3]:
        pointers.append({"witness": w["name"], "spec": w.get("spec"), "band_hz": w["best_band"],
                         "delta_chi2": w["delta_chi2"]})
    if best is None:
        return {"effect": None, "explains": False, "pointers": pointers,
                "message": "no candidate is significant; the witnesses point at: " +
                           "; ".join(f"{p['witness']} ({p['band_hz'][0]:.3g}-{p['band_hz'][1]:.3g} Hz)" for p in pointers)}
    specs = [e.cli_spec() for e in effects] + [best["cli_spec"]]
    value = ",".join(specs)
    option = "--effects " + (f'"{value}"' if any(ch in value for ch in ';|&<> ') else value)
    explains = best["explained_fraction"] >= 0.5 or not fails
    out = {"effect": best["effect"], "spec": best["spec"], "cli_spec": best["cli_spec"], "option": option,
           "explains": bool(explains), "explained_fraction": best["explained_fraction"]}
    if not explains:
        out["pointers"] = pointers
        out["message"] = (f"no candidate explains the excess (the best, {best['cli_spec']}, explains "
                          f"{100 * best['explained_fraction']:.0f} %); the witnesses point at: " +
                          "; ".join(f"{p['witness']} ({p['band_hz'][0]:.3g}-{p['band_hz'][1]:.3g} Hz)" for p in pointers))
    return out


def _with_noise_levels(dg: Diagnoser, model: ModelFit) -> ModelFit:
    """``model`` refitted with the secondary-noise levels profiled (``noise_model="fitted"``).

    The model's searched parameters stay at the estimates the search found (``model.effects``
    holds the effects at those estimates), and the search results are carried over."""
    searches = dict(model.searches)
    _, fitted = profile_noise_model(dg, model.effects, first=model)
    fitted.searches = searches
    return fitted


def refit(source, effects=("linear-ttl",), *, settings: DiagnoseSettings | None = None, effect_modules=(),
          dws_asd: float | None = None, baseline=("linear-ttl",)) -> dict:
    """Refit already-computed data with a given list of effects and report the change.

    Parameters
    ----------
    source : Telemetry, TDIData, list of TDIData, or Diagnoser
        - a :class:`~ttlcore.io.telemetry.Telemetry`: every effect is available;
        - TDI outputs (one :class:`~ttlcore.tdi.data.TDIData`, or a list of contiguous
          segments such as the pipeline's hourly TDI, concatenated here): ``linear-ttl``,
          ``drift`` and ``step`` (modulated TDI regressors, no DWS series needed);
        - a :class:`Diagnoser` already built (its spectra and columns are reused, so
          successive refits with changing models cost only the new columns).
    effects : sequence of str or Effect
        The model, e.g. ``["linear-ttl", "drift", "step:t_step=50400"]``.
    baseline : sequence
        The model the change is measured against (default the linear TTL alone).

    Returns
    -------
    dict
        ``{"model": {effects, n_parameters, chi2_dof, adequacy, coefficients},
        "baseline": {...}, "change": {"delta_chi2", "log_bayes_factor", "bands_before",
        "bands_after"}, "_internals": {"diagnoser", "fit", "baseline_fit"}}``.
    """
    if isinstance(source, Diagnoser):
        dg = source
    elif isinstance(source, TDIData):
        dg = Diagnoser.from_tdi(source, settings, dws_asd=dws_asd, effect_modules=effect_modules)
    elif isinstance(source, (list, tuple)) and source and all(isinstance(x, TDIData) for x in source):
        dg = Diagnoser.from_tdi(concatenate_tdi(source), settings, dws_asd=dws_asd, effect_modules=effect_modules)
    elif hasattr(source, "dws_phi"):
        dg = Diagnoser.from_telemetry(source, settings, effect_modules)
    else:
        raise ConfigError(f"refit: cannot refit a {type(source).__name__}; give telemetry, TDI data or a Diagnoser")
    model = dg.fit(make_effects(list(effects), effect_modules))
    if dg.settings.noise_model == "fitted":
        model = _with_noise_levels(dg, model)
    base = dg.fit(make_effects(list(baseline), effect_modules))
    ev = dg.change(base, model)
    return {
        "model": model_json(dg, model), "baseline": model_json(dg, base),
        "change": {"delta_chi2": None if ev is None else ev["delta_chi2"],
                   "log_bayes_factor": None if ev is None else ev["log_bayes_factor"],
                   "chi2_dof_before": base.chi2_dof, "chi2_dof_after": model.chi2_dof,
                   "bands_before": [float(x) for x in base.bands.chi2_dof],
                   "bands_after": [float(x) for x in model.bands.chi2_dof]},
        "_internals": {"diagnoser": dg, "fit": model, "baseline_fit": base},
    }


def concatenate_tdi(segments) -> TDIData:
    """Join contiguous TDI segments (same channels, names and rate) into one."""
    first = segments[0]
    for a, b in zip(segments[:-1], segments[1:]):
        if b.channels != first.channels or b.names != first.names or b.fs != first.fs:
            raise ConfigError("TDI segments differ in channels, regressor names or rate")
        if abs(b.t0 - (a.t0 + a.size / a.fs)) > 0.5 / a.fs:
            raise ConfigError(f"TDI segments are not contiguous: one ends at {a.t0 + a.size / a.fs} s, the next starts at {b.t0} s")
    return replace(first, data=np.concatenate([x.data for x in segments], axis=-1),
                   regressors=np.concatenate([x.regressors for x in segments], axis=-1),
                   ltt_mean=np.mean([x.ltt_mean for x in segments], axis=0))


def strip_internals(report: dict) -> dict:
    """The report without its in-memory objects (what ``--json`` writes)."""
    return {k: v for k, v in report.items() if not k.startswith("_")}


def text_report(report: dict, source: str = "", max_candidates: int = 5) -> str:
    """The one-minute text report."""
    lines = []
    m = report["model"]
    ad = report["adequacy"]
    lines.append(f"{source}: model {', '.join(m['effects'])} ({m['n_parameters']} parameters), "
                 f"chi2/dof {ad['chi2_dof']:.3f} against the instrument noise model"
                 f"{' (fitted levels)' if ad['noise_model'].get('kind') == 'fitted' else ''} "
                 f"({1e3 * ad['band'][0]:.3g} mHz - {ad['band'][1]:.3g} Hz, tolerance {100 * ad['tolerance']:.0f} %)")
    if "before" in report:
        b = report["before"]
        lines.append("  before -> after (" + ", ".join(report["change"]["added"]) + "):")
        lines.append("    band [Hz]            chi2/dof before   after")
        for bb, ba in zip(b["adequacy"]["bands"], ad["bands"]):
            lines.append(f"    {bb['f_lo']:.4f} - {bb['f_hi']:.4f}      {bb['chi2_dof']:8.3f}{' FAIL' if bb['fails'] else '     '}"
                         f"  {ba['chi2_dof']:8.3f}{' FAIL' if ba['fails'] else ''}")
        ch = report["change"]
        if ch.get("delta_chi2") is not None:
            lines.append(f"    evidence for the change: delta chi2 {ch['delta_chi2']:.1f}, log Bayes factor {ch['log_bayes_factor']:.1f}")
        if "max_abs_error" in b["coefficients"] and "max_abs_error" in m["coefficients"]:
            lines.append(f"    max |coefficient error|: {1e3 * b['coefficients']['max_abs_error']:.4f} -> "
                         f"{1e3 * m['coefficients']['max_abs_error']:.4f} mm/rad "
                         f"({b['coefficients']['max_abs_error_over_sigma']:.1f} -> {m['coefficients']['max_abs_error_over_sigma']:.1f} sigma)")
    elif "max_abs_error" in m["coefficients"]:
        c = m["coefficients"]
        lines.append(f"  truth: max |coefficient error| {1e3 * c['max_abs_error']:.4f} mm/rad ({c['max_abs_error_over_sigma']:.1f} sigma)")
    lines.append("  where the model fails:")
    lines += [f"    {x}" for x in ad["summary"]]
    cands = report["candidates"]
    lines.append("  candidates (effect: delta chi2 / dof, log Bayes factor, share of the excess, where):")
    for c in cands[:max_candidates]:
        where = c["where"]
        bands = ", ".join(f"{lo:.3g}-{hi:.3g} Hz" for lo, hi in where["main_bands"][:3])
        links = ", ".join(x["group"] for x in where["links"][:3])
        extra = f", t_step {where['t_step'] / 3600:.2f} h" if "t_step" in where else ""
        if "offsets" in where:
            top = sorted(where["offsets"].items(), key=lambda kv: -abs(kv[1]))[:3]
            extra += ", offsets " + ", ".join(f"{k.rsplit('.', 1)[-1]} {v:+.3g} s" for k, v in top)
        if "search" in c.get("searched", {}):
            est = c["searched"]["search"]["estimates"]
            extra += ", " + ", ".join(f"{k} {v:.4g}" for k, v in est.items())
        label = c["effect"] if c["cli_spec"] == c["effect"] else c["cli_spec"]
        lines.append(f"    {'*' if c['significant'] else ' '} {label:<16} {c['delta_chi2']:10.1f} / {c['n_parameters']:<3d}"
                     f" logB {c['log_bayes_factor']:9.1f}  {100 * c['explained_fraction']:5.0f} %  [{bands}; {links}{extra}]")
    if not any(c["significant"] for c in cands):
        lines.append("    no candidate is significant")
    w = report.get("witnesses")
    if w:
        lines.append(f"  top witnesses ({w['n_witnesses']} tried): " +
                     "; ".join(f"{x['name']} (delta chi2 {x['delta_chi2']:.0f}, coherence peaks at "
                               f"{_hz(x['peak_frequency'])})" for x in w["overall"][:3]))
    rec = report.get("recommendation")
    if rec and rec.get("option"):
        lines.append(f"  best next step: add {rec['cli_spec']}:  ttl diagnose {source or 'DATA'} {rec['option']}")
    if rec and rec.get("message"):
        lines.append(f"  {rec['message']}")
    return "\n".join(lines)
