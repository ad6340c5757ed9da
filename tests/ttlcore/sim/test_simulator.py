"""Simulator checks against independent sources: the TTL formula of docs/physics.md evaluated
with pytdi's interpolation and the analytic ASD models.  (pytdi's X2 of the simulated laser
noise is checked in tests/ttlcore/tdi/test_tdi.py, on the Keplerian day that module simulates
for its own laser-suppression check: the same simulation, made once.)"""

import numpy as np
import pytest
from pytdi.dsp import timeshift as pytdi_timeshift
from scipy import signal

from ttlcore.conventions import COEFFICIENT_NAMES, DAY, LINKS, C, reverse
from ttlcore.io.truth import NOISE_COMPONENTS
from ttlcore.sim import noise_models
from ttlcore.sim.coefficients import make_coefficients
from ttlcore.sim.simulator import NoiseSwitches, SimulationConfig, Simulator, simulate

HOUR = 3600.0


def ttl_formula(dws_phi, dws_eta, coeffs, ltt, fs):
    """docs/physics.md: ttl_ij = -(1/c)[C_rx phi'_ij + C_rx eta'_ij + D_ij(C_tx phi'_ji + C_tx eta'_ji)],
    delays by pytdi's Lagrange interpolation (order 31), coefficients at emission time."""
    name = {n: k for k, n in enumerate(COEFFICIENT_NAMES)}
    out = np.empty_like(dws_phi)
    for k, link in enumerate(LINKS):
        j = LINKS.index(reverse(link))
        rx = coeffs[name[f"{link}.phi.rx"]] * dws_phi[k] + coeffs[name[f"{link}.eta.rx"]] * dws_eta[k]
        src = (
            coeffs[name[f"{reverse(link)}.phi.tx"]] * dws_phi[j] + coeffs[name[f"{reverse(link)}.eta.tx"]] * dws_eta[j]
        )
        out[k] = -(rx + pytdi_timeshift(src, -ltt[k] * fs, 31)) / C
    return out


@pytest.mark.parametrize("orbit", ["unequal", "keplerian"])
def test_ttl_equals_physics_formula(orbit):
    coeffs = make_coefficients("lisainstrument").with_drift({"12.phi.tx": 0.05e-3, "31.eta.rx": -0.02e-3})
    cfg = SimulationConfig(
        duration=2 * HOUR,
        orbit=orbit,
        coefficients=coeffs,
        seed=3,
        noises=NoiseSwitches.parse("ttl,sc_jitter,mosa_jitter"),
    )
    tm, truth = simulate(cfg, chunk_size=2000)
    expected = ttl_formula(tm.dws_phi, tm.dws_eta, truth["coefficients"], tm.ltt, tm.fs)
    # the formula needs ~33 + 16 samples of history that the test's series lack
    sl = np.s_[:, 64:-16]
    rel = np.max(np.abs(tm.eta[sl] - expected[sl])) / np.max(np.abs(expected[sl]))
    assert rel < 1e-10, rel
    assert np.array_equal(tm.eta, truth["ttl"])  # only TTL is on


def test_chunking_is_invisible_across_the_day_boundary():
    # Every noise is random-access by absolute sample, so chunks of 5 h (boundaries at odd
    # hours, and one chunk across the day boundary at 24 h) must reproduce one-piece
    # generation to rounding; then first differences at the boundaries are those of the bulk.
    cfg = SimulationConfig(duration=26 * HOUR, orbit="keplerian", seed=5, noises=NoiseSwitches.parse("all,-laser"))
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
    cfg = SimulationConfig(duration=HOUR, orbit="keplerian", seed=2, truth_noises=tuple(NOISE_COMPONENTS))
    tm, truth = simulate(cfg)
    total = truth["ttl"] + sum(truth[f"noises/{k}"] for k in ("laser", "oms", "backlink", "telescope", "test_mass"))
    assert np.max(np.abs(total - tm.eta)) <= 1e-12 * np.max(np.abs(tm.eta))
    assert np.allclose(tm.dws_phi - truth["noises/dws_phi"], truth["angular_velocity/phi"], rtol=0, atol=1e-22)


# ---------------------------------------------------------------------------
# Every noise and jitter series of a noise-only day against its ASD model
# ---------------------------------------------------------------------------
#
# Estimator: a Hann-windowed periodogram of the whole day per channel, divided bin by bin
# by the model PSD, averaged over the bins of a band and over the channels of one noise.
# Hann sidelobes fall as f^-6 in power, faster than any model here rises towards low
# frequencies, and the main-lobe smoothing biases an f^-2 spectrum by ~1.5 % at 0.1 mHz.
# Statistics: a day holds ~BT independent bins in a band of width B (Hann correlates
# neighbours: ENBW 1.5 bins).  The bands below are wide enough at low frequency that the
# 1-sigma scatter of the band-averaged ASD ratio is at most 3.5 % (bands are merged until
# it is), so the 10 % tolerance is at least 2.9 sigma.  The generator alone is checked to 3 % scatter
# down to 0.1 mHz on 55-day series in test_noise.py.

BANDS = np.geomspace(1e-4, 1.5, 22)  # 5 per decade; merged upwards from 0.1 mHz until wide enough


def band_ratios(series, fs, model_psd, sources=None):
    """Band-averaged ratio of periodogram to model and its 1-sigma ASD scatter.

    ``sources`` is the number of independent noise sources behind the channels (e.g. 3
    lasers behind the 6 laser terms); adjacent bands are merged, from the lowest up,
    until the expected scatter is at most 3.5 %.
    """
    x = np.atleast_2d(series)
    sources = sources or x.shape[0]
    f, p = signal.periodogram(x, fs=fs, window="hann", detrend="linear", axis=-1)
    keep = f > 0
    f, r = f[keep], p[:, keep] / model_psd(f[keep])
    out, lo = [], BANDS[0]
    for hi in BANDS[1:]:
        sel = (f >= lo) & (f < hi)
        sigma = 0.5 / np.sqrt(sources * sel.sum() / 1.5)
        if sigma > 0.035 and hi < BANDS[-1]:
            continue  # merge with the next band
        out.append((lo, hi, r[:, sel].mean(), sigma))
        lo = hi
    return out


def assert_matches(series, fs, model_psd, label, sources=None):
    bands = band_ratios(series, fs, model_psd, sources)
    assert bands[0][0] == 1e-4 and bands[-1][1] == 1.5
    for lo, hi, ratio, sigma_asd in bands:
        err = abs(np.sqrt(ratio) - 1)
        assert err < 0.10, (
            f"{label}: ASD off by {100 * err:.1f} % in {lo:.2e}-{hi:.2e} Hz (1 sigma {100 * sigma_asd:.1f} %)"
        )


@pytest.fixture(scope="module")
def noise_day():
    cfg = SimulationConfig(duration=DAY, orbit="equal", seed=11, truth_noises=tuple(NOISE_COMPONENTS))
    tm, truth = simulate(cfg)
    return cfg, tm, truth


def test_secondary_noise_asds(noise_day):
    cfg, tm, truth = noise_day
    assert_matches(truth["noises/oms"], tm.fs, lambda f: noise_models.oms(f) ** 2, "oms")
    assert_matches(truth["noises/backlink"], tm.fs, lambda f: noise_models.backlink(f) ** 2, "backlink")
    assert_matches(truth["noises/telescope"], tm.fs, lambda f: noise_models.telescope(f) ** 2, "telescope")
    # eta holds delta_ij + D_ij delta_ji of two independent test masses: PSD 2 S_acc
    assert_matches(truth["noises/test_mass"], tm.fs, lambda f: 2 * noise_models.test_mass(f) ** 2, "test_mass")


def test_laser_noise_asd(noise_day):
    # The three laser noises p_i, as the simulator draws them at its 16-Hz physics rate.
    # (The laser terms D_ij p_j - p_i of eta are checked by their cancellation in X2 below
    # and by the component sum above; six terms of three lasers add no statistics.)
    cfg, tm, truth = noise_day
    sim = Simulator(cfg)
    fsu = cfg.fs * cfg.laser_upsampling
    p = sim.streams["laser"].get(0, int(DAY * fsu))
    assert_matches(p, fsu, lambda f: noise_models.laser(f) ** 2, "laser")


def test_jitter_and_dws_asds(noise_day):
    cfg, tm, truth = noise_day
    jit = cfg.jitter

    def shape(level):
        return lambda f: (2 * np.pi * f * level) ** 2 * (1 + (jit["fknee"] / f) ** 4)

    # total phi_ij = phi_SC_i + phi_MOSA_ij; eta_ij = cos(a) eta_SC - sin(a) theta_SC + eta_MOSA
    # (cos^2 + sin^2 = 1, SC angles of equal level): velocity PSDs add
    assert_matches(
        truth["angular_velocity/phi"], tm.fs, lambda f: shape(jit["sc"])(f) + shape(jit["mosa_phi"])(f), "phi velocity"
    )
    assert_matches(
        truth["angular_velocity/eta"], tm.fs, lambda f: shape(jit["sc"])(f) + shape(jit["mosa_eta"])(f), "eta velocity"
    )

    def dws(f):
        return (2 * np.pi * f * jit["dws"]) ** 2

    assert_matches(np.vstack([truth["noises/dws_phi"], truth["noises/dws_eta"]]), tm.fs, dws, "dws noise")


def test_coloured_jitter_follows_its_shape():
    # knees at 8 mHz and 0.1 Hz: f^-2 below and above, white between (the coloured-jitter
    # variant of `ttl scenarios`); same tolerance as the white case above
    jitter = {"sc": 5e-9, "mosa_phi": 2e-9, "mosa_eta": 1e-9, "fknee": 8e-3, "fhigh": 0.1, "dws": 70e-9 / 335}
    cfg = SimulationConfig(
        duration=DAY / 2,
        orbit="equal",
        seed=12,
        jitter=jitter,
        noises=NoiseSwitches.parse("none,sc_jitter,mosa_jitter"),
    )
    tm, truth = simulate(cfg)

    def shape(level):  # velocity PSD of the angle ASD level * sqrt(1 + (fk/f)^4) / sqrt(1 + (f/fh)^4)
        return lambda f: (2 * np.pi * f * level) ** 2 * (1 + (8e-3 / f) ** 4) / (1 + (f / 0.1) ** 4)

    assert_matches(truth["angular_velocity/phi"], tm.fs, lambda f: shape(5e-9)(f) + shape(2e-9)(f), "phi velocity")
    assert_matches(truth["angular_velocity/eta"], tm.fs, lambda f: shape(5e-9)(f) + shape(1e-9)(f), "eta velocity")
