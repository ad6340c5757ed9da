"""Lagrange interpolation taps: reading a sampled series at fractional positions.

Centred Lagrange interpolation of odd order ``N`` (``N + 1`` taps), as in lisainstrument
and pytdi.  For a read position ``p = k + eps`` (``k`` integer, ``0 <= eps < 1``) the
interpolated value is

    x(p) = sum_{m=-(N-1)/2}^{(N+1)/2} w_m(eps) x[k + m],
    w_m(eps) = prod_{l != m} (eps - l) / (m - l),

evaluated in barycentric form (exact at integer positions).

The taps depend only on the read positions, so one set of taps serves any number of
channels: :func:`lagrange_taps` and :func:`shift_taps` compute them once and
:func:`apply_taps` applies them to an array of shape ``(..., n)``.

On the lowest floor of ttlcore (numpy only, docs/architecture.md): the file readers
(:mod:`ttlcore.io.lisainstrument` forms ``eta`` from delayed beat notes) and TDI
(:mod:`ttlcore.tdi.interpolation`, the delay operator, and everything that imports the
taps from there) share them, and neither of those two floors imports the other for them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

#: Default interpolation order (odd), as in lisainstrument and pytdi.
DEFAULT_ORDER = 31


def _check_order(order: int) -> int:
    order = int(order)
    if order < 1 or order % 2 == 0:
        raise ValueError(f"Lagrange interpolation order must be a positive odd integer, got {order}")
    return order


def lagrange_weights(eps: np.ndarray, order: int = DEFAULT_ORDER) -> np.ndarray:
    """Lagrange weights ``w_m(eps)`` for stencil offsets ``m = -(N-1)/2 .. (N+1)/2``.

    Evaluated in barycentric form, ``w_m = P(eps) / ((eps - m) d_m)`` with
    ``P(eps) = prod_l (eps - l)`` and ``d_m = prod_{l != m} (m - l)``; read positions on
    the sample grid (``eps == 0``) get the exact weights ``w_m = delta_{m0}``.

    Parameters
    ----------
    eps : array_like, shape (n,)
        Fractional part of the read position, in ``[0, 1)``.
    order : int
        Odd interpolation order ``N``.

    Returns
    -------
    ndarray, shape (N + 1, n)
        The weights, one row per stencil offset.
    """
    order = _check_order(order)
    eps = np.asarray(eps, dtype=float)
    offsets = np.arange(-(order - 1) // 2, (order + 1) // 2 + 1)
    denom = _denominators(order)[:, None]
    w = np.empty((offsets.size, eps.size))
    for b0 in range(0, eps.size, _BLOCK):  # blocks keep the temporaries in cache
        e = eps[b0 : b0 + _BLOCK]
        on_grid = e == 0.0
        e = np.where(on_grid, 0.5, e)  # placeholder, replaced below
        prod = np.ones_like(e)
        for l in offsets:
            prod *= e - l
        diff = e[None, :] - offsets[:, None]
        diff *= denom
        np.divide(prod[None, :], diff, out=w[:, b0 : b0 + e.size])
        if np.any(on_grid):
            w[:, b0 + np.flatnonzero(on_grid)] = (offsets == 0)[:, None]
    return w


_DENOMINATORS: dict[int, np.ndarray] = {}


def _denominators(order: int) -> np.ndarray:
    """``d_m = prod_{l != m} (m - l)`` for the stencil of ``order`` (cached)."""
    if order not in _DENOMINATORS:
        offsets = np.arange(-(order - 1) // 2, (order + 1) // 2 + 1)
        _DENOMINATORS[order] = np.array([np.prod([float(m - l) for l in offsets if l != m]) for m in offsets])
    return _DENOMINATORS[order]


@dataclass(frozen=True)
class Taps:
    """Precomputed interpolation taps for a set of read positions.

    Attributes
    ----------
    base : ndarray of int, shape (n,)
        Index of the first stencil sample for each output sample.
    weights : ndarray, shape (N + 1, n)
        Lagrange weights.
    """

    base: np.ndarray
    weights: np.ndarray

    @property
    def order(self) -> int:
        return self.weights.shape[0] - 1

    def __len__(self) -> int:
        return self.base.size


def lagrange_taps(positions: np.ndarray, order: int = DEFAULT_ORDER) -> Taps:
    """Taps that read a series at fractional sample ``positions``.

    Parameters
    ----------
    positions : array_like, shape (n,)
        Read positions in samples of the input series (``0`` is its first sample).
    order : int
        Odd interpolation order.
    """
    order = _check_order(order)
    positions = np.asarray(positions, dtype=float)
    k = np.floor(positions)
    eps = positions - k
    base = k.astype(np.int64) - (order - 1) // 2
    return Taps(base=base, weights=lagrange_weights(eps, order))


def apply_taps(x: np.ndarray, taps: Taps, fill: float = np.nan) -> np.ndarray:
    """Evaluate ``x`` (shape ``(..., m)``) at the positions the taps were built for.

    Output samples whose stencil leaves ``[0, m)`` are set to ``fill``.

    Delays vary slowly, so the integer part of the shift is constant over long runs;
    within a run the stencils are contiguous windows of ``x`` and the sum over taps is one
    ``einsum`` over a sliding-window view (no gather).  Shifts that jump often fall back
    to a gather per tap.

    Returns
    -------
    ndarray, shape (..., n)
    """
    x = np.asarray(x)
    m = x.shape[-1]
    npts, n = taps.weights.shape
    out = np.empty(x.shape[:-1] + (n,), dtype=np.result_type(x.dtype, float))
    if n == 0:
        return out
    base = taps.base
    breaks = np.flatnonzero(np.diff(base)) if n > 1 else np.array([], dtype=int)
    breaks = breaks[base[breaks + 1] - base[breaks] != 1] + 1  # where the integer shift changes
    if breaks.size > n // 64:
        return _apply_taps_gather(x, taps, fill)
    for s0, s1 in zip(np.r_[0, breaks], np.r_[breaks, n]):
        b0 = int(base[s0])
        lo = min(max(s0, s0 - b0), s1)  # first k with base >= 0
        hi = max(min(s1, s0 + m - npts - b0 + 1), lo)  # past the last k with base + npts <= m
        out[..., s0:lo] = fill
        out[..., hi:s1] = fill
        for c0 in range(lo, hi, _BLOCK):  # blocks keep the working set in cache
            c1 = min(c0 + _BLOCK, hi)
            first = b0 + (c0 - s0)
            window = sliding_window_view(x[..., first : first + (c1 - c0) + npts - 1], npts, axis=-1)
            w = taps.weights[:, c0:c1]
            if w.strides[-1] == 0:  # one stencil broadcast (a constant shift): the same sums
                w = np.ascontiguousarray(w)
            out[..., c0:c1] = np.einsum("...nj,jn->...n", window, w)
    return out


_BLOCK = 1 << 14


def _apply_taps_gather(x: np.ndarray, taps: Taps, fill: float) -> np.ndarray:
    m = x.shape[-1]
    npts = taps.weights.shape[0]
    valid = (taps.base >= 0) & (taps.base + npts <= m)
    base = np.clip(taps.base, 0, max(m - npts, 0))
    out = np.zeros(x.shape[:-1] + (taps.base.size,), dtype=np.result_type(x.dtype, float))
    for j in range(npts):
        out += taps.weights[j] * np.take(x, base + j, axis=-1)
    if not np.all(valid):
        out[..., ~valid] = fill
    return out


def shift_taps(shift, n: int, order: int = DEFAULT_ORDER, offset: int = 0) -> Taps:
    """Taps for ``y[k] = x(offset + k + shift[k])``, ``k = 0 .. n-1``.

    The integer and fractional parts are taken from ``shift`` itself, not from
    ``k + shift``, so the fractional part carries no rounding error that grows with ``k``.
    ``offset`` (integer) lets the input start ``offset`` samples before the output,
    e.g. a history buffer kept for delays.
    """
    order = _check_order(order)
    if np.ndim(shift) == 0 and np.isfinite(shift):
        # one shift for every sample: one stencil, its weights broadcast (read-only) instead
        # of a copy per sample (32 x 8 B a sample at order 31: 88 MB for a day at 4 Hz)
        whole = float(np.floor(shift))
        base = np.arange(n, dtype=np.int64) + int(offset) + int(whole) - (order - 1) // 2
        w = lagrange_weights(np.array([float(shift) - whole]), order)
        return Taps(base=base, weights=np.broadcast_to(w, (w.shape[0], n)))
    shift = np.broadcast_to(np.asarray(shift, dtype=float), (n,))
    if not np.all(np.isfinite(shift)):
        # undefined shifts (e.g. nested delays reaching before the data) read nothing:
        # put their stencil far out of range so apply_taps fills them
        shift = np.where(np.isfinite(shift), shift, -float(1 << 40))
    whole = np.floor(shift)
    eps = shift - whole
    base = np.arange(n, dtype=np.int64) + int(offset) + whole.astype(np.int64) - (order - 1) // 2
    return Taps(base=base, weights=lagrange_weights(eps, order))
