"""Whitening of band-limited spectra with per-bin weights ``W = S^-1`` (the inverse noise
CSD) for the frequency-domain GLS fit (:mod:`ttlcore.estimate.fit`): the weights' Cholesky
factor ``W = L L^H`` (robust to bins made singular to rounding by a loud transient), the
spectra whitened with it, and a :class:`Whitener` holding the factor and the whitened
errors-in-variables responses of one set of weights, so that summing many segments with the
same weights (the rolling fit's per-segment sums) takes them once.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Whitener:
    """The whitening of one set of weights: ``Lh`` (m, c, c), ``L^H`` of the Cholesky factor
    ``W = L L^H``, and ``groups``, the errors-in-variables responses whitened with it
    (``(index block, L^H T sqrt(S_dws))`` per DWS channel; None without the term);
    ``cache`` what is taken once per set of weights (:func:`ttlcore.estimate.sums.eiv_bands`)."""

    Lh: np.ndarray
    groups: list | None = None
    cache: dict = field(default_factory=dict, compare=False, repr=False)


def whitener(weights: np.ndarray, eiv_response: list | None = None, dws_psd: np.ndarray | None = None) -> Whitener:
    """The :class:`Whitener` of ``weights`` (m, c, c) and of the errors-in-variables
    responses ``eiv_response`` with the readout PSD ``dws_psd`` (:func:`accumulate`)."""
    Lh = np.conj(np.swapaxes(cholesky_factor(weights), -1, -2))
    groups = None
    if eiv_response is not None and dws_psd is not None:
        scale = np.sqrt(dws_psd)[:, None, None]
        groups = [(np.ix_(idx, idx), np.matmul(Lh, T) * scale) for idx, T in eiv_response]
    return Whitener(Lh, groups)


def whiten(weights: np.ndarray, d: np.ndarray, R: np.ndarray, Lh: np.ndarray | None = None):
    """Whiten stacked spectra with the Cholesky factor of the weights ``W = L L^H``.

    Returns ``L^H`` (m, c, c) and the whitened data ``L^H d`` (m, S, c) and regressors
    ``L^H R`` (m, S, c, P), bins first, for ``d`` (S, m, c) and ``R`` (S, m, c, P) as
    :func:`stack_spectra` gives them.  ``Lh``: the factor, when already taken
    (:attr:`Whitener.Lh` of these weights).
    """
    if Lh is None:
        Lh = np.conj(np.swapaxes(cholesky_factor(weights), -1, -2))
    wd = np.matmul(Lh[:, None], np.swapaxes(d, 0, 1)[..., None])[..., 0]
    wR = np.matmul(Lh[:, None], np.swapaxes(R, 0, 1))
    return Lh, wd, wR


def inverse_csd(csd: np.ndarray) -> np.ndarray:
    """The weights ``W = S^-1`` (m, c, c).  A bin whose CSD is singular to rounding (one
    loud transient makes a residual CSD nearly of rank one) is inverted on its eigenvalues
    clipped at 1e-12 of its largest; every other bin's inverse is unchanged."""
    try:
        return np.linalg.inv(csd)
    except np.linalg.LinAlgError:
        pass
    out = np.empty_like(csd)
    for m in range(csd.shape[0]):
        try:
            out[m] = np.linalg.inv(csd[m])
        except np.linalg.LinAlgError:
            S = 0.5 * (csd[m] + csd[m].conj().T)
            lam, V = np.linalg.eigh(S)
            lam = np.maximum(lam, 1e-12 * max(lam[-1], np.finfo(float).tiny))
            out[m] = (V / lam) @ V.conj().T
    return out


def cholesky_factor(weights: np.ndarray) -> np.ndarray:
    """``L`` with ``W = L L^H`` per bin.  Where rounding makes a bin's weights not positive
    definite (a residual CSD dominated by one loud transient is nearly of rank one, and its
    inverse loses the small eigenvalues), that bin's factor is taken from its eigenvalues,
    clipped at 1e-12 of the largest: the weights of every other bin are the Cholesky
    factor's, unchanged."""
    try:
        return np.linalg.cholesky(weights)
    except np.linalg.LinAlgError:
        pass
    W = 0.5 * (weights + np.conj(np.swapaxes(weights, -1, -2)))
    lam, V = np.linalg.eigh(W)
    lam = np.maximum(lam, 1e-12 * lam[..., -1:])
    L = V * np.sqrt(lam)[..., None, :]
    out = np.empty_like(W)
    for m in range(W.shape[0]):  # Cholesky where it works, the eigen-factor where not
        try:
            out[m] = np.linalg.cholesky(weights[m])
        except np.linalg.LinAlgError:
            out[m] = L[m]
    return out
