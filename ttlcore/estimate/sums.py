"""The per-band sums of whitened spectra behind the GLS fit's normal equations
(:class:`ttlcore.estimate.gls.NormalEquations`): of a stack of segments at once
(:func:`band_sums`, what :func:`ttlcore.estimate.fit.accumulate` returns), of each segment of
the stack on its own (:func:`segment_sums`: the rolling fit's per-segment sums after a full
refit, from the whitening that refit already did), and the errors-in-variables term of one
set of weights (:func:`eiv_bands`: the same for every segment, taken once per set).

Every product is real: ``Re(z^H z) = X^T X`` with the real stacking ``X = [Re z; Im z]``,
a quarter of the complex product's work.
"""

from __future__ import annotations

import numpy as np

from .gls import NormalEquations
from .whitening import Whitener

__all__ = ["band_slices", "band_sums", "eiv_bands", "segment_sums"]


def band_slices(f: np.ndarray, band_edges) -> list[tuple[int, int]]:
    """``(start, stop)`` bin ranges of the bands ``[edge_g, edge_g+1)`` in the sorted ``f``
    (the first and last band take the bins below and above the edges)."""
    cut = np.searchsorted(f, np.asarray(band_edges)[1:-1], side="left")
    bounds = np.concatenate([[0], cut, [f.size]])
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


def _real_stack(z: np.ndarray, axis: int = 0) -> np.ndarray:
    """``[Re z; Im z]`` along ``axis`` (real form of complex inner products)."""
    return np.concatenate([z.real, z.imag], axis=axis)


def eiv_bands(prepared: Whitener, slices, P: int) -> np.ndarray | None:
    """The errors-in-variables term ``E_g`` (G, P, P) of one segment under the weights of
    ``prepared`` (its whitened readout-noise responses, :attr:`Whitener.groups`), per band
    of ``slices``; None without the term.

    ``E_g`` does not depend on the data, only on the weights: a segment's sums with the
    same weights all have the same one, and it is kept on ``prepared`` (the rolling fit's
    per-segment sums took it again for every segment: 96 small products per segment, half
    of an incremental update).  Per bin, then summed per band: the same numbers as one
    product per band to rounding (1e-16 relative).
    """
    if not prepared.groups:
        return None
    key = (tuple(slices), int(P))
    cached = prepared.cache.get(key)
    if cached is not None:
        return cached
    E = np.zeros((len(slices), P, P))
    for block, wT in prepared.groups:
        X = _real_stack(wT, axis=1)  # (m, 2c, q)
        per_bin = np.einsum("mkq,mkr->mqr", X, X)
        for g, (m0, m1) in enumerate(slices):
            if m1 > m0:
                E[g][block] += per_bin[m0:m1].sum(axis=0)
    E.flags.writeable = False
    prepared.cache[key] = E
    return E


def band_sums(wd: np.ndarray, wR: np.ndarray, slices, names, band_edges, eiv: np.ndarray | None) -> NormalEquations:
    """The normal equations of whitened spectra ``wd`` (m, S, c) and ``wR`` (m, S, c, P)
    summed over their ``S`` segments, per band of ``slices``; ``eiv``: :func:`eiv_bands`
    of the weights (one segment's), or None."""
    S, c, P = wR.shape[1], wR.shape[2], wR.shape[3]
    neq = NormalEquations.zeros(names, band_edges, nchan=c)
    # f is sorted, so each band is a contiguous run of bins: slices, no copies
    for g, (m0, m1) in enumerate(slices):
        if m1 == m0:
            continue
        X = _real_stack(wR[m0:m1].reshape(-1, P))
        y = _real_stack(wd[m0:m1].reshape(-1))
        neq.N[g] = X.T @ X
        neq.b[g] = X.T @ y
        neq.dd[g] = float(y @ y)
        neq.nbins[g] = (m1 - m0) * S
    if eiv is not None:
        neq.E += eiv * S
    return neq


def segment_sums(
    wd: np.ndarray, wR: np.ndarray, C: np.ndarray, slices, names, band_edges, eiv: np.ndarray | None
) -> list[tuple[NormalEquations, np.ndarray]]:
    """Per segment of whitened spectra ``wd`` (m, S, c) and ``wR`` (m, S, c, P): its
    normal equations (:func:`band_sums` of that segment alone) and its sandwich scores
    ``sum_f Re(u) Re(u)^T`` at ``C`` (:func:`ttlcore.estimate.fit.score_matrix`), all
    segments in one batched product per band.

    The rolling fit's full refit whitened every segment of its window with its final
    weights; summing each segment from those arrays replaces a whitening and a sum per
    segment (the same numbers to rounding).
    """
    m, S, c, P = wR.shape
    N = np.zeros((S, len(slices), P, P))
    b = np.zeros((S, len(slices), P))
    dd = np.zeros((S, len(slices)))
    nbins = np.zeros(len(slices), dtype=int)
    for g, (m0, m1) in enumerate(slices):
        if m1 == m0:
            continue
        X = _real_stack(np.moveaxis(wR[m0:m1], 1, 0).reshape(S, -1, P), axis=1)  # (S, 2 n c, P)
        y = _real_stack(np.moveaxis(wd[m0:m1], 1, 0).reshape(S, -1), axis=1)  # (S, 2 n c)
        Xt = np.swapaxes(X, 1, 2)
        N[:, g] = np.matmul(Xt, X)
        b[:, g] = np.matmul(Xt, y[..., None])[..., 0]
        dd[:, g] = np.einsum("sk,sk->s", y, y)
        nbins[g] = m1 - m0
    wr = wd - wR @ C  # whitened residual L^H r, (m, S, c)
    u = np.einsum("mscp,msc->smp", wR.real, wr.real) + np.einsum("mscp,msc->smp", wR.imag, wr.imag)
    M = np.matmul(np.swapaxes(u, 1, 2), u)  # (S, P, P)
    E = np.zeros((len(slices), P, P)) if eiv is None else eiv
    return [
        (NormalEquations(tuple(names), np.asarray(band_edges), N[s], b[s], dd[s], E, nbins.copy(), c), M[s])
        for s in range(S)
    ]
