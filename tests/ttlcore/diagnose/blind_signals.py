"""Blind signals for the diagnosis tests, made by code the diagnosis never runs.

- gravitational-wave chirps projected by lisagwresponse (``ReadStrain`` on a lisaorbits
  Keplerian orbit file that the simulator reads too; the strain is a leading-order
  (Newtonian quadrupole) inspiral written here, cut smoothly at the innermost stable
  orbit) and scaled to a requested optimal SNR computed here (pytdi-free: our TDI of the
  link responses against the analytic secondary-noise PSD of ``ttlcore.estimate.noise_psd``,
  the same reference as ``diagnose_helpers.injected_asd_ratio``);
- test-mass glitches from lisaglitch (``IntegratedShapeletGlitch``: the LISA Pathfinder
  model, velocity [m/s]), placed as docs/physics.md places a test mass: ``2 v / c`` into
  ``eta_ij`` and, delayed by ``L_ji``, into ``eta_ji``;
- gaps from lisa-gap (``GapMaskGenerator``: NaN, missing data);
- a noise level that doubles: extra Gaussian OMS-shaped noise (the paper's 15 pm/sqrt(Hz)
  with its 2 mHz corner, written here) on every link for a few hours, which doubles the
  OMS part of the PSD there.
"""

from __future__ import annotations

import warnings

import numpy as np

from ttlcore.conventions import LINKS
from ttlcore.estimate.noise_psd import tdi_noise_csd
from ttlcore.io.telemetry import Telemetry
from ttlcore.tdi.data import compute_tdi

C = 299792458.0
G_MSUN_S = 4.925490947e-6  # G M_sun / c^3 [s]
MPC_S = 3.0856775814913673e22 / C  # one megaparsec in light seconds


def chirp_strain(t, t_c, m_total, q, distance_mpc, iota, phi_c=0.0, taper_cycles=2.0):
    """h+, hx of a leading-order inspiral of total mass ``m_total`` [M_sun], mass ratio
    ``q`` <= 1, merging at ``t_c`` [s], at ``distance_mpc``; cut at the innermost stable
    circular orbit (``f = 1 / (6^1.5 pi M)``) by a cosine taper over ``taper_cycles``.

    ``f(tau) = (5 / tau)^(3/8) / (8 pi Mc^(5/8))``, ``Phi = -2 (tau / (5 Mc))^(5/8)``,
    ``h = 4 Mc^(5/3) (pi f)^(2/3) / D`` (Mc, M, D in seconds)."""
    m1 = m_total / (1 + q)
    m2 = m_total - m1
    mc = (m1 * m2) ** 0.6 / m_total**0.2 * G_MSUN_S
    m_s = m_total * G_MSUN_S
    d = distance_mpc * MPC_S
    f_isco = 1.0 / (6**1.5 * np.pi * m_s)
    tau_isco = 5.0 * mc * (8 * np.pi * mc * f_isco) ** (-8 / 3)
    tau = np.maximum(t_c - np.asarray(t, dtype=float), tau_isco)
    f = (5.0 / tau) ** 0.375 / (8 * np.pi * mc**0.625)
    phase = -2.0 * (tau / (5.0 * mc)) ** 0.625 + phi_c
    amp = 4.0 * mc ** (5 / 3) * (np.pi * f) ** (2 / 3) / d
    # smooth end: past the ISCO the frequency is held and the amplitude tapered to zero
    after = np.asarray(t, dtype=float) - (t_c - tau_isco)
    span = taper_cycles / f_isco
    w = np.where(after <= 0, 1.0, np.where(after >= span, 0.0, 0.5 + 0.5 * np.cos(np.pi * np.clip(after / span, 0, 1))))
    phase = np.where(after > 0, phase + 2 * np.pi * f_isco * np.maximum(after, 0), phase)
    hp = amp * w * (1 + np.cos(iota) ** 2) / 2 * np.cos(2 * phase)
    hc = amp * w * np.cos(iota) * np.sin(2 * phase)
    return hp, hc


def random_merger(rng, duration: float, t_c=(0.3, 0.95), log10_mass=(5.3, 6.3)) -> dict:
    """A merger's parameters drawn from ``rng`` (for :func:`gw_link_responses`): coalescence at a
    random share ``t_c`` of ``duration`` [s], total mass log-uniform in ``log10_mass`` [solar
    masses], random mass ratio, inclination, sky position and polarisation, 10 Gpc (the
    tests scale it to an SNR)."""
    return dict(
        t_c=rng.uniform(*t_c) * duration,
        m_total=10 ** rng.uniform(*log10_mass),
        q=rng.uniform(0.3, 1.0),
        distance_mpc=1e4,
        iota=rng.uniform(0, np.pi),
        beta=rng.uniform(-1.2, 1.2),
        lam=rng.uniform(0, 2 * np.pi),
        psi=rng.uniform(0, np.pi),
    )


def write_orbits(path, duration: float) -> None:
    """A lisaorbits Keplerian orbit file covering ``duration`` [s] (and some margin)."""
    import lisaorbits

    n = int(duration / 1e4) + 6
    lisaorbits.KeplerianOrbits().write(str(path), dt=1.0e4, size=n, t0=-2.0e4, mode="w")


def gw_link_responses(orbit_path, duration: float, fs: float, t0: float = 0.0, **source) -> np.ndarray:
    """lisagwresponse's link responses (6, n) on ``t = t0 + arange(n) / fs`` of the chirp
    ``source`` (``t_c``, ``m_total``, ``q``, ``distance_mpc``, ``iota``, ``beta``,
    ``lam``, ``psi``), links in lisagwresponse's order 12, 23, 31, 13, 32, 21 (ours)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import lisagwresponse
    src = dict(source)
    beta, lam, psi = src.pop("beta"), src.pop("lam"), src.pop("psi")
    t_s = t0 + np.arange(-2000.0, duration + 2000.0, 1.0)
    hp, hc = chirp_strain(t_s, **src)
    # the polarisation angle rotates (h+, hx) by 2 psi (lisagwresponse's convention)
    c2, s2 = np.cos(2 * psi), np.sin(2 * psi)
    hp, hc = c2 * hp - s2 * hc, s2 * hp + c2 * hc
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rs = lisagwresponse.ReadStrain(t_s, hp, hc, gw_beta=beta, gw_lambda=lam, orbits=str(orbit_path))
        t = t0 + np.arange(int(duration * fs)) / fs
        y = rs.compute_gw_response(t).T
    return np.asarray(y)


def optimal_snr(tm_like: Telemetry, eta_signal: np.ndarray, band=(3e-3, 0.8)) -> float:
    """Optimal SNR of a signal in ``eta`` (6, n): A, E, T of it (our TDI, no regressors),
    ``rho^2 = 4 sum |x(f)|^2 / S(f) df`` over the band against the analytic secondary noise
    (diagonal), the edges of the TDI start-up cut."""
    only = Telemetry(
        t0=tm_like.t0, fs=tm_like.fs, eta=eta_signal, dws_phi=tm_like.dws_phi, dws_eta=tm_like.dws_eta, ltt=tm_like.ltt
    )
    td = compute_tdi(only, names=()).to_aet()
    x = td.data
    ok = np.isfinite(x).all(axis=0)
    x = np.where(ok, x, 0.0)
    n = x.shape[1]
    X = np.fft.rfft(x, axis=1) / td.fs
    f = np.fft.rfftfreq(n, 1 / td.fs)
    sel = (f >= band[0]) & (f <= band[1])
    S = np.real(np.einsum("mii->mi", tdi_noise_csd(f[sel], td.ltt_mean)))  # (m, 3)
    df = f[1] - f[0]
    return float(np.sqrt(4 * np.sum(np.abs(X[:, sel]) ** 2 / S.T) * df))


def glitch_eta(t, ltt, glitches) -> np.ndarray:
    """``eta`` (6, n) of test-mass glitches from lisaglitch: each ``(mosa, t_inj, level,
    beta)`` an ``IntegratedShapeletGlitch`` (velocity [m/s]; its velocity step ``Delta v``
    is ``level``: the signal rises from 0 to ``level``, checked against lisaglitch in
    ``test_glitches.py``) on
    test mass ``mosa``, entering ``eta_mosa`` as ``2 v(t) / c`` and ``eta_ji`` as
    ``2 v(t - L_ji) / c``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import lisaglitch
    out = np.zeros((6, np.size(t)))
    for mosa, t_inj, level, beta in glitches:
        g = lisaglitch.IntegratedShapeletGlitch(inj_point=f"tm_{mosa}", t_inj=t_inj, level=level, beta=beta)
        i = LINKS.index(mosa)
        j = LINKS.index(mosa[::-1])
        out[i] += 2 * g.compute_signal(np.asarray(t)) / C
        out[j] += 2 * g.compute_signal(np.asarray(t) - ltt[j]) / C
    return out


def gap_mask(t, n_gaps_per_day: float, duration_hr: float, seed: int, nan: bool = True) -> np.ndarray:
    """A lisa-gap planned-gap mask (1 valid; NaN, or 0 with ``nan=False``, in a gap) on ``t`` [s]."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import lisagap
    defs = {
        "planned": {"blind": {"rate_per_year": n_gaps_per_day * 365.25, "duration_hr": duration_hr}},
        "unplanned": {},
    }
    gen = lisagap.GapMaskGenerator(np.asarray(t, dtype=float), defs, treat_as_nan=nan, planseed=seed)
    return np.asarray(gen.generate_mask(), dtype=float)


def oms_noise_eta(n: int, fs: float, seed: int, scale: float = 0.5) -> np.ndarray:
    """Gaussian noise (6, n) [fractional frequency] with an OMS-shaped PSD on every link:
    displacement ASD ``scale x 15 pm/sqrt(Hz) sqrt(1 + (2 mHz / f)^4)``, times ``2 pi f / c``
    (at ``scale`` 1 the hours holding it read chi2/dof 4.5-4.8 on a simulated day: the
    simulator's summed OMS noise is below 15 pm; 0.5 about doubles it)."""
    rng = np.random.default_rng(seed)
    f = np.fft.rfftfreq(n, 1 / fs)
    f[0] = f[1]
    asd = scale * 15e-12 * np.sqrt(1 + (2e-3 / f) ** 4) * 2 * np.pi * f / C
    w = rng.standard_normal((6, n))
    W = np.fft.rfft(w, axis=1) * asd * np.sqrt(fs / 2)
    return np.fft.irfft(W, n=n, axis=1)
