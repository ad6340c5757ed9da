r"""Gravitational-wave sources: quasi-monochromatic galactic binaries and verification binaries.

Waveform convention (lisagwresponse's ``GalacticBinary``, followed exactly)
----------------------------------------------------------------------------
With ``tau = t - t_init`` (barycentric time) the GW phase and the source-frame
polarisations are

    Phi(t)    = 2 pi (f0 tau + fdot tau^2 / 2) - phi0,
    h_plus    = -A (1 + cos^2 i) cos Phi,
    h_cross   = -2 A cos i sin Phi,

and the polarisation angle ``psi`` and the sky position are applied by
:func:`ttlcore.gw.response.link_response` (its rotation of the polarisation basis by ``psi`` is
identical to lisagwresponse's rotation of ``(h_plus, h_cross)`` by ``2 psi``).

``A`` is the usual catalogue amplitude of galactic binaries (Kupfer et al. 2018, 2024;
the LISA Data Challenges; lisagwresponse's ``VerificationBinary``),

    A = 2 (G M_c)^(5/3) (pi f)^(2/3) / (c^4 d),     M_c = (m1 m2)^(3/5) / (m1 + m2)^(1/5),

for which the quadrupole strain of a circular binary is ``h_plus = A (1 + cos^2 i)
cos(...)``, ``h_cross = 2 A cos i sin(...)`` (e.g. Maggiore, *Gravitational Waves* vol. 1,
eq. 4.29: ``h_plus = (4/d) (G M_c/c^2)^(5/3) (pi f/c)^(2/3) (1 + cos^2 i)/2 cos``). So the
peak ``|h_plus|`` of a face-on source is ``2 A``, not ``A``: the often-quoted form
``h_plus = A (1 + cos^2 i)/2 cos Phi`` goes with an amplitude twice as large as the one
above. The overall minus sign and ``-phi0`` are lisagwresponse's phase conventions
(a constant phase offset).

Quadrupole (GW-driven) frequency derivative, used when no measured value is given:

    fdot = (96/5) pi^(8/3) (G M_c / c^3)^(5/3) f^(11/3).

Verification binaries
---------------------
:data:`VERIFICATION_BINARIES` holds HM Cnc and ZTF J1539+5027, the two sources of the
paper (GW frequencies 6.220 and 4.822 mHz, as it quotes from Kupfer et al. 2024). Their
input values are in :data:`VERIFICATION_BINARY_PARAMETERS`, each with its source. The
Kupfer et al. (2024, ApJ 963, 100) table itself could not be consulted from the
environment where this module was written; the values below come from the discovery and
follow-up papers and the amplitudes are *computed* from the formula above. What was and
was not checked:

- HM Cnc: the mass ratio q = 0.50 +- 0.13 (Roelofs et al. 2010, ApJL 711, L138, abstract)
  and the adopted masses 0.55 + 0.27 Msun, inclination 38 deg and distance 5 kpc are the
  values of Roelofs et al. (2010) used by Kupfer et al. (2018, MNRAS 480, 302) and, for
  want of a Gaia parallax, kept in Kupfer et al. (2024). They give A = 6.4e-23, the
  amplitude Kupfer et al. (2018) list. The masses are uncertain: Munday et al. (2023,
  MNRAS 518, 5123) favour ~1.0 + 0.17 Msun, which has nearly the same chirp mass (0.335
  vs 0.331 Msun), so A changes by < 1 %. The orbital frequency derivative ~3.57e-16 Hz/s
  (Munday et al. 2023; Strohmayer 2021) is quoted to 3 digits from memory of those papers,
  not re-read here; over one day it changes the phase by ~1e-5 rad, i.e. nothing.
  Polarisation angle and initial phase are unknown (set to 0).
- ZTF J1539+5027: period 414.7915404(29) s, masses 0.610 (+0.017 -0.022) + 0.210
  (+0.014 -0.015) Msun and inclination 84.15 (+0.64 -0.57) deg from Burdge et al. (2019,
  Nature 571, 528), checked against a public summary of that paper (its infobox, citing
  it). The distance is quoted there as "2.3 kpc" / 8000 ly; our 2.34 kpc agrees to those
  digits but its third digit is from memory, so A (~1.0e-22) carries that ~2 % uncertainty.
  dP/dt = -2.373e-11 s/s is from memory and was NOT re-checked (it changes the phase by
  ~1e-5 rad over a day).
- Positions: Gaia DR2 (epoch J2015.5, ICRS) as quoted by SIMBAD-derived pages; converted
  to ecliptic coordinates (mean ecliptic and equinox of J2000) by
  :func:`equatorial_to_ecliptic`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..conventions import C, finite_number
from .response import link_response

__all__ = [
    "GM_SUN",
    "PARSEC",
    "OBLIQUITY_J2000",
    "GalacticBinary",
    "chirp_mass",
    "strain_amplitude",
    "gw_frequency_derivative",
    "equatorial_to_ecliptic",
    "hms_to_rad",
    "dms_to_rad",
    "VERIFICATION_BINARY_PARAMETERS",
    "VERIFICATION_BINARIES",
]

#: Heliocentric gravitational constant G M_sun [m^3/s^2] (IAU 2015 nominal, as lisaconstants).
GM_SUN = 1.3271244e20
#: Parsec [m] (IAU 2015: 648000 au / pi).
PARSEC = 648_000.0 / math.pi * 149_597_870_700.0
#: Mean obliquity of the ecliptic at J2000 [rad] (IAU 2006: 84381.406 arcsec).
OBLIQUITY_J2000 = math.radians(84381.406 / 3600.0)


# ---------------------------------------------------------------------------
# Binary physics
# ---------------------------------------------------------------------------


def chirp_mass(m1: float, m2: float) -> float:
    """Chirp mass ``(m1 m2)^(3/5) / (m1 + m2)^(1/5)``, in the unit of ``m1, m2``."""
    m1, m2 = float(m1), float(m2)
    if m1 <= 0 or m2 <= 0:
        raise ValueError(f"masses must be positive, got {m1!r}, {m2!r}")
    return (m1 * m2) ** 0.6 / (m1 + m2) ** 0.2


def strain_amplitude(chirp_mass_msun: float, f_gw: float, distance_pc: float) -> float:
    """Catalogue amplitude ``A = 2 (G M_c)^(5/3) (pi f)^(2/3) / (c^4 d)`` (module docstring).

    Parameters
    ----------
    chirp_mass_msun : float
        Chirp mass [solar masses].
    f_gw : float
        Gravitational-wave frequency (twice the orbital frequency) [Hz].
    distance_pc : float
        Distance [pc].
    """
    tm = float(chirp_mass_msun) * GM_SUN / C**3  # G M_c / c^3 [s]
    d = float(distance_pc) * PARSEC / C  # d / c [s]
    return 2.0 * tm ** (5.0 / 3.0) * (math.pi * float(f_gw)) ** (2.0 / 3.0) / d


def gw_frequency_derivative(chirp_mass_msun: float, f_gw: float) -> float:
    """Quadrupole GW-driven ``df/dt = (96/5) pi^(8/3) (G M_c/c^3)^(5/3) f^(11/3)`` [Hz/s]."""
    tm = float(chirp_mass_msun) * GM_SUN / C**3
    return 96.0 / 5.0 * math.pi ** (8.0 / 3.0) * tm ** (5.0 / 3.0) * float(f_gw) ** (11.0 / 3.0)


# ---------------------------------------------------------------------------
# Sky coordinates
# ---------------------------------------------------------------------------


def hms_to_rad(hours: float, minutes: float, seconds: float) -> float:
    """Right ascension ``h m s`` -> radians."""
    return math.radians(15.0 * (hours + minutes / 60.0 + seconds / 3600.0))


def dms_to_rad(degrees: float, arcmin: float, arcsec: float, sign: int = 1) -> float:
    """Declination ``sign * (d m s)`` -> radians (pass ``sign=-1`` for southern ``-0 d ...``)."""
    return math.radians(sign * (abs(degrees) + arcmin / 60.0 + arcsec / 3600.0))


def equatorial_to_ecliptic(ra: float, dec: float, obliquity: float = OBLIQUITY_J2000) -> tuple[float, float]:
    """Equatorial (ICRS/J2000) ``(ra, dec)`` -> ecliptic ``(beta, lam)``, all in radians.

    Rotation about the x axis (the equinox) by the obliquity ``eps``:

        sin(beta)            = sin(dec) cos(eps) - cos(dec) sin(eps) sin(ra),
        cos(beta) cos(lam)   = cos(dec) cos(ra),
        cos(beta) sin(lam)   = sin(dec) sin(eps) + cos(dec) cos(eps) sin(ra),

    ``lam`` in ``[0, 2 pi)``. Ignores the ~20 mas ICRS frame bias and, for the default
    J2000 obliquity, precession: astropy's ``BarycentricMeanEcliptic`` agrees to well
    below an arcsecond, far below anything the GW response can resolve.
    """
    ra, dec, eps = float(ra), float(dec), float(obliquity)
    sb = math.sin(dec) * math.cos(eps) - math.cos(dec) * math.sin(eps) * math.sin(ra)
    x = math.cos(dec) * math.cos(ra)
    y = math.sin(dec) * math.sin(eps) + math.cos(dec) * math.cos(eps) * math.sin(ra)
    beta = math.atan2(sb, math.hypot(x, y))
    lam = math.atan2(y, x) % (2 * math.pi)
    return beta, lam


# ---------------------------------------------------------------------------
# Galactic binary
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class GalacticBinary:
    """Quasi-monochromatic circular binary (lisagwresponse's ``GalacticBinary`` waveform).

    Parameters
    ----------
    f0 : float
        Gravitational-wave frequency at ``t_init`` [Hz].
    fdot : float
        Frequency derivative [Hz/s].
    amplitude : float
        Catalogue amplitude ``A`` (module docstring; peak ``|h_plus| = A (1 + cos^2 i)``).
    inclination : float
        Inclination ``i`` of the orbital plane to the line of sight [rad].
    psi : float
        Polarisation angle [rad] (applied by the response, not by :meth:`hplus`).
    phi0 : float
        Initial phase [rad]; ``Phi(t_init) = -phi0``.
    beta, lam : float
        Ecliptic latitude and longitude [rad].
    t_init : float
        Reference time of ``f0`` and ``phi0`` [s].
    name : str
        Label.
    """

    f0: float
    fdot: float
    amplitude: float
    inclination: float
    psi: float
    phi0: float
    beta: float
    lam: float
    t_init: float = 0.0
    name: str = ""
    #: Free-form provenance of the parameters (not used in computations).
    meta: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self):
        for key in ("f0", "fdot", "amplitude", "inclination", "psi", "phi0", "beta", "lam", "t_init"):
            object.__setattr__(self, key, finite_number(getattr(self, key), f"GalacticBinary {key}", error=ValueError))
        if self.f0 <= 0:
            raise ValueError(f"GalacticBinary f0 must be positive, got {self.f0!r}")
        if self.amplitude < 0:
            raise ValueError(f"GalacticBinary amplitude must be non-negative, got {self.amplitude!r}")

    def frequency(self, t) -> np.ndarray:
        """Instantaneous GW frequency ``f0 + fdot (t - t_init)`` [Hz]."""
        return self.f0 + self.fdot * (np.asarray(t, dtype=float) - self.t_init)

    def phase(self, t) -> np.ndarray:
        """``Phi(t) = 2 pi (f0 tau + fdot tau^2 / 2) - phi0``, ``tau = t - t_init`` [rad]."""
        tau = np.asarray(t, dtype=float) - self.t_init
        return 2.0 * np.pi * tau * (self.f0 + 0.5 * self.fdot * tau) - self.phi0

    def hplus(self, t) -> np.ndarray:
        """Source-frame ``h_plus(t) = -A (1 + cos^2 i) cos Phi(t)``."""
        ci = math.cos(self.inclination)
        return -self.amplitude * (1.0 + ci * ci) * np.cos(self.phase(t))

    def hcross(self, t) -> np.ndarray:
        """Source-frame ``h_cross(t) = -2 A cos(i) sin Phi(t)``."""
        return -2.0 * self.amplitude * math.cos(self.inclination) * np.sin(self.phase(t))

    def response(self, orbit, t) -> np.ndarray:
        """Six link responses ``(6, n)`` [fractional frequency] (:func:`ttlcore.gw.response.link_response`)."""

        return link_response(orbit, t, self.hplus, self.hcross, self.beta, self.lam, self.psi)

    @classmethod
    def from_system(
        cls,
        *,
        period: float,
        m1: float,
        m2: float,
        distance_pc: float,
        inclination: float,
        beta: float,
        lam: float,
        fdot: float | None = None,
        psi: float = 0.0,
        phi0: float = 0.0,
        t_init: float = 0.0,
        name: str = "",
        meta: dict | None = None,
    ) -> GalacticBinary:
        """Build from orbital period [s], masses [Msun], distance [pc] and angles [rad].

        ``f0 = 2 / period``; ``amplitude`` from :func:`strain_amplitude`; ``fdot`` the
        given (measured) GW frequency derivative, else :func:`gw_frequency_derivative`.
        """
        f0 = 2.0 / float(period)
        mc = chirp_mass(m1, m2)
        amp = strain_amplitude(mc, f0, distance_pc)
        fd = gw_frequency_derivative(mc, f0) if fdot is None else float(fdot)
        return cls(
            f0=f0,
            fdot=fd,
            amplitude=amp,
            inclination=inclination,
            psi=psi,
            phi0=phi0,
            beta=beta,
            lam=lam,
            t_init=t_init,
            name=name,
            meta=dict(meta or {}),
        )


# ---------------------------------------------------------------------------
# Verification binaries
# ---------------------------------------------------------------------------

#: Input values of the verification binaries, with their sources (module docstring for
#: what could and could not be checked). Angles in degrees, period in s, masses in Msun,
#: distance in pc, ``fdot_gw`` in Hz/s (GW frequency, i.e. twice the orbital one).
VERIFICATION_BINARY_PARAMETERS: dict[str, dict] = {
    "HM Cnc": {
        # Orbital period 321.529 s (X-ray/optical timing; Israel et al. 2002, Strohmayer
        # 2005, Roelofs et al. 2010): f_gw = 2/P = 6.2203 mHz, "6.220 mHz" in the paper
        # and Kupfer et al. 2024 (digits beyond 6.220 mHz not verified here).
        "period": 321.529,
        # Orbital fdot ~3.57e-16 Hz/s (Munday et al. 2023; Strohmayer 2021), doubled for
        # the GW frequency. Approximate (see module docstring); irrelevant over a day.
        "fdot_gw": 2 * 3.57e-16,
        # Masses 0.55 + 0.27 Msun, i = 38 deg, d = 5 kpc: Roelofs et al. 2010 (ApJL 711,
        # L138; q = 0.50 +- 0.13), as adopted by Kupfer et al. 2018 (MNRAS 480, 302) and
        # Kupfer et al. 2024 (no usable Gaia parallax for HM Cnc).
        "m1": 0.55,
        "m2": 0.27,
        "inclination_deg": 38.0,
        "distance_pc": 5000.0,
        # Gaia DR2 654879021108862464 (ICRS): RA 08h06m22.95196s, Dec +15d27m31.0073s.
        "ra_hms": (8, 6, 22.95196),
        "dec_dms": (15, 27, 31.0073, +1),
        "references": "Roelofs et al. 2010 ApJL 711 L138; Munday et al. 2023 MNRAS 518 5123; "
        "Kupfer et al. 2018 MNRAS 480 302; Kupfer et al. 2024 ApJ 963 100; Gaia DR2",
    },
    "ZTF J1539": {
        # ZTF J153932.16+502738.8, Burdge et al. 2019 (Nature 571, 528):
        # P = 414.7915404(29) s -> f_gw = 4.8217 mHz ("4.822 mHz" in the paper).
        "period": 414.7915404,
        # dP/dt = -2.373e-11 s/s (Burdge et al. 2019, as remembered here):
        # fdot_gw = -2 Pdot / P^2.
        "fdot_gw": 2 * 2.373e-11 / 414.7915404**2,
        # M_A = 0.610 (+0.017 -0.022), M_B = 0.210 (+0.014 -0.015) Msun,
        # i = 84.15 (+0.64 -0.57) deg (Burdge et al. 2019).
        "m1": 0.610,
        "m2": 0.210,
        "inclination_deg": 84.15,
        # d = 2.34 kpc (Burdge et al. 2019; secondary sources quote 2.3 kpc).
        "distance_pc": 2340.0,
        # Gaia DR2 1402814555998561280 (ICRS): RA 15h39m32.1588s, Dec +50d27m38.783s.
        "ra_hms": (15, 39, 32.1588),
        "dec_dms": (50, 27, 38.783, +1),
        "references": "Burdge et al. 2019 Nature 571 528; Kupfer et al. 2024 ApJ 963 100; Gaia DR2",
    },
}


def _verification_binary(name: str, p: dict) -> GalacticBinary:
    ra = hms_to_rad(*p["ra_hms"])
    d, m, s, sign = p["dec_dms"]
    dec = dms_to_rad(d, m, s, sign)
    beta, lam = equatorial_to_ecliptic(ra, dec)
    return GalacticBinary.from_system(
        period=p["period"],
        m1=p["m1"],
        m2=p["m2"],
        distance_pc=p["distance_pc"],
        inclination=math.radians(p["inclination_deg"]),
        beta=beta,
        lam=lam,
        fdot=p["fdot_gw"],
        psi=0.0,
        phi0=0.0,
        name=name,
        meta={"ra": ra, "dec": dec, "chirp_mass": chirp_mass(p["m1"], p["m2"]), "references": p["references"]},
    )


#: HM Cnc and ZTF J1539 as :class:`GalacticBinary` (``psi = phi0 = 0``, ``t_init = 0``).
VERIFICATION_BINARIES: dict[str, GalacticBinary] = {
    name: _verification_binary(name, p) for name, p in VERIFICATION_BINARY_PARAMETERS.items()
}
