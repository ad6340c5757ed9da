r"""Plane gravitational-wave response of the six LISA links (fractional frequency).

This is the standard one-arm response, in the conventions of lisagwresponse
(``ResponseFromStrain.compute_gw_response`` with its default ``shift_sun="never"``), so
that for the same strain, sky position, orbit and times both give the same numbers
(checked in ``tests/ttlcore/gw/test_gw.py``; ttlcore never imports lisagwresponse).

Sky frame and polarisation basis
--------------------------------
The source sits at ecliptic latitude ``beta`` and longitude ``lam`` (barycentric
ecliptic axes, the axes of the orbit positions). The wave propagates along

    k = -(cos(beta) cos(lam), cos(beta) sin(lam), sin(beta))     (from the source to the Sun),

and the polarisation basis, before the polarisation angle, is (lisagwresponse's
``set_position``)

    u0 = (sin(lam), -cos(lam), 0),
    v0 = (-sin(beta) cos(lam), -sin(beta) sin(lam), cos(beta)),

(``u0 = -e_lam`` and ``v0 = e_beta``, the unit vectors of decreasing longitude and
increasing latitude at the source position; ``u0 x v0 = k``).
The polarisation angle ``psi`` rotates the basis,

    u = cos(psi) u0 + sin(psi) v0,     v = -sin(psi) u0 + cos(psi) v0,

and the strain tensor is ``h_ab = h_plus e+_ab + h_cross ex_ab`` with
``e+ = u u - v v`` and ``ex = u v + v u``. Projected on the basis ``(u0, v0)`` this gives

    h_plus0  = h_plus cos(2 psi) - h_cross sin(2 psi),
    h_cross0 = h_plus sin(2 psi) + h_cross cos(2 psi),

which is exactly how lisagwresponse's ``GalacticBinary`` applies its ``psi`` to the
source-frame strain, so ``hplus, hcross`` here are the polarisations in the source's
own frame (``psi = 0`` means the lisagwresponse basis itself).

Link response
-------------
For link ``ij`` (received at spacecraft ``i`` at time ``t``, emitted by spacecraft ``j``
at ``t_e = t - tau_ij(t)``), with ``x_i`` the spacecraft positions,

    n_ij   = (x_i(t) - x_j(t_e)) / |x_i(t) - x_j(t_e)|      (unit vector emitter -> receiver),
    xi+    = (u . n_ij)^2 - (v . n_ij)^2,      xix = 2 (u . n_ij)(v . n_ij),
    H(s)   = h_plus(s) xi+ + h_cross(s) xix,
    y_ij(t) = [ H(t_e - k . x_j(t_e) / c) - H(t - k . x_i(t) / c) ] / (2 (1 - k . n_ij)).

``h_plus(s)``, ``h_cross(s)`` are the strain at the solar-system barycentre at time ``s``
(``k . x / c`` is the arrival-time shift of the plane wave from the barycentre to the
position ``x``). The antenna patterns use ``n_ij`` of the actual light path, evaluated
at each sample, so arm flexing and rotation are included. ``y`` is the fractional
frequency deviation ``delta nu / nu`` of the received beam (docs/physics.md units).

Two limits (derived in the tests):

- long wavelength, ``f L / c << 1``: ``y_ij(t) ~ -(L / 2c) n_ij . (dh/dt) . n_ij``,
  evaluated at the arm midpoint when the light passes it;
- for a monochromatic wave on a static arm, ``|y_ij| = |H| |sin(pi f (1 - k.n_ij) L/c)| /
  (1 - k.n_ij)``: the single-link transfer function vanishes where
  ``f (1 - k.n_ij) L / c`` is an integer.

Time frames
-----------
``t`` is the time coordinate of the orbit: ``orbit.ltt`` and ``orbit.positions`` are
evaluated at ``t`` (and at ``t - tau``). For an :class:`~ttlcore.sim.orbits.OrbitFile` use
``dataset="tcb/ltt"`` to reproduce lisagwresponse's TCB response exactly; with the default
``"tps/ppr"`` the delays are pseudo-ranges on the TPS grid, which differ from the TCB light
travel times by far less than anything that matters at mHz frequencies but not by zero.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..conventions import LINKS, C
from ..sim.orbits import Orbit, as_times

__all__ = ["propagation_basis", "antenna_patterns", "link_response"]

#: Receiver and emitter spacecraft index (0-based) of each link, in LINKS order.
_RECEIVER = np.array([int(link[0]) - 1 for link in LINKS])
_EMITTER = np.array([int(link[1]) - 1 for link in LINKS])

# Samples per chunk in link_response (bounds the (6, chunk, 3) work arrays to a few MB).
_CHUNK = 1 << 16


def propagation_basis(beta: float, lam: float, psi: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Propagation direction ``k`` and polarisation vectors ``u, v`` (module docstring).

    Parameters
    ----------
    beta, lam : float
        Ecliptic latitude and longitude of the source [rad].
    psi : float
        Polarisation angle [rad]; rotates ``(u0, v0)`` by ``psi`` about ``k``.

    Returns
    -------
    k, u, v : ndarray, shape (3,)
        Unit vectors, mutually orthogonal, ``u x v = k``.
    """
    beta, lam, psi = float(beta), float(lam), float(psi)
    cb, sb, cl, sl = np.cos(beta), np.sin(beta), np.cos(lam), np.sin(lam)
    k = -np.array([cb * cl, cb * sl, sb])
    u0 = np.array([sl, -cl, 0.0])
    v0 = np.array([-sb * cl, -sb * sl, cb])
    cp, sp = np.cos(psi), np.sin(psi)
    return k, cp * u0 + sp * v0, -sp * u0 + cp * v0


def antenna_patterns(n: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``xi+ = (u.n)^2 - (v.n)^2`` and ``xix = 2 (u.n)(v.n)`` for unit vectors ``n`` (..., 3)."""
    un = n @ u
    vn = n @ v
    return un * un - vn * vn, 2.0 * un * vn


def _strain(h: Callable, s: np.ndarray, name: str) -> np.ndarray:
    out = np.asarray(h(s), dtype=float)
    if out.shape != s.shape:
        try:
            out = np.broadcast_to(out, s.shape)
        except ValueError:
            raise ValueError(f"{name}(t) returned shape {out.shape} for times of shape {s.shape}") from None
    return out


def link_response(
    orbit: Orbit,
    t,
    hplus: Callable[[np.ndarray], np.ndarray],
    hcross: Callable[[np.ndarray], np.ndarray],
    beta: float,
    lam: float,
    psi: float = 0.0,
) -> np.ndarray:
    """Response ``y_ij(t)`` of the six links to a plane wave (module docstring for the equations).

    Parameters
    ----------
    orbit : Orbit
        Spacecraft positions and light travel times (``positions``, ``ltt``).
    t : array_like, shape (n,)
        Reception times [s], in the orbit's time coordinate.
    hplus, hcross : callable
        Strain polarisations at the barycentre, in the source frame (before ``psi``):
        vectorised functions of a 1-D time array returning an array of the same shape.
    beta, lam : float
        Ecliptic latitude and longitude of the source [rad].
    psi : float
        Polarisation angle [rad].

    Returns
    -------
    ndarray, shape (6, n)
        Fractional-frequency response of the links ``12, 23, 31, 13, 32, 21``.
    """
    t = as_times(t)
    k, u, v = propagation_basis(beta, lam, psi)
    out = np.empty((6, t.size))
    for start in range(0, t.size, _CHUNK):
        sl = slice(start, start + _CHUNK)
        out[:, sl] = _link_response_chunk(orbit, t[sl], hplus, hcross, k, u, v)
    return out


def _link_response_chunk(orbit, t, hplus, hcross, k, u, v) -> np.ndarray:
    n = t.size
    tau = np.asarray(orbit.ltt(t), dtype=float)  # (6, n)
    if tau.shape != (6, n):
        raise ValueError(f"orbit.ltt returned shape {tau.shape}, expected (6, {n})")
    x_rec = np.asarray(orbit.positions(t), dtype=float)  # (3 SC, n, 3)
    t_emit = t[None, :] - tau  # (6, n)

    # Emitter positions at the emission times: each spacecraft emits on two links, so
    # evaluate its position once on both links' emission times.
    x_emit = np.empty((6, n, 3))
    for sc in range(3):
        links = np.flatnonzero(_EMITTER == sc)
        pos = np.asarray(orbit.positions(t_emit[links].ravel()), dtype=float)[sc]  # (len*n, 3)
        x_emit[links] = pos.reshape(len(links), n, 3)

    nvec = x_rec[_RECEIVER] - x_emit  # (6, n, 3)
    nvec /= np.linalg.norm(nvec, axis=-1, keepdims=True)
    xi_plus, xi_cross = antenna_patterns(nvec, u, v)  # (6, n)
    k_n = nvec @ k  # (6, n)

    # Barycentric arrival times of the wavefront at the receivers (one per spacecraft)
    # and at the emitters (one per link); evaluate the strain once on all of them.
    s_rec = t[None, :] - (x_rec @ k) / C  # (3, n)
    s_emit = t_emit - (x_emit @ k) / C  # (6, n)
    s = np.concatenate([s_rec.ravel(), s_emit.ravel()])
    hp = _strain(hplus, s, "hplus")
    hc = _strain(hcross, s, "hcross")
    hp_rec, hp_emit = hp[: 3 * n].reshape(3, n), hp[3 * n :].reshape(6, n)
    hc_rec, hc_emit = hc[: 3 * n].reshape(3, n), hc[3 * n :].reshape(6, n)

    d_plus = hp_emit - hp_rec[_RECEIVER]
    d_cross = hc_emit - hc_rec[_RECEIVER]
    return (xi_plus * d_plus + xi_cross * d_cross) / (2.0 * (1.0 - k_n))
