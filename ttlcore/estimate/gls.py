"""The GLS engine with errors in variables: one solver for every model (docs/physics.md, fit).

Every fit in ttlcore - ``ttl analyze``'s 24 coefficients, the rolling fitter (with or
without a model's extra columns), ``ttl diagnose``'s and ``ttl refit``'s models - reduces
its whitened data to the same sufficient statistics per frequency band,

    N_g = Re sum R^H S^-1 R,    b_g = Re sum R^H S^-1 d,    dd_g = sum d^H S^-1 d,

and the errors-in-variables term ``E_g`` (the expected DWS readout-noise part of ``N_g``),
and solves them here (:func:`solve`): ``theta = (N - E)^-1 b``, ``Cov = (2 (N - E))^-1``
(times the window's variance factor, which the caller applies).  What differs between the
callers is the noise model ``S`` they whiten with (:mod:`ttlcore.estimate.fit`: re-estimated
from the residual; :mod:`ttlcore.diagnose.whitened`: the instrument noise model, fitted
levels) and the columns ``R`` (the 24 TDI regressors, or a model's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["NormalEquations", "sandwich", "set_apart", "sigma_ratio", "solve"]


@dataclass
class NormalEquations:
    """Sufficient statistics of the linear-Gaussian fit, per frequency band.

    ``Q_g(C) = C^T N_g C - 2 C^T b_g + dd_g`` is the whitened residual power of band ``g``
    (``log L = -sum_g Q_g``); ``E_g`` the expected DWS-noise part of ``N_g``; ``nbins_g``
    the number of complex frequency bins (summed over segments) and ``nchan`` the channels
    per bin, so band ``g`` holds ``2 nchan nbins_g`` real degrees of freedom.
    Additive: windows are built by adding and subtracting segments.
    """

    names: tuple
    band_edges: np.ndarray
    N: np.ndarray
    b: np.ndarray
    dd: np.ndarray
    E: np.ndarray
    nbins: np.ndarray
    nchan: int = 3

    @classmethod
    def zeros(cls, names, band_edges, nchan: int = 3) -> NormalEquations:
        G, P = len(band_edges) - 1, len(names)
        return cls(
            tuple(names),
            np.asarray(band_edges),
            np.zeros((G, P, P)),
            np.zeros((G, P)),
            np.zeros(G),
            np.zeros((G, P, P)),
            np.zeros(G, dtype=int),
            nchan,
        )

    def __add__(self, other: NormalEquations) -> NormalEquations:
        return NormalEquations(
            self.names,
            self.band_edges,
            self.N + other.N,
            self.b + other.b,
            self.dd + other.dd,
            self.E + other.E,
            self.nbins + other.nbins,
            self.nchan,
        )

    def __sub__(self, other: NormalEquations) -> NormalEquations:
        return NormalEquations(
            self.names,
            self.band_edges,
            self.N - other.N,
            self.b - other.b,
            self.dd - other.dd,
            self.E - other.E,
            self.nbins - other.nbins,
            self.nchan,
        )

    def total(self, eiv: bool = True) -> tuple[np.ndarray, np.ndarray, float]:
        """``(N - E, b, dd)`` summed over bands (``N`` alone if ``eiv`` is False)."""
        N = self.N.sum(axis=0) - (self.E.sum(axis=0) if eiv else 0.0)
        return N, self.b.sum(axis=0), float(self.dd.sum())

    def chi2_per_band(self, C: np.ndarray, eiv: bool = False) -> np.ndarray:
        """``2 Q_g(C)``: chi^2 of each band at coefficients ``C``."""
        N = self.N - (self.E if eiv else 0.0)
        q = np.einsum("p,gpq,q->g", C, N, C) - 2 * self.b @ C + self.dd
        return 2 * q

    def dof_per_band(self) -> np.ndarray:
        return 2 * self.nchan * self.nbins


def inverse(N: np.ndarray) -> np.ndarray:
    """``N^-1`` of a normal matrix, with the parameters the data do not determine set apart.

    A regressor without information (a zero row and column: a glitch's column before its
    time, in a rolling window) or a combination of regressors without it (collinear
    columns: after their times, glitches on one test mass are all constant velocity steps,
    which TDI nearly cancels) gets an infinite variance and no covariance with the others;
    the informed parameters keep the inverse of their own block (the same numbers as a
    model without the others).  Found from the eigenvalues of ``N`` scaled to unit
    diagonal: below ``1e-12`` of the largest, a direction is not determined.
    """
    d = np.real(np.diag(N))
    live = d > 0.0
    if live.all():
        try:
            return np.linalg.inv(N)
        except np.linalg.LinAlgError:
            pass
    if not live.any():
        raise np.linalg.LinAlgError("no regressor holds any information: the normal matrix is zero")
    idx = np.flatnonzero(live)
    scale = 1.0 / np.sqrt(d[idx])
    w, V = np.linalg.eigh(N[np.ix_(idx, idx)] * np.outer(scale, scale))
    null = w <= 1e-12 * w.max()
    # parameters that take part in an undetermined direction
    loose = np.zeros(d.size, dtype=bool)
    loose[idx] = np.any(np.abs(V[:, null]) > 1e-6, axis=1) if null.any() else False
    loose |= ~live
    keep = np.flatnonzero(~loose)
    out = np.zeros_like(N)
    if keep.size:
        out[np.ix_(keep, keep)] = np.linalg.inv(N[np.ix_(keep, keep)])
    out[loose, loose] = np.inf
    return out


def set_apart(N: np.ndarray, prior_scale: np.ndarray | None) -> np.ndarray:
    """``N`` with the parameters the data determine worse than their prior says set apart
    (their rows and columns zeroed, so that :func:`inverse` gives them coefficient 0 and
    infinite variance); ``N`` itself when there are none.

    ``prior_scale`` (one per parameter, in its unit: the expected size of its coefficient,
    :attr:`ttlcore.effects.Column.prior_scale`; ``inf`` never sets one apart): a parameter
    whose standard deviation ``sqrt(diag (2 N)^-1)`` is above its prior scale.  A glitch
    whose FFT segments are all left out (gated, or outliers of a rolling window) keeps a
    trace of information in the segments after it - the velocity step that stays, which
    TDI nearly cancels - and was fitted at -19 +- 5 m/s for a 4.5e-10 m/s glitch; with it
    subtracted, the hour of the glitch read chi^2/dof 1.2e25 (issue 24).
    """
    if prior_scale is None:
        return N
    loose = 0.5 * np.real(np.diag(inverse(N))) > np.asarray(prior_scale, dtype=float) ** 2
    if not loose.any() or loose.all():
        return N
    N = N.copy()
    N[loose, :] = 0.0
    N[:, loose] = 0.0
    return N


def solve(
    neq: NormalEquations, eiv: bool = True, prior_scale: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """GLS estimate and covariance from the normal equations: ``C = (N - E)^-1 b``,
    ``Cov = (2 (N - E))^-1`` (:func:`inverse`: a regressor without information gets
    coefficient 0 and infinite variance; so does one the data determine worse than its
    ``prior_scale``, :func:`set_apart`).  Without ``prior_scale``, or when every parameter
    is determined, the numbers are those of the plain solve.
    """
    N, b, _ = neq.total(eiv)
    N = set_apart(N, prior_scale)
    Ninv = inverse(N)
    live = np.isfinite(np.diag(Ninv))
    C = np.zeros_like(b)
    C[live] = Ninv[np.ix_(live, live)] @ b[live]
    if live.all():
        C = np.linalg.solve(N, b)  # the well-conditioned path, as before
    cov = 0.5 * Ninv
    return C, 0.5 * (cov + cov.T)


def sandwich(N: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``N^-1 M N^-1`` (symmetrised): the robust covariance of a GLS estimate from its
    normal matrix ``N`` and the sum ``M`` of its scores' outer products; a regressor
    without information (:func:`inverse`) keeps an infinite variance."""
    Ninv = inverse(N)
    live = np.isfinite(np.diag(Ninv))
    cov = np.diag(np.where(live, 0.0, np.inf))
    block = np.ix_(live, live)
    cov[block] = Ninv[block] @ M[block] @ Ninv[block]
    return 0.5 * (cov + cov.T)


def sigma_ratio(cov_robust: np.ndarray, cov_model: np.ndarray) -> float:
    """Median over the determined parameters of ``sigma_robust / sigma_model``: how far the
    sandwich covariance (:func:`sandwich`) widens the model-based one.

    A parameter the data do not determine (infinite variance, :func:`inverse`) is left
    out; NaN when no parameter is determined.
    """
    robust, model = np.real(np.diag(cov_robust)), np.real(np.diag(cov_model))
    determined = np.isfinite(robust) & np.isfinite(model) & (model > 0.0) & (robust >= 0.0)
    if not determined.any():
        return float("nan")
    return float(np.median(np.sqrt(robust[determined] / model[determined])))
