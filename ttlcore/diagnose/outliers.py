"""What the noise levels' fit leaves out: outlying segments and narrowband excess.

The levels of :mod:`ttlcore.diagnose.noise_model` are amplitudes of broadband shapes.  A loud
transient (a merger, glitches) fills the segments it falls in, and power in a few bins (a
chirp's track, a line, a resonance) pins a level at its bound without informing it; both are
found here on the residual of the linear model and left out of the levels' fit
(:func:`ttlcore.diagnose.noise_model.profile_noise_model`; docs/diagnostics.md, "Signals,
glitches, noise changes").
"""

from __future__ import annotations

import numpy as np
from scipy import stats

__all__ = [
    "NARROWBAND_Z",
    "OUTLIER_ALPHA",
    "bin_runs",
    "narrowband_excess",
    "outlying_segments",
    "residual_periodogram",
]


#: z-score above the broadband continuum at which a window of bins is narrowband excess
#: (:func:`narrowband_excess`)
NARROWBAND_Z = 5.0


def narrowband_excess(f, P, S, n_segments: int, kappa: float = 1.0, width: int = 16, z: float = NARROWBAND_Z):
    """Bins (m,) of bool whose residual power is a narrowband excess over its neighbours.

    Levels are amplitudes of broadband shapes: power in a few bins (a chirp's track, a line,
    a resonance) does not inform them, and a loud one pins them at their bounds.  Per channel
    ``q_kc = P_kcc / (n S_kcc)`` (1 in expectation) averaged over ``width`` bins (standard
    deviation ``sqrt(kappa / (n width))``) against its median over one octave around the bin
    (a wrong level is broadband and moves it alike): ``z`` sigma above it in any channel is
    excess, with ``width`` bins either side (z = 5 over ~10^3 windows a day: one false flag
    in about a thousand diagnoses).

    Parameters
    ----------
    f : ndarray (m,)
        Analysis frequencies [Hz] (increasing; notches may leave holes).
    P : ndarray (m, 3, 3)
        ``sum_s r_s r_s^H`` of the residual (:func:`residual_periodogram`).
    S : ndarray (m, 3, 3)
        The model CSD the residual is compared with.
    n_segments : int
    kappa : float
        Variance factor of the tapered segments.
    """
    f = np.asarray(f, dtype=float)
    m = f.size
    out = np.zeros(m, dtype=bool)
    if m < 4 * width or n_segments < 1:
        return out
    q = np.real(np.einsum("mii->mi", P)) / (n_segments * np.maximum(np.real(np.einsum("mii->mi", S)), 1e-300))
    kernel = np.ones(width) / width
    qbar = np.stack([np.convolve(q[:, c], kernel, mode="same") for c in range(q.shape[1])], axis=1)
    sd = np.sqrt(kappa / (n_segments * width))
    # the continuum on a log grid (20 points an octave), each the median over one octave
    centres = np.exp(np.arange(np.log(f[0]), np.log(f[-1]) + 0.035, np.log(2) / 20))
    lo = np.searchsorted(f, centres / np.sqrt(2))
    hi = np.searchsorted(f, centres * np.sqrt(2))
    cont = np.array([np.median(qbar[a:b], axis=0) if b > a else np.ones(q.shape[1]) for a, b in zip(lo, hi)])
    cont_f = np.stack([np.interp(np.log(f), np.log(centres), cont[:, c]) for c in range(q.shape[1])], axis=1)
    hot = np.any((qbar - cont_f) / sd > z, axis=1)
    if hot.any():
        out = np.convolve(hot.astype(float), np.ones(2 * width + 1), mode="same") > 0
    return out


def bin_runs(f, mask) -> tuple:
    """``((f_lo, f_hi), ...)`` [Hz] of the runs of ``mask`` over ``f``."""
    idx = np.flatnonzero(mask)
    cut = np.flatnonzero(np.diff(idx) > 1)
    runs = zip(np.r_[idx[:1], idx[cut + 1]], np.r_[idx[cut], idx[-1:]]) if idx.size else ()
    return tuple((float(f[a]), float(f[b])) for a, b in runs)


def residual_periodogram(residual_w: np.ndarray, Lh: np.ndarray, keep=None) -> np.ndarray:
    """``P = sum_s r_s r_s^H`` (m, 3, 3) of residual spectra given whitened, ``w = L^H r``
    (S, m, 3), with ``L^H`` (m, 3, 3) the whitening of the noise model they were taken with;
    ``keep`` (S,) of bool: the segments summed (default all)."""
    if keep is not None:
        residual_w = residual_w[np.asarray(keep, dtype=bool)]
    r = np.linalg.solve(Lh[None], residual_w[..., None])[..., 0]
    return np.einsum("smi,smj->mij", r, r.conj())


#: Significance (over all segments and bands, Bonferroni) at which a segment's chi^2 in a
#: band is an outlier against the other segments (:func:`outlying_segments`).
OUTLIER_ALPHA = 1e-3


def outlying_segments(
    chi2_seg_band, dof_seg_band, kappa: float, tolerance: float, alpha: float = OUTLIER_ALPHA
) -> np.ndarray:
    """Segments whose residual is an outlier against the others, (S,) of bool.

    Per band ``g`` the reference level is that of the quietest segment, ``min_s chi2 /
    dof``, at least 1 (the noise model); segment ``s`` is an outlier when, in some band,
    ``chi2_sg / (level_g (1 + tol) kappa)`` has p < ``alpha / (S G)`` with ``dof / kappa``
    degrees of freedom.  A loud transient (a merger, glitches, a chirp in band for hours)
    fills the segments it falls in; a missing effect or a wrong level fills all alike.  (The median as reference let a chirp in band in three of
    four segments pin the levels at their bounds: the quiet hours read 0.89.)  When every
    segment is an outlier (a chirp over a whole live window, each segment loud in some
    band), the excess is not localised: none is left out (levels fitted on all the data).

    Parameters
    ----------
    chi2_seg_band : ndarray (S, G)
        chi^2 of the whitened residual per segment and band.
    dof_seg_band : ndarray (G,) or (S, G)
        Its degrees of freedom.
    """
    chi2 = np.asarray(chi2_seg_band, dtype=float)
    S, G = chi2.shape
    dof = np.broadcast_to(np.asarray(dof_seg_band, dtype=float), chi2.shape)
    if S < 3:
        return np.zeros(S, dtype=bool)
    k = dof / kappa
    level = np.maximum(np.min(chi2 / dof, axis=0), 1.0)
    p = stats.chi2.sf(chi2 / (level[None, :] * (1 + tolerance) * kappa), k)
    out = (p < alpha / (S * G)).any(axis=1)
    return np.zeros(S, dtype=bool) if out.all() else out
