"""The 24 TTL regressors: DWS witnesses placed on their links (docs/physics.md, fit).

From ``ttl_ij = -(1/c)[C[ij,phi,rx] phi'_ij + C[ij,eta,rx] eta'_ij + D_ij(C[ji,phi,tx] phi'_ji + C[ji,eta,tx] eta'_ji)]``
the regressor of coefficient

- ``m.a.rx`` is ``-(1/c) DWS_a[m]`` on link ``m`` (undelayed);
- ``m.a.tx`` is ``-(1/c) D_{ij} DWS_a[m]`` on link ``ij = reverse(m)``, i.e. MOSA ``m = ji``'s
  readout delayed along the link it transmits on.

so that ``eta = sum_k C_k w_k + (other terms)``.  A witness is described by the link it sits
on and the extra delay chain applied before it enters that link; TDI applies that extra
delay first, at every sample (:func:`ttlcore.tdi.engine.predelayed`), then the link's chains.
"""

from __future__ import annotations

import numpy as np

from ..conventions import COEFFICIENT_NAMES, LINKS, C, parse_coefficient_name, reverse
from .combinations import AET_MATRIX, MICHELSON, link_responses


def witness_placement(mosa: str, side: str) -> tuple[str, bool]:
    """``(link, delayed)``: where a witness of MOSA ``mosa`` enters the data.

    Side ``rx``: on the MOSA's own link ``mosa``, undelayed.  Side ``tx``: on the link it
    transmits on, ``reverse(mosa)``, after that link's delay ``D_ij`` (``delayed`` True).
    The TTL regressors (:func:`placement`) and the diagnosis's witness columns
    (:mod:`ttlcore.effects`) are both placed so.
    """
    return (mosa, False) if side == "rx" else (reverse(mosa), True)


def placement(name: str) -> tuple[str, tuple[str, ...], str, str]:
    """``(link, extra_chain, mosa, angle)`` of the regressor of coefficient ``name``
    (:func:`witness_placement`; the extra chain is ``(link,)`` when delayed)."""
    mosa, angle, side = parse_coefficient_name(name)
    link, delayed = witness_placement(mosa, side)
    return link, ((link,) if delayed else ()), mosa, angle


def ttl_witnesses(dws_phi: np.ndarray, dws_eta: np.ndarray, names=COEFFICIENT_NAMES) -> tuple[dict, dict]:
    """Group the regressors' witness series by (link, extra chain) for TDI.

    Parameters
    ----------
    dws_phi, dws_eta : ndarray, shape (6, n)
        DWS readouts [rad/s] in MOSA order.
    names : sequence of str
        Coefficient names to build (default all 24).

    Returns
    -------
    witnesses : dict
        ``(link, extra) -> ndarray (k, n)`` of ``-DWS/c``.
    index : dict
        ``(link, extra) -> list of positions in names``, to scatter TDI outputs back.
    """
    dws = {"phi": np.asarray(dws_phi), "eta": np.asarray(dws_eta)}
    groups: dict[tuple, list] = {}
    for k, name in enumerate(names):
        link, extra, mosa, angle = placement(name)
        groups.setdefault((link, extra), []).append((k, mosa, angle))
    witnesses, index = {}, {}
    for key, items in groups.items():
        witnesses[key] = np.stack([-dws[a][LINKS.index(m)] / C for _, m, a in items])
        index[key] = [k for k, _, _ in items]
    return witnesses, index


def dws_channel(name: str) -> tuple[str, str]:
    """``(mosa, angle)``: the DWS readout a regressor is made of (shared by its rx and tx)."""
    _, _, mosa, angle = placement(name)
    return mosa, angle


def regressor_responses(f: np.ndarray, ltt, names=COEFFICIENT_NAMES, combinations=None, aet: bool = True) -> np.ndarray:
    """Frequency response of each regressor's TDI output to its own DWS readout, static delays.

    ``T[f, c, k]``: a unit-PSD perturbation of the DWS readout behind regressor ``k`` appears
    in channel ``c`` with amplitude ``T`` (including the ``-1/c`` of the TTL term and, for Tx
    regressors, the pre-delay ``D_ij``).  Used for the DWS-noise (errors-in-variables)
    correction of the fit and for diagnostics.

    Returns
    -------
    ndarray, shape (m, 3, P), complex
    """
    combinations = combinations or MICHELSON
    f = np.asarray(f, dtype=float)
    out = np.zeros((f.size, len(combinations), len(names)), dtype=complex)
    cache = {}
    for k, name in enumerate(names):
        link, extra, _, _ = placement(name)
        if extra not in cache:
            cache[extra] = np.stack([link_responses(comb, f, ltt, extra) for comb in combinations])  # (3, 6, m)
        out[:, :, k] = cache[extra][:, LINKS.index(link), :].T * (-1.0 / C)
    if aet:
        out = np.einsum("ia,mak->mik", AET_MATRIX, out)
    return out
