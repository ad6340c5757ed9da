"""Simulator checks against independent sources: the TTL formula of PHYSICS.md evaluated
with pytdi's interpolation, the analytic ASD models, and pytdi's X2."""

import numpy as np
import pytest
from pytdi.dsp import timeshift as pytdi_timeshift
from scipy import signal

from ttlcore import noise_models
from ttlcore.coefficients import make_coefficients
from ttlcore.conventions import C, COEFFICIENT_NAMES, DAY, LINKS, reverse
from ttlcore.simulator import NoiseSwitches, SimulationConfig, Simulator, anti_alias_filter, simulate

HOUR = 3600.0


def ttl_formula(dws_phi, dws_eta, coeffs, ltt, fs):
    """PHYSICS.md: ttl_ij = -(1/c)[C_rx phi'_ij + C_rx eta'_ij + D_ij(C_tx phi'_ji + C_tx eta'_ji)],
    delays by pytdi's Lagrange interpolation (order 31), coefficients at emission time."""
    name = {n: k for k, n in enumerate(COEFFICIENT_NAMES)}
    out = np.empty_like(dws_phi)
    for k, link in enumerate(LINKS):
        j = LINKS.index(reverse(link))
        rx = coeffs[name[f"{link}.phi.rx"]] * dws_phi[k] + coeffs[name[f"{link}.eta.rx"]] * dws_eta[k]
        src = coeffs[name[f"{reverse(link)}.phi.tx"]] * dws_phi[j] + coeffs[name[f"{reverse(link)}.eta.tx"]] * dws_eta[j]
        out[k] = -(rx + pytdi_timeshift(src, -ltt[k] * fs, 31)) / C
    return out


@pytest.mark.parametrize("orbit", ["unequal", "keplerian"])
def test_ttl_equals_physics_formula(orbit):
    coeffs = make_coefficients("lisainstrument").with_drift({"12.phi.tx": 0.05e-3, "31.eta.rx": -0.02e-3})
    cfg = SimulationConfig(
        duration=2 * HOUR, orbit=orbit, coefficients=coeffs, seed=3,
        noises=NoiseSwitches.parse("ttl,sc_jitter,mosa_jitter"),
    )
    tm, truth = simulate(cfg, chunk_size=2000)
    expected = ttl_formula(tm.dws_phi, tm.dws_eta, truth["coefficients"], tm.ltt, tm.fs)
    # the formula needs ~33 + 16 samples of history that the test's series lack
    sl = np.s_[:, 64:-16]
    rel = np.max(np.abs(tm.eta[sl] - expected[sl])) / np.max(np.abs(expected[sl]))
    assert rel < 1e-10, rel
    assert np.array_equal(tm.eta, truth["ttl"])  # only TTL is on


def test_chunking_is_invisible_over_two_days():
    # Every noise is random-access by absolute sample, so chunks of 5 h (boundaries at odd
    # hours and across the day boundary at 24 h) must reproduce one-piece generation to
    # rounding; then first differences at the boundaries are those of the bulk.
    cfg = SimulationConfig(duration=2 * DAY, orbit="keplerian", seed=5, noises=NoiseSwitches.parse("all,-laser"))
    sim = Simulator(cfg)
    n = sim.size
    whole, _ = sim.chunk(0, n)
    pieces = [tm for tm, _ in Simulator(cfg).chunks(chunk_size=int(5 * HOUR * cfg.fs))]
    joined = np.concatenate([p.eta for p in pieces], axis=1)
    assert np.max(np.abs(joined - whole.eta)) <= 1e-12 * np.max(np.abs(whole.eta))
    dws = np.concatenate([p.dws_phi for p in pieces], axis=1)
    assert np.max(np.abs(dws - whole.dws_phi)) <= 1e-12 * np.max(np.abs(whole.dws_phi))
    # boundary first differences against the bulk: all boundaries within the bulk's 99.99 % range
    step = int(5 * HOUR * cfg.fs)
    boundaries = np.arange(step, n, step)
    diffs = np.abs(np.diff(joined, axis=1))
    bulk = np.quantile(diffs, 0.9999, axis=1)
    assert np.all(diffs[:, boundaries - 1] < bulk[:, None])
    day = int(DAY * cfg.fs)
    assert np.all(diffs[:, day - 1] < bulk)


def test_laser_chunking_is_invisible():
    cfg = SimulationConfig(duration=6 * HOUR, orbit="keplerian", seed=9, noises=NoiseSwitches.parse("laser"))
    sim = Simulator(cfg)
    whole = sim.laser_terms(0, sim.size)
    parts = np.concatenate([sim.laser_terms(n0, 7777) for n0 in range(0, sim.size, 7777)], axis=1)[:, : sim.size]
    assert np.max(np.abs(parts - whole)) <= 1e-12 * np.max(np.abs(whole))


def test_components_add_up_to_eta():
    cfg = SimulationConfig(duration=HOUR, orbit="keplerian", seed=2, truth_noises=("laser", "oms", "backlink", "telescope", "test_mass", "dws_phi", "dws_eta"))
    tm, truth = simulate(cfg)
    total = truth["ttl"] + sum(truth[f"noises/{k}"] for k in ("laser", "oms", "backlink", "telescope", "test_mass"))
    assert np.max(np.abs(total - tm.eta)) <= 1e-12 * np.max(np.abs(tm.eta))
    assert np.allclose(tm.dws_phi - truth["noises/dws_phi"], truth["angular_velocity/phi"], rtol=0, atol=1e-22)


# ---------------------------------------------------------------------------
# Every noise and jitter series of a noise-only day against its ASD model
# ---------------------------------------------------------------------------

BANDS = np.geomspace(1e-4, 1.5, 22)  # 21 log-spaced bands, 5 per decade


def band_ratio(x, fs, model_psd, nperseg):
    """Ratio of Welch PSD to model PSD, both averaged over the bins of each band; also the
    expected relative standard deviation of the band-averaged estimate."""
    f, p = signal.welch(x, fs=fs, window="nuttall", nperseg=nperseg, noverlap=nperseg // 2, axis=-1)
    p = np.atleast_2d(p).mean(axis=0)
    nch = np.atleast_2d(x).shape[0]
    nseg = 2 * x.shape[-1] // nperseg - 1
    out = []
    for lo, hi in zip(BANDS[:-1], BANDS[1:]):
        sel = (f >= lo) & (f < hi)
        if sel.sum() == 0:
            continue
        ratio = p[sel].mean() / model_psd(f[sel]).mean()
        # Welch with 50 % overlap Nuttall: ~nseg independent averages per bin (overlap
        # correlation for Nuttall is small); adjacent bins of a Nuttall window are ~1/2 correlated
        dof = nch * nseg * max(sel.sum() / 2, 1)
        out.append((lo, hi, ratio, 1 / np.sqrt(dof)))
    return out


@pytest.fixture(scope="module")
def noise_day():
    cfg = SimulationConfig(duration=DAY, orbit="equal", seed=11, truth_noises=("laser", "oms", "backlink", "telescope", "test_mass", "dws_phi", "dws_eta"))
    tm, truth = simulate(cfg)
    return cfg, tm, truth


def _check(series, fs, psd, label, nperseg):
    for lo, hi, ratio, sigma in band_ratio(series, fs, psd, nperseg):
        asd_err = abs(np.sqrt(ratio) - 1)
        # the tolerance is 10 % in ASD; we also require it to exceed 3 sigma of the estimate
        assert asd_err < 0.10, f"{label}: band {lo:.2e}-{hi:.2e} Hz ASD off by {100 * asd_err:.1f} % (sigma {100 * sigma / 2:.1f} %)"


def _nperseg_for(lo):
    return 1 << 16


def test_secondary_noise_asds(noise_day):
    cfg, tm, truth = noise_day
    fs = tm.fs
    f_psd = lambda model: (lambda f: model(f) ** 2)
    _check(truth["noises/oms"], fs, f_psd(noise_models.oms), "oms", 1 << 15)
    _check(truth["noises/backlink"], fs, f_psd(noise_models.backlink), "backlink", 1 << 15)
    _check(truth["noises/telescope"], fs, f_psd(noise_models.telescope), "telescope", 1 << 15)
    # eta holds delta_ij + D_ij delta_ji: two independent test masses, PSD 2 S_acc
    _check(truth["noises/test_mass"], fs, lambda f: 2 * noise_models.test_mass(f) ** 2, "test_mass", 1 << 15)


def test_laser_term_asd(noise_day):
    cfg, tm, truth = noise_day
    # D_ij p_j - p_i of two independent lasers: PSD 2 S_p, times the anti-alias filter's gain
    h = anti_alias_filter(cfg.fs * cfg.laser_upsampling, cfg.laser_upsampling)
    gain = lambda f: np.abs(signal.freqz(h, worN=f, fs=cfg.fs * cfg.laser_upsampling)[1]) ** 2
    _check(truth["noises/laser"], tm.fs, lambda f: 2 * noise_models.laser(f) ** 2 * gain(f), "laser", 1 << 15)


def test_jitter_and_dws_asds(noise_day):
    cfg, tm, truth = noise_day
    jit = cfg.jitter
    sc = lambda f: (2 * np.pi * f * jit["sc"]) ** 2 * (1 + (jit["fknee"] / f) ** 4)
    mphi = lambda f: (2 * np.pi * f * jit["mosa_phi"]) ** 2 * (1 + (jit["fknee"] / f) ** 4)
    meta = lambda f: (2 * np.pi * f * jit["mosa_eta"]) ** 2 * (1 + (jit["fknee"] / f) ** 4)
    # total phi_ij = phi_SC_i + phi_MOSA_ij; total eta_ij = cos a eta_SC - sin a theta_SC + eta_MOSA
    _check(truth["angular_velocity/phi"], tm.fs, lambda f: sc(f) + mphi(f), "phi velocity", 1 << 15)
    _check(truth["angular_velocity/eta"], tm.fs, lambda f: sc(f) + meta(f), "eta velocity", 1 << 15)
    dws = lambda f: (2 * np.pi * f * jit["dws"]) ** 2
    _check(np.vstack([truth["noises/dws_phi"], truth["noises/dws_eta"]]), tm.fs, dws, "dws noise", 1 << 15)
