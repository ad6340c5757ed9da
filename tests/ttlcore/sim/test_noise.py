"""Tests of the analytic noise models and of the streaming Gaussian noise generator.

Every statistical check states, in a comment, why its tolerance is what it is.  The
references are independent of the code under test: lisainstrument's noise definitions
(models), direct time-domain convolution (block machinery), scipy's Welch estimator
(spectra), scipy.stats (continuity, Gaussianity).
"""

from __future__ import annotations

import concurrent.futures
import functools
import math
import pickle
import tracemalloc
import warnings

import numpy as np
import pytest
import scipy.fft as sfft
import scipy.signal
import scipy.stats

from ttlcore.conventions import NU0, C
from ttlcore.sim import noise_models as nm
from ttlcore.sim.noise import (
    WHITE_BLOCK,
    NoiseFilter,
    NoiseStream,
    default_filter_length,
    generate,
    run_block_length,
)

DAY = 86_400
FS = 4.0


# ---------------------------------------------------------------------------
# Models
# ---------------------------------------------------------------------------


def test_levels_and_shapes():
    # Paper appendix numbers.
    assert nm.OMS_LINK == pytest.approx(7.2355e-12, rel=1e-4)  # sqrt(6.35^2 + 3.32^2 + 1.42^2/2) pm
    assert nm.BACKLINK_LINK == pytest.approx(3e-12 / math.sqrt(2), rel=1e-12)
    assert nm.TELESCOPE_LINK == pytest.approx(math.sqrt(1 + 4 + 2.25) * 1e-15, rel=1e-12)
    assert nm.laser(np.array([10.0]))[0] == pytest.approx(30.0 / NU0, rel=1e-9)
    # test mass: (f / 8 mHz)^4 (docs/physics.md), not the paper's typo (8 mHz / f)^4: the
    # velocity ASD rises like f well above 8 mHz.
    assert nm.test_mass(np.array([2.0]))[0] / nm.test_mass(np.array([1.0]))[0] == pytest.approx(2.0, rel=1e-4)
    assert nm.test_mass(np.array([1e-2]))[0] == pytest.approx(
        2.4e-15 / (2 * np.pi * 1e-2 * C) * math.sqrt(1 + 0.04**2) * math.sqrt(1 + 1.25**4), rel=1e-12
    )
    f = np.logspace(-4, 0, 7)
    s_oms, s_acc = nm.secondary_single_link(f)
    np.testing.assert_allclose(s_oms, nm.oms(f) ** 2 + nm.backlink(f) ** 2 + nm.telescope(f) ** 2, rtol=1e-14)
    np.testing.assert_allclose(s_acc, nm.test_mass(f) ** 2, rtol=1e-14)
    np.testing.assert_allclose(nm.dws_readout(f), 70e-9 / 335)
    np.testing.assert_allclose(nm.MODELS["dws_velocity"](f), 2 * np.pi * f * 70e-9 / 335, rtol=1e-14)


def test_models_picklable():
    for name, model in nm.MODELS.items():
        clone = pickle.loads(pickle.dumps(model))
        f = np.array([1e-3, 0.1])
        np.testing.assert_array_equal(clone(f), model(f), err_msg=name)


def test_models_match_lisainstrument():
    """Continuous models against lisainstrument's noise definitions (an independent implementation).

    lisainstrument gives the PSD of its discrete-time generator, which follows the
    continuous model to <1 % between 0.1 mHz (above its own 1e-5 Hz regularisation) and
    30 mHz, then departs from it near Nyquist (discrete differentiators), so the
    comparison is made there with a 2 % tolerance.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from lisainstrument.noisy import noise_defs_lisa as li
        from lisainstrument.noisy.noise_defs import psd_onesided_from_psd_twosided as onesided

    f = np.logspace(-4, np.log10(3e-2), 15)

    def asd(noise_def, scale=1.0):
        return np.sqrt(onesided(noise_def.discrete_psd_twosided(f))) * scale

    refs = {
        "laser": asd(li.NoiseDefLaser(30.0, "white+infrared_stationary", 1e-5, FS, "l"), 1 / NU0),
        "test_mass": asd(li.NoiseDefTestMass(2.4e-15, "original-stationary", 0.4e-3, 8e-3, 0.0, 1e-5, FS, "t"), 1 / C),
        "oms": asd(li.NoiseDefOMS(nm.OMS_LINK, 1e-5, 2e-3, FS, "o")),
        "backlink": asd(li.NoiseDefBacklink(nm.BACKLINK_LINK, 1e-5, 2e-3, FS, "b")),
        "sc_jitter_velocity": asd(li.NoiseDefAngularJitter(5e-9, 1e-5, 0.8e-3, FS, "j")),
        "mosa_jitter_phi_velocity": asd(li.NoiseDefAngularJitter(2e-9, 1e-5, 0.8e-3, FS, "p")),
        "mosa_jitter_eta_velocity": asd(li.NoiseDefAngularJitter(1e-9, 1e-5, 0.8e-3, FS, "e")),
        "dws_velocity": asd(li.NoiseDefDWS(70e-9 / 335, FS, "d")),
    }
    for name, ref in refs.items():
        np.testing.assert_allclose(nm.MODELS[name](f), ref, rtol=0.02, err_msg=name)


# ---------------------------------------------------------------------------
# Filter design (deterministic)
# ---------------------------------------------------------------------------

SPECTRAL_CASES = [(name, FS) for name in nm.MODELS] + [("laser", 16.0)]


def test_default_filter_length():
    assert default_filter_length(4.0) == 2**20
    assert default_filter_length(16.0) == 2**22


@pytest.mark.parametrize("name,fs", SPECTRAL_CASES)
def test_filter_response_matches_model(name, fs):
    # Deterministic: the PSD of the FIR output for unit white input, 2 |H(f)|^2 / fs, on a
    # 4x oversampled grid (so between the design frequencies too).  Truncation and taper
    # errors are ~1e-3 at 0.1 mHz and far smaller above; 1 % leaves margin.
    model = nm.MODELS[name]
    flt = NoiseFilter(model, fs)
    f, psd = flt.response_psd(oversample=4)
    sel = (f >= 1e-4) & (f <= fs / 2)
    np.testing.assert_allclose(psd[sel], model(f[sel]) ** 2, rtol=0.01)


# ---------------------------------------------------------------------------
# Spectra of generated series
# ---------------------------------------------------------------------------

WINDOW = "nuttall"  # 4-term Nuttall: sidelobes < -93 dB, enough for the 1e9 dynamic range of the red models


def _bands(fmax: float, fmin: float = 1e-4) -> list[tuple[float, float]]:
    """Octave bands from ``fmin`` [Hz], the last one ending at ``fmax``."""
    edges = [fmin]
    while edges[-1] * 2 < fmax:
        edges.append(edges[-1] * 2)
    edges.append(fmax)
    return list(zip(edges[:-1], edges[1:]))


@functools.cache
def _window_correlations(nperseg: int, max_lag: int = 12) -> tuple[np.ndarray, float]:
    """``c_f(d)`` for ``d = 0 .. max_lag - 1`` and ``c_t(1)`` of the Welch window (see below)."""
    w = scipy.signal.get_window(WINDOW, nperseg)
    norm = np.sum(w * w) ** 2
    c_f = np.abs(sfft.rfft(w * w)[:max_lag]) ** 2 / norm
    step = nperseg // 2
    c_t1 = float(np.sum(w[step:] * w[: nperseg - step])) ** 2 / norm
    return c_f, c_t1


def _expected_asd_scatter(psd_bins: np.ndarray, nperseg: int, nseg: int) -> float:
    """Expected relative standard deviation of ``sqrt(mean of Welch PSD over a band)``.

    For Gaussian noise whose PSD varies slowly on the scale of a bin, the windowed
    periodogram bins ``k`` and ``k + d`` of one segment have correlation
    ``c_f(d) = |sum w^2 exp(-2 pi i d n / N)|^2 / (sum w^2)^2``, and the periodograms of
    segments ``j`` hops apart (50 % overlap) correlate by
    ``c_t(j) = (sum w[n] w[n + j N/2])^2 / (sum w^2)^2``.  The variance of the band
    mean of the PSD estimate, relative to its mean, is then
    ``[sum_{k,l} S_k S_l c_f(k - l) / (sum S)^2] * [sum_{|j| < nseg} (1 - |j|/nseg) c_t(j) / nseg]``
    (the model PSD ``S`` weights the bins, which matters for the steep red models);
    the ASD scatter is half the relative PSD scatter.
    """
    c_f, c_t1 = _window_correlations(nperseg)
    s = np.asarray(psd_bins, dtype=float)
    num = float(s @ s) + 2 * sum(c_f[d] * float(s[:-d] @ s[d:]) for d in range(1, min(c_f.size, s.size)))
    var_f = num / s.sum() ** 2
    var_t = (1 + 2 * (1 - 1 / nseg) * c_t1 * (nseg > 1)) / nseg  # hops >= 2 do not overlap
    return 0.5 * math.sqrt(var_f * var_t)


def _welch_streamed(stream: NoiseStream, nperseg: int, nseg: int, per_call: int = 3):
    """Welch PSD of channel 0 over ``nseg`` half-overlapping segments, read chunk by chunk.

    Identical to one ``scipy.signal.welch`` call on the whole series (each segment is
    detrended, windowed and averaged the same way) but with bounded memory.  Welch runs
    in a worker thread while the next chunk is generated (both release the GIL), which
    uses the second core.
    """
    step = nperseg // 2

    def welch(x):
        return scipy.signal.welch(x, stream.fs, window=WINDOW, nperseg=nperseg, noverlap=step)

    acc, f, pending = 0.0, None, []
    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
        for s0 in range(0, nseg, per_call):
            k = min(per_call, nseg - s0)
            x = stream.get(s0 * step, s0 * step + nperseg + (k - 1) * step)[0]
            pending.append((k, pool.submit(welch, x)))
            del x
            while len(pending) > 1:  # at most two chunks in memory
                k0, fut = pending.pop(0)
                f, p = fut.result()
                acc = acc + p * k0
        for k0, fut in pending:
            f, p = fut.result()
            acc = acc + p * k0
    return f, acc / nseg


# The fast suite checks the 4 Hz series from 0.4 mHz (the lowest band, which decides the
# length, has 4 times the bins: a quarter of the data); the science suite checks every
# series from 0.1 mHz, the 16 Hz laser (2^23-sample segments) included.  The filters
# themselves are checked deterministically at both rates above.
@pytest.mark.parametrize(
    "name,fs,fmin",
    [(n, fs, 4e-4) for n, fs in SPECTRAL_CASES if fs == FS]
    + [pytest.param(n, fs, 1e-4, marks=pytest.mark.science) for n, fs in SPECTRAL_CASES],
)
def test_generated_spectrum_matches_model(name, fs, fmin):
    """Welch ASD of a generated series within 10 % of the model in octave bands from ``fmin``.

    Segments of 2^19 s (bins of 1.9 uHz) resolve the lowest band (0.1-0.2 mHz, 52 bins)
    finely enough that the window's smoothing biases the steep f^-4 PSDs by < 0.5 %.
    The number of segments is chosen from :func:`_expected_asd_scatter` so that the
    expected ASD scatter is <= 3 % in every band (the lowest band decides: 55 to 75 days
    from 0.1 mHz, cheap to generate); 10 % is then a > 3.3-sigma bound in the lowest band
    and a far larger one above (the scatter falls like 1/sqrt(bandwidth)).
    """
    model = nm.MODELS[name]
    fmax = 1.5 if fs == FS else 0.9 * fs / 2
    nperseg = int(round(2**19 * fs))  # 2^21 samples at 4 Hz, 2^23 at 16 Hz
    fbins = np.arange(nperseg // 2 + 1) * fs / nperseg
    bands = _bands(fmax, fmin)
    masks = [(fbins >= lo) & (fbins < hi) for lo, hi in bands]
    target = 0.03
    worst1 = max(_expected_asd_scatter(model(fbins[m]) ** 2, nperseg, 1) for m in masks)
    nseg = max(2, math.ceil((worst1 / target) ** 2 * 1.01))  # scatter ~ 1/sqrt(nseg); 1 % for the overlap term
    scatters = [_expected_asd_scatter(model(fbins[m]) ** 2, nperseg, nseg) for m in masks]
    assert max(scatters) <= 0.03, (nseg, scatters)

    # block_length = 2N: the fastest block size for a long sequential read; the values
    # equal those of any other block size up to FFT round-off.
    flt = NoiseFilter(model, fs)
    stream = NoiseStream(flt, fs, seed=20240607, key=f"spectrum.{name}", block_length=2 * flt.length, cache_blocks=1)
    f, psd = _welch_streamed(stream, nperseg, nseg)
    assert np.allclose(f, fbins)
    failures = []
    for (lo, hi), m, sigma in zip(bands, masks, scatters):
        ratio = math.sqrt(psd[m].mean() / np.mean(model(f[m]) ** 2))
        if abs(ratio - 1) > 0.10:
            failures.append(f"{lo:.3g}-{hi:.3g} Hz: ASD ratio {ratio:.3f} (expected scatter {sigma:.3f})")
    assert not failures, f"{name} at {fs} Hz ({nseg} segments): " + "; ".join(failures)


# ---------------------------------------------------------------------------
# Block machinery against direct convolution
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("block_length", [16, 37, 64, 1000])
def test_matches_direct_convolution(block_length):
    # y[n] = sum_k h[k] w[n - k] computed by np.convolve on the stream's own white noise:
    # an independent reference for the overlap-save indexing (incl. negative indices and
    # white-noise block boundaries at multiples of 2^16).  Only round-off differs.
    flt = NoiseFilter(nm.laser, FS, fmin=0.05, length=64)
    stream = NoiseStream(flt, FS, seed=3, key="direct", n_channels=2, block_length=block_length)
    start, stop = -WHITE_BLOCK - 300, -WHITE_BLOCK + 700
    w = stream.white(start - flt.length + 1, stop)
    y = stream.get(start, stop)
    for c in range(2):
        ref = np.convolve(w[c], flt.taps, mode="valid")
        np.testing.assert_allclose(y[c], ref, rtol=0, atol=1e-12 * np.abs(ref).max())


def test_run_sized_blocks_give_the_same_noise():
    """A short run's blocks (run_block_length) hold the whole run in block 0, and the noise
    is that of the default blocks to rounding: the simulator sizes its blocks to the run
    without changing a seeded realisation."""
    taps, n, margin = 2**16, 3000, 100
    block = run_block_length(n, taps, margin)
    assert block % 4096 == 0 and block < taps // 2 and block // 16 >= margin
    assert block - block // 16 >= n + margin
    assert run_block_length(10 * taps, taps, margin) == taps // 2  # long runs: the default
    flt = NoiseFilter(nm.test_mass, FS, fmin=1e-3, length=taps)
    short = NoiseStream(flt, FS, seed=7, key="sized", n_channels=2, block_length=block, keep_white=False)
    default = NoiseStream(flt, FS, seed=7, key="sized", n_channels=2)
    a, b = short.get(-margin, n + margin), default.get(-margin, n + margin)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.abs(b).max())
    assert len(short._blocks) == 1  # the run in one block
    assert len(short._white) == 1  # and no white noise kept for a next block that never comes


# ---------------------------------------------------------------------------
# Reproducibility, independence, random access
# ---------------------------------------------------------------------------


def test_reproducible_and_independent():
    n = 2**18
    model = nm.dws_readout  # white: correlation of two independent series is N(0, 1/n)
    a = generate(model, FS, n, seed=1, key="dws.12", n_channels=2)
    b = NoiseStream(model, FS, seed=1, key="dws.12", n_channels=2).get(0, n)
    np.testing.assert_array_equal(a, b)
    others = {
        "other key": generate(model, FS, n, seed=1, key="dws.21")[0],
        "other seed": generate(model, FS, n, seed=2, key="dws.12")[0],
        "other channel": a[1],
    }
    # |r| < 5 / sqrt(n): a 5-sigma bound for independent white series.
    for what, x in others.items():
        r = np.corrcoef(a[0], x)[0, 1]
        assert abs(r) < 5 / math.sqrt(n), (what, r)
        assert not np.array_equal(a[0], x)


def test_chunk_size_invariance_and_negative_start():
    fs = FS
    model = nm.laser
    flt = NoiseFilter(model, fs)
    start, span = -10_000, int(2 * DAY * fs)
    hour = int(3600 * fs)

    def read(piece, order=1):
        stream = NoiseStream(flt, fs, seed=11, key="chunks", n_channels=2)
        edges = list(range(start, start + span, piece)) + [start + span]
        parts = {}
        pairs = list(zip(edges[:-1], edges[1:]))[::order]
        for lo, hi in pairs:
            parts[lo] = stream.get(lo, hi)
        return np.concatenate([parts[lo] for lo, _ in sorted(pairs)], axis=1)

    one = read(span)
    scale = np.abs(one).max()
    for piece, order in ((hour, 1), (7 * hour, 1), (5 * hour + 17, -1)):
        other = read(piece, order)
        assert other.shape == one.shape
        assert np.max(np.abs(other - one)) <= 1e-12 * scale, (piece, order)
    # A fresh stream reading only a short negative range sees the same numbers.
    fresh = NoiseStream(flt, fs, seed=11, key="chunks", n_channels=2).get(-5000, -4000)
    assert np.max(np.abs(fresh - one[:, 5000:6000])) <= 1e-12 * scale
    # A different block size changes only the FFT round-off.
    other_block = NoiseStream(flt, fs, seed=11, key="chunks", n_channels=2, block_length=3 * hour).get(
        start, start + span
    )
    assert np.max(np.abs(other_block - one)) <= 1e-10 * scale


def test_continuity_at_block_boundaries():
    # Read 2 days in 1-hour pieces from a stream whose internal output blocks are also
    # 1 hour long (offset by block_origin), giving 47 piece boundaries and 48 internal
    # overlap-save block boundaries.  The first difference of laser noise is dominated by
    # its white part, so the |diff| values across those boundaries, hours apart, are
    # independent draws from the bulk |diff| distribution: a KS test must not reject at
    # p = 1e-3 (a discontinuity of even a fraction of the low-frequency amplitude, 1e4
    # times the white level, would give p ~ 0).
    fs = FS
    hour = int(3600 * fs)
    stream = NoiseStream(nm.laser, fs, seed=5, key="continuity", block_length=hour)
    assert stream.block_origin % hour != 0
    x = np.concatenate([stream.get(k * hour, (k + 1) * hour)[0] for k in range(48)])
    d = np.abs(np.diff(x))  # d[i] = |x[i + 1] - x[i]|
    pieces = np.arange(1, 48) * hour - 1
    blocks = np.arange(48) * hour + stream.block_origin % hour - 1
    boundary = np.concatenate([pieces, blocks])
    assert boundary.size == 95 and np.unique(boundary).size == 95
    bulk = np.delete(d, boundary)
    p = scipy.stats.ks_2samp(d[boundary], bulk).pvalue
    assert p > 1e-3, p
    # z-test on the mean square: the mean of 95 squared Gaussian diffs has relative
    # standard deviation sqrt(2/95); |z| < 4.
    z = (np.mean(d[boundary] ** 2) / np.mean(bulk**2) - 1) / math.sqrt(2 / boundary.size)
    assert abs(z) < 4, z


# ---------------------------------------------------------------------------
# Gaussianity
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["oms", "telescope", "test_mass", "dws_velocity", "mosa_jitter_eta_velocity"])
def test_gaussian_kurtosis(name):
    # For a Gaussian linear process the sample kurtosis of n samples has standard deviation
    # sqrt(24 sum_k rho_k^4 / n) (rho: autocorrelation, from the filter taps), the skewness
    # sqrt(6 sum_k rho_k^3 / n); 5 sigma bounds.
    model = nm.MODELS[name]
    flt = NoiseFilter(model, FS)
    n = int(DAY * FS)
    x = NoiseStream(flt, FS, seed=9, key=f"gauss.{name}").get(0, n)[0]
    acf = sfft.irfft(np.abs(sfft.rfft(flt.taps, n=2 * flt.length)) ** 2)[: flt.length]
    rho = acf / acf[0]
    lags = np.arange(min(n, rho.size))
    weight = 1 - lags / n
    sum4 = 1 + 2 * np.sum(weight[1:] * rho[1 : lags.size] ** 4)
    sum3 = 1 + 2 * np.sum(weight[1:] * np.abs(rho[1 : lags.size]) ** 3)
    kurt = scipy.stats.kurtosis(x, fisher=False)
    skew = scipy.stats.skew(x)
    assert abs(kurt - 3) < 5 * math.sqrt(24 * sum4 / n), (kurt, sum4)
    assert abs(skew) < 5 * math.sqrt(6 * sum3 / n), (skew, sum3)


# ---------------------------------------------------------------------------
# Memory and API
# ---------------------------------------------------------------------------


def test_memory_bounded():
    # Reading day after day must not accumulate: the caches hold at most cache_blocks
    # output blocks and the white noise of one FFT span, and the traced peak for 12 days
    # equals that for 3 days (5 % slack for allocator noise).
    fs = FS
    n_day = int(DAY * fs)
    flt = NoiseFilter(nm.oms, fs)

    def run(days):
        stream = NoiseStream(flt, fs, seed=4, key="memory", n_channels=3)
        tracemalloc.start()
        try:
            for d in range(days):
                stream.get(d * n_day - 100, (d + 1) * n_day)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        bound = (
            3
            * 8
            * (stream.cache_blocks * stream.block_length + stream.fft_length - stream.block_length + 2 * WHITE_BLOCK)
        )
        assert stream.cache_nbytes <= bound
        return peak

    p3, p12 = run(3), run(12)
    assert p12 <= 1.05 * p3, (p3, p12)


def test_api_errors_and_shapes():
    s = NoiseStream(nm.dws_readout, FS, seed=0, key="api", n_channels=3, filter_length=64)
    assert s.get(5, 5).shape == (3, 0)
    assert s.get(-7, 5).shape == (3, 12)
    with pytest.raises(ValueError):
        s.get(5, 4)
    with pytest.raises(TypeError):
        s.get(0.5, 4)
    with pytest.raises(ValueError):
        NoiseStream(nm.dws_readout, FS, seed=-1, key="api")
    with pytest.raises(ValueError):
        NoiseStream(nm.dws_readout, FS, seed=0, key="api", filter_length=63)
    with pytest.raises(ValueError):
        NoiseStream(lambda f: -np.ones_like(f), FS, seed=0, key="api", filter_length=64)
    g = generate(nm.laser, FS, 100, seed=0, key="api", start=-50, filter_length=256)
    ref = NoiseStream(nm.laser, FS, seed=0, key="api", filter_length=256).get(-50, 50)
    np.testing.assert_array_equal(g, ref)
