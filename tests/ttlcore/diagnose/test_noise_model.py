"""The fitted noise model (ttlcore.noise_model): recovery of known levels, null days at the
2 % tolerance, and an injected effect that the noise levels must not absorb."""

from dataclasses import replace

import numpy as np
import pytest

from ttlcore.diagnose.diagnoser import DiagnoseSettings, diagnose
from ttlcore.diagnose.noise_model import BOUNDS, NoiseModel, basis_csds, fit_noise_model, profile_noise_model
from ttlcore.diagnose.whitened import whiten_telemetry
from ttlcore.effects import injection_from_spec, make_effects
from ttlcore.estimate.fit import model_csd
from ttlcore.estimate.noise_psd import tdi_noise_csd
from ttlcore.io.telemetry import Telemetry
from ttlcore.sim.simulator import SimulationConfig, simulate

LTT = np.array([8.425, 8.372, 8.322, 8.322, 8.372, 8.322])
SECONDARY = ("oms", "backlink", "telescope")


def test_nominal_model_is_the_fixed_model_and_components_add_up():
    f = np.geomspace(3e-3, 0.8, 400)
    nm = NoiseModel.nominal(LTT)
    # all levels at the paper's values: exactly the fixed instrument model (regularised)
    assert np.allclose(nm.csd(f), model_csd(f, LTT), rtol=1e-12, atol=0)
    # the OMS and test-mass components with unit levels add up to the analytic CSD of
    # ttlcore.noise_psd (an independent implementation: per-link loop over the sources)
    B = basis_csds(f, LTT, ("oms", "tm_acc", "tm_rise"))
    assert np.allclose(B.sum(axis=0), tdi_noise_csd(f, LTT), rtol=1e-10, atol=0)
    # per-link OMS components add up to the all-link one
    per = basis_csds(f, LTT, tuple(f"oms.{k}" for k in ("12", "23", "31", "13", "32", "21")))
    assert np.allclose(per.sum(axis=0), basis_csds(f, LTT, ("oms",))[0], rtol=1e-12)


def test_whittle_fit_recovers_levels_within_fisher_sigmas():
    # complex Gaussian spectra drawn from a CSD with known levels: the estimates scatter
    # around the truth with the Fisher sigmas (pulls of 16 realisations: mean ~0, rms ~1)
    f = np.linspace(3e-3, 0.8, 1500)
    truth = np.array([1.3, 0.7, 1.5, 0.004])
    names = ("oms", "tm_acc", "tm_rise", "floor")
    B = basis_csds(f, LTT, names)
    L = np.linalg.cholesky(np.einsum("k,kmij->mij", truth, B))
    rng = np.random.default_rng(3)
    pulls = []
    for _ in range(16):
        # 32 segments: enough information for the Fisher sigmas of the low-frequency test-mass
        # levels to be accurate (the likelihood near Gaussian in them)
        x = (rng.standard_normal((32, f.size, 3)) + 1j * rng.standard_normal((32, f.size, 3))) / np.sqrt(2)
        r = np.einsum("mij,smj->smi", L, x)
        nm = fit_noise_model(f, np.einsum("smi,smj->mij", r, r.conj()), 32, LTT, names=names, bounded=False)
        assert nm.converged
        pulls.append((np.array(nm.levels) - truth) / nm.sigma)
    pulls = np.array(pulls)
    # 16 draws: the mean of unit-variance pulls is within 3/sqrt(16) = 0.75 of 0, the rms
    # within [0.55, 1.45] (the 3-sigma range of the rms of 16 chi^2_1 draws)
    assert np.all(np.abs(pulls.mean(axis=0)) < 0.75), pulls.mean(axis=0)
    rms = np.sqrt((pulls**2).mean(axis=0))
    assert np.all((rms > 0.55) & (rms < 1.45)), rms


def test_bounded_levels_stop_at_the_instruments_known_range():
    # spectra with OMS-shaped noise 40 % above the paper's level (as a TTL-type residual
    # looks): the bounded fit stops at the OMS bound and says so, the unbounded one follows
    f = np.linspace(3e-3, 0.8, 1500)
    names = ("oms", "tm_acc", "tm_rise", "floor")
    B = basis_csds(f, LTT, names)
    S = np.einsum("k,kmij->mij", [1.4, 1.0, 1.0, 0.01], B)
    rng = np.random.default_rng(5)
    x = (rng.standard_normal((8, f.size, 3)) + 1j * rng.standard_normal((8, f.size, 3))) / np.sqrt(2)
    r = np.einsum("mij,smj->smi", np.linalg.cholesky(S), x)
    P = np.einsum("smi,smj->mij", r, r.conj())
    nm = fit_noise_model(f, P, 8, LTT, names=names)
    assert nm.levels[0] == pytest.approx(BOUNDS["oms"][1]) and "oms" in nm.at_bound
    free = fit_noise_model(f, P, 8, LTT, names=names, bounded=False)
    assert abs(free.levels[0] - 1.4) < 3 * free.sigma[0] and not free.at_bound


def _scaled(tm, truth, k_oms: float, k_tm: float) -> Telemetry:
    """Telemetry whose OMS-type and test-mass noises are scaled by ``k`` in amplitude, from
    the simulator's own noise components (stored alone in the truth file)."""
    eta = tm.eta + (k_oms - 1) * sum(truth[f"noises/{n}"] for n in SECONDARY) + (k_tm - 1) * truth["noises/test_mass"]
    return replace(tm, eta=eta)


HOURS = 3 * 3600.0


@pytest.fixture(scope="module")
def short_day():
    cfg = SimulationConfig(duration=HOURS, orbit="keplerian", seed=41, truth_noises=SECONDARY + ("test_mass",))
    return simulate(cfg, chunk_size=int(HOURS * 4))


def test_fitted_levels_recover_scaled_simulator_noises(short_day):
    # OMS-type noises x 1.02 in amplitude (PSD x 1.0404, inside the allowed +-5 %), test
    # masses x 1.5 (PSD x 2.25): the fitted PSD scale factors recover them within 3 Fisher
    # sigmas
    tm, truth = short_day
    k_oms, k_tm = 1.02, 1.5
    dg = whiten_telemetry(_scaled(tm, truth, k_oms, k_tm), DiagnoseSettings(noise_model="fitted"))
    nm, fit = profile_noise_model(dg, make_effects(["linear-ttl"]))
    lv, sg = dict(zip(nm.names, nm.levels)), dict(zip(nm.names, nm.sigma))
    assert abs(lv["oms"] - k_oms**2) < 3 * sg["oms"], (lv, sg)
    # the test-mass PSD is one shape in the simulator: both parts scale together
    assert abs(lv["tm_acc"] - k_tm**2) < 3 * sg["tm_acc"], (lv, sg)
    assert abs(lv["tm_rise"] - k_tm**2) < 3 * sg["tm_rise"], (lv, sg)
    assert not nm.at_bound
    # the fitted model passes at the 2 % tolerance
    assert not fit.bands.fails.any(), fit.bands.chi2_dof
    assert np.all(np.abs(fit.bands.chi2_dof - 1) < 0.06), fit.bands.chi2_dof
    # the noise parameters count in the degrees of freedom (24 columns + 4 levels)
    dof_raw = 6 * dg.grid.f.size * len(dg.grid.starts)
    assert fit.bands.dof.sum() == pytest.approx(dof_raw - 24 - nm.n_parameters)


def test_short_null_day_passes_at_two_percent(short_day):
    tm, _ = short_day
    s = DiagnoseSettings()
    assert s.noise_model == "fitted" and s.tolerance == 0.02
    rep = diagnose(tm, settings=s, witnesses=False, candidates=["drift"]).to_json()
    ad = rep["adequacy"]
    assert ad["noise_model"]["kind"] == "fitted" and ad["tolerance"] == 0.02
    assert set(ad["noise_model"]["parameters"]) == {"oms", "tm_acc", "tm_rise", "floor"}
    assert not ad["fails"], ad["summary"]


@pytest.mark.science
def test_injected_effect_still_fails_with_the_fitted_noise_model():
    # a timing offset of SC1 (a named effect), well above the noise: the fitted levels
    # must not absorb it; the adequacy test fails with the fitted model, and the effect is
    # found; the null day of the same seed passes (test above)
    inj = injection_from_spec("timing-offset:sc1.d1=0.35")
    tm, _ = simulate(
        SimulationConfig(duration=6 * 3600.0, orbit="keplerian", seed=41, injections=(inj,)), chunk_size=6 * 3600 * 4
    )
    rep = diagnose(tm, witnesses=False, candidates=["timing-offset"]).to_json()
    assert rep["adequacy"]["noise_model"]["kind"] == "fitted"
    assert rep["adequacy"]["fails"], rep["adequacy"]["summary"]
    assert rep["candidates"][0]["significant"]


@pytest.mark.science
def test_lisainstrument_null_day_passes_at_two_percent(tmp_path):
    # outside data: a lisainstrument day (Keplerian orbits, every default noise and the TTL
    # coupling on); the fixed model reads chi2/dof 1.07 at low and 0.93 at high frequency,
    # the fitted one passes the 2 % test in every band and reads 1 within the scatter
    from lisainstrument_sim import simulate_lisainstrument

    from ttlcore.io.reader import read_telemetry

    path = tmp_path / "null.h5"
    simulate_lisainstrument(path, duration=86400, orbits="keplerian", seed=6)
    rep = diagnose(read_telemetry(path), witnesses=False, candidates=["drift"]).to_json()
    ad = rep["adequacy"]
    assert ad["noise_model"]["kind"] == "fitted" and ad["tolerance"] == 0.02
    assert not ad["fails"], ad["summary"]
    for b in ad["bands"]:  # within 2 % plus three times the statistical scatter of the band
        assert abs(b["chi2_dof"] - 1) < 0.02 + 3 * np.sqrt(2 * ad["variance_factor"] / b["dof"]), ad["bands"]
    assert abs(ad["chi2_dof"] - 1) < 0.01


@pytest.mark.science
def test_simulator_null_day_passes_at_two_percent():
    tm, _ = simulate(SimulationConfig(duration=86400.0, orbit="keplerian", seed=32), chunk_size=86400 * 4)
    rep = diagnose(tm, witnesses=False, candidates=["drift"]).to_json()
    ad = rep["adequacy"]
    assert not ad["fails"], ad["summary"]
    for b in ad["bands"]:
        assert abs(b["chi2_dof"] - 1) < 0.02 + 3 * np.sqrt(2 * ad["variance_factor"] / b["dof"]), ad["bands"]
    # the simulator's levels are the paper's: the OMS level (it dominates above 10 mHz) within
    # 3 % of 1 (measured 0.983 +- 0.006 on this seed: the floor term shares its high-frequency
    # shape)
    assert abs(ad["noise_model"]["parameters"]["oms"]["psd_scale"] - 1) < 0.03


def test_newton_distance_is_the_newton_step_in_sigmas():
    """Two levels with Fisher matrix F and score g: the distance to the optimum is the
    Newton step F^-1 g over the sigmas sqrt(diag F^-1), computed here by hand for a 2x2
    matrix; a level held at its bound with the score pushing it outward does not count."""
    from ttlcore.diagnose.noise_model import newton_distance

    F = np.array([[4.0, 1.0], [1.0, 2.0]])
    g = np.array([0.1, -0.3])
    det = 4.0 * 2.0 - 1.0
    inv = np.array([[2.0, -1.0], [-1.0, 4.0]]) / det
    step = inv @ g
    expected = np.max(np.abs(step) / np.sqrt(np.diag(inv)))
    limits = [(1e-5, None), (1e-5, None)]
    assert newton_distance([1.0, 1.0], g, F, limits) == pytest.approx(expected, rel=1e-12)
    # the second level at its upper bound, pushed up (negative score of -log L): only the
    # first is free, its step g_0 / F_00 over its sigma 1 / sqrt(F_00)
    at_bound = [(1e-5, None), (0.5, 1.0)]
    assert newton_distance([1.0, 1.0], g, F, at_bound) == pytest.approx(abs(0.1 / 4.0) * 2.0, rel=1e-12)
