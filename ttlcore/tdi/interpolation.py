"""Fractional time shifts by Lagrange interpolation: the delay operator of TDI.

The delay operator of docs/physics.md, ``D x(t) = x(t - tau(t))``, is evaluated on sampled data
by centred Lagrange interpolation of odd order ``N`` (``N + 1`` taps), as in lisainstrument
and pytdi (:func:`delay`, :func:`timeshift`).  The taps themselves (weights, :class:`Taps`,
:func:`shift_taps`, :func:`apply_taps`) live on the lowest floor of ttlcore,
:mod:`ttlcore._lagrange`, which the file readers share; they are importable from here as
before.
"""

from __future__ import annotations

import numpy as np

from .._lagrange import DEFAULT_ORDER, Taps, apply_taps, lagrange_taps, lagrange_weights, shift_taps
from .._lagrange import _check_order as _check_order  # the engine checks orders with it

__all__ = [
    "DEFAULT_ORDER",
    "Taps",
    "apply_taps",
    "delay",
    "lagrange_taps",
    "lagrange_weights",
    "shift_taps",
    "timeshift",
]


def timeshift(x: np.ndarray, shift, order: int = DEFAULT_ORDER, fill: float = np.nan) -> np.ndarray:
    """Shift ``x`` in time by ``shift`` samples: ``y[k] = x(k + shift[k])``.

    A delay by ``tau`` seconds at sampling rate ``fs`` is ``shift = -tau * fs``.

    Parameters
    ----------
    x : array_like, shape (..., n)
        Series sampled uniformly.
    shift : float or array_like, shape (n,)
        Shift in samples (negative for a delay).
    order : int
        Odd Lagrange order.
    fill : float
        Value of samples whose stencil leaves the data.
    """
    x = np.asarray(x)
    return apply_taps(x, shift_taps(shift, x.shape[-1], order), fill=fill)


def delay(
    x: np.ndarray, tau, fs: float, order: int = DEFAULT_ORDER, fill: float = np.nan, history: int = 0
) -> np.ndarray:
    """Apply the delay operator ``D x(t) = x(t - tau(t))`` (``tau`` in seconds).

    Parameters
    ----------
    x : ndarray, shape (..., history + n)
        Input series; its first ``history`` samples precede the output window.
    tau : float or ndarray, shape (n,) or (rows, n)
        Delay [s] at each output sample; 2-D for one delay series per row of ``x``.
    history : int
        Number of leading samples of ``x`` before the first output sample.

    Returns
    -------
    ndarray, shape (..., n)
    """
    x = np.asarray(x)
    n = x.shape[-1] - int(history)
    tau = np.asarray(tau, dtype=float)
    if tau.ndim == 2:  # one delay series per row of x
        if tau.shape[0] != x.shape[0]:
            raise ValueError(f"{tau.shape[0]} delay series for {x.shape[0]} rows")
        return np.stack([delay(row, t, fs, order, fill, history) for row, t in zip(x, tau)])
    taps = shift_taps(-tau * fs, n, order, offset=history)
    return apply_taps(x, taps, fill=fill)
