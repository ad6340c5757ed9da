r"""Massive black-hole binary mergers: a closed-form inspiral-merger-ringdown waveform.

Approximant ("PhenomA amplitude, TaylorF2 phase, exponential merger phase")
--------------------------------------------------------------------------
Frequency domain, dominant (2, 2) harmonic, non-spinning, quasi-circular; detector-frame
(redshifted) masses ``m1, m2``, total ``M``, symmetric mass ratio ``eta``, chirp mass
``Mc = eta^(3/5) M`` (all as times, ``G m / c^3``), luminosity distance ``d``:

    h~_plus(f)  = (1 + cos^2 i) / 2 * A(f) exp(-i Psi(f)),
    h~_cross(f) = -i cos(i) * A(f) exp(-i Psi(f)).

Amplitude ``A(f)``: IMRPhenomA (Ajith et al. 2008, PRD 77, 104017, eq. 4.13 with the
coefficients of their table I as corrected in arXiv:0712.0343, the values lalsimulation's
``LALSimIMRPhenom.c`` uses):

    A = Q(f_merg) (f / f_merg)^(-7/6)                        f < f_merg,
        Q(f_merg) (f / f_merg)^(-2/3)                        f_merg <= f < f_ring,
        Q(f_merg) w L(f, f_ring, sigma)                     f >= f_ring,
    Q(f) = sqrt(5/24) pi^(-2/3) Mc^(5/6) f^(-7/6) / d        (the stationary-phase Newtonian amplitude),
    L = sigma / (2 pi ((f - f_ring)^2 + sigma^2 / 4)),  w = (pi sigma / 2) (f_ring / f_merg)^(-2/3),
    pi M f_x = a_x eta^2 + b_x eta + c_x   for f_merg, f_ring, sigma, f_cut,

continued smoothly beyond PhenomA's ``f_cut`` by a cosine taper to zero at ``2 f_cut``
(instead of a hard cut, which would ring in the time domain).

Phase: the PhenomA phase fit is not usable over a whole day of inspiral (its group delay is
not monotonic below ``M f ~ 0.01``, checked), so the phase is

- below ``f_j = 0.018 / M`` (the end of PhenomD's inspiral region): TaylorF2 to 2PN order
  (e.g. Buonanno et al. 2009, PRD 80, 084043, table I),
  ``Psi = 2 pi f t_c - phi_c - pi/4 + 3/(128 eta v^5) [1 + (3715/756 + 55 eta/9) v^2 - 16 pi v^3
  + (15293365/508032 + 27145 eta/504 + 3085 eta^2/72) v^4]``, ``v = (pi M f)^(1/3)``;
- above ``f_j``: the group delay ``t(f) = Psi'(f) / 2 pi`` continues C1 from its
  TaylorF2 value ``t_j`` and slope ``s_j`` and approaches the merger time exponentially,
  ``t(f) = t_j + (t_m - t_j) (1 - exp(-(f - f_j) s_j / (t_m - t_j)))``, where ``t_m`` is
  the time given as coalescence time ``t_c``: the merger-ringdown frequencies all arrive
  at ``t_c`` (the amplitude peaks there). The phase is the integral of ``2 pi t(f)``.

Time domain: ``h~`` is filled on the FFT grid of a window (default 8 days before to 1 day
after ``t_c``, 2 s sampling, Nyquist 0.25 Hz, ten times the highest frequency present)
and inverse-FFT'd; the inspiral is started at the frequency reached 90 % of the window
before ``t_c`` (Newtonian chirp time) with a cosine taper over [f_low, 1.5 f_low], so the
signal neither wraps around nor starts abruptly. The link response evaluates the strain at
arbitrary times by a cubic spline of the 2-s series (error < 1e-4 of the amplitude at
30 mHz).

Limits: no spins, no higher harmonics, no precession; the merger phase is a smooth
interpolation, not calibrated to numerical relativity; TaylorF2 at 2PN has phase errors of
order radians over the last days of inspiral compared to state-of-the-art models. The
*amplitude spectrum* - what matters for the TTL fit and for the GW-intact check - follows
PhenomA, which matches numerical relativity to ~10 % for comparable masses. For parameter
estimation use a library approximant (IMRPhenomD/HM via lalsimulation or bbhx) and inject
its link response through a lisagwresponse file (``--gw FILE``).

The paper's two mergers (LDC Sangria, its table II): MBHB1 3.20e6 + 3.06e6 Msun at
z = 2.88 (luminosity distance 24.83 Gpc; the paper's "kly" is a typo for Gpc: Planck-2018
gives 24.5 Gpc at z = 2.88), t_c = 13.62e6 s; MBHB2 9.16e5 + 7.02e5 Msun at z = 1.10
(7.71 Gpc), t_c = 11.26e6 s. The masses are taken as *detector-frame* masses, as the LDC
catalogue stores them: the paper's response maxima "above 2 mHz and around 10 mHz" are
PhenomA's ring-down frequencies for these masses (2.6 and 9.9 mHz), and would be 3.9 times
lower for source-frame masses. Sky position, inclination, polarisation and phase are not in
the paper: the values of :data:`PAPER_MBHBS` are our choices.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from ..conventions import C
from .sources import GM_SUN

__all__ = ["MBHB", "PAPER_MBHBS", "GPC", "phenoma_parameters", "fd_amplitude", "fd_phase", "time_domain"]

#: Gigaparsec [m].
GPC = 1e9 * 648_000.0 / math.pi * 149_597_870_700.0

# IMRPhenomA frequency coefficients (a eta^2 + b eta + c) / (pi M): f_merg, f_ring, sigma, f_cut
_PA_A = np.array([2.9740e-1, 5.9411e-1, 5.0801e-1, 8.4845e-1])
_PA_B = np.array([4.4810e-2, 8.9794e-2, 7.7515e-2, 1.2848e-1])
_PA_C = np.array([9.5560e-2, 1.9111e-1, 2.2369e-2, 2.7299e-1])
#: End of the TaylorF2 region, M f.
MF_JOIN = 0.018


@dataclass(frozen=True)
class MBHB:
    """A non-spinning massive black-hole binary merger (module docstring).

    Parameters
    ----------
    m1, m2 : float
        Detector-frame masses [Msun].
    distance : float
        Luminosity distance [m].
    t_c : float
        Merger (coalescence) time [s], barycentric.
    inclination, psi, phi_c : float
        Inclination, polarisation angle, coalescence phase [rad].
    beta, lam : float
        Ecliptic latitude and longitude [rad].
    name : str
    """

    m1: float
    m2: float
    distance: float
    t_c: float
    inclination: float = math.pi / 3
    psi: float = 0.0
    phi_c: float = 0.0
    beta: float = 0.0
    lam: float = 0.0
    name: str = ""

    def __post_init__(self):
        for key in ("m1", "m2", "distance"):
            v = float(getattr(self, key))
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"MBHB {key} must be positive, got {getattr(self, key)!r}")
        for key in ("t_c", "inclination", "psi", "phi_c", "beta", "lam"):
            if not math.isfinite(float(getattr(self, key))):
                raise ValueError(f"MBHB {key} must be finite, got {getattr(self, key)!r}")

    @property
    def total_mass_s(self) -> float:
        return (self.m1 + self.m2) * GM_SUN / C**3

    @property
    def eta(self) -> float:
        return self.m1 * self.m2 / (self.m1 + self.m2) ** 2

    def to_dict(self) -> dict:
        return asdict(self)


def phenoma_parameters(m_s: float, eta: float) -> dict:
    """PhenomA ``f_merg, f_ring, sigma, f_cut`` [Hz] for total mass ``m_s`` [s] and ``eta``."""
    v = (_PA_A * eta**2 + _PA_B * eta + _PA_C) / (math.pi * m_s)
    return dict(zip(("f_merg", "f_ring", "sigma", "f_cut"), (float(x) for x in v)))


def fd_amplitude(f, m_s: float, eta: float, distance_s: float) -> np.ndarray:
    """``A(f)`` of the module docstring (without the taper at low frequency) [1/Hz]."""
    f = np.asarray(f, dtype=float)
    p = phenoma_parameters(m_s, eta)
    fm, fr, sg, fc = p["f_merg"], p["f_ring"], p["sigma"], p["f_cut"]
    mc = eta**0.6 * m_s
    q_m = math.sqrt(5 / 24) * math.pi ** (-2 / 3) * mc ** (5 / 6) * fm ** (-7 / 6) / distance_s
    out = np.zeros_like(f)
    pos = f > 0
    fp = f[pos]
    a = np.where(fp < fm, (fp / fm) ** (-7 / 6), (fp / fm) ** (-2 / 3))
    lor = sg / (2 * np.pi * ((fp - fr) ** 2 + sg**2 / 4))
    w = 0.5 * np.pi * sg * (fr / fm) ** (-2 / 3)
    a = np.where(fp >= fr, w * lor, a)
    taper = np.where(fp <= fc, 1.0, np.where(fp >= 2 * fc, 0.0, 0.5 * (1 + np.cos(np.pi * (fp - fc) / fc))))
    out[pos] = q_m * a * taper
    return out


def _taylorf2(f, m_s, eta):
    """TaylorF2 2PN phase without the ``2 pi f t_c - phi_c - pi/4`` part, and its f-derivative."""
    v = (np.pi * m_s * f) ** (1 / 3)
    c2 = 3715 / 756 + 55 * eta / 9
    c3 = -16 * np.pi
    c4 = 15293365 / 508032 + 27145 * eta / 504 + 3085 * eta**2 / 72
    pref = 3 / (128 * eta)
    psi = pref * v**-5 * (1 + c2 * v**2 + c3 * v**3 + c4 * v**4)
    # d/dv, then dv/df = v / (3 f)
    dpsi_dv = pref * (-5 * v**-6 - 3 * c2 * v**-4 - 2 * c3 * v**-3 - c4 * v**-2)
    return psi, dpsi_dv * v / (3 * f)


def fd_phase(f, m_s: float, eta: float, t_c: float, phi_c: float = 0.0) -> np.ndarray:
    """``Psi(f)`` of the module docstring [rad] (``t_c`` in the time origin of the FFT window)."""
    f = np.asarray(f, dtype=float)
    fj = MF_JOIN / m_s
    out = np.zeros_like(f)
    pos = f > 0
    fp = f[pos]
    lo = fp <= fj
    psi_lo, _ = _taylorf2(fp[lo], m_s, eta)
    res = np.empty_like(fp)
    res[lo] = 2 * np.pi * fp[lo] * t_c + psi_lo
    # group delay and slope of the TaylorF2 part at f_j (relative to t_c)
    h = 1e-4 * fj
    psi_j, dpsi_j = _taylorf2(np.array([fj]), m_s, eta)
    _, dpsi_jp = _taylorf2(np.array([fj + h]), m_s, eta)
    _, dpsi_jm = _taylorf2(np.array([fj - h]), m_s, eta)
    t_j = float(dpsi_j[0]) / (2 * np.pi)  # < 0: before t_c
    s_j = float(dpsi_jp[0] - dpsi_jm[0]) / (2 * h) / (2 * np.pi)  # > 0
    gap = -t_j
    delta = gap / s_j
    x = fp[~lo] - fj
    # integral of 2 pi [t_c + t_j + gap (1 - exp(-x / delta))] dx
    integral = 2 * np.pi * ((t_c + t_j + gap) * x - gap * delta * (1 - np.exp(-x / delta)))
    res[~lo] = 2 * np.pi * fj * t_c + float(psi_j[0]) + integral
    out[pos] = res - phi_c - np.pi / 4
    return out


def chirp_time(f, m_s: float, eta: float) -> np.ndarray:
    """Newtonian time to coalescence from GW frequency ``f``: ``5 M / (256 eta) (pi M f)^(-8/3)`` [s]."""
    return 5 * m_s / (256 * eta) * (np.pi * m_s * np.asarray(f, dtype=float)) ** (-8 / 3)


def time_domain(source: MBHB, *, before: float = 8 * 86400.0, after: float = 86400.0, dt: float = 2.0):
    """Barycentric ``h_plus, h_cross`` of ``source`` on a uniform grid (source frame, before ``psi``).

    Returns
    -------
    t : ndarray (n,)
        Times [s] from ``t_c - before`` to ``t_c + after``.
    hplus, hcross : ndarray (n,)
    """
    m_s, eta = source.total_mass_s, source.eta
    d_s = source.distance / C
    n = int(2 ** math.ceil(math.log2((before + after) / dt)))
    t_w = source.t_c - before
    f = np.fft.rfftfreq(n, dt)
    f_low = float((0.9 * before * 256 * eta / (5 * m_s)) ** (-3 / 8) / (np.pi * m_s))
    amp = fd_amplitude(f, m_s, eta, d_s)
    ramp = np.clip((f - f_low) / (0.5 * f_low), 0, 1)
    amp *= 0.5 * (1 - np.cos(np.pi * ramp))
    psi = fd_phase(f, m_s, eta, before, source.phi_c)
    base = amp * np.exp(-1j * psi)
    ci = math.cos(source.inclination)
    hp = np.fft.irfft(0.5 * (1 + ci * ci) * base / dt, n)
    hc = np.fft.irfft(-1j * ci * base / dt, n)
    t = t_w + np.arange(n) * dt
    return t, hp, hc


class MBHBWaveform:
    """``h_plus(t)``, ``h_cross(t)`` of an :class:`MBHB` as callables (cubic spline of :func:`time_domain`);
    zero outside the window."""

    def __init__(self, source: MBHB, **kw):
        self.source = source
        self.t, hp, hc = time_domain(source, **kw)
        self._sp = CubicSpline(self.t, np.stack([hp, hc], axis=-1), axis=0)

    def _eval(self, s, k):
        s = np.asarray(s, dtype=float)
        out = self._sp(s)[..., k]
        return np.where((s >= self.t[0]) & (s <= self.t[-1]), out, 0.0)

    def hplus(self, s):
        return self._eval(s, 0)

    def hcross(self, s):
        return self._eval(s, 1)


#: The paper's two mergers (module docstring); angles are our choices.
PAPER_MBHBS = {
    "mbhb1": dict(
        m1=3.20e6,
        m2=3.06e6,
        distance=24.83 * GPC,
        t_c=13.62e6,
        inclination=math.pi / 3,
        psi=0.4,
        phi_c=0.0,
        beta=0.3,
        lam=1.0,
        name="mbhb1",
    ),
    "mbhb2": dict(
        m1=9.16e5,
        m2=7.02e5,
        distance=7.71 * GPC,
        t_c=11.26e6,
        inclination=math.pi / 4,
        psi=1.2,
        phi_c=0.0,
        beta=-0.5,
        lam=4.0,
        name="mbhb2",
    ),
}
#: The paper's data-segment start times t0 [s] for the two mergers.
PAPER_MBHB_T0 = {"mbhb1": 13.57e6, "mbhb2": 11.22e6}
