"""Tests of ttlcore.sim.orbits: static arms, Keplerian orbits, lisaorbits files, factories.

Each physics check compares against something independent of the code under test:
the paper's numbers, Newtonian two-body invariants (vis-viva, period), finite differences,
the exact light-time equation evaluated from the positions, or the lisaorbits package
(a test-only dependency, used to write reference orbit files).
"""

from __future__ import annotations

import json
import shutil
import warnings

import h5py
import numpy as np
import pytest

from ttlcore.conventions import ARM_LENGTH, ASTRONOMICAL_UNIT, DAY, LINKS, C
from ttlcore.errors import ConfigError, TelemetryError
from ttlcore.sim.orbits import (
    GM_SUN,
    KeplerianOrbit,
    Orbit,
    OrbitFile,
    StaticOrbit,
    equal_arms,
    from_description,
    make_orbit,
    paper_unequal,
)

RECEIVER = [int(link[0]) - 1 for link in LINKS]
EMITTER = [int(link[1]) - 1 for link in LINKS]


@pytest.fixture(scope="module")
def lisaorbits():
    with warnings.catch_warnings():
        # lisaconstants warns about the installed astropy version; irrelevant here.
        warnings.simplefilter("ignore")
        return pytest.importorskip("lisaorbits")


@pytest.fixture(scope="module")
def kepler():
    return KeplerianOrbit()


# Reference file: lisaorbits' default KeplerianOrbits (relativistic: Shapiro delay, TPS),
# 30 samples every 1e4 s starting at t0 = 5000 s (so the grid does not start at zero).
FILE_T0, FILE_DT, FILE_SIZE = 5000.0, 1.0e4, 30


@pytest.fixture(scope="module")
def lisa_file(tmp_path_factory, lisaorbits):
    path = tmp_path_factory.mktemp("orbits") / "keplerian.h5"
    model = lisaorbits.KeplerianOrbits()
    model.write(str(path), dt=FILE_DT, size=FILE_SIZE, t0=FILE_T0, mode="w")
    return path, model


def _exact_light_time_residual(orbit: Orbit, t: np.ndarray) -> np.ndarray:
    """|tau_ij(t) - |x_i(t) - x_j(t - tau_ij)| / c| from the positions alone, shape (6, n)."""
    tau = orbit.ltt(t)
    x = orbit.positions(t)
    out = np.empty_like(tau)
    for k in range(6):
        x_emit = orbit.positions(t - tau[k])[EMITTER[k]]
        out[k] = np.abs(tau[k] - np.linalg.norm(x[RECEIVER[k]] - x_emit, axis=-1) / C)
    return out


# ---------------------------------------------------------------------------
# Keplerian orbits
# ---------------------------------------------------------------------------


def test_keplerian_shapes(kepler):
    t = np.linspace(0.0, 100.0, 7)
    assert kepler.ltt(t).shape == (6, 7)
    assert kepler.ltt_rate(t).shape == (6, 7)
    assert kepler.positions(t).shape == (3, 7, 3)
    assert kepler.velocities(t).shape == (3, 7, 3)
    # a scalar is one sample
    assert kepler.ltt(3.0).shape == (6, 1)
    np.testing.assert_array_equal(kepler.ltt(3.0)[:, 0], kepler.ltt(np.array([3.0]))[:, 0])


def test_keplerian_solves_keplers_equation(kepler):
    # E - e sin E = M (mod 2 pi) with M_k = n (t - t_init) + m_init1 - 2 pi (k - 1)/3, to
    # machine precision (|M| <= pi + e, so a few 1e-16 rad of rounding).
    t = np.linspace(-1e7, 4e7, 5001)
    n = np.sqrt(GM_SUN / ASTRONOMICAL_UNIT**3)
    mean = n * t[None, :] - 2 * np.pi * np.arange(3)[:, None] / 3
    E = kepler.eccentric_anomaly(t)
    e = kepler.eccentricity
    residual = np.angle(np.exp(1j * (E - e * np.sin(E) - mean)))
    assert np.max(np.abs(residual)) < 1e-13
    # First-order construction: e = L / (2 sqrt(3) a), up to relative corrections of
    # order alpha = L / (2 a) = 8e-3 (the second-order terms give 1.8e-3).
    assert abs(e / (ARM_LENGTH / (2 * np.sqrt(3) * ASTRONOMICAL_UNIT)) - 1) < 1e-2


def test_keplerian_ltt_range_over_one_day(kepler):
    t = np.arange(0.0, DAY + 1.0, 10.0)
    tau = kepler.ltt(t)
    # Nominal L / c = 8.339 s; the cartwheel's arms differ from L by < 0.5 % (see the
    # geometry test), i.e. by < 0.04 s, so every LTT must lie in [8.30, 8.35] s.
    assert tau.min() > 8.30 and tau.max() < 8.35


def test_keplerian_ltt_rates(kepler):
    t = np.arange(0.0, DAY + 1.0, 60.0)
    rate = kepler.ltt_rate(t)
    # Independent check of the analytic derivative: 4th-order central difference with
    # h = 100 s. Truncation h^4 tau^(5) / 30 ~ 1e8 * 0.02 s * (2e-7 /s)^5 ~ 1e-27 s/s; the
    # ~1e-12 s rounding noise of tau contributes ~1e-14 s/s; rates are ~3e-9 s/s.
    h = 100.0
    fd = (8 * (kepler.ltt(t + h) - kepler.ltt(t - h)) - (kepler.ltt(t + 2 * h) - kepler.ltt(t - 2 * h))) / (12 * h)
    np.testing.assert_allclose(rate, fd, rtol=0, atol=1e-13)
    # Arm flexing. The rate d tau/dt (s/s, = (dL/dt)/c) is what docs/physics.md calls the
    # "relative rate of about 1e-9": over the first day each link's largest |d tau/dt|
    # lies in [1e-10, 1e-7] and the largest exceeds 1e-9. (For lisaorbits' default
    # Keplerian orbits the values are 3.3e-9 for 12, 31, 3.1e-9 for 13, 21, and 1.0e-10 for
    # 23, 32, which are near a turning point on day one; dividing by tau ~ 8.3 s gives
    # 1.2e-11 .. 4e-10 per second.)
    max_rate = np.abs(rate).max(axis=1)
    assert np.all(max_rate >= 1e-10) and np.all(max_rate <= 1e-7), max_rate
    assert max_rate.max() > 1e-9
    # Over a year every arm flexes with |d tau/dt| up to 3.2e-9 .. 3.4e-9 s/s: check
    # the order of magnitude ([1e-9, 1e-8]) on a coarse grid.
    year = np.linspace(0.0, 365.25 * DAY, 2000)
    yearly = np.abs(kepler.ltt_rate(year)).max(axis=1)
    assert np.all((yearly > 1e-9) & (yearly < 1e-8)), yearly


def test_keplerian_ltt_solves_light_time_equation(kepler):
    t = np.linspace(0.0, DAY, 2001)
    residual = _exact_light_time_residual(kepler, t)
    # The emitter position is evaluated here exactly (Kepler's equation at t - tau), not
    # by the Taylor expansion the solver uses. The floor is double-precision rounding
    # of heliocentric coordinates (a few ulp of 1 AU = 3e-5 m each, ~1e-13 s); 1e-11 s
    # is stricter than the 1e-9 s the simulator needs.
    assert residual.max() < 1e-11, residual.max()


def test_keplerian_geometry(kepler):
    t = np.linspace(0.0, 365.25 * DAY, 730)
    x = kepler.positions(t)
    # Arm lengths stay within 1 % of the nominal 2.5e9 m (the cartwheel flexes by ~0.4 %).
    for i, j in ((0, 1), (1, 2), (2, 0)):
        arm = np.linalg.norm(x[i] - x[j], axis=-1)
        assert np.max(np.abs(arm / ARM_LENGTH - 1)) < 0.01
    # The constellation centre is 1 AU from the Sun up to O(e^2) ~ 2e-5 relative terms.
    centre = np.linalg.norm(x.mean(axis=0), axis=-1)
    assert np.max(np.abs(centre / ASTRONOMICAL_UNIT - 1)) < 1e-3
    # It lies in the ecliptic (|z| / R < e^2) and goes round the Sun once a year.
    assert np.max(np.abs(x.mean(axis=0)[:, 2])) / ASTRONOMICAL_UNIT < 1e-4


def test_keplerian_two_body_invariants(kepler):
    t = np.linspace(0.0, 365.25 * DAY, 500)
    x, v = kepler.positions(t), kepler.velocities(t)
    r = np.linalg.norm(x, axis=-1)
    # Vis-viva: v^2/2 - GM/r = -GM/(2a) for every Keplerian orbit, independently of e, i
    # and the phases; double-precision cancellation leaves ~1e-13 relative.
    energy = 0.5 * np.sum(v * v, axis=-1) - GM_SUN / r
    np.testing.assert_allclose(energy, -GM_SUN / (2 * ASTRONOMICAL_UNIT), rtol=1e-11)
    # Angular momentum x cross v is conserved (Kepler's second law), 1e-11 relative.
    h = np.cross(x, v)
    np.testing.assert_allclose(h, np.broadcast_to(h[:, :1], h.shape), rtol=0, atol=1e-11 * np.abs(h).max())
    # Period 2 pi / n with n = sqrt(GM / a^3) (Kepler's third law): positions repeat to
    # the rounding of the phase n t (~1e-15 rad * 1 AU ~ 1e-3 m).
    period = 2 * np.pi / np.sqrt(GM_SUN / ASTRONOMICAL_UNIT**3)
    np.testing.assert_allclose(kepler.positions(t[:20] + period), x[:, :20], rtol=0, atol=1e-2)
    # Velocities are the derivatives of the positions (4th-order central difference,
    # h = 10 s: truncation ~ h^4 a n^5 / 30 ~ 1e-21 m/s, rounding ~ 3e-5 m / 10 s).
    tt, step = t[:50], 10.0
    fd = (
        8 * (kepler.positions(tt + step) - kepler.positions(tt - step))
        - (kepler.positions(tt + 2 * step) - kepler.positions(tt - 2 * step))
    ) / (12 * step)
    np.testing.assert_allclose(kepler.velocities(tt), fd, rtol=0, atol=1e-4)


def test_keplerian_matches_lisaorbits_newtonian(tmp_path, lisaorbits, kepler):
    # Same model, parameters and phases (L = 2.5e9 m, a = 1 AU, lambda1 = m_init1 =
    # t_init = 0), with lisaorbits' relativistic extras switched off: iterative light
    # time without Shapiro delay. Both are then the same Newtonian light-time equation,
    # so the files must agree to rounding: positions to a few ulp of 1 AU (3e-5 m each),
    # LTTs to ~1e-12 s.
    path = tmp_path / "newtonian.h5"
    model = lisaorbits.KeplerianOrbits(
        L=ARM_LENGTH, lambda1=0.0, m_init1=0.0, t_init=0.0, tt_method="iterative", tt_niter=6, ignore_shapiro=True
    )
    model.write(str(path), dt=3600.0, size=25, t0=0.0, mode="w")
    with h5py.File(path, "r") as f:
        t = f.attrs["t0"] + np.arange(f.attrs["size"]) * f.attrs["dt"]
        ltt_file = f["tcb/ltt"][:].T  # (6, n), same link order 12, 23, 31, 13, 32, 21
        x_file = f["tcb/x"][:].transpose(1, 0, 2)  # (3 SC, n, 3)
        v_file = f["tcb/v"][:].transpose(1, 0, 2)
        d_ltt_file = f["tcb/d_ltt"][:].T
    np.testing.assert_allclose(kepler.positions(t), x_file, rtol=0, atol=1e-3)
    np.testing.assert_allclose(kepler.velocities(t), v_file, rtol=0, atol=1e-9)
    np.testing.assert_allclose(kepler.ltt(t), ltt_file, rtol=0, atol=1e-11)
    np.testing.assert_allclose(kepler.ltt_rate(t), d_ltt_file, rtol=0, atol=1e-14)


def test_keplerian_matches_lisaorbits_default(lisa_file, kepler):
    # lisaorbits' default LTTs add the Shapiro delay R_s ln((r_e + r_r + d)/(r_e + r_r - d)) / c
    # (R_s = 2 GM/c^2, about 1.6e-7 s here) to a second-order analytic expansion of the
    # light-time equation. Our Newtonian LTTs must differ from the file by exactly that
    # delay, computed here from our positions, up to the truncation of their expansion
    # (third order in v/c: ~ tau (v/c)^3 ~ 1e-11 s).
    path, _ = lisa_file
    with h5py.File(path, "r") as f:
        t = f.attrs["t0"] + np.arange(f.attrs["size"]) * f.attrs["dt"]
        ltt_file = f["tcb/ltt"][:].T
    tau = kepler.ltt(t)
    x = kepler.positions(t)
    r_s = 2 * GM_SUN / C**2
    shapiro = np.empty_like(tau)
    for k in range(6):
        x_emit = kepler.positions(t - tau[k])[EMITTER[k]]
        r_e = np.linalg.norm(x_emit, axis=-1)
        r_r = np.linalg.norm(x[RECEIVER[k]], axis=-1)
        d = np.linalg.norm(x[RECEIVER[k]] - x_emit, axis=-1)
        shapiro[k] = r_s * np.log((r_e + r_r + d) / (r_e + r_r - d)) / C
    assert np.all((ltt_file - tau > 1.5e-7) & (ltt_file - tau < 1.8e-7))
    np.testing.assert_allclose(tau + shapiro, ltt_file, rtol=0, atol=5e-11)


def test_keplerian_parameters_change_the_orbit():
    base = KeplerianOrbit()
    t = np.array([0.0, 1000.0])
    for kwargs in ({"lambda1": 0.3}, {"m_init1": 0.3}, {"t_init": 1e5}, {"arm_length": 2.0e9}):
        assert not np.allclose(KeplerianOrbit(**kwargs).positions(t), base.positions(t), rtol=1e-9)
    # a shifted epoch is a time shift
    shifted = KeplerianOrbit(t_init=1e5)
    np.testing.assert_allclose(shifted.ltt(t + 1e5), base.ltt(t), rtol=0, atol=1e-11)
    # arm length scales the LTTs
    assert abs(KeplerianOrbit(arm_length=2.0e9).ltt(t).mean() - 2.0e9 / C) < 0.01 * 2.0e9 / C


def test_keplerian_bad_parameters():
    with pytest.raises(ConfigError, match="arm_length"):
        KeplerianOrbit(arm_length=-1.0)
    with pytest.raises(ConfigError, match="lambda1"):
        KeplerianOrbit(lambda1="north")


# ---------------------------------------------------------------------------
# lisaorbits files
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("dataset", ["tcb/ltt", "tps/ppr"])
def test_orbit_file_reproduces_samples(lisa_file, dataset):
    path, _ = lisa_file
    orbit = OrbitFile(path, dataset=dataset)
    with h5py.File(path, "r") as f:
        grid = f.attrs["t0"] + np.arange(f.attrs["size"]) * f.attrs["dt"]
        samples = f[dataset][:].T
        x = f["tcb/x"][:].transpose(1, 0, 2)
        v = f["tcb/v"][:].transpose(1, 0, 2)
    np.testing.assert_array_equal(orbit.ltt(grid), samples)
    np.testing.assert_array_equal(orbit.positions(grid), x)
    np.testing.assert_array_equal(orbit.velocities(grid), v)
    assert orbit.t_range == (FILE_T0, FILE_T0 + (FILE_SIZE - 1) * FILE_DT)


def test_orbit_file_interpolates_ltt(lisa_file):
    # Between samples (dt = 1e4 s) compare with the generating model itself. Quintic
    # splines err by ~dt^6 tau^(6) ~ 1e24 * 0.02 s * (2e-7/s)^6 ~ 1e-18 s; what remains
    # is the ~1e-12 s rounding noise of lisaorbits' own LTTs. The simulator needs 1e-9 s.
    path, model = lisa_file
    orbit = OrbitFile(path, dataset="tcb/ltt")
    t = np.linspace(FILE_T0, FILE_T0 + (FILE_SIZE - 1) * FILE_DT, 997)[1:-1]
    np.testing.assert_allclose(orbit.ltt(t), model.compute_ltt(t).T, rtol=0, atol=1e-10)
    # Rates (~3e-9 s/s): the spline derivative errs by ~dt^5 tau^(6) ~ 1e-22 s/s, the file's
    # rounding noise gives ~1e-12 s / dt = 1e-16 s/s.
    np.testing.assert_allclose(orbit.ltt_rate(t), model.compute_ltt_derivative(t).T, rtol=0, atol=1e-14)
    # Positions (|x| = 1 AU, sixth derivative ~ a n^6): spline error ~1e-4 m at dt = 1e4 s.
    np.testing.assert_allclose(orbit.positions(t), model.compute_position(t).transpose(1, 0, 2), rtol=0, atol=1e-2)
    np.testing.assert_allclose(orbit.velocities(t), model.compute_velocity(t).transpose(1, 0, 2), rtol=0, atol=1e-8)


def test_orbit_file_interpolates_ppr(lisa_file):
    # tps/ppr is sampled in the receiver's proper time tau; its value at tau is the PPR at
    # the TCB time t = tau + delta_t_receiver(tau), which lisaorbits computes directly.
    path, model = lisa_file
    orbit = OrbitFile(path)  # default dataset tps/ppr
    assert orbit.dataset == "tps/ppr"
    tau = np.linspace(FILE_T0, FILE_T0 + (FILE_SIZE - 1) * FILE_DT, 601)[1:-1]
    delta_t = model.compute_tcb_deviation(tau, [1, 2, 3])  # (n, 3)
    t_tcb = tau[:, None] + delta_t[:, RECEIVER]
    expected = model.compute_ppr(t_tcb).T
    np.testing.assert_allclose(orbit.ltt(tau), expected, rtol=0, atol=1e-10)
    # PPRs differ from LTTs by the TPS offsets (~1e-8 s after a few days): the datasets are distinct.
    assert not np.array_equal(orbit.ltt(tau), OrbitFile(path, dataset="tcb/ltt").ltt(tau))


def test_orbit_file_missing_dataset(lisa_file, tmp_path):
    path, _ = lisa_file
    broken = tmp_path / "no_ppr.h5"
    shutil.copy(path, broken)
    with h5py.File(broken, "a") as f:
        del f["tps/ppr"]
        del f["tcb/x"]
    with pytest.raises(TelemetryError) as info:
        OrbitFile(broken, dataset="tps/ppr")
    assert str(broken) in str(info.value) and "tps/ppr" in str(info.value)
    assert info.value.dataset == "tps/ppr"
    # The other dataset still works; the positions fail only when asked for.
    orbit = OrbitFile(broken, dataset="tcb/ltt")
    assert orbit.ltt([FILE_T0]).shape == (6, 1)
    with pytest.raises(TelemetryError, match="tcb/x") as info:
        orbit.positions([FILE_T0])
    assert str(broken) in str(info.value)


def test_orbit_file_errors(lisa_file, tmp_path):
    path, _ = lisa_file
    orbit = OrbitFile(path, dataset="tcb/ltt")
    with pytest.raises(TelemetryError, match="outside the file's range") as info:
        orbit.ltt([FILE_T0 - 1.0, FILE_T0 + 10.0])
    assert str(path) in str(info.value) and "tcb/ltt" in str(info.value)
    with pytest.raises(TelemetryError, match="outside"):
        orbit.positions([FILE_T0 + FILE_SIZE * FILE_DT])
    not_hdf5 = tmp_path / "junk.h5"
    not_hdf5.write_text("not an HDF5 file")
    with pytest.raises(TelemetryError) as info:
        OrbitFile(not_hdf5)
    assert str(not_hdf5) in str(info.value)
    no_grid = tmp_path / "no_grid.h5"
    with h5py.File(no_grid, "w") as f:
        f["tcb/ltt"] = np.full((4, 6), 8.3)
    with pytest.raises(TelemetryError, match="t0"):
        OrbitFile(no_grid, dataset="tcb/ltt")
    bad_shape = tmp_path / "bad_shape.h5"
    with h5py.File(bad_shape, "w") as f:
        f.attrs.update({"t0": 0.0, "dt": 1.0, "size": 4})
        f["tcb/ltt"] = np.full((4, 5), 8.3)
    with pytest.raises(TelemetryError, match="shape"):
        OrbitFile(bad_shape, dataset="tcb/ltt")
    with pytest.raises(ConfigError, match="dataset"):
        OrbitFile(path, dataset="tcb/x")


# ---------------------------------------------------------------------------
# Static arms
# ---------------------------------------------------------------------------


def test_paper_unequal_values():
    orbit = paper_unequal()
    # The paper's static unequal arms (section "changing arm lengths").
    paper = {"12": 8.425, "13": 8.322, "23": 8.372, "21": 8.322, "31": 8.322, "32": 8.372}
    tau = orbit.ltt(np.arange(5.0))
    for k, link in enumerate(LINKS):
        np.testing.assert_array_equal(tau[k], paper[link])
    np.testing.assert_array_equal(orbit.ltt_rate(np.arange(5.0)), 0.0)
    np.testing.assert_array_equal(orbit.velocities(np.arange(5.0)), 0.0)


def test_static_positions_match_mean_arms():
    orbit = paper_unequal()
    x = orbit.positions(np.zeros(3))
    assert x.shape == (3, 3, 3)
    ltt = orbit.values
    for i, j in ((1, 2), (2, 3), (3, 1)):
        arm = np.linalg.norm(x[i - 1, 0] - x[j - 1, 0])
        expected = C * 0.5 * (ltt[f"{i}{j}"] + ltt[f"{j}{i}"])
        assert abs(arm / expected - 1) < 1e-12  # exact up to rounding
    np.testing.assert_allclose(x[:, 0].mean(axis=0), 0.0, atol=1e-3)  # centred on the origin


def test_equal_arms():
    orbit = equal_arms()
    np.testing.assert_array_equal(orbit.ltt([0.0, 1.0]), ARM_LENGTH / C)
    assert abs(ARM_LENGTH / C - 8.339) < 1e-3
    x = orbit.positions([0.0])[:, 0]
    for i, j in ((0, 1), (1, 2), (2, 0)):
        assert abs(np.linalg.norm(x[i] - x[j]) / ARM_LENGTH - 1) < 1e-12
    np.testing.assert_array_equal(equal_arms(2.0e9).ltt([0.0]), 2.0e9 / C)
    with pytest.raises(ConfigError):
        equal_arms(-1.0)


def test_static_orbit_validation():
    with pytest.raises(ConfigError, match="21"):
        StaticOrbit({"12": 8.3, "23": 8.3, "31": 8.3, "13": 8.3, "32": 8.3})
    with pytest.raises(ConfigError, match="triangle"):
        StaticOrbit([1.0, 10.0, 1.0, 1.0, 10.0, 1.0])  # L_23 = 10 > L_12 + L_31 = 2
    with pytest.raises(ConfigError):
        StaticOrbit([8.3] * 5)
    orbit = StaticOrbit([8.1, 8.2, 8.3, 8.4, 8.5, 8.6])  # sequence in LINKS order
    assert orbit.values == dict(zip(LINKS, [8.1, 8.2, 8.3, 8.4, 8.5, 8.6]))


# ---------------------------------------------------------------------------
# Factories and descriptions
# ---------------------------------------------------------------------------


def test_make_orbit(lisa_file):
    path, _ = lisa_file
    assert make_orbit("equal").describe() == equal_arms().describe()
    assert make_orbit("EQUAL", arm_length=2e9).describe() == equal_arms(2e9).describe()
    assert make_orbit("unequal").describe() == paper_unequal().describe()
    kep = make_orbit("keplerian", lambda1=0.1)
    assert isinstance(kep, KeplerianOrbit) and kep.lambda1 == 0.1
    from_file = make_orbit(str(path))
    assert isinstance(from_file, OrbitFile) and from_file.dataset == "tps/ppr"
    assert make_orbit(f"{path}:tcb/ltt").dataset == "tcb/ltt"
    assert make_orbit(path, dataset="tcb/ltt").dataset == "tcb/ltt"


def test_make_orbit_errors(tmp_path, lisa_file):
    path, _ = lisa_file
    with pytest.raises(ConfigError, match="unknown orbit spec 'circular'"):
        make_orbit("circular")
    with pytest.raises(ConfigError, match="no such orbit file"):
        make_orbit(str(tmp_path / "missing.h5"))
    with pytest.raises(ConfigError, match="radius"):
        make_orbit("keplerian", radius=1.0)
    with pytest.raises(ConfigError, match="arm_length"):
        make_orbit("unequal", arm_length=2e9)
    with pytest.raises(ConfigError, match="dataset"):
        make_orbit(f"{path}:tcb/ltt", dataset="tps/ppr")


def test_describe_round_trip(lisa_file):
    path, _ = lisa_file
    t = np.linspace(FILE_T0, FILE_T0 + 1e5, 11)
    orbits = [
        equal_arms(),
        paper_unequal(),
        StaticOrbit([8.1, 8.2, 8.3, 8.4, 8.5, 8.6], name="custom"),
        KeplerianOrbit(arm_length=2.4e9, t_init=123.0, lambda1=0.2, m_init1=-0.4, delta=0.0),
        OrbitFile(path, dataset="tcb/ltt", order=3),
    ]
    for orbit in orbits:
        description = orbit.describe()
        rebuilt = from_description(json.loads(json.dumps(description)))
        assert type(rebuilt) is type(orbit)
        assert rebuilt.describe() == description
        assert rebuilt.name == orbit.name
        np.testing.assert_array_equal(rebuilt.ltt(t), orbit.ltt(t))
        np.testing.assert_array_equal(rebuilt.positions(t), orbit.positions(t))
        assert make_orbit(description).describe() == description
    with pytest.raises(ConfigError, match="type"):
        from_description({"type": "spiral"})
    with pytest.raises(ConfigError):
        from_description({"type": "keplerian", "radius": 1.0})
