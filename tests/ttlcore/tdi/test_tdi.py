"""TDI against pytdi, against the analytic noise PSDs, streaming against batch."""

import numpy as np
import pytest
from pytdi.michelson import X2_ETA, Y2_ETA, Z2_ETA
from scipy import signal

from ttlcore.conventions import ARM_LENGTH, DAY, LINKS, C
from ttlcore.estimate.noise_psd import simulated_single_link, tdi_noise_csd, x2_psd_equal_arms
from ttlcore.sim.simulator import SimulationConfig, simulate
from ttlcore.tdi.combinations import AET_MATRIX, X2, Y2, Z2, aet
from ttlcore.tdi.data import TDIData, TDIStream, compute_tdi, compute_tdi_arrays, lowpass_decimate, lowpass_taps

HOUR = 3600.0
SECONDARY = ("oms", "backlink", "telescope", "test_mass")


def pytdi_xyz(eta, ltt, fs):
    """pytdi's X2, Y2, Z2 on eta variables; unit='phase' applies D x(t) = x(t - tau(t)),
    the operator of docs/physics.md (its 'frequency' unit adds lisainstrument's Doppler factors)."""
    delays = {f"d_{l}": ltt[k] for k, l in enumerate(LINKS)}
    meas = {f"eta_{l}": eta[k] for k, l in enumerate(LINKS)}
    return np.stack([c.build(delays, fs, order=5)(meas, order=31, unit="phase") for c in (X2_ETA, Y2_ETA, Z2_ETA)])


def band_rms(x, fs, lo, hi):
    """RMS of x restricted to [lo, hi] Hz (Hann-windowed spectrum)."""
    f, p = signal.periodogram(x, fs=fs, window="hann", axis=-1)
    sel = (f >= lo) & (f <= hi)
    return np.sqrt(np.sum(p[..., sel], axis=-1))


# Static unequal arms go through the same engine code as Keplerian ones (no constant-delay
# path in ttlcore.tdi.engine: every delay is a Chebyshev interpolant in time), so the fast
# suite checks the Keplerian case, the general one; the static case runs in `make test-science`
@pytest.mark.parametrize("orbit", [pytest.param("unequal", marks=pytest.mark.science), "keplerian"])
def test_xyz_agree_with_pytdi(orbit):
    # Simulated eta (laser noise on: the strictest data) through both implementations;
    # both evaluate the same Lagrange polynomials, so the 1e-6 asked is met by far.
    tm, _ = simulate(SimulationConfig(duration=3 * HOUR, orbit=orbit, seed=4))
    ours = compute_tdi(tm, names=()).data
    ref = pytdi_xyz(tm.eta, tm.ltt, tm.fs)
    ok = np.isfinite(ours).all(axis=0)
    ok[: int(70 * tm.fs)] = False  # pytdi pads before the data with zeros, we give NaN
    diff = band_rms(ours[:, ok] - ref[:, ok], tm.fs, 1e-4, 0.9)
    scale = band_rms(ref[:, ok], tm.fs, 1e-4, 0.9)
    assert np.all(diff / scale < 1e-6), diff / scale


def test_regressors_agree_with_pytdi_natural_usage():
    # pytdi as a user would call it (tests/pytdi_reference.py)
    from dataclasses import replace

    from pytdi_reference import pytdi_natural

    tm, _ = simulate(SimulationConfig(duration=HOUR, orbit="keplerian", seed=5))
    ours = compute_tdi(tm)
    _, ref = pytdi_natural(tm)
    skip = int(120 * tm.fs)  # pytdi pads before the data with zeros, we give NaN
    used = np.any(ref[..., skip:] != 0, axis=-1)
    assert np.all(ours.regressors[~used][..., skip:] == 0)  # links a combination does not use

    def rel(a, b):
        """Largest relative RMS difference over the outputs, on samples finite in both."""
        ok = np.isfinite(a).all(axis=(0, 1)) & np.isfinite(b).all(axis=(0, 1))
        ok[: skip * a.shape[-1] // tm.size] = False
        a, b = a[..., ok], b[..., ok]
        u = np.any(b != 0, axis=-1)
        return np.max(np.sqrt(np.mean((a - b) ** 2, axis=-1))[u] / np.sqrt(np.mean(b**2, axis=-1))[u])

    # the same order-31 interpolations (Tx: pre-delay, then the chain), all frequencies;
    # the block engine's FFT rounding and Chebyshev weights stay below 1e-10 (measured 5e-12)
    assert rel(ours.regressors, ref) < 1e-9
    # what the fit uses: after its 0.9-1.1 Hz low-pass and decimation to 2 Hz (measured 6e-12)
    low, low_ref = ours.decimated(2), replace(ours, regressors=ref).decimated(2)
    assert rel(low.regressors, low_ref.regressors) < 1e-9


def test_lowpass_decimate_is_the_causal_fir_and_flags_nan_in_every_array():
    # the FFT convolution equals the direct causal FIR, every second sample kept; an output a
    # NaN sample of any array reaches is NaN in all; data and regressors of TDIData.decimated
    # are those of the arrays decimated alone (one FFT worker or two: the same numbers)
    rng = np.random.default_rng(3)
    n, fs = 3001, 4.0
    a, b = rng.standard_normal((2, n)), rng.standard_normal((3, 2, n))
    b[1, 0, 1500] = np.nan
    h = lowpass_taps(fs)
    da, db = lowpass_decimate([a, b], h, 2)
    direct = np.stack([np.convolve(x, h)[:n:2] for x in a])
    spoiled = np.zeros(len(range(0, n, 2)), dtype=bool)
    spoiled[750 : (1500 + h.size - 1) // 2 + 1] = True
    assert np.array_equal(np.isnan(da), np.broadcast_to(spoiled, da.shape))
    assert np.array_equal(np.isnan(db), np.broadcast_to(spoiled, db.shape))
    np.testing.assert_allclose(da[:, ~spoiled], direct[:, ~spoiled], rtol=0, atol=1e-12)
    td = TDIData(t0=0.0, fs=fs, channels=("X2", "Y2", "Z2"), data=b[:, 0], regressors=b[:, 1:])
    dec = td.decimated(2, workers=1)
    (alone,) = lowpass_decimate([b], h, 2, workers=2)
    assert np.array_equal(dec.data, alone[:, 0], equal_nan=True)
    assert np.array_equal(dec.regressors, alone[:, 1:], equal_nan=True)
    assert dec.t0 == -(h.size - 1) / 2 / fs and dec.fs == fs / 2


def test_combinations_are_rotations_and_aet_is_orthonormal():
    assert Y2 == X2.rotated("Y2") and Z2 == Y2.rotated("Z2") and Z2.rotated("X2") == X2
    assert np.allclose(AET_MATRIX @ AET_MATRIX.T, np.eye(3))
    assert len(X2.terms) == 16 and abs(sum(f for f, _, _ in X2.terms)) < 1e-15


def test_analytic_x2_psd_matches_physics_formula():
    # numeric responses through the actual delay polynomials vs the closed form of docs/physics.md
    f = np.geomspace(1e-4, 1.0, 400)
    s_oms, s_acc = simulated_single_link(f)
    csd = tdi_noise_csd(f, [ARM_LENGTH / C] * 6, aet=False)
    assert np.allclose(csd[:, 0, 0].real, x2_psd_equal_arms(f, s_oms, s_acc), rtol=1e-9, atol=0)
    aet_csd = tdi_noise_csd(f, [ARM_LENGTH / C] * 6)
    off = np.abs(aet_csd[:, 0, 1]) / np.sqrt(aet_csd[:, 0, 0].real * aet_csd[:, 1, 1].real)
    assert np.max(off) < 1e-9  # A and E uncorrelated for equal arms


@pytest.fixture(scope="module")
def keplerian_day():
    cfg = SimulationConfig(duration=DAY, orbit="keplerian", seed=21, truth_noises=("laser",) + SECONDARY)
    tm, truth = simulate(cfg)
    return tm, truth


def test_streaming_hours_equal_whole_day(keplerian_day):
    tm, _ = keplerian_day
    whole = compute_tdi(tm)
    stream = TDIStream()
    pieces = [stream.push(tm.slice(k * 14400, (k + 1) * 14400)) for k in range(24)]
    data = np.concatenate([p.data for p in pieces], axis=1)
    regs = np.concatenate([p.regressors for p in pieces], axis=2)
    after = slice(int(60 * tm.fs), None)  # away from the first minute
    # the pieces cut the engine's blocks elsewhere: its FFTs round at ~1e-16 of eta, which
    # TDI suppresses by ~1e5, and the Chebyshev weights differ by < 1e-11 (measured 5e-11
    # and 3e-11 of the largest output), far below any noise in the outputs
    np.testing.assert_allclose(
        data[:, after], whole.data[:, after], rtol=0, atol=2e-10 * np.nanmax(np.abs(whole.data)), equal_nan=True
    )
    np.testing.assert_allclose(
        regs[..., after],
        whole.regressors[..., after],
        rtol=0,
        atol=2e-10 * np.nanmax(np.abs(whole.regressors)),
        equal_nan=True,
    )
    assert np.isfinite(data[:, int(80 * tm.fs) :]).all()


def _tdi_of(series, tm):
    z = np.zeros_like(series)
    return compute_tdi_arrays(series, z, z, tm.ltt, tm.fs, tm.t0, names=()).data


def test_laser_noise_suppressed_below_secondary_noise(keplerian_day):
    # Our X2 of the laser terms alone (= the laser residual of X2(eta), by linearity)
    # stays below 10 % of the secondary noises' ASD in every band from 0.1 mHz to 0.9 Hz.
    tm, truth = keplerian_day
    laser = _tdi_of(truth["noises/laser"], tm)[0]
    secondary = _tdi_of(sum(truth[f"noises/{k}"] for k in SECONDARY), tm)[0]
    ok = np.isfinite(laser) & np.isfinite(secondary)
    f, pl = signal.periodogram(laser[ok], fs=tm.fs, window="hann")
    _, ps = signal.periodogram(secondary[ok], fs=tm.fs, window="hann")
    edges = np.geomspace(1e-4, 0.9, 31)
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (f >= lo) & (f < hi)
        ratio = np.sqrt(pl[sel].mean() / ps[sel].mean())
        assert ratio < 0.1, f"laser residual {ratio:.3f} of the secondary-noise ASD in {lo:.2e}-{hi:.2e} Hz"


def test_x2_suppresses_laser_noise_below_secondary_noises(keplerian_day):
    """The simulator's laser noise through an outside TDI: Keplerian arms, every noise on,
    pytdi's X2 (order 31) of the laser terms stays below 10 % of the X2 of the secondary
    noises (in ASD) from 0.1 mHz to 0.9 Hz (the same check with our TDI is
    test_laser_noise_suppressed_below_secondary_noise).

    pytdi is evaluated with ``unit="phase"``: its delay operator is then exactly the
    docs/physics.md ``D x(t) = x(t - tau(t))`` our eta-level model uses (its "frequency"
    evaluation adds the Doppler factor ``1 - dtau/dt`` that lisainstrument's beat notes carry).
    By linearity, X2 of the laser terms alone is the laser-noise residual of X2(eta).
    """
    tm, truth = keplerian_day
    delays = {f"d_{l}": tm.ltt[k] for k, l in enumerate(LINKS)}
    x2 = X2_ETA.build(delays, tm.fs, order=5)

    def X(series):
        return x2({f"eta_{l}": series[k] for k, l in enumerate(LINKS)}, order=31, unit="phase")

    laser = X(truth["noises/laser"])
    secondary = X(sum(truth[f"noises/{k}"] for k in SECONDARY))
    skip = 400  # first 100 s: nested delays (7 x 8.3 s) reach before the data
    f, p_laser = signal.periodogram(laser[skip:], fs=tm.fs, window="hann")
    _, p_sec = signal.periodogram(secondary[skip:], fs=tm.fs, window="hann")
    edges = np.geomspace(1e-4, 0.9, 31)
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (f >= lo) & (f < hi)
        ratio = np.sqrt(p_laser[sel].mean() / p_sec[sel].mean())
        assert ratio < 0.1, f"laser residual {ratio:.3f} of secondary ASD in {lo:.2e}-{hi:.2e} Hz"


def test_simulated_secondary_noise_matches_analytic_tdi_psd(keplerian_day):
    # docs/physics.md: a noise-only day matches the analytic TDI PSDs within 10 %.  Log bands
    # (5 per decade) from 1 mHz; bins within 2 % of a response zero are left out (there the
    # PSD is ~0 and one day's resolution mixes in the neighbours).  One day gives >= 100
    # independent Welch estimates per band above 1 mHz: ~5 % scatter in PSD, 2.5 % in ASD.
    tm, truth = keplerian_day
    xyz = _tdi_of(sum(truth[f"noises/{k}"] for k in SECONDARY), tm)
    ok = np.isfinite(xyz).all(axis=0)
    a = aet(xyz[:, ok])
    f, p = signal.welch(a, fs=tm.fs, window="hann", nperseg=1 << 14, axis=-1)
    model = np.real(np.einsum("mii->im", tdi_noise_csd(f[1:], tm.ltt)))
    f, p = f[1:], p[:, 1:]
    zero_spacing = C / (4 * ARM_LENGTH)
    away = np.abs(f / zero_spacing - np.round(f / zero_spacing)) > 0.02
    edges = np.geomspace(1e-3, 0.9, 16)
    for ch, name in ((0, "A"), (1, "E")):
        for lo, hi in zip(edges[:-1], edges[1:]):
            sel = (f >= lo) & (f < hi) & away
            ratio = np.sqrt(p[ch, sel].mean() / model[ch, sel].mean())
            assert abs(ratio - 1) < 0.10, f"{name}: ASD ratio {ratio:.3f} in {lo:.2e}-{hi:.2e} Hz"
