"""Stationary Gaussian noise with any one-sided ASD: reproducible, random-access, streamable.

A :class:`NoiseStream` is an infinite, stationary Gaussian time series (one or several
independent channels) whose one-sided PSD is ``asd(f)^2`` (any callable ASD model, e.g.
those of :mod:`ttlcore.sim.noise_models`).  ``get(start, stop)`` returns the samples with
ABSOLUTE indices ``start .. stop - 1`` (negative indices are fine: the noise exists
before ``t0``), and the numbers do not depend on how the series is read: in one piece,
in chunks of any size, in any order, by a fresh or a long-lived stream.  Memory is
bounded by the filter length, never by the span read.

Method
------
1. **FIR filter, designed once per stream** (:class:`NoiseFilter`).  The target response
   on the rfft grid ``f_k = k fs / N`` of a length-``N`` impulse response is
   ``H(f_k) = sqrt(S(f_k) fs / 2)`` with ``S = asd^2`` (unit-variance white noise through
   ``H`` has one-sided PSD ``2 |H|^2 / fs = S``).  Its inverse rfft is a zero-phase
   (symmetric) impulse response; a circular shift by ``N/2`` makes it causal (a pure
   delay, irrelevant for stationary noise), and a cosine taper on the outer
   :data:`TAPER_FRACTION` of the span (12.5 % at each end) brings the ends smoothly to
   zero to limit truncation ripple.

2. **Low-frequency regularisation.**  Red models (laser ``f^-2``, test mass ``f^-2``,
   jitter velocities ``f^-1`` in ASD) diverge at ``f -> 0``, and a finite filter cannot
   reproduce them there.  The ASD is therefore evaluated at the smooth effective
   frequency ``f_eff = (f^4 + fmin^4)^(1/4)``: ``asd(f_eff) = asd(f)`` to a relative
   ``(fmin/f)^4 / 4`` times the log-slope (2.5e-5 times the slope at ``f = 10 fmin``),
   and the ASD levels off smoothly below ``fmin`` (default 1e-5 Hz, a tenth of the lowest
   analysis frequency 0.1 mHz).  Unlike a hard ``asd(max(f, fmin))``, whose kink makes an
   impulse response decaying only like ``1/t^2``, ``f_eff`` is analytic on the real axis;
   its nearest complex singularities (``f^4 = -fmin^4``) lie at ``|Im f| = fmin/sqrt(2)``,
   so the impulse response decays like ``exp(-sqrt(2) pi fmin |t|)``.

3. **Filter length.**  ``N`` is the smallest power of two with ``N >= 2.5 fs / fmin``
   (:func:`default_filter_length`): ``2^20`` at 4 Hz (3.0 days) and ``2^22`` at 16 Hz.
   Each half of the response then spans at least ``1.25 / fmin``, i.e. 5.5 decay times
   ``1 / (sqrt(2) pi fmin)`` of step 2, at whose end the envelope is below ``4e-3`` of its
   peak and beyond which lies only ~1e-5 of the filter energy; the frequency grid ``fs / N`` (3.8 uHz at 4 Hz) resolves the 1e-5 Hz corner.
   The realised response (:meth:`NoiseFilter.response_psd`) matches the model PSD to
   better than 1 % from 0.1 mHz to Nyquist for every model of
   :data:`ttlcore.sim.noise_models.MODELS` (checked by the tests).

4. **White noise indexed by absolute sample number.**  The sample axis is cut into
   fixed blocks of :data:`WHITE_BLOCK` = 2^16 samples; block ``k`` of channel ``c`` is
   drawn by ``np.random.default_rng(SeedSequence([seed, crc32(key), c, zigzag(k)]))``
   (``zigzag`` maps ..., -2, -1, 0, 1, ... to 3, 1, 0, 2, ... so negative blocks work).
   Any sample is thus reachable without generating its predecessors, and different
   keys, seeds and channels give independent streams.  The block size does not depend on
   the filter, so the white noise of a (seed, key, channel) is the same for any design.

5. **Block convolution.**  The output axis is cut into fixed blocks of ``B`` samples
   aligned on an absolute grid (``B = N/2`` by default; block 0 starts at
   ``block_origin = -B/16``, 2.3 h before sample 0 at 4 Hz, so that reading day 0 with a
   short history margin touches a single block).  Output block ``b`` is computed
   by overlap-save: the ``M = next_fast_len(N + B - 1)`` white samples ending where the
   block ends go through one rfft, a product with the filter spectrum (computed once per
   stream, shared by all channels) and one irfft (``scipy.fft``, ``workers=-1``,
   channels vectorised in batches); the last ``B`` outputs are free of circular wrap.
   A block is a deterministic function of its index, computed by exactly the same
   operations whatever the reading pattern, so chunk-size invariance is exact (bit for
   bit, not merely to FFT round-off).  The most recent ``cache_blocks`` output blocks
   (default 2) and the white blocks overlapping the next block's input span are kept,
   so sequential reads compute every block once and generate every white sample once.

Why not something else: frequency-domain synthesis of a whole series needs the whole
span in memory and cannot be continued; IIR filtering (lisainstrument's approach)
handles only rational/power-law shapes, needs a burn-in and sequential state, so it
cannot give random access.  The FIR route accepts any ASD callable, is exactly
stationary from sample ``-inf``, and costs ``O(log N)`` per sample.

Block size trade-off: ``B = N/2`` (1.5 days at 4 Hz, FFT length ``1.5 N``) costs about
1.5 times the FFT work per output sample of ``B = N`` (``M / B`` = 3 instead of 2) but
halves the granularity and the memory; reading one day
at 4 Hz computes one or two 1.5-day blocks.  Persistent memory per channel is about
``N + 2^16`` cached white samples plus ``cache_blocks * B`` outputs (17 MB at 4 Hz,
67 MB at 16 Hz), plus batch temporaries of about ``3 M`` floats per channel of a batch
and the shared filter spectrum (``M/2`` complex), independent of the span read.
A run shorter than ``B`` (the simulator knows its length) takes the smallest block that
holds it (:func:`run_block_length`): one FFT of ``N + B`` instead of ``1.5 N`` per channel,
and no white noise kept for a next block; a 2-h simulation then costs 7.4 s of CPU and
0.8 GB instead of 12 s and 1.7 GB.  The FFT of one filter length per channel remains: the
1e-5 Hz corner needs ``N`` = 3 days of taps at 4 Hz whatever the run's length.
"""

from __future__ import annotations

import logging
import math
import operator
import os
import zlib
from collections import OrderedDict
from collections.abc import Callable

import numpy as np
import scipy.fft as sfft

logger = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_FMIN",
    "WHITE_BLOCK",
    "FILTER_SPAN",
    "TAPER_FRACTION",
    "default_filter_length",
    "run_block_length",
    "regularized_frequency",
    "key_hash",
    "NoiseFilter",
    "NoiseStream",
    "generate",
]

#: Default frequency [Hz] below which the ASD is levelled off.
DEFAULT_FMIN = 1e-5
#: Size of the white-noise blocks drawn from one seed sequence [samples].
WHITE_BLOCK = 2**16
#: The default filter length covers at least ``FILTER_SPAN / fmin`` seconds.
FILTER_SPAN = 2.5
#: Fraction of the impulse response (both ends together) under the cosine taper.
TAPER_FRACTION = 0.25
#: Upper bound on the number of float64 elements per channel batch of one FFT.
BATCH_ELEMENTS = 2**23


def default_filter_length(fs: float, fmin: float = DEFAULT_FMIN) -> int:
    """Smallest power of two ``N >= FILTER_SPAN * fs / fmin`` (at least 16).

    Parameters
    ----------
    fs : float
        Sampling frequency [Hz].
    fmin : float
        Regularisation frequency [Hz].

    Returns
    -------
    int
        ``2^20`` at 4 Hz and ``2^22`` at 16 Hz for the default ``fmin = 1e-5`` Hz.
    """
    n = FILTER_SPAN * float(fs) / float(fmin)
    return max(16, 1 << int(math.ceil(math.log2(n))))


def run_block_length(n_samples: int, filter_length: int, margin: int = 0) -> int:
    """Output block size ``B`` for a run of ``n_samples`` read from sample 0 (with up to
    ``margin`` samples more on either side): the default ``filter_length // 2`` for long
    runs, and for shorter ones the smallest multiple of 4096 whose block 0 holds the whole
    run, so that a 2-h run does not pay for FFTs of 1.5 filter lengths (4.5 days at 4 Hz).

    Only the cost depends on ``B``: every output sample is the same convolution of the same
    white samples whatever the block size, equal to floating-point rounding (~1e-16 relative)
    between two sizes, and bit for bit across reading patterns for one size.

    Parameters
    ----------
    n_samples : int
        Samples of the run at the stream's rate.
    filter_length : int
        Taps of the stream's filter (``N``).
    margin : int
        Samples read before 0 (delay history) and after the end.
    """
    default = max(1, filter_length // 2)
    # block 0 spans [-(B // 16), B - B // 16): B // 16 >= margin before 0, 15/16 B >= the rest
    need = max(16 * margin, -(-(n_samples + 2 * margin) * 16 // 15))
    return min(default, -(-need // 4096) * 4096)


def regularized_frequency(f, fmin: float):
    """Smooth effective frequency ``(f^4 + fmin^4)^(1/4)`` at which the ASD is evaluated."""
    f = np.asarray(f, dtype=float)
    return (f**4 + float(fmin) ** 4) ** 0.25


def key_hash(key: str) -> int:
    """Stable 32-bit hash (CRC-32 of the UTF-8 bytes) of a stream key."""
    return zlib.crc32(str(key).encode("utf-8")) & 0xFFFFFFFF


def _zigzag(k: int) -> int:
    """Map any integer to a non-negative one, bijectively (0, -1, 1, -2, ... -> 0, 1, 2, 3, ...)."""
    return 2 * k if k >= 0 else -2 * k - 1


def _taper(n: int, fraction: float) -> np.ndarray:
    """Window of length ``n``, symmetric about ``n/2``: 1 in the middle, cosine to 0 at the ends."""
    d = np.abs(np.arange(n) - n // 2) / (n / 2.0)  # 0 at the centre, 1 at index 0
    w = np.ones(n)
    if fraction > 0:
        edge = 1.0 - fraction
        outer = d > edge
        w[outer] = 0.5 * (1.0 + np.cos(np.pi * (d[outer] - edge) / fraction))
    return w


class NoiseFilter:
    """FIR filter that turns unit-variance white noise into noise of a given ASD.

    Parameters
    ----------
    asd : callable
        One-sided ASD model, ``asd(f)`` for an array of frequencies ``f > 0`` [Hz].
    fs : float
        Sampling frequency [Hz].
    fmin : float
        Regularisation frequency [Hz]: the ASD is evaluated at
        ``(f^4 + fmin^4)^(1/4)`` (see the module docstring).
    length : int, optional
        Number of taps ``N`` (even); :func:`default_filter_length` by default.
    taper : float
        Fraction of the impulse response under the cosine taper (0 disables it).

    Attributes
    ----------
    taps : ndarray, shape (N,)
        Causal impulse response (peak at index ``N/2``).
    """

    def __init__(
        self,
        asd: Callable,
        fs: float,
        *,
        fmin: float = DEFAULT_FMIN,
        length: int | None = None,
        taper: float = TAPER_FRACTION,
    ):
        fs = float(fs)
        fmin = float(fmin)
        if not (np.isfinite(fs) and fs > 0):
            raise ValueError(f"sampling frequency fs must be positive, got {fs!r}")
        if not (np.isfinite(fmin) and 0 < fmin < fs / 2):
            raise ValueError(f"fmin must be in (0, fs/2) = (0, {fs / 2}) Hz, got {fmin!r}")
        if not callable(asd):
            raise TypeError(f"asd must be a callable ASD model f -> ASD(f), got {type(asd).__name__}")
        if length is None:
            length = default_filter_length(fs, fmin)
        length = operator.index(length)
        if length < 2 or length % 2:
            raise ValueError(f"filter_length must be an even integer >= 2, got {length}")
        if not 0.0 <= taper < 1.0:
            raise ValueError(f"taper fraction must be in [0, 1), got {taper!r}")
        if length < fs / fmin:
            logger.warning(
                "filter length %d covers %.3g s < 1/fmin = %.3g s: the spectrum near fmin will be smeared",
                length,
                length / fs,
                1.0 / fmin,
            )
        self.asd = asd
        self.fs = fs
        self.fmin = fmin
        self.length = length
        self.taper = float(taper)

        f = np.arange(length // 2 + 1) * (fs / length)
        amp = np.broadcast_to(np.asarray(asd(regularized_frequency(f, fmin)), dtype=float), f.shape)
        if not np.all(np.isfinite(amp)) or np.any(amp < 0):
            bad = f[~(np.isfinite(amp) & (amp >= 0))]
            raise ValueError(
                f"ASD model {getattr(asd, '__name__', asd)!r} returned non-finite or negative "
                f"values at {bad.size} frequencies (first {bad[0]:.3g} Hz)"
            )
        h = sfft.irfft(amp * np.sqrt(fs / 2.0), n=length)
        h = np.roll(h, length // 2)
        h *= _taper(length, self.taper)
        self.taps = h
        self._spectra: dict[int, np.ndarray] = {}
        logger.debug("designed FIR noise filter: N=%d (%.3g s), fs=%g Hz, fmin=%g Hz", length, length / fs, fs, fmin)

    def psd(self, f):
        """Target one-sided PSD ``asd(f_eff)^2`` (the model after regularisation)."""
        f = np.asarray(f, dtype=float)
        return np.broadcast_to(np.asarray(self.asd(regularized_frequency(f, self.fmin)), dtype=float), f.shape) ** 2

    def spectrum(self, nfft: int) -> np.ndarray:
        """``rfft(taps, n=nfft)``, cached per ``nfft`` (shared by the streams using this filter)."""
        nfft = operator.index(nfft)
        if nfft < self.length:
            raise ValueError(f"nfft={nfft} shorter than the filter ({self.length} taps)")
        spec = self._spectra.get(nfft)
        if spec is None:
            spec = sfft.rfft(self.taps, n=nfft, workers=-1)
            self._spectra[nfft] = spec
        return spec

    def response_psd(self, oversample: int = 4) -> tuple[np.ndarray, np.ndarray]:
        """One-sided PSD of the filter output for unit white input, ``2 |H(f)|^2 / fs``.

        Parameters
        ----------
        oversample : int
            The response is evaluated on the rfft grid of ``oversample * N`` points.

        Returns
        -------
        f, psd : ndarray
            Frequencies [Hz] (from 0 to Nyquist) and the realised PSD.
        """
        n = operator.index(oversample) * self.length
        h = sfft.rfft(self.taps, n=n, workers=-1)
        return np.arange(h.size) * (self.fs / n), 2.0 * np.abs(h) ** 2 / self.fs


class NoiseStream:
    """Infinite stationary Gaussian noise with a given one-sided ASD, read by absolute index.

    Parameters
    ----------
    asd : callable or NoiseFilter
        One-sided ASD model ``asd(f)`` [unit/sqrt(Hz)], or an already designed
        :class:`NoiseFilter` (then ``fmin`` and ``filter_length`` are ignored) to share
        one design between streams.
    fs : float
        Sampling frequency [Hz].
    seed : int
        Non-negative master seed.
    key : str
        Name of the noise (e.g. ``"laser"``, ``"oms.12"``); streams with different keys
        are independent.
    n_channels : int
        Number of independent channels (channel ``c`` of a stream is independent of the
        other channels and of every other key).
    fmin : float
        Regularisation frequency [Hz] (see the module docstring).
    filter_length : int, optional
        Number of FIR taps ``N``; :func:`default_filter_length` by default.
    block_length : int, optional
        Output block size ``B`` [samples]; ``N // 2`` by default.
    cache_blocks : int
        Number of most recent output blocks kept in memory.
    keep_white : bool
        Keep the white noise that the next output block will reuse (default).  False for a
        stream whose reads fit in one block (:func:`run_block_length`): that white noise
        (``N`` samples per channel, 8 MB at 4 Hz) would never be used again.

    Notes
    -----
    ``get`` is deterministic: the samples at given absolute indices do not depend on the
    reading pattern (see the module docstring).  The white noise relies on numpy's
    ``PCG64``/``SeedSequence`` streams, which numpy keeps stable across versions.
    """

    def __init__(
        self,
        asd,
        fs: float,
        *,
        seed: int,
        key: str,
        n_channels: int = 1,
        fmin: float = DEFAULT_FMIN,
        filter_length: int | None = None,
        block_length: int | None = None,
        cache_blocks: int = 2,
        keep_white: bool = True,
    ):
        if isinstance(asd, NoiseFilter):
            if not math.isclose(asd.fs, float(fs)):
                raise ValueError(f"NoiseFilter designed for fs={asd.fs} Hz used at fs={fs} Hz")
            self.filter = asd
        else:
            self.filter = NoiseFilter(asd, fs, fmin=fmin, length=filter_length)
        try:
            seed = operator.index(seed)
        except TypeError:
            raise TypeError(f"seed must be an integer, got {type(seed).__name__}") from None
        if seed < 0:
            raise ValueError(f"seed must be non-negative, got {seed}")
        if not isinstance(key, str):
            raise TypeError(f"key must be a string, got {type(key).__name__}")
        n_channels = operator.index(n_channels)
        if n_channels < 1:
            raise ValueError(f"n_channels must be >= 1, got {n_channels}")
        n_taps = self.filter.length
        if block_length is None:
            block_length = max(1, n_taps // 2)
        block_length = operator.index(block_length)
        if block_length < 1:
            raise ValueError(f"block_length must be >= 1, got {block_length}")
        cache_blocks = operator.index(cache_blocks)
        if cache_blocks < 1:
            raise ValueError(f"cache_blocks must be >= 1, got {cache_blocks}")

        self.fs = float(fs)
        self.seed = seed
        self.key = key
        self.n_channels = n_channels
        self.block_length = block_length
        self.cache_blocks = cache_blocks
        #: Absolute index at which output block 0 starts.  Slightly negative, so that a read
        #: of the first day with a short history margin (delays, interpolation) before
        #: sample 0 still falls in one block.
        self.block_origin = -(block_length // 16)
        self._key_hash = key_hash(key)
        self.fft_length = sfft.next_fast_len(n_taps + block_length - 1, real=True)
        self._hf = self.filter.spectrum(self.fft_length)
        cpu = os.cpu_count() or 1
        self._batch = max(1, min(n_channels, max(cpu, BATCH_ELEMENTS // self.fft_length)))
        self._blocks: OrderedDict[int, np.ndarray] = OrderedDict()
        self._white: OrderedDict[int, np.ndarray] = OrderedDict()
        # A sequential read reuses only the last M - B white samples of the previous FFT
        # span; blocks are touched in increasing order, so an LRU of that size (+1 for
        # misalignment) keeps exactly them.
        self._white_capacity = -(-(self.fft_length - block_length) // WHITE_BLOCK) + 1 if keep_white else 1

    # -- white noise ----------------------------------------------------------------

    def _white_block(self, k: int) -> np.ndarray:
        blk = self._white.get(k)
        if blk is not None:
            self._white.move_to_end(k)
            return blk
        zk = _zigzag(k)
        blk = np.empty((self.n_channels, WHITE_BLOCK))
        for c in range(self.n_channels):
            rng = np.random.default_rng(np.random.SeedSequence([self.seed, self._key_hash, c, zk]))
            blk[c] = rng.standard_normal(WHITE_BLOCK)
        self._white[k] = blk
        while len(self._white) > self._white_capacity:
            self._white.popitem(last=False)
        return blk

    def white(self, start: int, stop: int, channels: slice = slice(None)) -> np.ndarray:
        """Unit-variance white noise driving the filter, samples ``start .. stop - 1``.

        Parameters
        ----------
        start, stop : int
            Absolute sample indices (may be negative), ``stop >= start``.
        channels : slice
            Channels to return.

        Returns
        -------
        ndarray, shape (n_selected_channels, stop - start)
        """
        start, stop = self._check_range(start, stop)
        n_sel = len(range(self.n_channels)[channels])
        out = np.empty((n_sel, stop - start))
        if stop == start:
            return out
        for k in range(start // WHITE_BLOCK, (stop - 1) // WHITE_BLOCK + 1):
            b0 = k * WHITE_BLOCK
            lo, hi = max(start, b0), min(stop, b0 + WHITE_BLOCK)
            out[:, lo - start : hi - start] = self._white_block(k)[channels, lo - b0 : hi - b0]
        return out

    # -- output blocks --------------------------------------------------------------

    def _compute_block(self, b: int) -> np.ndarray:
        B, M = self.block_length, self.fft_length
        lo = (b + 1) * B + self.block_origin - M
        out = np.empty((self.n_channels, B))
        for c0 in range(0, self.n_channels, self._batch):
            sel = slice(c0, min(self.n_channels, c0 + self._batch))
            x = self.white(lo, lo + M, sel)
            spec = sfft.rfft(x, axis=-1, workers=-1)
            del x
            spec *= self._hf
            y = sfft.irfft(spec, n=M, axis=-1, workers=-1)
            del spec
            out[sel] = y[:, M - B :]
        return out

    def _block(self, b: int) -> np.ndarray:
        blk = self._blocks.get(b)
        if blk is not None:
            self._blocks.move_to_end(b)
            return blk
        blk = self._compute_block(b)
        self._blocks[b] = blk
        while len(self._blocks) > self.cache_blocks:
            self._blocks.popitem(last=False)
        return blk

    @staticmethod
    def _check_range(start, stop) -> tuple[int, int]:
        try:
            start, stop = operator.index(start), operator.index(stop)
        except TypeError:
            raise TypeError(
                f"start and stop must be integers (absolute sample indices), got {start!r}, {stop!r}"
            ) from None
        if stop < start:
            raise ValueError(f"stop ({stop}) must be >= start ({start})")
        return start, stop

    def get(self, start: int, stop: int) -> np.ndarray:
        """Noise samples with absolute indices ``start .. stop - 1`` (sample ``i`` at ``t0 + i / fs``).

        Parameters
        ----------
        start, stop : int
            Absolute sample indices, may be negative; ``stop >= start``.

        Returns
        -------
        ndarray, shape (n_channels, stop - start), float64
        """
        start, stop = self._check_range(start, stop)
        B = self.block_length
        out = np.empty((self.n_channels, stop - start))
        if stop == start:
            return out
        o = self.block_origin
        for b in range((start - o) // B, (stop - 1 - o) // B + 1):
            b0 = b * B + o
            lo, hi = max(start, b0), min(stop, b0 + B)
            out[:, lo - start : hi - start] = self._block(b)[:, lo - b0 : hi - b0]
        return out

    def clear_cache(self) -> None:
        """Drop the cached output and white-noise blocks (results are unchanged)."""
        self._blocks.clear()
        self._white.clear()

    @property
    def cache_nbytes(self) -> int:
        """Bytes held by the output and white-noise caches."""
        return sum(a.nbytes for a in self._blocks.values()) + sum(a.nbytes for a in self._white.values())

    def __repr__(self) -> str:
        return (
            f"NoiseStream(key={self.key!r}, seed={self.seed}, fs={self.fs}, n_channels={self.n_channels}, "
            f"filter_length={self.filter.length}, block_length={self.block_length})"
        )


def generate(asd, fs: float, n: int, *, seed: int, key: str, n_channels: int = 1, start: int = 0, **kw) -> np.ndarray:
    """One-shot noise series: ``NoiseStream(asd, fs, ...).get(start, start + n)``.

    Parameters
    ----------
    asd : callable or NoiseFilter
        One-sided ASD model.
    fs : float
        Sampling frequency [Hz].
    n : int
        Number of samples.
    seed, key, n_channels
        As for :class:`NoiseStream`.
    start : int
        Absolute index of the first sample.
    **kw
        Further :class:`NoiseStream` options (``fmin``, ``filter_length``, ``block_length``).

    Returns
    -------
    ndarray, shape (n_channels, n)
    """
    n = operator.index(n)
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    stream = NoiseStream(asd, fs, seed=seed, key=key, n_channels=n_channels, cache_blocks=1, **kw)
    return stream.get(start, start + n)
