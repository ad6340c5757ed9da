"""Spectral estimates: segment FFTs for the fit, the Welch ASD (the one estimator of the
package: figures, scenarios, monitor), log-frequency averaging for plots and the
log-averaged displacement ASD that figures and the monitor draw.

Normalisation of :func:`segment_fft`: for a stationary series with one-sided PSD ``S(f)``,

    X(f_k) = sqrt(2 / (fs * sum(w^2))) * sum_n w_n x_n exp(-2 pi i k n / N)

has ``E|X(f_k)|^2 = S(f_k)`` (away from leakage), so cross-spectral matrices of ``X`` are
directly in PSD units and ``X^H S^-1 X`` is a chi^2-like quantity.
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sp_fft
from scipy import signal

from ..conventions import ffd_to_displacement_asd


def window(name: str, n: int) -> np.ndarray:
    """Window of length ``n``: ``"rect"``, ``"hann"``, ``"tukey:<alpha>"``, or any scipy name."""
    if name in ("rect", "boxcar", "none"):
        return np.ones(n)
    if name.startswith("tukey"):
        alpha = float(name.split(":", 1)[1]) if ":" in name else 0.1
        return signal.windows.tukey(n, alpha)
    return signal.get_window(name, n, fftbins=True)


def segment_fft(x: np.ndarray, fs: float, win: np.ndarray, workers: int | None = -1) -> tuple[np.ndarray, np.ndarray]:
    """Windowed, PSD-normalised rFFT along the last axis.

    ``workers``: threads of the transform (scipy.fft's: -1 one per core; None the calling
    thread's default, ``scipy.fft.set_workers``, 1 unless set).  The transforms of a batch
    are split between the threads, so the result does not depend on it; code that already
    runs in several threads (the diagnosis' candidates) asks for one.

    Returns
    -------
    f : ndarray, shape (n // 2 + 1,)
    X : ndarray, shape (..., n // 2 + 1), complex
    """
    x = np.asarray(x)
    n = x.shape[-1]
    return sp_fft.rfftfreq(n, 1 / fs), psd_scale(fs, win) * sp_fft.rfft(x * win, axis=-1, workers=workers)


def psd_scale(fs: float, win: np.ndarray) -> float:
    """The factor of :func:`segment_fft`, ``sqrt(2 / (fs sum(win^2)))``: ``|X|^2`` of the
    scaled transform of a series windowed by ``win`` is its one-sided PSD [unit^2/Hz]."""
    return np.sqrt(2.0 / (fs * np.sum(win**2)))


def default_nperseg(n: int, fs: float, max_seconds: float = 16384.0) -> int:
    """Welch segment: 2^16 samples at 4 Hz (4.6 h) or the largest power of two giving at
    least three half-overlapping segments."""
    cap = int(2 ** np.floor(np.log2(max(max_seconds * fs, 16))))
    fit = int(2 ** np.floor(np.log2(max(n / 2, 16))))
    return max(16, min(cap, fit))


def welch_asd(x, fs: float, nperseg: int | None = None, window_name: str = "hann"):
    """One-sided Welch ASD (50 % overlap) along the last axis; returns ``(f, asd)``.

    Samples (columns) that are not finite in every row are dropped first.  Each segment
    loses its *window-weighted* mean: scipy's default ``detrend="constant"`` removes the
    plain mean, which for TDI outputs (no power at DC, large power at high frequency) is
    dominated by the segment edges' high-frequency content; the window then leaks that
    spurious offset into the first bins, which after the ``1/f`` displacement conversion
    stand orders of magnitude above the true ASD.  The weighted mean zeroes the windowed
    DC exactly instead.

    Parameters
    ----------
    x : array_like, shape (..., n)
    fs : float
        Sampling rate [Hz].
    nperseg : int, optional
        Segment length in samples (default: the whole series).
    window_name : str
        scipy window name.
    """
    x = np.asarray(x)
    x = x[..., np.all(np.isfinite(np.atleast_2d(x)), axis=0)] if x.ndim > 1 else x[np.isfinite(x)]
    nperseg = int(min(nperseg or x.shape[-1], x.shape[-1]))
    w = signal.get_window(window_name, nperseg)
    w = w / w.sum()

    def detrend(seg):
        return seg - np.tensordot(seg, w, axes=(-1, 0))[..., None]

    f, p = signal.welch(x, fs=fs, window=window_name, nperseg=nperseg, noverlap=nperseg // 2, detrend=detrend, axis=-1)
    return f, np.sqrt(p)


def log_average(f: np.ndarray, y: np.ndarray, per_decade: int = 40, fmin: float | None = None):
    """Average ``y`` (PSD or ASD^2-like, last axis over ``f``) in log-spaced frequency bins.

    Used for plots: at low frequency each bin keeps its own value, at high frequency many
    bins are averaged.  Returns ``(f_centres, y_averaged)`` for non-empty bins.
    """
    f = np.asarray(f)
    y = np.asarray(y)
    pos = f > 0
    fmin = fmin or f[pos][0]
    edges = 10 ** np.arange(np.log10(fmin), np.log10(f[-1]) + 1 / per_decade, 1 / per_decade)
    idx = np.digitize(f, edges)
    fc, out = [], []
    for k in np.unique(idx[pos]):
        sel = pos & (idx == k)
        fc.append(np.exp(np.mean(np.log(f[sel]))))
        out.append(np.mean(y[..., sel], axis=-1))
    return np.array(fc), np.moveaxis(np.array(out), 0, -1)


def log_displacement_asd(f: np.ndarray, psd: np.ndarray, per_decade: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A fractional-frequency PSD [1/Hz] on ``f`` (no DC), log-averaged (:func:`log_average`,
    on the PSD) and converted to a displacement ASD [m/sqrt(Hz)]: ``(f_centres, asd)``."""
    fc, p = log_average(f, psd, per_decade=per_decade)
    return fc, ffd_to_displacement_asd(np.sqrt(p), fc)


def displacement_asd(
    x, fs: float, nperseg: int | None = None, per_decade: int = 40
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Log-averaged displacement ASD of a fractional-frequency series (a TDI channel).

    Welch (:func:`welch_asd`, segments of ``nperseg`` samples, default
    :func:`default_nperseg`), the DC bin dropped, then :func:`log_displacement_asd`.

    Returns
    -------
    f : ndarray
        Centres of the log-spaced bins [Hz].
    asd : ndarray
        Displacement ASD [m/sqrt(Hz)] there.
    f_welch : ndarray
        The Welch grid without DC, for curves that must be averaged on the same bins.
    """
    x = np.asarray(x, dtype=float)
    f, a = welch_asd(x, fs, nperseg or default_nperseg(x.shape[-1], fs))
    fc, asd = log_displacement_asd(f[1:], a[..., 1:] ** 2, per_decade)
    return fc, asd, f[1:]


def longest_run(ok: np.ndarray) -> slice:
    """The longest run of True in a 1-D boolean mask, as a slice (empty when there is none).

    For spectra of series with gaps: splicing the valid stretches together would put a step
    in the series and leak its power over the band.
    """
    ok = np.asarray(ok, dtype=bool)
    if ok.all():
        return slice(0, ok.size)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
    if edges.size == 0:
        return slice(0, 0)
    starts, stops = edges[::2], edges[1::2]
    k = int(np.argmax(stops - starts))
    return slice(int(starts[k]), int(stops[k]))


def smooth_csd(csd: np.ndarray, half_width: int) -> np.ndarray:
    """Running mean of a (m, k, k) cross-spectral matrix over ``2 half_width + 1`` bins."""
    if half_width <= 0:
        return csd
    kernel = np.ones(2 * half_width + 1)
    num = signal.oaconvolve(csd, kernel[:, None, None], mode="same", axes=0)
    den = np.convolve(np.ones(csd.shape[0]), kernel, mode="same")
    return num / den[:, None, None]


def smooth_csd_variable(csd: np.ndarray, half_widths: np.ndarray) -> np.ndarray:
    """Running mean of a (m, k, k) matrix over bins ``[i - w_i, i + w_i]`` (clipped to the
    data), with a half-width ``w_i`` per bin (e.g. growing with frequency)."""
    m = csd.shape[0]
    w = np.asarray(half_widths, dtype=int)
    lo = np.clip(np.arange(m) - w, 0, m)
    hi = np.clip(np.arange(m) + w + 1, 0, m)
    cs = np.concatenate([np.zeros((1,) + csd.shape[1:], dtype=csd.dtype), np.cumsum(csd, axis=0)])
    return (cs[hi] - cs[lo]) / (hi - lo)[:, None, None]
