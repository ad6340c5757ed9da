"""TDI of telemetry: the data and every TTL regressor through X2, Y2, Z2 (and A, E, T).

:func:`compute_tdi` turns a :class:`~ttlcore.io.telemetry.Telemetry` into a :class:`TDIData`:
``data`` (3, n) and ``regressors`` (3, P, n) for the combinations, sharing the nested delays
between the data and all regressors (the block engine :func:`ttlcore.tdi.engine.tdi_columns`).  :class:`TDIStream` does the same one segment at a time, keeping the
tail of telemetry the nested delays reach back to, so that a day fed in hourly pieces
gives the same result as the whole day.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import fft as sp_fft
from scipy import signal

from ..conventions import COEFFICIENT_NAMES, LINKS
from ..io.telemetry import Telemetry
from .combinations import AET, MICHELSON, aet
from .engine import DEFAULT_DELAY_ORDER, Part, tdi_columns
from .interpolation import DEFAULT_ORDER
from .regressors import ttl_witnesses


@dataclass
class TDIData:
    """TDI outputs of data and regressors over one stretch of time.

    Attributes
    ----------
    t0 : float
        Time of the first sample [s].
    fs : float
        Sampling rate [Hz].
    channels : tuple of str
        ``("X2", "Y2", "Z2")`` or ``("A", "E", "T")``.
    data : ndarray, shape (3, n)
        TDI of ``eta`` (fractional frequency).
    regressors : ndarray, shape (3, P, n)
        TDI of each regressor (fractional frequency per m/rad), so that
        ``data ~ sum_k C_k regressors[:, k]``.
    names : tuple of str
        Regressor (coefficient) names.
    ltt_mean : ndarray, shape (6,)
        Mean light travel times [s], for frequency responses.
    """

    t0: float
    fs: float
    channels: tuple
    data: np.ndarray
    regressors: np.ndarray
    names: tuple = COEFFICIENT_NAMES
    ltt_mean: np.ndarray = field(default_factory=lambda: np.full(6, np.nan))

    @property
    def size(self) -> int:
        return self.data.shape[-1]

    @property
    def t(self) -> np.ndarray:
        return self.t0 + np.arange(self.size) / self.fs

    def to_aet(self) -> TDIData:
        """A, E, T from X2, Y2, Z2."""
        if self.channels == AET:
            return self
        return replace(self, channels=AET, data=aet(self.data), regressors=aet(self.regressors))

    def valid_slice(self) -> slice:
        """Samples where data and all regressors are finite (delays inside the data)."""
        ok = np.isfinite(self.data).all(axis=0) & np.isfinite(self.regressors).all(axis=(0, 1))
        idx = np.flatnonzero(ok)
        return slice(int(idx[0]), int(idx[-1]) + 1) if idx.size else slice(0, 0)

    def slice(self, sl: slice) -> TDIData:
        start, stop, _ = sl.indices(self.size)
        return replace(
            self,
            t0=self.t0 + start / self.fs,
            data=self.data[:, start:stop],
            regressors=self.regressors[:, :, start:stop],
        )

    def decimated(
        self,
        factor: int = 2,
        passband: float = 0.9,
        stopband: float = 1.1,
        attenuation_db: float = 180.0,
        workers: int | None = -1,
    ) -> TDIData:
        """Anti-alias low-pass and decimation of data and regressors alike (the paper fits at
        2 Hz after such a filter).

        A causal Kaiser-window FIR (``passband`` to ``stopband`` Hz, ``attenuation_db``) is
        applied and every ``factor``-th sample kept; ``t0`` moves back by the filter's group
        delay.  Besides aliasing, the filter removes what TDI leaves above 1 Hz (laser noise
        that order-31 interpolation near Nyquist cannot cancel), which would otherwise leak
        into the fit band of segment FFTs.  The filter is linear and the same for data and
        regressors, so the TTL model stays exact.  ``workers``: FFT threads
        (:func:`lowpass_decimate`).
        """
        h = lowpass_taps(self.fs, passband, stopband, attenuation_db)
        data, regs = lowpass_decimate([self.data, self.regressors], h, factor, workers)
        return replace(self, t0=self.t0 - (h.size - 1) / 2 / self.fs, fs=self.fs / factor, data=data, regressors=regs)

    def model(self, coefficients: np.ndarray) -> np.ndarray:
        """``sum_k C_k regressors[:, k]``: the TTL model in TDI, shape (3, n)."""
        return np.einsum("k,ckn->cn", np.asarray(coefficients), self.regressors)


def lowpass_taps(fs: float, passband: float = 0.9, stopband: float = 1.1, attenuation_db: float = 180.0) -> np.ndarray:
    """Kaiser-window low-pass FIR taps (odd length, linear phase)."""
    numtaps, beta = signal.kaiserord(attenuation_db, (stopband - passband) / (fs / 2))
    numtaps |= 1
    return signal.firwin(numtaps, (passband + stopband) / 2, window=("kaiser", beta), fs=fs)


def lowpass_decimate(arrays, taps: np.ndarray, factor: int, workers: int | None = -1) -> list[np.ndarray]:
    """Series through the causal FIR ``taps`` and decimated by ``factor`` along the last axis
    (:meth:`TDIData.decimated`); NaN samples count as zero, and an output that a NaN sample
    reaches is NaN in every array (a sample time where any series is not finite).

    Parameters
    ----------
    arrays : list of ndarray
        Series of one length ``n`` on one time grid, shapes ``(..., n)``.
    taps : ndarray
        FIR taps (:func:`lowpass_taps`).
    factor : int
        Decimation factor.
    workers : int or None
        FFT threads (scipy.fft's: -1 one per core, None the calling thread's default); each
        row is transformed alone, so the result does not depend on it.

    Returns
    -------
    list of ndarray
        Shapes ``(..., len(range(0, n, factor)))``: output ``i`` is the convolution at
        input sample ``factor * i``.
    """
    n = arrays[0].shape[-1]
    nfft = sp_fft.next_fast_len(n + taps.size - 1, real=True)
    response = sp_fft.rfft(taps, nfft)

    def filt(x):  # causal linear convolution by FFT (exact: nfft covers the full length)
        rows = x.reshape(-1, n)
        out = np.empty((rows.shape[0], len(range(0, n, factor))))
        for r0 in range(0, rows.shape[0], 8):  # a few rows at a time: bounded temporaries
            chunk = np.nan_to_num(rows[r0 : r0 + 8], nan=0.0)  # NaN (delays before the data) -> 0, flagged below
            spec = sp_fft.rfft(chunk, nfft, axis=-1, workers=workers)
            del chunk
            spec *= response
            out[r0 : r0 + 8] = sp_fft.irfft(spec, nfft, axis=-1, workers=workers)[..., :n:factor]
        return out.reshape(x.shape[:-1] + (out.shape[-1],))

    ok = np.ones(n, dtype=bool)
    for x in arrays:
        ok &= np.isfinite(x).reshape(-1, n).all(axis=0)
    spoiled = np.convolve((~ok).astype(float), np.ones(taps.size))[:n:factor] > 0  # outputs touched by NaN input
    out = []
    for x in arrays:
        y = filt(x)
        y[..., spoiled] = np.nan
        out.append(y)
    return out


def history_samples(
    fs: float,
    ltt_max: float = 8.6,
    order: int = DEFAULT_ORDER,
    delay_order: int = DEFAULT_DELAY_ORDER,
    combinations=MICHELSON,
) -> int:
    """Input samples the combinations reach back to: the longest chain plus the Tx
    pre-delay, times the largest light travel time, plus the stencils of both
    interpolations (chain and pre-delay) and of the delay interpolation."""
    longest = max(c.max_chain_length for c in combinations) + 1
    return int(np.ceil(longest * ltt_max * fs)) + 2 * (order // 2 + 1) + delay_order + 8


def compute_tdi_arrays(
    eta,
    dws_phi,
    dws_eta,
    ltt,
    fs: float,
    t0: float,
    *,
    history: int = 0,
    names=COEFFICIENT_NAMES,
    order: int = DEFAULT_ORDER,
    delay_order: int = DEFAULT_DELAY_ORDER,
    combinations=MICHELSON,
) -> TDIData:
    """TDI of ``eta`` and of the regressors ``names``, on arrays whose first ``history``
    samples precede the output (``t0`` is the time of the first output sample).

    One call of the block engine :func:`ttlcore.tdi.engine.tdi_columns`: column 0 is
    ``eta`` (one part per link), column ``1 + k`` the witness of regressor ``k`` on its link
    (Tx witnesses pre-delayed at every input sample first, :func:`ttlcore.tdi.engine.predelayed`)."""
    witnesses, index = ttl_witnesses(dws_phi, dws_eta, names)
    eta = np.asarray(eta)
    parts = [Part(0, link, (), eta[k]) for k, link in enumerate(LINKS)]
    for (link, extra), w in witnesses.items():
        parts += [Part(1 + k, link, extra, row) for row, k in zip(w, index[(link, extra)])]
    out = tdi_columns(
        parts, 1 + len(names), ltt, fs, history=history, combinations=combinations, order=order, delay_order=delay_order
    )
    return TDIData(
        t0=float(t0),
        fs=float(fs),
        channels=tuple(cb.name for cb in combinations),
        data=out[:, 0],
        regressors=out[:, 1:],
        names=tuple(names),
        ltt_mean=np.nanmean(np.asarray(ltt)[:, history:], axis=-1),
    )


def compute_tdi(
    tm: Telemetry,
    names=COEFFICIENT_NAMES,
    order: int = DEFAULT_ORDER,
    delay_order: int = DEFAULT_DELAY_ORDER,
    combinations=MICHELSON,
) -> TDIData:
    """TDI of a whole telemetry stretch; the first ~70 s are NaN (delays reach before the data)."""
    return compute_tdi_arrays(
        tm.eta,
        tm.dws_phi,
        tm.dws_eta,
        tm.ltt,
        tm.fs,
        tm.t0,
        history=0,
        names=names,
        order=order,
        delay_order=delay_order,
        combinations=combinations,
    )


class TDIStream:
    """Streaming TDI: feed consecutive telemetry segments, get TDI for each segment's samples.

    The stream keeps the last :func:`history_samples` samples of ``eta``, DWS and delays,
    so its output equals :func:`compute_tdi` on the concatenated telemetry (to rounding),
    except that the very first segment starts with NaN like the batch result.
    """

    def __init__(
        self,
        names=COEFFICIENT_NAMES,
        order: int = DEFAULT_ORDER,
        delay_order: int = DEFAULT_DELAY_ORDER,
        combinations=MICHELSON,
        ltt_max: float = 8.6,
    ):
        self.names = tuple(names)
        self.order = order
        self.delay_order = delay_order
        self.combinations = combinations
        self.ltt_max = ltt_max
        self._tail: Telemetry | None = None
        self.next_t0: float | None = None

    def reset(self) -> None:
        """Forget the tail (after a gap); the next segment starts like a first one."""
        self._tail = None
        self.next_t0 = None

    def push(self, tm: Telemetry) -> TDIData:
        """TDI for the samples of ``tm`` (which must follow the previous segment)."""
        fs = tm.fs
        hist = history_samples(
            fs, max(self.ltt_max, float(np.max(tm.ltt))), self.order, self.delay_order, self.combinations
        )
        if self._tail is not None:
            expected = self.next_t0
            assert expected is not None  # set with the tail
            if abs(tm.t0 - expected) > 0.5 / fs or tm.fs != self._tail.fs:
                raise ValueError(f"segment at t0={tm.t0} does not follow the previous one (expected t0={expected})")
            tail = self._tail
            arrays = [
                np.concatenate([getattr(tail, k), getattr(tm, k)], axis=1) for k in ("eta", "dws_phi", "dws_eta", "ltt")
            ]
            h = tail.size
        else:
            arrays = [tm.eta, tm.dws_phi, tm.dws_eta, tm.ltt]
            h = 0
        eta, dws_phi, dws_eta, ltt = arrays
        out = compute_tdi_arrays(
            eta,
            dws_phi,
            dws_eta,
            ltt,
            fs=fs,
            t0=tm.t0,
            history=h,
            names=self.names,
            order=self.order,
            delay_order=self.delay_order,
            combinations=self.combinations,
        )
        keep = min(hist, arrays[0].shape[-1])
        self._tail = Telemetry(
            t0=tm.t0 + tm.duration - keep / fs,
            fs=fs,
            eta=eta[:, -keep:].copy(),
            dws_phi=dws_phi[:, -keep:].copy(),
            dws_eta=dws_eta[:, -keep:].copy(),
            ltt=ltt[:, -keep:].copy(),
        )
        self.next_t0 = tm.t0 + tm.size / fs
        return out
