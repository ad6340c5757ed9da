"""Fit of the TTL coupling coefficients in the frequency domain (docs/physics.md, fit).

Model, per frequency bin ``f`` of each segment (A, E, T jointly):

    d(f) = R(f) C + n(f),      n ~ CN(0, S(f)),

with ``d`` the TDI data, ``R`` the 24 regressor columns and ``S`` the 3x3 noise
cross-spectral matrix (segment FFTs normalised so that ``E[n n^H] = S``, see
:mod:`ttlcore.estimate.spectra`).  The complex-Gaussian log-likelihood is

    log L(C) = -sum_f (d - R C)^H S^-1 (d - R C) + const = -(C^T N C - 2 C^T b + dd),

with the sufficient statistics ``N = Re sum R^H S^-1 R``, ``b = Re sum R^H S^-1 d`` and
``dd = sum d^H S^-1 d``: the generalised-least-squares estimate ``C = N^-1 b`` is the exact
posterior mean under a flat prior and ``Cov = (2N)^-1`` its covariance.

Errors in variables: the regressors are built from DWS readouts with readout noise, so
``E[N] = N_true + E`` with ``E_kl = sum_f S_dws(f) Re(T_k^H S^-1 T_l)`` for regressors
``k, l`` made of the same DWS channel (``T`` the TDI response of that channel's noise,
:func:`ttlcore.tdi.regressors.regressor_responses`).  Plain least squares is therefore biased
towards zero; subtracting ``E`` removes the bias: ``C = (N - E)^-1 b``,
``Cov = (2 (N - E))^-1``.

Whitening without knowledge of GW signals: the first pass weights with the analytic
secondary-noise CSD for the actual arms (:func:`ttlcore.estimate.noise_psd.tdi_noise_csd`,
regularised at the response zeros); later passes re-estimate ``S`` from the residual,
averaged over segments and smoothed over neighbouring bins, until the coefficients move by
less than ``tol`` standard deviations.

The statistics are accumulated per segment and per frequency band
(:class:`NormalEquations`, additive), so a rolling one-day fitter can add the newest
segment and drop the oldest, and the batch fit uses exactly the same sums.
"""

# size: the frequency-domain GLS fit as one pipeline - segment spectra, notches, noise CSD,
# weights, errors in variables, the fit and its result - read top to bottom as docs/physics.md
# describes it; the solver is in gls.py, the whitening with the weights in whitening.py.

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage

from ..conventions import COEFFICIENT_NAMES, LINKS
from ..conventions import C as C_LIGHT
from ..tdi.combinations import AET_MATRIX, MICHELSON, link_responses
from ..tdi.data import TDIData
from ..tdi.regressors import dws_channel, placement
from .gls import NormalEquations, sandwich, set_apart, sigma_ratio, solve
from .noise_psd import tdi_noise_csd
from .spectra import segment_fft, smooth_csd, smooth_csd_variable, window
from .sums import band_slices, band_sums, eiv_bands, segment_sums
from .whitening import Whitener, inverse_csd, whiten, whitener

log = logging.getLogger(__name__)

#: Default fit band [Hz] (the paper's).
DEFAULT_BAND = (3e-3, 0.9)
#: DWS readout noise in angle [rad/sqrt(Hz)] (paper appendix, lisainstrument default).
DWS_ASD = 70e-9 / 335


def dws_asd_from_config(config: dict, default: float = DWS_ASD) -> float:
    """DWS readout-noise level [rad/sqrt(Hz)] the telemetry was made with, for the
    errors-in-variables correction: 0 when the source says DWS noise was off.

    Our files: ``config["noises"]["dws"]`` and ``config["jitter"]["dws"]``; lisainstrument
    files: ``config["noises"]["dws"]`` and the metadata's ``dws_asds`` (mean over MOSAs).
    Unknown sources get ``default`` (the paper's 70/335 nrad/sqrt(Hz)).
    """
    noises = config.get("noises") or {}
    if noises.get("dws") is False:
        return 0.0
    if isinstance(config.get("jitter"), dict) and "dws" in config["jitter"]:
        return float(config["jitter"]["dws"])
    asds = (config.get("lisainstrument_metadata") or {}).get("dws_asds")
    if isinstance(asds, dict) and asds:
        return float(np.mean([float(v) for v in asds.values()]))
    if isinstance(asds, (int, float)):
        return float(asds)
    return default


# ---------------------------------------------------------------------------
# Segment spectra
# ---------------------------------------------------------------------------


@dataclass
class SegmentSpectra:
    """Band-limited, PSD-normalised spectra of one segment.

    Attributes
    ----------
    t0 : float
        Start time of the segment [s].
    duration : float
        Segment length [s].
    f : ndarray, shape (m,)
        Frequencies [Hz] inside the band.
    d : ndarray, shape (m, c), complex
        Data spectra (channels A, E, T).
    R : ndarray, shape (m, c, P), complex
        Regressor spectra.
    valid_fraction : float
        Fraction of the segment's samples that were finite (the rest were zeroed).
    """

    t0: float
    duration: float
    f: np.ndarray
    d: np.ndarray
    R: np.ndarray
    valid_fraction: float = 1.0


#: Length of the half-cosine tapers at the edges of a gap inside a segment [s].
GAP_TAPER = 900.0


def gap_taper(ok: np.ndarray, samples: int) -> np.ndarray:
    """Weights that go to zero smoothly into each gap *inside* a segment: 0 in the gap, a
    half-cosine ramp of ``samples`` on each valid side of it, 1 elsewhere.  Gaps touching
    the segment's ends (the delays before the data) are left to the segment window.  A
    sharp edge would multiply the series by a step and leak its (red) low-frequency power
    over the band; the ramp keeps that leakage down (data and regressors get the same
    weights, so the model stays exact)."""
    w = ok.astype(float)
    n = ok.size
    edges = np.flatnonzero(np.diff(np.concatenate([[0], (~ok).astype(np.int8), [0]])))
    ramp = 0.5 * (1 - np.cos(np.pi * (np.arange(1, samples + 1)) / (samples + 1)))  # rising, (0, 1)
    for start, stop in zip(edges[::2], edges[1::2]):
        if start == 0 or stop == n or samples <= 0:
            continue
        a = max(0, start - samples)
        w[a:start] = np.minimum(w[a:start], ramp[::-1][samples - (start - a) :])
        b = min(n, stop + samples)
        w[stop:b] = np.minimum(w[stop:b], ramp[: b - stop])
    return w


def spectra_of_segment(
    data: np.ndarray, regressors: np.ndarray, t0: float, fs: float, band=DEFAULT_BAND, window_name: str = "rect"
) -> SegmentSpectra | None:
    """Spectra of one segment of TDI outputs (data (c, n), regressors (c, P, n)).

    Samples where data or any regressor are not finite (delays reaching before the start of
    the data, a gap in the telemetry) are set to zero in all series alike, which keeps the
    model exact, with tapers of :data:`GAP_TAPER` into the gaps inside the segment
    (:func:`gap_taper`); the PSD normalisation uses the window's power, and the spectra of
    a segment with a gap are scaled by ``sqrt(n_eff / n_eff0)`` (:func:`effective_samples`
    with and without the gap) so that the segment weighs in the fit by the information it
    still holds.  Returns None if less than half is valid.
    """
    n = data.shape[-1]
    ok = np.isfinite(data).all(axis=0) & np.isfinite(regressors).all(axis=(0, 1))
    frac = ok.mean() if n else 0.0
    if frac < 0.5:
        return None
    w = window(window_name, n)
    scale = 1.0
    if not ok.all():
        # the invalid runs at the ends (the delays before the data) are the window's business,
        # as they were: only gaps inside the segment are tapered and cost information
        valid = np.flatnonzero(ok)
        edges = np.zeros(n, dtype=bool)
        edges[valid[0] : valid[-1] + 1] = True
        tapered = w * gap_taper(ok, int(round(GAP_TAPER * fs)))
        if not ok[edges].all():
            scale = np.sqrt(effective_samples(tapered) / effective_samples(w * edges))
        w = tapered
    d = np.where(ok, data, 0.0)
    R = np.where(ok, regressors, 0.0)
    f, D = segment_fft(d, fs, w)
    _, RR = segment_fft(R, fs, w)
    sel = (f >= band[0]) & (f <= band[1])
    D, RR = D[:, sel], RR[:, :, sel]
    if scale != 1.0:  # the information the gap took, out of data and model alike
        D, RR = D * scale, RR * scale
    return SegmentSpectra(
        t0=float(t0),
        duration=n / fs,
        f=f[sel],
        d=D.T.copy(),
        R=np.moveaxis(RR, 2, 0).copy(),
        valid_fraction=float(frac),
    )


def effective_samples(w: np.ndarray) -> float:
    """Effective number of independent samples of a series weighted by ``w``,
    ``(sum w^2)^2 / sum w^4`` (``n`` for the rectangular window).

    The fit's statistics of one segment are, by Parseval, time-domain sums weighted by
    ``w^2``; their variance goes with ``sum w^4`` and the PSD normalisation of
    :func:`ttlcore.estimate.spectra.segment_fft` divides by ``sum w^2``.  A segment with a
    gap, normalised that way, would weigh in the fit as much as a whole one (and its sigmas
    would not grow); :func:`spectra_of_segment` scales its spectra by the square root of
    its effective samples over those of the window without the gap, so that its normal
    equations carry only the information left."""
    w2 = np.square(w)
    return float(np.sum(w2) ** 2 / np.sum(w2**2))


def segment_spectra(
    td: TDIData,
    band=DEFAULT_BAND,
    segment_duration: float = 21600.0,
    window_name: str = "tukey:0.1",
    overlap: float = 0.0,
    decimate: bool = True,
) -> list[SegmentSpectra]:
    """Cut TDI outputs (A, E, T) into segments of ``segment_duration`` overlapping by
    ``overlap`` (Welch's scheme) from the first sample and take their spectra; a trailing
    partial segment is dropped.  With ``decimate`` the outputs are first low-passed and
    decimated to 2 Hz (:meth:`TDIData.decimated`)."""
    td = td.to_aet()
    if decimate and td.fs > 2.0:
        td = td.decimated(int(round(td.fs / 2.0)))
    L = int(round(segment_duration * td.fs))
    hop = max(1, int(round(L * (1 - overlap))))
    out = []
    for s0 in range(0, td.size - L + 1, hop):
        sp = spectra_of_segment(
            td.data[:, s0 : s0 + L], td.regressors[:, :, s0 : s0 + L], td.t0 + s0 / td.fs, td.fs, band, window_name
        )
        if sp is not None:
            out.append(sp)
    if not out:
        raise ValueError(f"no segment of {segment_duration} s with at least half of its samples valid")
    return out


# ---------------------------------------------------------------------------
# Noise models
# ---------------------------------------------------------------------------


def notch_mask(
    f: np.ndarray,
    ltt_mean,
    depth: float = 0.1,
    half_width: int = 20,
    channel_depth: float = 0.3,
    max_half_width: float = 7.5e-3,
) -> np.ndarray:
    """Bins to keep: False near the zeros of the TDI response.

    At those zeros (near multiples of ``c / 4L``, about 30 mHz) signal and noise both
    vanish, so they carry little information, but what the model leaves out fills them: a
    segment's finite resolution leaks power from the neighbouring bins, and the residual
    laser noise of unequal arms does not vanish there. Weighting them by the model would
    overstate their information. A bin is left out when either test finds a zero:

    1. the secondary-noise model summed over A, E and T drops below ``depth`` times its
       running mean over ``2 half_width + 1`` bins (the mean, pulled up by the response's
       peaks, makes the exclusion wide where the resolution is coarse and leakage large);
    2. the model of one channel drops below ``channel_depth`` times the running median of
       that channel over the same bins, the window kept within ``+-max_half_width`` [Hz]
       (and at least two bins either side).

    The second test is needed because with unequal arms the channels' zeros part: above
    ~0.4 Hz the sum no longer dips at a zero of T (or A) alone, while those bins, weighted
    by the model, showed 3-9 times the expected residual power on a simulated null day
    (6-h segments, Keplerian arms) and let a narrow-line candidate (q 300 at 0.72 Hz) look
    significant; bins whose channel model fell to 0.1-0.3 of the median still carried
    1.6-2.6 times the expected power above 0.4 Hz, those above 0.3 at most 1.3 times. It
    uses a median of the log PSD because a mean over a few dozen coarse bins of a spectrum
    as steep as T's at low frequency lies far above its lowest bins, while the median of a
    monotonic stretch is its middle value and a zero a few bins wide does not move it; at
    the ends of ``f`` the log PSD is continued by point reflection (``2 log S_0 - log S_k``,
    monotonic stays monotonic), so that the first and last bins are compared with
    themselves. The limit in Hz keeps the window inside a quarter of the response's period
    on coarse grids (41 bins of a 10-min segment would span two periods).

    ``f`` is a contiguous stretch of a uniform frequency grid [Hz].
    """
    psd = np.real(np.einsum("mii->mi", tdi_noise_csd(f, ltt_mean)))  # (m, 3)
    total = psd.sum(axis=1)
    keep = total >= depth * smooth_csd(total[:, None, None], half_width)[:, 0, 0]
    m = psd.shape[0]
    df = float(f[1] - f[0]) if m > 1 else 1.0
    w = min(half_width, max(2, int(max_half_width / df)), m - 1)
    log_psd = np.log(np.maximum(psd, np.finfo(float).tiny))
    ext = np.concatenate([2 * log_psd[:1] - log_psd[w:0:-1], log_psd, 2 * log_psd[-1:] - log_psd[-2 : -w - 2 : -1]])
    local = ndimage.median_filter(ext, size=(2 * w + 1, 1), mode="nearest")[w : w + m]
    return keep & np.all(log_psd >= np.log(channel_depth) + local, axis=1)


def variance_factor(window_name: str, n: int, overlap: float) -> float:
    """Ratio of the estimator's true variance to the one computed as if all bins and
    segments were independent, for spectra locally flat over a bin.

    The fit statistic ``b = sum_f R^H W d`` of a windowed segment equals, by Parseval, a
    time-domain sum weighted by ``w^2``; its variance involves ``sum w^4`` and, between
    segments overlapping by ``hop``, ``sum w_n^2 w_{n+hop}^2``:

        kappa = n [sum w^4 + 2 sum_j sum_n w_n^2 w_{n + j hop}^2] / (sum w^2)^2 * (1 - overlap)

    which is 1 for the rectangular window without overlap, 1.94 for Hann without overlap
    and 1.14 for Hann with 50 % overlap (against rectangular: 14 % more variance instead of
    the leakage of a rectangular window).
    """
    w = window(window_name, n)
    hop = max(1, int(round(n * (1 - overlap))))
    w2 = w**2
    cross = sum(np.sum(w2[: n - j * hop] * w2[j * hop :]) for j in range(1, -(-n // hop)))
    return float(n * (np.sum(w2**2) + 2 * cross) / np.sum(w2) ** 2 * hop / n)


def regularise(csd: np.ndarray, floor: float = 1e-2, half_width: int = 10) -> np.ndarray:
    """Add ``floor`` times the locally smoothed diagonal, so that response zeros (where the
    model PSD vanishes but data and model may disagree slightly) do not get infinite weight."""
    diag = np.real(np.einsum("mii->mi", csd))
    smooth = smooth_csd(diag[:, :, None], half_width)[:, :, 0]
    out = csd.copy()
    idx = np.arange(csd.shape[1])
    out[:, idx, idx] += floor * smooth
    return out


def model_csd(f: np.ndarray, ltt_mean, s_oms=None, s_acc=None) -> np.ndarray:
    """Analytic secondary-noise CSD of A, E, T for the actual mean arms, regularised."""
    return regularise(tdi_noise_csd(f, ltt_mean, s_oms, s_acc))


def residual_csd(spectra: list[SegmentSpectra], C: np.ndarray, half_widths, stacked: tuple | None = None) -> np.ndarray:
    """Noise CSD re-estimated from the residual ``d - R C``: averaged over segments and
    smoothed over ``2 w + 1`` bins, ``w`` per bin (``half_widths``: int or array)."""
    d, R = stacked if stacked is not None else stack_spectra(spectra)
    r = d - R @ C  # (S, m, c)
    csd = np.einsum("smi,smj->mij", r, r.conj()) / len(spectra)
    w = np.broadcast_to(np.asarray(half_widths, dtype=int), (csd.shape[0],))
    return regularise(smooth_csd_variable(csd, w), floor=1e-6, half_width=int(np.max(w)))


def smoothing_half_widths(f: np.ndarray, fraction: float = 0.02, max_hz: float = 1e-3, min_bins: int = 2) -> np.ndarray:
    """Half-widths (bins) of the residual-CSD running mean: ``fraction * f`` in Hz, at least
    ``min_bins`` and at most ``max_hz``.  A width growing with frequency follows the
    steep low-frequency spectrum without bias and averages more where it is flat."""
    df = float(np.median(np.diff(f)))
    w = np.round(fraction * f / df)
    return np.clip(w, min_bins, max(min_bins, round(max_hz / df))).astype(int)


# ---------------------------------------------------------------------------
# Sufficient statistics
# ---------------------------------------------------------------------------


def default_band_edges(band=DEFAULT_BAND, n_bands: int = 8) -> np.ndarray:
    """Log-spaced band edges over the fit band, for per-band chi^2 and noise levels."""
    return np.geomspace(band[0], band[1] * (1 + 1e-9), n_bands + 1)


def accumulate(
    spectra: list[SegmentSpectra],
    weights: np.ndarray,
    band_edges,
    names,
    eiv_response: list | None = None,
    dws_psd: np.ndarray | None = None,
    stacked: tuple | None = None,
    prepared: Whitener | None = None,
    whitened: tuple | None = None,
) -> NormalEquations:
    """Sum the normal equations of ``spectra`` with per-bin weights ``W = S^-1`` (m, c, c).

    Each bin is whitened with the Cholesky factor ``W = L L^H`` (``x -> L^H x``), after
    which the per-band sums are plain matrix products (:func:`ttlcore.estimate.sums.band_sums`).
    ``eiv_response`` (:func:`eiv_responses`: per DWS channel, the regressors carrying its
    readout noise and their responses (m, c, q)) and ``dws_psd`` (m,) give the
    errors-in-variables term ``E_kl = sum_ch Re sum_f S_dws T_k,ch^H W T_l,ch``.  ``stacked``
    may pass the already stacked ``(d (S, m, c), R (S, m, c, P))``; ``prepared`` the
    :func:`whitener` of these weights (and of ``eiv_response``, ``dws_psd``), when many
    segments are summed with them one by one (the rolling fit's per-segment sums): the same
    numbers, the factor and the errors-in-variables term taken once; ``whitened`` the
    spectra already whitened with them, ``(wd (m, S, c), wR (m, S, c, P))`` (:func:`whiten`).
    """
    f = spectra[0].f
    if prepared is None:
        prepared = whitener(weights, eiv_response, dws_psd)
    if whitened is None:
        d, R = stacked if stacked is not None else stack_spectra(spectra)
        _, wd, wR = whiten(weights, d, R, Lh=prepared.Lh)
    else:
        wd, wR = whitened
    slices = band_slices(f, band_edges)
    return band_sums(wd, wR, slices, names, band_edges, eiv_bands(prepared, slices, len(names)))


def _eiv_channel(name: str):
    """DWS channel ``(mosa, angle)`` of a TTL regressor, None for another name."""
    try:
        return dws_channel(name)
    except ValueError:
        return None


def eiv_parts(names, extra: dict | None = None) -> list[tuple]:
    """Per regressor, the DWS readouts whose noise it carries: a tuple of parts
    ``((mosa, angle), link, extra_delays, response)``, each the plain witness ``-DWS/c`` of
    that channel placed on ``link`` after the delays ``extra_delays`` and filtered by
    ``response`` (``f -> complex``, or None).  The 24 TTL regressors from their names
    (:func:`ttlcore.tdi.regressors.placement`); other regressors (a model's columns) from
    ``extra`` (name -> parts; a name not in it carries none: columns made of products or
    modulations of the readouts, whose bias is second order in the small readout noise)."""
    out = []
    for name in names:
        if _eiv_channel(name) is not None:
            link, delays, mosa, angle = placement(name)
            out.append((((mosa, angle), link, tuple(delays), None),))
        else:
            out.append(tuple((extra or {}).get(name, ())))
    return out


def eiv_responses(f: np.ndarray, ltt_mean, names, extra: dict | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """The regressors' A, E, T responses to the DWS readout noise, by channel.

    For each DWS channel whose noise some regressors carry (:func:`eiv_parts`): their
    positions ``idx`` (q,) and responses ``T`` (m, 3, q), ``T_k = sum_parts -1/c r(f)
    TDI_link,delays(f)`` (:func:`ttlcore.tdi.combinations.link_responses`, static arms; for
    a TTL regressor :func:`ttlcore.tdi.regressors.regressor_responses`).  Regressors of one
    channel share its noise: the errors-in-variables term couples them (a witness of
    ``23.phi`` and the TTL regressors of ``23.phi``), regressors of different channels do not.
    """
    f = np.asarray(f, dtype=float)
    by_channel: dict = {}
    for k, parts in enumerate(eiv_parts(names, extra)):
        for channel, link, delays, response in parts:
            by_channel.setdefault(channel, {}).setdefault(k, []).append((link, tuple(delays), response))
    responses: dict = {}
    out = []
    for columns in by_channel.values():
        idx = np.array(sorted(columns))
        T = np.zeros((f.size, 3, idx.size), dtype=complex)
        for j, k in enumerate(idx):
            for link, delays, response in columns[k]:
                if delays not in responses:  # (3, 6, m): X2, Y2, Z2 per link
                    responses[delays] = np.stack([link_responses(comb, f, ltt_mean, delays) for comb in MICHELSON])
                t = responses[delays][:, LINKS.index(link), :].T * (-1.0 / C_LIGHT)  # (m, 3)
                T[:, :, j] += t if response is None else t * np.asarray(response(f))[:, None]
        out.append((idx, np.einsum("ia,mak->mik", AET_MATRIX, T)))
    return out


def stack_spectra(spectra: list[SegmentSpectra]) -> tuple[np.ndarray, np.ndarray]:
    """``(d (S, m, c), R (S, m, c, P))`` of a list of segment spectra."""
    return np.stack([sp.d for sp in spectra]), np.stack([sp.R for sp in spectra])


# ---------------------------------------------------------------------------
# Results
# ---------------------------------------------------------------------------


@dataclass
class FitResult:
    """Fitted coefficients with honest uncertainties and diagnostics.

    Attributes
    ----------
    names : tuple of str
    coefficients : ndarray (P,)
        [m/rad].
    covariance : ndarray (P, P)
        [m^2/rad^2].
    chi2, dof : float
        Whitened residual power against the final noise model and its degrees of freedom.
    band : tuple
        Fit band [Hz].
    method : str
        ``"gls"``, ``"ols"`` (no whitening iterations, no EIV) or ``"mcmc"``.
    """

    names: tuple
    coefficients: np.ndarray
    covariance: np.ndarray
    chi2: float
    dof: float
    band: tuple
    method: str
    eiv: bool = True
    iterations: int = 0
    converged: bool = True
    band_edges: np.ndarray | None = None
    chi2_per_band: np.ndarray | None = None
    dof_per_band: np.ndarray | None = None
    t_start: float = float("nan")
    t_stop: float = float("nan")
    n_segments: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))

    @property
    def chi2_dof(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else float("nan")

    @property
    def correlation(self) -> np.ndarray:
        s = self.sigma
        return self.covariance / np.outer(s, s)

    def identifiability(self, n_modes: int = 3) -> dict:
        """Condition number of the correlation matrix and its weakest eigen-combinations."""
        live = np.flatnonzero(np.isfinite(self.sigma))  # a column without information: left out
        if live.size == 0:  # nothing determined at all (a window that holds no valid data)
            return {"condition_number": None, "weakest_combinations": []}
        corr = self.correlation[np.ix_(live, live)]
        vals, vecs = np.linalg.eigh(np.linalg.inv(corr))  # small eigenvalue = poorly determined
        modes = []
        for k in range(min(n_modes, len(vals))):
            v = vecs[:, k]
            top = np.argsort(-np.abs(v))[:4]
            modes.append(
                {
                    "relative_information": float(vals[k] / vals[-1]),
                    "combination": {self.names[live[i]]: round(float(v[i]), 3) for i in top},
                }
            )
        return {"condition_number": float(np.linalg.cond(corr)), "weakest_combinations": modes}

    def to_json(self, truth: np.ndarray | None = None) -> dict:
        """The ``fit.json`` content (m/rad; keys ``<mosa>.<phi|eta>.<rx|tx>``)."""
        out = {
            "names": list(self.names),
            "coefficients": dict(zip(self.names, map(float, self.coefficients))),
            "sigma": dict(zip(self.names, map(float, self.sigma))),
            "covariance": self.covariance.tolist(),
            "correlation": self.correlation.tolist(),
            "chi2": float(self.chi2),
            "dof": float(self.dof),
            "chi2_dof": float(self.chi2_dof),
            "band": list(map(float, self.band)),
            "method": self.method,
            "errors_in_variables_corrected": bool(self.eiv),
            "iterations": int(self.iterations),
            "converged": bool(self.converged),
            "window": {"t_start": self.t_start, "t_stop": self.t_stop, "segments": self.n_segments},
            "identifiability": self.identifiability(),
            "units": "m/rad",
        }
        if self.band_edges is not None and self.chi2_per_band is not None and self.dof_per_band is not None:
            out["per_band"] = [
                {
                    "f_lo": float(lo),
                    "f_hi": float(hi),
                    "chi2": float(c),
                    "dof": float(d),
                    "chi2_dof": float(c / d) if d else None,
                }
                for lo, hi, c, d in zip(
                    self.band_edges[:-1], self.band_edges[1:], self.chi2_per_band, self.dof_per_band
                )
            ]
        if truth is not None:
            truth = np.asarray(truth, dtype=float)
            err = self.coefficients - truth
            out["truth"] = dict(zip(self.names, map(float, truth)))
            out["error"] = dict(zip(self.names, map(float, err)))
            out["max_abs_error"] = float(np.max(np.abs(err)))
            out["normalised_chi2"] = float(err @ np.linalg.solve(self.covariance, err))
        out.update(self.extra)
        return out


# ---------------------------------------------------------------------------
# The fit
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class FitSettings:
    """Settings shared by the batch analysis and the streaming fitter."""

    band: tuple = DEFAULT_BAND
    #: FFT segment length [s]; 6 h resolves the TDI response's notches and keeps leakage
    #: from low frequencies out of the band's lowest bins (1 h segments understate the
    #: variance by ~25 %, measured over seeds)
    segment_duration: float = 21600.0
    window: str = "tukey:0.1"
    overlap: float = 0.0
    notch: bool = True
    robust_covariance: bool = True
    eiv: bool = True
    #: most reweighting passes; a fit on one FFT segment (the live fitter's first hour)
    #: contracts slowly, by about a factor 2 per pass from a first step of ~8 sigma, and
    #: needs 10-14 passes to reach ``tol`` (measured over seeds); a day's window needs 4-6
    iterations: int = 25
    #: stop iterating when no coefficient moves by more than this many sigma
    tol: float = 1e-2
    n_bands: int = 8
    #: DWS readout noise [rad/sqrt(Hz)] for the errors-in-variables term; None: the paper's
    #: level (``ttl analyze`` fills it from the telemetry, see :func:`dws_asd_from_config`)
    dws_asd: float | None = None
    #: half-width of the running mean of the residual CSD: this fraction of the frequency,
    #: between 2 bins and ``smooth_max_hz``
    smooth_fraction: float = 0.02
    smooth_max_hz: float = 1e-3
    #: low-pass and decimate TDI outputs to 2 Hz before the segment FFTs (the paper does);
    #: the low-pass also removes the laser noise TDI leaves above 1 Hz, which would leak
    #: into the band (without it sigma grows by ~50 %, measured)
    decimate: bool = True


def fit_spectra(
    spectra: list[SegmentSpectra],
    ltt_mean,
    settings: FitSettings | None = None,
    names=COEFFICIENT_NAMES,
    method: str = "gls",
    eiv_extra: dict | None = None,
    prior_scale: np.ndarray | None = None,
    per_segment: bool = False,
) -> tuple[FitResult, dict]:
    """GLS fit of the coefficients from segment spectra (see the module docstring).

    ``method="ols"`` gives plain least squares for comparison: white weights, no
    errors-in-variables correction, no iterations.  ``prior_scale`` (one per regressor,
    ``inf`` for none): a regressor the data determine worse than that is set apart
    (:func:`ttlcore.estimate.gls.set_apart`: a model's glitch whose FFT segments are left out).

    Returns
    -------
    FitResult
    dict
        Internals: the final ``normal_equations``, ``weights`` (m, c, c) and ``noise_csd``
        on the bins kept, the ``notch`` mask of the bins kept (None without notches), the
        ``eiv_response`` and ``dws_psd`` of the errors-in-variables term, the
        ``band_edges`` and the ``variance_factor`` (what an update with these weights needs,
        see :class:`ttlcore.estimate.rolling.RollingFit`), and the ``whitener`` of the
        weights (:class:`~ttlcore.estimate.whitening.Whitener`).  With ``per_segment``, also
        ``segment_sums``: per segment, its normal equations and sandwich scores under the
        final weights at the estimate (:func:`ttlcore.estimate.sums.segment_sums`, from the
        spectra the last pass whitened).
    """
    s = settings or FitSettings()
    f = spectra[0].f
    edges = default_band_edges(s.band, s.n_bands)
    kappa = variance_factor(s.window, 4096, s.overlap)  # depends on the window's shape only
    if s.notch:
        keep = notch_mask(f, ltt_mean)
        spectra = [
            SegmentSpectra(sp.t0, sp.duration, sp.f[keep], sp.d[keep], sp.R[keep], sp.valid_fraction) for sp in spectra
        ]
        f = f[keep]
    if method == "ols":
        c = spectra[0].d.shape[1]
        W = np.broadcast_to(np.eye(c), (f.size, c, c))
        neq = accumulate(spectra, W, edges, names)
        C, cov_unit = solve(neq, eiv=False, prior_scale=prior_scale)
        chi2 = neq.chi2_per_band(C)
        dof = neq.dof_per_band().sum() - len(names)
        cov = kappa * cov_unit * chi2.sum() / dof  # residual-variance scaled, as OLS reports it
        return _result(names, C, cov, chi2, neq, s, "ols", False, 0, True, spectra), {
            "normal_equations": neq,
            "weights": W,
        }
    T = eiv_responses(f, ltt_mean, names, eiv_extra) if s.eiv else None
    stacked = stack_spectra(spectra)
    half_widths = smoothing_half_widths(f, s.smooth_fraction, s.smooth_max_hz)
    dws_psd = (2 * np.pi * f * (DWS_ASD if s.dws_asd is None else s.dws_asd)) ** 2
    csd = model_csd(f, ltt_mean)
    C_prev, converged, it, change = None, False, 0, np.nan
    for it in range(s.iterations + 1):
        W, whitened = inverse_csd(csd), None  # the last pass's whitened spectra freed first
        prepared = whitener(W, T, dws_psd)
        # the spectra whitened with these weights: summed here, and for the last pass's
        # weights used again by the sandwich and the per-segment sums (no second whitening)
        whitened = whiten(W, *stacked, Lh=prepared.Lh)[1:]
        neq = accumulate(spectra, W, edges, names, prepared=prepared, whitened=whitened)
        C, cov = solve(neq, eiv=s.eiv, prior_scale=prior_scale)
        sig = np.sqrt(np.diag(cov))
        if C_prev is not None:
            change = np.max(np.abs(C - C_prev) / sig)
            log.debug("iteration %d: max coefficient change %.3g sigma", it, change)
            if change < s.tol:
                converged = True
                break
        C_prev = C
        csd = residual_csd(spectra, C, half_widths, stacked=stacked)
    chi2 = neq.chi2_per_band(C, eiv=s.eiv)
    cov_model = kappa * cov
    cov_robust = kappa * sandwich_covariance(spectra, W, C, neq, s.eiv, prior_scale=prior_scale, whitened=whitened)
    res = _result(
        names, C, cov_robust if s.robust_covariance else cov_model, chi2, neq, s, method, s.eiv, it, converged, spectra
    )
    res.extra["variance_factor"] = kappa
    res.extra["last_change_sigma"] = float(change)
    res.extra["covariance_model_based"] = cov_model.tolist()
    res.extra["sigma_ratio_robust_to_model"] = sigma_ratio(cov_robust, cov_model)
    internals = {
        "normal_equations": neq,
        "weights": W,
        "whitener": prepared,
        "noise_csd": csd,
        "notch": keep if s.notch else None,
        "eiv_response": T,
        "dws_psd": dws_psd,
        "band_edges": edges,
        "variance_factor": kappa,
    }
    if per_segment and whitened is not None:
        internals["segment_sums"] = _segment_sums(whitened, C, f, edges, names, prepared)
    return res, internals


def _segment_sums(whitened: tuple, C: np.ndarray, f: np.ndarray, edges, names, prepared: Whitener) -> list:
    """:func:`ttlcore.estimate.sums.segment_sums` of the whitened spectra of a fit."""
    slices = band_slices(f, edges)
    wd, wR = whitened
    return segment_sums(wd, wR, C, slices, names, edges, eiv_bands(prepared, slices, len(names)))


def sandwich_covariance(
    spectra: list[SegmentSpectra],
    weights: np.ndarray,
    C: np.ndarray,
    neq: NormalEquations,
    eiv: bool = True,
    stacked: tuple | None = None,
    prior_scale: np.ndarray | None = None,
    whitened: tuple | None = None,
) -> np.ndarray:
    """Robust (sandwich) covariance of the GLS estimate (regressors set apart by
    ``prior_scale`` as in the estimate, :func:`ttlcore.estimate.gls.set_apart`).

    ``Cov = (N - E)^-1 [sum_{s,f} Re(u) Re(u)^T] (N - E)^-1`` with the per-bin scores
    ``u = R^H W r`` of the residual ``r = d - R C``.  If the weights are the exact inverse
    noise CSD this equals ``(2 (N - E))^-1``; where the noise model is off (smoothing near
    steep spectral features, unmodelled lines) it stays honest.
    """
    N, _, _ = neq.total(eiv)
    return sandwich(set_apart(N, prior_scale), score_matrix(spectra, weights, C, stacked, whitened=whitened))


def score_matrix(
    spectra: list[SegmentSpectra],
    weights: np.ndarray,
    C: np.ndarray,
    stacked: tuple | None = None,
    Lh: np.ndarray | None = None,
    whitened: tuple | None = None,
) -> np.ndarray:
    """``sum_{s,f} Re(u) Re(u)^T`` of the per-bin scores ``u = R^H W (d - R C)`` (the middle
    of :func:`sandwich_covariance`; additive over segments).  ``Lh``: :attr:`Whitener.Lh`
    of ``weights``, when already taken; ``whitened``: the spectra already whitened with
    them, ``(wd, wR)`` as :func:`whiten` returns them."""
    if whitened is not None:
        wd, wR = whitened
    else:
        d, R = stacked if stacked is not None else stack_spectra(spectra)
        _, wd, wR = whiten(weights, d, R, Lh=Lh)
    wr = wd - wR @ C  # whitened residual L^H r, (m, S, c)
    # Re(R^H W r) = Re((L^H R)^H L^H r), one row per bin and segment
    u = (np.einsum("mscp,msc->msp", wR.real, wr.real) + np.einsum("mscp,msc->msp", wR.imag, wr.imag)).reshape(
        -1, C.size
    )
    return u.T @ u


def _result(names, C, cov, chi2_bands, neq, s, method, eiv, it, converged, spectra) -> FitResult:
    dof_bands = neq.dof_per_band().astype(float)
    return FitResult(
        names=tuple(names),
        coefficients=C,
        covariance=cov,
        chi2=float(chi2_bands.sum()),
        dof=float(dof_bands.sum() - len(names)),
        band=tuple(s.band),
        method=method,
        eiv=eiv,
        iterations=it,
        converged=converged,
        band_edges=neq.band_edges,
        chi2_per_band=chi2_bands,
        dof_per_band=dof_bands,
        t_start=spectra[0].t0,
        t_stop=spectra[-1].t0 + spectra[-1].duration,
        n_segments=len(spectra),
    )


def fit_tdi(
    td: TDIData,
    settings: FitSettings | None = None,
    method: str = "gls",
    extra: TDIData | None = None,
    eiv_extra: dict | None = None,
) -> tuple[FitResult, dict]:
    """Fit the coefficients on TDI outputs (any of X/Y/Z or A/E/T; A, E, T are used).

    ``extra``: TDI of further regressors (model effects, :mod:`ttlcore.effects`) on the same
    samples and channels, fitted jointly with ``td``'s (their names follow in the result);
    ``eiv_extra``: the DWS readouts whose noise each of them carries (:func:`eiv_parts`).
    """
    s = settings or FitSettings()
    if extra is not None:
        td = with_extra_regressors(td, extra)
    spectra = segment_spectra(td, s.band, s.segment_duration, s.window, s.overlap, s.decimate)
    res, internals = fit_spectra(spectra, td.ltt_mean, s, td.names, "ols" if method == "ols" else "gls", eiv_extra)
    internals["spectra"] = spectra
    return res, internals


def with_extra_regressors(td: TDIData, extra: TDIData) -> TDIData:
    """``td`` with the regressor columns of ``extra`` appended (same time grid and channels)."""

    if (
        extra.channels != td.channels
        or extra.size != td.size
        or abs(extra.t0 - td.t0) > 0.5 / td.fs
        or extra.fs != td.fs
    ):
        raise ValueError(
            f"extra regressors do not match the TDI data (channels {extra.channels} vs {td.channels}, "
            f"{extra.size} vs {td.size} samples, t0 {extra.t0} vs {td.t0})"
        )
    clash = set(extra.names) & set(td.names)
    if clash:
        raise ValueError(f"extra regressor names already present: {sorted(clash)}")
    return replace(
        td,
        regressors=np.concatenate([td.regressors, extra.regressors], axis=1),
        names=tuple(td.names) + tuple(extra.names),
    )
