"""Adequacy of a fitted model: the whitened residual against the instrument noise model.

docs/diagnostics.md.  The reference is *not* re-estimated from the residual
(that would absorb the very effect we look for) but the instrument's noise model:

    S(f) = S_sec(f) + sum_ch |sum_{k in ch} C_k T_k(f)|^2 S_dws(f)

with ``S_sec`` the analytic secondary-noise CSD of A, E, T for the mean arms
(:func:`ttlcore.estimate.fit.model_csd`, paper appendix levels, docs/physics.md "Analytic secondary-noise
PSD") and the second term the DWS readout noise (``S_dws = (2 pi f a_dws)^2``, angle ASD
``a_dws``) that the subtraction injects through the fitted coefficients ``C`` (the "TTL
residual" of docs/physics.md; ``T_k`` the TDI response of regressor ``k`` to its DWS channel,
:func:`ttlcore.tdi.regressors.regressor_responses`).

For a frequency band (or a time segment) holding ``n`` complex bins of the three
channels, the whitened residual power ``chi2 = sum r^H S^-1 r`` has mean
``dof = 2 * 3 * n`` (minus the fitted parameters' share) if the model is right.  Neighbouring
bins of a tapered segment are correlated, which inflates the variance of ``chi2`` by the
factor ``kappa`` of :func:`ttlcore.estimate.fit.variance_factor`; ``chi2 / kappa`` is then close to a
chi^2 variable with ``dof / kappa`` degrees of freedom (Satterthwaite).  The noise model is
trusted within a stated relative ``tolerance`` on its PSD: default 2 % with the
secondary-noise levels fitted (:mod:`ttlcore.diagnose.noise_model`; lisainstrument and
simulator null days then read 1 within the statistical scatter, docs/diagnostics.md), 5 %
with the paper's fixed levels (a simulated noise-only day matches them to a few per cent,
a lisainstrument day to 7 %).  The p-value of a band is that of ``chi2 / (1 + tolerance)``: a band *fails* when even a noise level higher by the
tolerance cannot explain its residual at significance ``alpha``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from ..conventions import COEFFICIENT_NAMES
from ..estimate.fit import model_csd
from ..tdi.regressors import dws_channel, regressor_responses

#: Relative tolerance on the noise model's PSD (see the module docstring).
DEFAULT_TOLERANCE = 0.02
#: Tolerance advised with the fixed noise model (``--noise-model fixed``).
FIXED_MODEL_TOLERANCE = 0.05
#: Significance level of a failure.
DEFAULT_ALPHA = 1e-3
#: Default diagnosis band [Hz]: above ~0.8 Hz the residual laser noise of TDI at 4 Hz
#: (Lagrange interpolation near Nyquist, Keplerian arms) exceeds the secondary noises by
#: up to a factor of ten in PSD (measured on simulated days: chi2/dof 2 to 9 in 0.8-0.9 Hz,
#: 1.0 below), and the secondary-noise model does not describe it.
DIAGNOSIS_BAND = (3e-3, 0.8)


def instrument_noise_csd(
    f: np.ndarray,
    ltt_mean,
    coefficients=None,
    dws_asd: float = 0.0,
    names=COEFFICIENT_NAMES,
    secondary: np.ndarray | None = None,
) -> np.ndarray:
    """The instrument noise model ``S(f)`` of the module docstring, shape (m, 3, 3) (A, E, T).

    Parameters
    ----------
    f : ndarray (m,)
        Frequencies [Hz].
    ltt_mean : array_like (6,)
        Mean light travel times [s].
    coefficients : ndarray (P,) or (P, n_t), optional
        Fitted TTL coefficients [m/rad] for ``names`` (the DWS term is left out if None);
        with a time axis (a model with drifts or steps) the DWS term is averaged over it.
    dws_asd : float
        DWS readout noise, angle ASD [rad/sqrt(Hz)].
    secondary : ndarray (m, 3, 3), optional
        The secondary-noise CSD to use instead of the fixed ``S_sec`` (a fitted
        :class:`ttlcore.diagnose.noise_model.NoiseModel`'s ``csd(f)``).
    """
    csd = model_csd(f, ltt_mean) if secondary is None else np.asarray(secondary)
    if coefficients is None or dws_asd <= 0:
        return csd
    names = [n for n in names]
    T = regressor_responses(f, ltt_mean, names)  # (m, 3, P)
    dws_psd = (2 * np.pi * np.asarray(f) * dws_asd) ** 2
    groups: dict = {}
    for k, n in enumerate(names):
        groups.setdefault(dws_channel(n), []).append(k)
    C = np.asarray(coefficients, dtype=float)
    # time-varying coefficients (24, n_t): the noise of a stationary readout through
    # coefficients that change is, on average, the mean of |sum_k C_k(t) T_k|^2
    Cs = C.T if C.ndim == 2 else C[None, :]
    for ks in groups.values():
        acc = np.zeros((np.size(f), 3, 3), dtype=complex)
        for Ct in Cs:
            g = T[:, :, ks] @ Ct[ks]  # (m, 3)
            acc += np.einsum("mi,mj->mij", g, g.conj())
        csd = csd + acc / len(Cs) * dws_psd[:, None, None]
    return csd


def p_value(chi2, dof, kappa: float = 1.0, tolerance: float = DEFAULT_TOLERANCE):
    """Upper-tail p-value of ``chi2`` with ``dof`` degrees of freedom, for bins correlated by
    ``kappa`` and a noise model trusted within ``tolerance`` (module docstring)."""
    chi2 = np.asarray(chi2, dtype=float)
    dof = np.asarray(dof, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(dof > 0, stats.chi2.sf(chi2 / ((1 + tolerance) * kappa), np.maximum(dof, 1e-9) / kappa), np.nan)


@dataclass
class BandTable:
    """chi^2 per band (and per channel) of one residual against the noise model."""

    edges: np.ndarray
    chi2: np.ndarray  # (G,)
    dof: np.ndarray  # (G,)
    channel_chi2: np.ndarray  # (G, 3)
    channel_dof: np.ndarray  # (G, 3)
    kappa: float
    tolerance: float
    alpha: float

    @property
    def chi2_dof(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.chi2 / self.dof

    @property
    def p_values(self) -> np.ndarray:
        return p_value(self.chi2, self.dof, self.kappa, self.tolerance)

    @property
    def fails(self) -> np.ndarray:
        return self.p_values < self.alpha

    def channel_fails(self) -> np.ndarray:
        return p_value(self.channel_chi2, self.channel_dof, self.kappa, self.tolerance) < self.alpha

    def to_json(self, channels=("A", "E", "T")) -> list[dict]:
        out = []
        cf = self.channel_fails()
        for g in range(len(self.chi2)):
            out.append(
                {
                    "f_lo": float(self.edges[g]),
                    "f_hi": float(self.edges[g + 1]),
                    "chi2": float(self.chi2[g]),
                    "dof": float(self.dof[g]),
                    "chi2_dof": _f(self.chi2_dof[g]),
                    "p_value": _f(self.p_values[g]),
                    "fails": bool(self.fails[g]),
                    "channels": {
                        c: {
                            "chi2_dof": _f(self.channel_chi2[g, i] / self.channel_dof[g, i])
                            if self.channel_dof[g, i]
                            else None,
                            "fails": bool(cf[g, i]),
                        }
                        for i, c in enumerate(channels)
                    },
                }
            )
        return out


def _f(x):
    x = float(x)
    return x if np.isfinite(x) else None


def band_table(
    wr: np.ndarray,
    band_index: np.ndarray,
    edges,
    n_params: float = 0,
    kappa: float = 1.0,
    tolerance: float = DEFAULT_TOLERANCE,
    alpha: float = DEFAULT_ALPHA,
) -> BandTable:
    """chi^2 per band of whitened residual spectra ``wr`` (S, m, 3) (``L^H r`` with
    ``S^-1 = L L^H``); ``band_index`` (m,) the band of each bin.  The ``n_params`` fitted
    parameters remove their share of degrees of freedom in proportion to each band's."""
    G = len(edges) - 1
    p = np.abs(wr) ** 2  # (S, m, 3)
    per = np.zeros((G, 3))
    nb = np.zeros(G)
    for g in range(G):
        sel = band_index == g
        per[g] = 2 * p[:, sel].sum(axis=(0, 1))
        nb[g] = sel.sum() * wr.shape[0]
    dof_ch = 2 * nb[:, None] * np.ones(3)
    dof = dof_ch.sum(axis=1)
    if n_params and dof.sum() > 0:
        share = dof / dof.sum() * n_params
        dof = dof - share
        dof_ch = dof_ch - share[:, None] / 3
    return BandTable(np.asarray(edges), per.sum(axis=1), dof, per, dof_ch, kappa, tolerance, alpha)


def merged_band_edges(f: np.ndarray, edges: np.ndarray, dof_per_bin: int, min_dof: int) -> np.ndarray:
    """Merge adjacent bands (lowest first) until each holds at least ``min_dof`` degrees of
    freedom (``dof_per_bin`` per frequency bin)."""
    merged = list(np.asarray(edges, dtype=float))
    while len(merged) > 2:
        counts = np.histogram(f, bins=merged)[0] * dof_per_bin
        low = np.flatnonzero(counts < min_dof)
        if low.size == 0:
            break
        g = int(low[0])
        del merged[g + 1 if g < len(counts) - 1 else g]  # merge with the upper neighbour (the last: lower)
    return np.asarray(merged)


def third_octave_edges(band) -> np.ndarray:
    """Band edges [Hz] a third of an octave apart (ratio ``2^(1/3)``) from ``band[0]``, the
    last band (between 2/3 and 4/3 of a third of an octave) ending at ``band[1]``."""
    lo, hi = float(band[0]), float(band[1])
    n = max(1, int(round(np.log2(hi / lo) * 3)))
    edges = lo * 2.0 ** (np.arange(n + 1) / 3.0)
    edges[-1] = hi * (1 + 1e-9)
    return edges


def third_octave_table(
    wr: np.ndarray,
    f: np.ndarray,
    band,
    n_params: float = 0,
    kappa: float = 1.0,
    tolerance: float = DEFAULT_TOLERANCE,
    alpha: float = DEFAULT_ALPHA,
    min_dof: int = 2000,
) -> BandTable:
    """:func:`band_table` at third-octave resolution where the data allow it: third-octave
    bands (:func:`third_octave_edges`) holding fewer than ``min_dof`` degrees of freedom are
    merged with their neighbour (:func:`merged_band_edges`), so that the statistical scatter
    of chi2/dof, ``sqrt(2 kappa / dof)``, stays below the tolerance's scale everywhere.

    Parameters
    ----------
    wr : ndarray (S, m, 3)
        Whitened residual spectra.
    f : ndarray (m,)
        Their frequencies [Hz].
    band : tuple
        The analysed band [Hz].
    n_params : float
        Fitted parameters (linear and noise), shared among the bands by their dof.
    """
    edges = merged_band_edges(f, third_octave_edges(band), 6 * wr.shape[0], min_dof)
    idx = np.clip(np.searchsorted(edges, f, side="right") - 1, 0, len(edges) - 2)
    return band_table(wr, idx, edges, n_params, kappa, tolerance, alpha)


def describe_failures(table: BandTable, channels=("A", "E", "T")) -> list[str]:
    """Plain-language failures: contiguous failing bands with the failing channels."""
    out = []
    fails = table.fails
    cf = table.channel_fails()
    g = 0
    while g < len(fails):
        if not fails[g]:
            g += 1
            continue
        h = g
        while h + 1 < len(fails) and fails[h + 1]:
            h += 1
        chans = [c for i, c in enumerate(channels) if cf[g : h + 1, i].any()]
        worst = g + int(np.nanargmax(table.chi2_dof[g : h + 1]))
        out.append(
            f"fails between {_hz(table.edges[g])} and {_hz(table.edges[h + 1])} in {', '.join(chans) or 'the sum of A, E, T'} "
            f"(chi2/dof up to {table.chi2_dof[worst]:.2f}, p = {table.p_values[worst]:.1e})"
        )
        g = h + 1
    return out


def describe_time_failures(t_start, t_stop, fails, t0: float) -> list[str]:
    """``fails after 14 h`` / ``fails between 3 h and 9 h`` from per-segment flags."""
    out: list[str] = []
    fails = np.asarray(fails, dtype=bool)
    if not fails.any():
        return out
    if fails.all():
        return ["fails in every time segment"]
    k = 0
    while k < len(fails):
        if not fails[k]:
            k += 1
            continue
        j = k
        while j + 1 < len(fails) and fails[j + 1]:
            j += 1
        a, b = (t_start[k] - t0) / 3600, (t_stop[j] - t0) / 3600
        if j == len(fails) - 1:
            out.append(f"fails after {a:.1f} h")
        elif k == 0:
            out.append(f"fails before {b:.1f} h")
        else:
            out.append(f"fails between {a:.1f} h and {b:.1f} h")
        k = j + 1
    return out


def _hz(f: float) -> str:
    return f"{1e3 * f:.3g} mHz" if f < 0.1 else f"{f:.3g} Hz"
