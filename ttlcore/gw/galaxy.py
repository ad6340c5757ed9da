r"""Many quasi-monochromatic binaries at once: fast link responses and a galactic population.

Fast response of many binaries (:func:`binaries_link_signal`)
---------------------------------------------------------------
Each binary ``b`` is the :class:`ttlcore.gw.sources.GalacticBinary` waveform. Its link response
is linear in the strain, so with the *complex* strains

    Hp = -A (1 + cos^2 i) exp(i Phi),     Hx = 2 i A cos(i) exp(i Phi)

(whose real parts are ``h_plus``, ``h_cross``), the complex response ``Y_b,ij(t)``
(:func:`complex_response`, the equations of :mod:`ttlcore.gw.response` applied to complex strain)
has ``y_b,ij = Re Y_b,ij``. Over a chunk of ``n`` samples at ``fs`` starting at ``t_s``
write ``Y_b(t) = c_b(t) exp(2 pi i f_k (t - t_s))`` with ``f_k = k fs / n`` the FFT
frequency nearest to the binary's frequency. The factor ``c_b(t)`` varies slowly: the
residual frequency ``|f_b - f_k| <= fs / 2n`` turns it by at most ``pi`` over the chunk,
and the orbital motion (Doppler, antenna patterns) changes it over hours. It is therefore
evaluated exactly only at ``M + 3`` nodes (spacing ``T / M``, ``T`` the chunk length,
``M >= 12`` and nodes at most 15 min apart) and interpolated between them with cubic
Lagrange weights ``w_m(t)``:

    y_ij(t) = Re sum_m w_m(t) sum_k [ sum_{b in bin k} c_b(t_m) ] exp(2 pi i k (t - t_s) fs / n),

and the inner sum over ``k`` is one inverse FFT per node and link. The cost is
``O(N_binaries * M)`` complex exponentials plus ``6 (M + 3)`` FFTs of the chunk length,
instead of ``O(N_binaries * n)``. Accuracy: a phasor turning by ``theta <= pi / M`` per node
interval is interpolated by cubic Lagrange to ``~ 3 theta^4 / 128 <= 2e-4`` relative
(``M = 12``); measured against the exact :func:`ttlcore.gw.response.link_response` of single binaries
to better than 1e-4 of the amplitude (``tests/ttlcore/gw/test_gw_sources.py``).

Galactic white-dwarf population (:func:`draw_galaxy`)
----------------------------------------------------
A documented toy model of the detached double-white-dwarf population, built to resemble the
LDC "Sangria" galaxy the paper uses (about 26 million detached binaries) without its
catalogue (not available offline):

- frequency distribution of a stationary population driven by gravitational radiation,
  ``dN/df ~ f^(-11/3)`` (Phinney 2001, astro-ph/0108028; Nelemans et al. 2001, A&A 375,
  890), normalised to ``n_ref = 2.6e7`` binaries above ``f_ref = 0.1 mHz`` and cut at
  ``f_max = 30 mHz``; only binaries above ``f_min`` (default 0.5 mHz) are drawn (there are
  ``n_ref (f_min / f_ref)^(-8/3)`` of them, 3.6e5 for the default). Those below change
  the link response by little: the response of a binary grows as ``f A ~ f^(5/3)``, so the
  population's variance per log-frequency grows as ``f^(5/3)`` and the binaries below
  0.5 mHz would add about ``(0.5 / 30)^(5/3) ~ 0.1 %`` of it. The fit band starts at 3 mHz;
- chirp masses log-normal, median 0.30 Msun, 0.15 dex, clipped to 0.15 - 1.0 Msun (DWD
  population syntheses peak at 0.25 - 0.35 Msun, e.g. Korol et al. 2017, MNRAS 470, 1894);
- positions: the Galaxy model of Nelemans et al. (2004, MNRAS 349, 181) as used by Korol
  et al. (2017): a disc ``rho ~ exp(-R / 2.5 kpc) sech^2(z / 0.3 kpc)`` holding 75 % of
  the binaries and a bulge ``rho ~ exp(-r^2 / 2 (0.5 kpc)^2)`` holding 25 %; the Sun at
  8.1 kpc from the centre, in the plane. Heliocentric positions give distance and galactic
  ``(l, b)``, converted to equatorial (ICRS) with the IAU galactic rotation matrix and to
  ecliptic with :func:`ttlcore.gw.sources.equatorial_to_ecliptic` (vectorised here);
- isotropic orientations (``cos i`` uniform), polarisation and phase uniform; frequency
  derivative the quadrupole value (:func:`ttlcore.gw.sources.gw_frequency_derivative`).

"Strain RMS" (the paper's table: 4.8e-22 and 5.9e-22 for its two days) is computed here as
the RMS over the day and the six links of the link response ``y_ij`` (fractional
frequency, what lisagwresponse hands to the simulator); see ``docs/gw.md`` for why this,
and not ``h_plus``, is the quantity the table can mean.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..conventions import LINKS, C
from .sources import GM_SUN, OBLIQUITY_J2000, PARSEC

__all__ = [
    "BinaryArrays",
    "complex_response",
    "binaries_link_signal",
    "draw_galaxy",
    "galactic_to_ecliptic",
    "GALAXY_DEFAULTS",
    "GAL_TO_ICRS",
]

_RECEIVER = np.array([int(link[0]) - 1 for link in LINKS])
_EMITTER = np.array([int(link[1]) - 1 for link in LINKS])

#: ICRS -> galactic rotation (rows: galactic x, y, z axes in ICRS; Hipparcos catalogue,
#: ESA 1997, vol. 1, sect. 1.5.3). ``r_gal = M r_icrs``; its transpose goes back.
GAL_TO_ICRS = np.array(
    [
        [-0.0548755604162154, -0.8734370902348850, -0.4838350155487132],
        [+0.4941094278755837, -0.4448296299600112, +0.7469822444972189],
        [-0.8676661490190047, -0.1980763734312015, +0.4559837761750669],
    ]
).T

#: Default population model parameters (module docstring).
GALAXY_DEFAULTS = {
    "n_ref": 2.6e7,
    "f_ref": 1e-4,
    "f_min": 5e-4,
    "f_max": 3e-2,
    "mc_median": 0.30,
    "mc_sigma_dex": 0.15,
    "mc_min": 0.15,
    "mc_max": 1.0,
    "disc_scale_length_kpc": 2.5,
    "disc_scale_height_kpc": 0.3,
    "bulge_radius_kpc": 0.5,
    "bulge_fraction": 0.25,
    "sun_radius_kpc": 8.1,
}


@dataclass
class BinaryArrays:
    """Parameters of many :class:`~ttlcore.gw.sources.GalacticBinary` as arrays of shape (N,)."""

    f0: np.ndarray
    fdot: np.ndarray
    amplitude: np.ndarray
    inclination: np.ndarray
    psi: np.ndarray
    phi0: np.ndarray
    beta: np.ndarray
    lam: np.ndarray
    t_init: float = 0.0

    def __post_init__(self):
        for name in ("f0", "fdot", "amplitude", "inclination", "psi", "phi0", "beta", "lam"):
            setattr(self, name, np.atleast_1d(np.asarray(getattr(self, name), dtype=float)))
        n = self.f0.size
        for name in ("fdot", "amplitude", "inclination", "psi", "phi0", "beta", "lam"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"BinaryArrays.{name}: shape {getattr(self, name).shape}, expected ({n},)")

    @property
    def size(self) -> int:
        return self.f0.size

    @classmethod
    def from_binaries(cls, binaries) -> BinaryArrays:
        binaries = list(binaries)
        t_init = {b.t_init for b in binaries}
        if len(t_init) > 1:
            raise ValueError("binaries with different t_init cannot be stacked")
        get = lambda k: np.array([getattr(b, k) for b in binaries], dtype=float)  # noqa: E731
        return cls(
            get("f0"),
            get("fdot"),
            get("amplitude"),
            get("inclination"),
            get("psi"),
            get("phi0"),
            get("beta"),
            get("lam"),
            t_init=t_init.pop() if t_init else 0.0,
        )

    def subset(self, sel) -> BinaryArrays:
        return BinaryArrays(
            self.f0[sel],
            self.fdot[sel],
            self.amplitude[sel],
            self.inclination[sel],
            self.psi[sel],
            self.phi0[sel],
            self.beta[sel],
            self.lam[sel],
            t_init=self.t_init,
        )


def _bases(p: BinaryArrays):
    """``k, u, v`` of :func:`ttlcore.gw.response.propagation_basis`, vectorised: each (N, 3)."""
    cb, sb, cl, sl = np.cos(p.beta), np.sin(p.beta), np.cos(p.lam), np.sin(p.lam)
    k = -np.stack([cb * cl, cb * sl, sb], axis=-1)
    u0 = np.stack([sl, -cl, np.zeros_like(sl)], axis=-1)
    v0 = np.stack([-sb * cl, -sb * sl, cb], axis=-1)
    cp, sp = np.cos(p.psi)[:, None], np.sin(p.psi)[:, None]
    return k, cp * u0 + sp * v0, -sp * u0 + cp * v0


def _geometry(orbit, t: np.ndarray):
    """Receiver positions (3, m, 3), emitter positions (6, m, 3), unit vectors n (6, m, 3), t_emit (6, m)."""
    tau = np.asarray(orbit.ltt(t), dtype=float)
    x_rec = np.asarray(orbit.positions(t), dtype=float)
    t_emit = t[None, :] - tau
    x_emit = np.empty((6, t.size, 3))
    for sc in range(3):
        links = np.flatnonzero(_EMITTER == sc)
        x_emit[links] = np.asarray(orbit.positions(t_emit[links].ravel()), dtype=float)[sc].reshape(
            len(links), t.size, 3
        )
    nvec = x_rec[_RECEIVER] - x_emit
    nvec /= np.linalg.norm(nvec, axis=-1, keepdims=True)
    return x_rec, x_emit, nvec, t_emit


def complex_response(orbit, t, p: BinaryArrays, geometry=None, bases=None) -> np.ndarray:
    """Complex link responses ``Y_b,ij(t)`` of many binaries, shape (N, 6, m); ``Re Y`` is the
    response of :func:`ttlcore.gw.response.link_response` to each binary (module docstring).
    ``geometry`` (of :func:`_geometry`) and ``bases`` (of :func:`_bases`) may be passed
    precomputed."""
    t = np.atleast_1d(np.asarray(t, dtype=float))
    x_rec, x_emit, nvec, t_emit = geometry if geometry is not None else _geometry(orbit, t)
    k, u, v = _bases(p) if bases is None else bases  # (N, 3)
    ci = np.cos(p.inclination)
    if t.size == 1:  # one node: plain matrix products, one exponential call
        n0, xr, xe = nvec[:, 0, :], x_rec[:, 0, :], x_emit[:, 0, :]
        un, vn, kn = u @ n0.T, v @ n0.T, k @ n0.T  # (N, 6)
        tau = np.concatenate([t[0] - (k @ xr.T) / C, t_emit[:, 0][None, :] - (k @ xe.T) / C], axis=1) - p.t_init
        ph = 2.0 * np.pi * tau * (p.f0[:, None] + 0.5 * p.fdot[:, None] * tau) - p.phi0[:, None]
        e = np.exp(1j * ph)  # (N, 9): 3 receivers, then 6 emitters
        num = (un * un - vn * vn) * (-p.amplitude * (1.0 + ci * ci))[:, None] + 1j * (2.0 * un * vn) * (
            2.0 * p.amplitude * ci
        )[:, None]
        return (num * (e[:, 3:] - e[:, _RECEIVER]) / (2.0 * (1.0 - kn)))[:, :, None]
    un = np.einsum("lmc,nc->nlm", nvec, u)
    vn = np.einsum("lmc,nc->nlm", nvec, v)
    xi_p, xi_c = un * un - vn * vn, 2.0 * un * vn  # (N, 6, m)
    kn = np.einsum("lmc,nc->nlm", nvec, k)
    s_rec = t[None, None, :] - np.einsum("smc,nc->nsm", x_rec, k) / C  # (N, 3, m)
    s_emit = t_emit[None] - np.einsum("lmc,nc->nlm", x_emit, k) / C  # (N, 6, m)

    def phase(s):
        tau = s - p.t_init
        shape = (-1,) + (1,) * (s.ndim - 1)
        return 2.0 * np.pi * tau * (p.f0.reshape(shape) + 0.5 * p.fdot.reshape(shape) * tau) - p.phi0.reshape(shape)

    e_rec = np.exp(1j * phase(s_rec))[:, _RECEIVER]
    e_emit = np.exp(1j * phase(s_emit))
    ap = (-p.amplitude * (1.0 + ci * ci))[:, None, None]
    ax = (2j * p.amplitude * ci)[:, None, None]
    return (xi_p * ap + xi_c * ax) * (e_emit - e_rec) / (2.0 * (1.0 - kn))


def _cubic_weights(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cubic Lagrange weights on unit-spaced nodes: for positions ``u`` return the first
    node index ``i - 1`` (i = floor(u)) and the four weights (4, len(u))."""
    i = np.floor(u).astype(int)
    x = u - i
    w = np.stack(
        [
            -x * (x - 1) * (x - 2) / 6.0,
            (x + 1) * (x - 1) * (x - 2) / 2.0,
            -(x + 1) * x * (x - 2) / 2.0,
            (x + 1) * x * (x - 1) / 6.0,
        ]
    )
    return i - 1, w


def binaries_link_signal(
    orbit, t, p: BinaryArrays, *, max_node_spacing: float = 900.0, min_nodes: int = 12, batch: int = 100_000
) -> np.ndarray:
    """Sum of the link responses of all binaries ``p`` on the uniform times ``t``, shape (6, n).

    Uses the node-and-FFT scheme of the module docstring; ``t`` must be uniformly sampled.
    """
    t = np.asarray(t, dtype=float)
    n = t.size
    if n < 2:
        return np.real(complex_response(orbit, t, p).sum(axis=0)) if p.size else np.zeros((6, n))
    dt = (t[-1] - t[0]) / (n - 1)
    span = n * dt
    m_int = max(int(min_nodes), int(math.ceil(span / max_node_spacing)))
    delta = span / m_int
    t_nodes = t[0] + (np.arange(m_int + 3) - 1) * delta
    out = np.zeros((6, n))
    if p.size == 0:
        return out
    # bins on the chunk's FFT grid; binaries at or above Nyquist cannot be represented
    t_mid = t[0] + 0.5 * span
    f_mid = p.f0 + p.fdot * (t_mid - p.t_init)
    kbin = np.rint(f_mid * span).astype(np.int64)
    keep = (kbin > 0) & (kbin < n // 2)
    if not np.all(keep):
        p = p.subset(keep)
        kbin = kbin[keep]
    fk = kbin / span
    first, w = _cubic_weights((t - t_nodes[0]) / delta)
    bases = _bases(p)
    for m in range(t_nodes.size):
        weight = np.zeros(n)
        for q in range(4):
            sel = first + q == m
            weight[sel] = w[q, sel]
        nz = weight != 0
        if not np.any(nz):
            continue
        tm = t_nodes[m : m + 1]
        geometry = _geometry(orbit, tm)
        acc = np.zeros((6, n), dtype=complex)
        for start in range(0, p.size, batch):
            sl = slice(start, start + batch)
            y = complex_response(orbit, tm, p.subset(sl), geometry, tuple(b[sl] for b in bases))[:, :, 0]  # (b, 6)
            y *= np.exp(-2j * np.pi * fk[sl] * (tm[0] - t[0]))[:, None]
            kb = kbin[sl]
            for link in range(6):
                acc[link] += np.bincount(kb, weights=y[:, link].real, minlength=n) + 1j * np.bincount(
                    kb, weights=y[:, link].imag, minlength=n
                )
        series = np.fft.ifft(acc, axis=-1) * n  # (6, n): sum_k A_k exp(2 pi i k j / n)
        out[:, nz] += (series[:, nz] * weight[nz]).real
    return out


# ---------------------------------------------------------------------------
# Sky coordinates
# ---------------------------------------------------------------------------


def galactic_to_ecliptic(l, b, obliquity: float = OBLIQUITY_J2000) -> tuple[np.ndarray, np.ndarray]:
    """Galactic ``(l, b)`` -> ecliptic ``(beta, lam)`` [rad], vectorised (ICRS via the
    Hipparcos rotation, then the J2000 obliquity as :func:`ttlcore.gw.sources.equatorial_to_ecliptic`)."""
    l, b = np.asarray(l, dtype=float), np.asarray(b, dtype=float)
    v_gal = np.stack([np.cos(b) * np.cos(l), np.cos(b) * np.sin(l), np.sin(b)], axis=-1)
    v_eq = v_gal @ GAL_TO_ICRS.T
    ce, se = math.cos(obliquity), math.sin(obliquity)
    x = v_eq[..., 0]
    y = ce * v_eq[..., 1] + se * v_eq[..., 2]
    z = -se * v_eq[..., 1] + ce * v_eq[..., 2]
    return np.arctan2(z, np.hypot(x, y)), np.mod(np.arctan2(y, x), 2 * np.pi)


# ---------------------------------------------------------------------------
# Population
# ---------------------------------------------------------------------------


def galaxy_size(f_min: float | None = None, **model) -> int:
    """Number of binaries the model holds above ``f_min`` (and below ``f_max``)."""
    m = {**GALAXY_DEFAULTS, **model}
    f_min = m["f_min"] if f_min is None else f_min
    above = lambda f: m["n_ref"] * (f / m["f_ref"]) ** (-8.0 / 3.0)  # noqa: E731
    return int(round(above(f_min) - above(m["f_max"])))


def draw_galaxy(seed: int = 0, *, t_init: float = 0.0, n: int | None = None, **model) -> BinaryArrays:
    """Draw the galactic population of the module docstring (``n`` overrides the model's count).

    Parameters
    ----------
    seed : int
        Seed of the draw (the same seed gives the same galaxy).
    t_init : float
        Reference time of the frequencies and phases [s].
    n : int, optional
        Number of binaries; default :func:`galaxy_size` of the model.
    **model
        Overrides of :data:`GALAXY_DEFAULTS`.
    """
    unknown = set(model) - set(GALAXY_DEFAULTS)
    if unknown:
        raise ValueError(f"unknown galaxy model parameters {sorted(unknown)}; known: {', '.join(GALAXY_DEFAULTS)}")
    m = {**GALAXY_DEFAULTS, **model}
    if not (0 < m["f_min"] < m["f_max"]):
        raise ValueError(f"galaxy f_min must be positive and below f_max, got {m['f_min']}, {m['f_max']}")
    n = galaxy_size(**m) if n is None else int(n)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x6A1A]))
    # f^(-11/3) between f_min and f_max by inverse transform of the CDF in f^(-8/3)
    a, bmax = m["f_min"] ** (-8 / 3), m["f_max"] ** (-8 / 3)
    f0 = (a - rng.random(n) * (a - bmax)) ** (-3 / 8)
    mc = 10 ** (math.log10(m["mc_median"]) + m["mc_sigma_dex"] * rng.standard_normal(n))
    mc = np.clip(mc, m["mc_min"], m["mc_max"])
    # positions [kpc], galactocentric: Sun at (-R0, 0, 0)
    n_bulge = rng.binomial(n, m["bulge_fraction"])
    n_disc = n - n_bulge
    rd, zd = m["disc_scale_length_kpc"], m["disc_scale_height_kpc"]
    # exponential surface density R exp(-R/rd): Gamma(2, rd); sech^2 vertical: z = zd * atanh(2u - 1)
    r_disc = rng.gamma(2.0, rd, n_disc)
    ph = rng.random(n_disc) * 2 * np.pi
    z_disc = zd * np.arctanh(np.clip(2 * rng.random(n_disc) - 1, -1 + 1e-15, 1 - 1e-15))
    disc = np.stack([r_disc * np.cos(ph), r_disc * np.sin(ph), z_disc], axis=-1)
    bulge = rng.normal(0.0, m["bulge_radius_kpc"], (n_bulge, 3))
    pos = np.concatenate([disc, bulge])[rng.permutation(n)]
    helio = pos - np.array([-m["sun_radius_kpc"], 0.0, 0.0])
    d_kpc = np.maximum(np.linalg.norm(helio, axis=-1), 0.05)  # nothing closer than 50 pc
    l_gal = np.arctan2(helio[:, 1], helio[:, 0])
    b_gal = np.arcsin(np.clip(helio[:, 2] / d_kpc, -1, 1))
    beta, lam = galactic_to_ecliptic(l_gal, b_gal)
    tm = mc * GM_SUN / C**3
    amp = 2.0 * tm ** (5 / 3) * (np.pi * f0) ** (2 / 3) / (d_kpc * 1e3 * PARSEC / C)
    fdot = 96 / 5 * np.pi ** (8 / 3) * tm ** (5 / 3) * f0 ** (11 / 3)
    inc = np.arccos(rng.uniform(-1, 1, n))
    psi = rng.uniform(0, np.pi, n)
    phi0 = rng.uniform(0, 2 * np.pi, n)
    return BinaryArrays(f0, fdot, amp, inc, psi, phi0, beta, lam, t_init=float(t_init))
