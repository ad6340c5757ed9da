"""Filter and derivative numerics of effect columns.

A column may carry a frequency response (a frequency-dependent coupling, applied on the
series' zero-padded FFT grid: :func:`filtered`, :func:`filtered_many`), the rational basis
of ``fd-coupling`` (:func:`rational_basis`, docs/diagnostics.md), the high-order central
finite differences of the shifted-witness effects (:func:`derivative`) and the factor of a
part's readout noise (:func:`readout_noise_factor`, the errors-in-variables term).
"""

from __future__ import annotations

from math import factorial

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view


def filtered(x: np.ndarray, fs: float, response) -> np.ndarray:
    """``x`` through the filter of frequency response ``response(f)``, applied on the
    series' own FFT grid (zero-padded to twice its length: no wrap-around for impulse
    responses shorter than the series).  NaN samples count as zero."""
    return filtered_many(x, fs, [response])[0]


def filtered_many(x: np.ndarray, fs: float, responses, transform: tuple | None = None) -> list[np.ndarray]:
    """``x`` through each filter of ``responses`` (:func:`filtered`), the series'
    transform computed once (or given: ``transform``, :func:`filter_transform` of ``x``,
    for many calls on one series)."""
    f, X, n = transform if transform is not None else filter_transform(x, fs)
    return [np.fft.irfft(X * r(f), 2 * n)[..., :n] for r in responses]


def filter_transform(x: np.ndarray, fs: float) -> tuple[np.ndarray, np.ndarray, int]:
    """The transform :func:`filtered_many` filters ``x`` with: ``(f, X, n)``, the series
    (NaN as zero) zero-padded to twice its length ``n``."""
    x = np.nan_to_num(np.asarray(x, dtype=float))
    n = x.shape[-1]
    nfft = 2 * n
    return np.fft.rfftfreq(nfft, 1.0 / fs), np.fft.rfft(x, nfft), n


# central finite differences (Fornberg): exact for polynomials of degree 2 HALF, close to the
# spectral derivative up to ~0.9 of Nyquist for band-limited series
_FD_HALF = 12


def _fd_weights(order: int, half: int = _FD_HALF) -> np.ndarray:
    j = np.arange(1, half + 1)

    base = np.array([factorial(half) ** 2 / (factorial(half - k) * factorial(half + k)) for k in j]) * (-1.0) ** (j + 1)
    if order == 1:
        c = base / j
        return np.r_[-c[::-1], 0.0, c]
    c = 2 * base / j**2
    return np.r_[c[::-1], -2 * np.sum(c), c]


def derivative(x: np.ndarray, fs: float, order: int = 1) -> np.ndarray:
    """First or second time derivative by a 25-point central difference along the last
    axis; the first and last 12 samples are NaN (they are outside the valid TDI output
    anyway or inside the segment window's taper)."""
    w = _fd_weights(order) * fs**order
    x = np.asarray(x, dtype=float)
    out = np.full(x.shape, np.nan)

    win = sliding_window_view(x, w.size, axis=-1)
    out[..., _FD_HALF:-_FD_HALF] = win @ w
    return out


def derivative_response(f):
    """The time derivative as a filter: ``2 pi i f`` (``f`` [Hz])."""
    return 2j * np.pi * np.asarray(f, dtype=float)


def rational_basis(kind: str, f: np.ndarray, f0: float, q: float | None = None) -> list[np.ndarray]:
    """The frequency-dependent coupling basis: one real pole or one complex pole pair
    with a numerator of full degree, ``x = i f / f0``,

    - ``pole1``: ``1/(1 + x)``, ``x/(1 + x)`` (a first-order path of corner ``f0``: low-pass,
      high-pass and constant couplings are combinations);
    - ``pole2``: ``1/D``, ``x/D``, ``x^2/D`` with ``D = 1 + x/q + x^2`` (a resonance at ``f0``
      of quality factor ``q``: its low-pass, band-pass, high-pass and notch forms and the
      constant coupling ``D/D`` are combinations).

    Any coupling ``H(f)`` that is a ratio of polynomials of that order in ``i f`` is fitted
    linearly once the poles are known; the poles are searched (:data:`Effect.searched`).
    """
    x = 1j * np.asarray(f, dtype=float) / float(f0)
    if kind == "pole1":
        inv = 1.0 / (1.0 + x)
        return [inv, x * inv]
    if q is None:
        raise ValueError(f"a {kind!r} basis needs q")
    inv = 1.0 / (1.0 + x / float(q) + x * x)  # 1/D: one division, the others products
    x_inv = x * inv
    return [inv, x_inv, x * x_inv]


def readout_noise_factor(f, shift):
    """Factor of a part's readout-noise response: a time shift [s] (the phase
    ``exp(2 pi i f shift)``) or a frequency response (m,) of a filtered column."""
    if isinstance(shift, np.ndarray):
        return shift[:, None]
    return np.exp(2j * np.pi * f * shift)[:, None] if shift else 1.0
