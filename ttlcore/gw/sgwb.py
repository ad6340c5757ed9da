r"""Isotropic stochastic gravitational-wave background on the six links.

Spectrum
--------
Power-law energy density (the paper's stellar-origin black-hole background, Babak et al.
2023):

    h^2 Omega_GW(f) = h^2 Omega_ref (f / f_ref)^alpha,   default 1.15e-12, 3 mHz, alpha = 2/3.

The strain spectrum follows from ``rho_GW = c^2 <dh_ab/dt dh^ab/dt> / (32 pi G)``:
``S_h(f) = 3 H_100^2 h^2 Omega_GW(f) / (2 pi^2 f^3)`` with ``H_100 = 100 km/s/Mpc``, where
``S_h`` is the *sum* of the one-sided PSDs of ``h_plus`` and ``h_cross`` over the whole sky:
with ``h_ab h^ab = 2 (h_plus^2 + h_cross^2)`` and ``rho_c = 3 H_0^2 c^2 / 8 pi G``,
``Omega(f) = (1 / rho_c) d rho / d ln f = (2 pi^2 / 3 H_0^2) f^3 S_h(f)`` (the standard
relation, e.g. Allen & Romano 1999, PRD 59, 102001). Checked independently in the tests
through the long-wavelength link PSD ``(4/15) (pi f L / c)^2 S_h``.

Link cross-spectra (the correct correlations)
---------------------------------------------
An isotropic unpolarised background is a sum of independent plane waves from all
directions. Discretise the sky into ``N_pix`` equal-area cells (a Fibonacci sphere) and give
each cell and polarisation an independent Gaussian strain of one-sided PSD
``S_h(f) / (2 N_pix)``. With the plane-wave transfer function of link ``ij`` for direction
``k`` and polarisation ``A`` (static geometry; :mod:`ttlcore.gw.response` in the frequency domain),

    R^A_ij(f, k) = xi^A_ij / (2 (1 - k.n_ij)) [exp(-2 pi i f (tau_ij + k.x_j / c)) - exp(-2 pi i f k.x_i / c)],

the six link responses are a zero-mean stationary Gaussian process with cross-spectral matrix

    S_y(f)[ij, lm] = S_h(f) / (2 N_pix) sum_{cells, A} R^A_ij(f, k) conj(R^A_lm(f, k)),

i.e. the sky integral of the overlap functions done by quadrature. The simulation draws
exactly this process: six unit white streams (random access by absolute sample index, so the
result does not depend on the chunking) through a 6 x 6 matrix FIR filter ``h(t)`` whose
frequency response is the Cholesky factor of ``S_y`` (times ``sqrt(fs / 2)``). Nothing needs
one random stream per sky cell, and the correlations between the links are those of the
sky integral, including the ones between ``ij`` and ``ji`` and between arms.

Limits (documented, measured in ``tests/ttlcore/gw/test_gw_sources.py``):

- the geometry is that of the orbit at the first sample simulated (arm lengths, triangle
  shape). An isotropic background is invariant under the constellation's rotation, so only
  the arm lengths matter, and they change by < 1e-3 over a day;
- quadrature: ``N_pix = 1024`` cells (measured: TDI X2 PSD within 1 % of a 20000-cell
  quadrature at 1 mHz - 0.2 Hz). Below ~0.1 Hz the integrand is smooth on the cell
  scale and the quadrature error is far below 1 %; towards 1 Hz it oscillates on the scale
  of a few cells and the error grows to a few per cent (a random-quadrature error, not a bias
  of any sign);
- frequency resolution: the filter has ``filter_length`` taps (default 2^14 at 4 Hz, 68 min),
  so the spectrum is represented with ~0.24 mHz resolution and below that the FIR's response
  interpolates it; the link PSD varies as ``f^(-1/3)`` there (``f^2 S_h``), i.e. slowly.
"""

from __future__ import annotations

import math

import numpy as np

from ..conventions import LINKS, C
from ..sim.noise import key_hash

__all__ = [
    "H100",
    "omega_power_law",
    "strain_psd",
    "fibonacci_sphere",
    "link_transfer",
    "link_csd",
    "StochasticBackgroundGenerator",
]

#: H_0 for h = 1: 100 km/s/Mpc in 1/s (1 Mpc = 3.0856775814913673e22 m).
H100 = 100e3 / 3.0856775814913673e22

_RECEIVER = np.array([int(link[0]) - 1 for link in LINKS])
_EMITTER = np.array([int(link[1]) - 1 for link in LINKS])


def omega_power_law(f, omega_h2: float = 1.15e-12, f_ref: float = 3e-3, alpha: float = 2.0 / 3.0) -> np.ndarray:
    """``h^2 Omega_GW(f) = omega_h2 (f / f_ref)^alpha``."""
    return omega_h2 * (np.asarray(f, dtype=float) / f_ref) ** alpha


def strain_psd(f, omega_h2: float = 1.15e-12, f_ref: float = 3e-3, alpha: float = 2.0 / 3.0) -> np.ndarray:
    """``S_h(f) = 3 H_100^2 h^2 Omega(f) / (2 pi^2 f^3)`` [1/Hz]: the sum of the one-sided PSDs
    of ``h_plus`` and ``h_cross`` over the sky (module docstring); 0 at ``f = 0``."""
    f = np.asarray(f, dtype=float)
    out = np.zeros_like(f)
    pos = f > 0
    out[pos] = 3 * H100**2 * omega_power_law(f[pos], omega_h2, f_ref, alpha) / (2 * np.pi**2 * f[pos] ** 3)
    return out


def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` nearly equal-area points on the unit sphere (golden-angle spiral), shape (n, 3)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z * z)
    ph = np.pi * (1 + 5**0.5) * i
    return np.stack([r * np.cos(ph), r * np.sin(ph), z], axis=-1)


def _polarisation_bases(k: np.ndarray):
    """Orthonormal ``u, v`` transverse to each propagation direction ``k`` (n, 3)."""
    ref = np.where(np.abs(k[:, 2:3]) < 0.9, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    u = np.cross(ref, k)
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    v = np.cross(k, u)
    return u, v


def link_transfer(f, k: np.ndarray, positions: np.ndarray, ltt: np.ndarray) -> np.ndarray:
    """Plane-wave transfer functions ``R^A_ij(f, k)`` of a static constellation.

    Parameters
    ----------
    f : array (nf,)
    k : array (nk, 3)
        Propagation directions (unit).
    positions : array (3, 3)
        Spacecraft positions [m].
    ltt : array (6,)
        Light travel times [s], LINKS order.

    Returns
    -------
    ndarray, complex, shape (nf, 6, 2 nk): polarisations ``+`` (first ``nk``) and ``x``.
    """
    f = np.asarray(f, dtype=float)
    u, v = _polarisation_bases(k)
    x = positions - positions.mean(axis=0)
    nvec = x[_RECEIVER] - x[_EMITTER]
    nvec /= np.linalg.norm(nvec, axis=-1, keepdims=True)  # (6, 3)
    nk = k.shape[0]
    un, vn = u @ nvec.T, v @ nvec.T  # (nk, 6)
    xi = np.concatenate([un * un - vn * vn, 2 * un * vn], axis=0).T  # (6, 2nk)
    kn = (k @ nvec.T).T  # (6, nk)
    kx = (k @ x.T).T / C  # (3, nk)
    d_emit = ltt[:, None] + kx[_EMITTER]  # (6, nk)
    d_rec = kx[_RECEIVER]
    ph = -2j * np.pi * f[:, None, None]
    common = (np.exp(ph * d_emit) - np.exp(ph * d_rec)) / (2 * (1 - kn))  # (nf, 6, nk)
    return np.concatenate([common * xi[:, :nk], common * xi[:, nk:]], axis=-1)


def link_csd(f, positions, ltt, n_pix: int = 1024, block: int = 128, **spectrum) -> np.ndarray:
    """Cross-spectral matrix of the six link responses ``S_y(f)``, shape (nf, 6, 6) (module docstring)."""
    f = np.asarray(f, dtype=float)
    k = fibonacci_sphere(n_pix)
    sh = strain_psd(f, **spectrum) / (2 * n_pix)
    out = np.empty((f.size, 6, 6), dtype=complex)
    for s in range(0, f.size, block):
        r = link_transfer(f[s : s + block], k, positions, np.asarray(ltt, dtype=float))
        out[s : s + block] = np.matmul(r, np.conj(np.swapaxes(r, 1, 2))) * sh[s : s + block, None, None]
    return out


class StochasticBackgroundGenerator:
    """Six correlated link series with cross-spectra :func:`link_csd`, read by absolute sample.

    Parameters
    ----------
    positions, ltt : arrays (3, 3), (6,)
        Static geometry of the constellation.
    fs : float
        Sampling rate [Hz].
    seed : int
    key : str
        Name of the white streams (independent of every other stream of the simulation).
    filter_length : int
        FIR taps (even).
    n_pix : int
        Sky cells of the quadrature.
    **spectrum
        ``omega_h2``, ``f_ref``, ``alpha`` of :func:`strain_psd`.
    """

    _BLOCK = 1 << 16

    def __init__(
        self,
        positions,
        ltt,
        fs: float,
        *,
        seed: int,
        key: str = "sgwb",
        filter_length: int = 1 << 14,
        n_pix: int = 1024,
        **spectrum,
    ):
        self.fs = float(fs)
        self.seed = int(seed)
        self.key = str(key)
        self._key_hash = key_hash(self.key)
        L = int(filter_length)
        if L % 2:
            L += 1
        self.filter_length = L
        f = np.fft.rfftfreq(L, 1 / self.fs)
        csd = link_csd(f, np.asarray(positions, dtype=float), np.asarray(ltt, dtype=float), n_pix=n_pix, **spectrum)
        csd[0] = 0.0
        # Cholesky factor per frequency; a tiny diagonal load keeps the rank-deficient
        # low-frequency matrices (ij and ji respond alike there) factorisable
        load = 1e-10 * np.maximum(np.trace(csd, axis1=1, axis2=2).real / 6, 1e-300)
        chol = np.linalg.cholesky(csd + load[:, None, None] * np.eye(6)[None])
        chol[0] = 0.0
        resp = chol * math.sqrt(self.fs / 2)  # unit-variance white -> one-sided PSD csd
        # centred (zero-phase) FIR, Hann-tapered at its ends
        taps = np.fft.irfft(resp, n=L, axis=0)  # (L, 6, 6), taps for lags 0..L/2-1 and -L/2..-1
        taps = np.fft.fftshift(taps, axes=0)  # lag -L/2 .. L/2-1
        taps *= np.hanning(L + 1)[:L, None, None]
        self.taps = np.ascontiguousarray(np.transpose(taps, (1, 2, 0)))  # (6 out, 6 in, L)
        self.csd_f, self.csd = f, csd

    def _white_block(self, b: int) -> np.ndarray:
        out = np.empty((6, self._BLOCK))
        zb = 2 * b if b >= 0 else -2 * b - 1
        for c in range(6):
            rng = np.random.default_rng(np.random.SeedSequence([self.seed, self._key_hash, c, zb]))
            out[c] = rng.standard_normal(self._BLOCK)
        return out

    def white(self, start: int, stop: int) -> np.ndarray:
        out = np.empty((6, stop - start))
        B = self._BLOCK
        for b in range(start // B, (stop - 1) // B + 1):
            lo, hi = max(start, b * B), min(stop, (b + 1) * B)
            out[:, lo - start : hi - start] = self._white_block(b)[:, lo - b * B : hi - b * B]
        return out

    def get(self, start: int, stop: int) -> np.ndarray:
        """Link responses at absolute samples ``start .. stop-1``, shape (6, stop - start)."""
        L = self.filter_length
        n = stop - start
        # y[j] = sum_q taps[q] w[j - (q - L/2)], q = 0..L-1
        w = self.white(start - L // 2 + 1, stop + L // 2)
        nfft = 1 << int(math.ceil(math.log2(w.shape[1] + L)))
        W = np.fft.rfft(w, nfft, axis=-1)
        H = np.fft.rfft(self.taps, nfft, axis=-1)
        Y = np.einsum("oif,if->of", H, W)
        full = np.fft.irfft(Y, nfft, axis=-1)
        return full[:, L - 1 : L - 1 + n]
