"""Spacecraft orbits and light travel times.

Every orbit model answers the same questions for an array of (reception) times ``t``:

- :meth:`Orbit.ltt`: the six light travel times ``tau_ij(t)`` [s] in the canonical link
  order ``12, 23, 31, 13, 32, 21`` (:data:`ttlcore.conventions.LINKS`), shape ``(6, n)``.
  Link ``ij`` is the beam received at spacecraft ``i`` at time ``t`` and emitted by
  spacecraft ``j`` at time ``t - tau_ij(t)``; the delay operator of docs/physics.md is
  ``D_ij x(t) = x(t - tau_ij(t))``.
- :meth:`Orbit.ltt_rate`: their time derivatives ``d tau_ij / dt`` [s/s], shape ``(6, n)``.
- :meth:`Orbit.positions`, :meth:`Orbit.velocities`: spacecraft 1, 2, 3 state vectors,
  shape ``(3, n, 3)`` (spacecraft, sample, x/y/z) in metres and m/s.
- :meth:`Orbit.describe`: a JSON-serialisable dict from which :func:`from_description`
  rebuilds the same orbit.

Models
------
:class:`StaticOrbit`
    Constant delays (:func:`equal_arms`, :func:`paper_unequal`).
:class:`KeplerianOrbit`
    Analytic Newtonian Keplerian orbits of the LISA "cartwheel" (the construction of
    lisaorbits' ``KeplerianOrbits``), light travel times from the flat-space light-time
    equation.
:class:`OrbitFile`
    A lisaorbits orbit file (HDF5, read with h5py only), ``tps/ppr`` or ``tcb/ltt``,
    interpolated in time by quintic splines.

:func:`make_orbit` builds any of them from a short spec string (``"equal"``,
``"unequal"``, ``"keplerian"`` or a file path).

All models are Newtonian: no Shapiro delay and no relativistic time-scale corrections are
added (an orbit *file* carries whatever its generator put in it).
"""

# size: three orbit models behind one interface (static arms, Keplerian, a lisaorbits file) and
# the factory that chooses; each is ~200 lines of geometry.

from __future__ import annotations

import logging
import math
import os
from collections.abc import Mapping, Sequence

import h5py
import numpy as np
from scipy.interpolate import make_interp_spline

from ..conventions import ARM_LENGTH, ASTRONOMICAL_UNIT, LINKS, C, finite_number
from ..errors import ConfigError, TelemetryError

logger = logging.getLogger(__name__)

__all__ = [
    "GM_SUN",
    "Orbit",
    "StaticOrbit",
    "KeplerianOrbit",
    "OrbitFile",
    "equal_arms",
    "paper_unequal",
    "make_orbit",
    "from_description",
    "PAPER_UNEQUAL_LTT",
    "ORBIT_FILE_DATASETS",
]

#: Heliocentric gravitational constant [m^3/s^2] (IAU 2015 nominal value, as lisaconstants).
GM_SUN = 1.3271244e20

#: Receiver and emitter spacecraft index (0-based) of each link, in :data:`LINKS` order.
_RECEIVER = np.array([int(link[0]) - 1 for link in LINKS])
_EMITTER = np.array([int(link[1]) - 1 for link in LINKS])

#: The paper's static unequal light travel times [s] (Paczkowski et al. 2022).
PAPER_UNEQUAL_LTT: dict[str, float] = {
    "12": 8.425,
    "23": 8.372,
    "31": 8.322,
    "13": 8.322,
    "32": 8.372,
    "21": 8.322,
}

#: Datasets of a lisaorbits file that :class:`OrbitFile` can use as delays.
ORBIT_FILE_DATASETS: tuple[str, ...] = ("tps/ppr", "tcb/ltt")

# Samples processed at once by the Keplerian light-time solver (keeps work arrays in cache).
_CHUNK = 1 << 15


def as_times(t) -> np.ndarray:
    """Times as a 1-D float array (a scalar becomes shape ``(1,)``)."""
    t = np.asarray(t, dtype=float)
    if t.ndim == 0:
        t = t.reshape(1)
    if t.ndim != 1:
        raise ValueError(f"times must be a scalar or a 1-D array, got shape {t.shape}")
    return t


def _ltt_mapping(ltt) -> dict[str, float]:
    """Normalise six light travel times (mapping by link or sequence in LINKS order)."""
    if isinstance(ltt, Mapping):
        keys = {str(k) for k in ltt}
        missing = [link for link in LINKS if link not in keys]
        extra = sorted(keys - set(LINKS))
        if missing or extra:
            raise ConfigError(
                f"orbit 'ltt' must give exactly the links {', '.join(LINKS)}"
                + (f"; missing {', '.join(missing)}" if missing else "")
                + (f"; unknown {', '.join(extra)}" if extra else "")
            )
        values = {link: ltt[link] if link in ltt else ltt[int(link)] for link in LINKS}
    else:
        seq = list(np.asarray(ltt, dtype=float).ravel()) if not isinstance(ltt, str) else None
        if seq is None or len(seq) != 6:
            raise ConfigError(f"orbit 'ltt' must be 6 values in the link order {', '.join(LINKS)}, got {ltt!r}")
        values = dict(zip(LINKS, seq))
    out = {}
    for link, value in values.items():
        out[link] = finite_number(value, f"orbit 'ltt[{link}]'", positive=True, unit="seconds")
    return out


class Orbit:
    """Base class of the orbit models.

    Subclasses implement :meth:`ltt`, :meth:`positions`, :meth:`velocities` and
    :meth:`describe`; :meth:`ltt_rate` has a finite-difference fallback here.

    Attributes
    ----------
    name : str
        Short human-readable name (``"equal"``, ``"unequal"``, ``"keplerian"``,
        ``"file:<basename>"`` ...).
    """

    name: str = "orbit"

    def ltt(self, t) -> np.ndarray:
        """Light travel times ``tau_ij(t)`` [s].

        Parameters
        ----------
        t : array_like, shape (n,)
            Reception times [s] (a scalar is treated as ``n = 1``).

        Returns
        -------
        ndarray, shape (6, n)
            ``tau_ij(t)`` for the links in :data:`~ttlcore.conventions.LINKS` order.
        """
        raise NotImplementedError

    def ltt_rate(self, t) -> np.ndarray:
        """Time derivatives ``d tau_ij / dt`` [s/s], shape ``(6, n)``.

        The base implementation is a fourth-order central finite difference with step
        ``h = 1 s``,

            tau'(t) ~ [8 (tau(t+h) - tau(t-h)) - (tau(t+2h) - tau(t-2h))] / (12 h),

        whose truncation error ``h^4 tau^(5) / 30`` is negligible for orbital motion.
        Subclasses override it with exact expressions.
        """
        t = as_times(t)
        h = 1.0
        return (8.0 * (self.ltt(t + h) - self.ltt(t - h)) - (self.ltt(t + 2 * h) - self.ltt(t - 2 * h))) / (12.0 * h)

    def positions(self, t) -> np.ndarray:
        """Spacecraft positions [m], shape ``(3, n, 3)``: spacecraft 1-3, sample, x/y/z."""
        raise NotImplementedError

    def velocities(self, t) -> np.ndarray:
        """Spacecraft velocities [m/s], shape ``(3, n, 3)``: spacecraft 1-3, sample, x/y/z."""
        raise NotImplementedError

    def describe(self) -> dict:
        """JSON-serialisable description; :func:`from_description` rebuilds the orbit."""
        raise NotImplementedError

    def ltt_dict(self, t) -> dict[str, np.ndarray]:
        """:meth:`ltt` as a dict ``{link: tau_link(t)}``."""
        values = self.ltt(t)
        return {link: values[k] for k, link in enumerate(LINKS)}

    def __repr__(self) -> str:
        try:
            return f"{type(self).__name__}({self.describe()!r})"
        except NotImplementedError:
            return f"{type(self).__name__}(name={self.name!r})"


# ---------------------------------------------------------------------------
# Static arms
# ---------------------------------------------------------------------------


class StaticOrbit(Orbit):
    """Constant light travel times.

    ``tau_ij(t) = tau_ij`` for every ``t``; ``d tau_ij/dt = 0``.

    The spacecraft positions are a fixed triangle in the ``z = 0`` plane, centred on the
    origin, with spacecraft 1 on the +x axis and side lengths

        L_ij = c (tau_ij + tau_ji) / 2,

    i.e. the mean of the two directions of each arm (the construction of lisaorbits'
    ``StaticConstellation.from_armlengths``): with ``m_1`` the median from spacecraft 1,

        x_1 = (2/3) m_1 = sqrt(2 L_12^2 + 2 L_31^2 - L_23^2) / 3,
        x_2 = (L_23^2 + L_31^2 - 5 L_12^2) / (18 x_1),
        x_3 = (L_12^2 + L_23^2 - 5 L_31^2) / (18 x_1),
        y_2 = -y_3 = -sqrt(16 A^2) / (6 x_1),  (A the triangle's area, Heron)

    A static triangle cannot have ``tau_ij != tau_ji`` (that needs motion), so for unequal
    forward and backward delays the positions are only approximate: they reproduce the
    mean arm lengths, not each delay. Velocities are zero.

    Parameters
    ----------
    ltt : mapping or sequence
        The six light travel times [s], as ``{"12": tau_12, ...}`` or a sequence in
        :data:`~ttlcore.conventions.LINKS` order.
    name : str
        Name of the orbit (``"equal"``, ``"unequal"``, ``"static"`` ...).
    """

    def __init__(self, ltt, name: str = "static"):
        self.name = str(name)
        self._ltt = _ltt_mapping(ltt)
        self._values = np.array([self._ltt[link] for link in LINKS])
        arm = {pair: C * 0.5 * (self._ltt[pair] + self._ltt[pair[::-1]]) for pair in ("12", "23", "31")}
        l12, l23, l31 = arm["12"], arm["23"], arm["31"]
        if not (l12 < l23 + l31 and l23 < l12 + l31 and l31 < l12 + l23):
            raise ConfigError(
                f"orbit 'ltt': the mean arm lengths {l12:.6g}, {l23:.6g}, {l31:.6g} m violate the triangle inequality"
            )
        x1 = math.sqrt(2 * l12**2 - l23**2 + 2 * l31**2) / 3
        x2 = (l23**2 + l31**2 - 5 * l12**2) / (18 * x1)
        x3 = (l12**2 + l23**2 - 5 * l31**2) / (18 * x1)
        area16 = (l12 + l23 + l31) * (-l12 + l23 + l31) * (l12 - l23 + l31) * (l12 + l23 - l31)
        y2 = -math.sqrt(area16) / (6 * x1)
        #: Fixed spacecraft positions [m], shape (3, 3) (spacecraft, x/y/z).
        self.sc_positions = np.array([[x1, 0.0, 0.0], [x2, y2, 0.0], [x3, -y2, 0.0]])

    @property
    def values(self) -> dict[str, float]:
        """The six constant light travel times [s], by link."""
        return dict(self._ltt)

    def ltt(self, t) -> np.ndarray:
        """Constant light travel times, shape ``(6, n)`` [s]."""
        t = as_times(t)
        return np.repeat(self._values[:, None], t.size, axis=1)

    def ltt_rate(self, t) -> np.ndarray:
        """Zeros, shape ``(6, n)`` [s/s]."""
        return np.zeros((6, as_times(t).size))

    def positions(self, t) -> np.ndarray:
        """Fixed triangle (see class docstring), shape ``(3, n, 3)`` [m]."""
        t = as_times(t)
        return np.repeat(self.sc_positions[:, None, :], t.size, axis=1)

    def velocities(self, t) -> np.ndarray:
        """Zeros, shape ``(3, n, 3)`` [m/s]."""
        return np.zeros((3, as_times(t).size, 3))

    def describe(self) -> dict:
        return {"type": "static", "name": self.name, "ltt": dict(self._ltt)}


def equal_arms(arm_length: float = ARM_LENGTH) -> StaticOrbit:
    """Static equal arms: all six ``tau_ij = L / c``.

    Parameters
    ----------
    arm_length : float
        Arm length ``L`` [m]; default the nominal 2.5e9 m (``tau = 8.339 s``).
    """
    arm_length = finite_number(arm_length, "orbit 'arm_length'", positive=True, unit="metres")
    return StaticOrbit({link: arm_length / C for link in LINKS}, name="equal")


def paper_unequal() -> StaticOrbit:
    """The paper's static unequal arms (:data:`PAPER_UNEQUAL_LTT`).

    ``tau_12 = 8.425, tau_13 = 8.322, tau_23 = 8.372, tau_21 = 8.322, tau_31 = 8.322,
    tau_32 = 8.372`` s.
    """
    return StaticOrbit(PAPER_UNEQUAL_LTT, name="unequal")


# ---------------------------------------------------------------------------
# Keplerian orbits
# ---------------------------------------------------------------------------


class KeplerianOrbit(Orbit):
    r"""Analytic Keplerian (Newtonian two-body) orbits of the LISA cartwheel.

    Each spacecraft follows its own heliocentric ellipse with semi-major axis ``a``
    (1 AU, period one year), eccentricity ``e`` and inclination ``i`` chosen so that the
    three spacecraft keep a nearly equilateral triangle of side ``L`` that rotates once
    a year ("cartwheel"). The construction is that of Nayak et al. (2006), used by
    lisaorbits' ``KeplerianOrbits`` (same parameter names and phases), which keeps the
    arm flexing minimal to second order in ``alpha``:

        alpha = L / (2 a),      nu = pi/3 + delta * alpha   (delta = 5/8),
        e     = sqrt(1 + (4/sqrt(3)) alpha cos(nu) + (4/3) alpha^2) - 1,
        tan i = alpha sin(nu) / (sqrt(3)/2 + alpha cos(nu)).

    To first order ``e = alpha/sqrt(3) = L / (2 sqrt(3) a)`` and ``i = alpha``
    (``delta = 0`` gives the plain first-order construction). With the mean motion
    ``n = sqrt(GM_sun / a^3)`` and, for spacecraft ``k = 1, 2, 3``,
    ``theta_k = 2 pi (k - 1) / 3``, ``lambda_k = lambda1 + theta_k``,
    ``M_k(t) = n (t - t_init) + m_init1 - theta_k``, Kepler's equation

        E_k - e sin(E_k) = M_k

    is solved for the eccentric anomaly ``E_k`` by Newton's method to machine precision,
    and the position (Sun at the origin, ecliptic axes) is

        xi   =  a cos(i) (cos E_k - e),
        eta  =  a sqrt(1 - e^2) sin E_k,
        zeta = -a sin(i) (cos E_k - e),
        x_k  = (cos(lambda_k) xi - sin(lambda_k) eta,  sin(lambda_k) xi + cos(lambda_k) eta,  zeta),

    with velocity from ``dE_k/dt = n / (1 - e cos E_k)``.

    Light travel times solve the flat-space (Newtonian) light-time equation

        tau_ij(t) = |x_i(t) - x_j(t - tau_ij(t))| / c

    by fixed-point iteration, ``tau <- |x_i(t) - x_j(t - tau)| / c`` (contraction factor
    ``|v_j|/c ~ 1e-4``), until the update is below 1e-13 s. No Shapiro delay (about
    1.6e-7 s for LISA) and no other relativistic correction is included; lisaorbits adds
    the Shapiro term by default. The emitter position is expanded about the reception
    time with the exact Keplerian derivatives,

        x_j(t - tau) = x_j - tau v_j + tau^2/2 a_j - tau^3/6 j_j + O(tau^4),
        a = -GM x / r^3,    j = da/dt = -GM (v / r^3 - 3 (x.v) x / r^5),

    so that, with ``d = x_i(t) - x_j(t)`` and everything at the reception time,

        |x_i(t) - x_j(t - tau)|^2 = c0 + c1 tau + c2 tau^2 + c3 tau^3,
        c0 = d.d,  c1 = 2 d.v_j,  c2 = v_j.v_j - d.a_j,  c3 = d.j_j / 3 - v_j.a_j.

    The iteration starts from the exact root of the quadratic truncation
    ``c^2 tau^2 = c0 + c1 tau + c2 tau^2`` and then converges in one or two steps. The
    neglected terms (``tau^4 a n^4 / 24 ~ 5e-14 m`` in the emitter position, ``~1e-21``
    relative in the squared distance) are far below the ~1e-5 m rounding floor of
    heliocentric coordinates in double precision, which limits the consistency
    ``|tau - |x_i(t) - x_j(t - tau)|/c|`` to ~1e-12 s.

    ``ltt`` for one day at 16 Hz (1.4 million samples) takes about 0.4 s.

    Parameters
    ----------
    arm_length : float
        Nominal (mean) arm length ``L`` [m].
    t_init : float
        Epoch [s] at which the mean anomaly of spacecraft 1 is ``m_init1``.
    lambda1 : float
        Longitude of periastron of spacecraft 1 [rad] (initial constellation angle).
    m_init1 : float
        Mean anomaly of spacecraft 1 at ``t_init`` [rad] (initial orbital phase).
    semi_major_axis : float
        ``a`` [m]; default 1 AU.
    delta : float
        Tilt perturbation ``delta`` of ``nu = pi/3 + delta alpha``; 5/8 minimises flexing.
    """

    name = "keplerian"

    def __init__(
        self,
        arm_length: float = ARM_LENGTH,
        t_init: float = 0.0,
        lambda1: float = 0.0,
        m_init1: float = 0.0,
        semi_major_axis: float = ASTRONOMICAL_UNIT,
        delta: float = 5.0 / 8.0,
    ):
        params = {}
        for key, value in (
            ("arm_length", arm_length),
            ("t_init", t_init),
            ("lambda1", lambda1),
            ("m_init1", m_init1),
            ("semi_major_axis", semi_major_axis),
            ("delta", delta),
        ):
            params[key] = finite_number(value, f"orbit '{key}'")
        if params["semi_major_axis"] <= 0:
            raise ConfigError(f"orbit 'semi_major_axis' must be positive, got {semi_major_axis!r}")
        if not 0 < params["arm_length"] < 0.1 * params["semi_major_axis"]:
            raise ConfigError(
                f"orbit 'arm_length' must be positive and small against the semi-major axis, got {arm_length!r}"
            )
        self.arm_length = params["arm_length"]
        self.t_init = params["t_init"]
        self.lambda1 = params["lambda1"]
        self.m_init1 = params["m_init1"]
        self.semi_major_axis = a = params["semi_major_axis"]
        self.delta = params["delta"]

        #: alpha = L / (2 a).
        self.alpha = alpha = self.arm_length / (2 * a)
        #: Tilt angle nu [rad].
        self.nu = nu = np.pi / 3 + self.delta * alpha
        #: Eccentricity.
        self.eccentricity = e = math.sqrt(1 + 4 * alpha * math.cos(nu) / math.sqrt(3) + 4 * alpha**2 / 3) - 1
        tan_i = alpha * math.sin(nu) / (math.sqrt(3) / 2 + alpha * math.cos(nu))
        #: Inclination [rad].
        self.inclination = math.atan(tan_i)
        #: Mean motion n [rad/s].
        self.mean_motion = math.sqrt(GM_SUN / a**3)
        self._theta = 2 * np.pi * np.arange(3) / 3
        self._m0 = self.m_init1 - self._theta  # (3,) mean anomalies at t_init
        lam = self.lambda1 + self._theta
        cos_i, sin_i = math.cos(self.inclination), math.sin(self.inclination)
        b = a * math.sqrt(1 - e**2)
        # position = P_k (cos E - e) + Q_k sin E, velocity = (-P_k sin E + Q_k cos E) dE/dt
        self._P = np.stack([a * cos_i * np.cos(lam), a * cos_i * np.sin(lam), np.full(3, -a * sin_i)], axis=1)
        self._Q = np.stack([-b * np.sin(lam), b * np.cos(lam), np.zeros(3)], axis=1)

    # -- Kepler's equation and the state vectors -------------------------------------

    def eccentric_anomaly(self, t) -> np.ndarray:
        """Eccentric anomalies ``E_k(t)`` [rad], shape ``(3, n)``, reduced to ``[-pi, pi) + O(e)``.

        Solves ``E - e sin E = M`` by Newton's method from the ``O(e^4)``-accurate series
        ``E0 = M + (e - e^3/8) sin M + e^2/2 sin 2M + 3 e^3/8 sin 3M``; see
        :meth:`_kepler` for the convergence criterion.
        """
        E, _, _ = self._kepler(as_times(t))
        return E

    def _kepler(self, t: np.ndarray):
        """Solve Kepler's equation; returns ``E, sin E, cos E``, each shape ``(3, n)``.

        ``sin M_k, cos M_k`` are obtained from those of spacecraft 1 by rotating by
        ``theta_k``. Writing ``E = M + d``, Newton steps
        ``d <- d - (d - e sin E) / (1 - e cos E)`` start from the series of :meth:`eccentric_anomaly` and are
        repeated until the largest step ``|dd|`` is below 1e-8; the remaining error is then
        ``~ e dd^2 / 2 < 1e-18`` rad, i.e. machine precision (one step suffices for LISA's
        ``e ~ 0.005``). ``sin E`` and ``cos E`` of the last iterate are rotated by ``dd`` to
        second order (error ``dd^3 < 1e-24``) instead of being recomputed.
        """
        e = self.eccentricity
        M1 = self.mean_motion * (t - self.t_init) + self.m_init1
        M1 = M1 - (2 * np.pi) * np.rint(M1 / (2 * np.pi))
        s1, c1 = np.sin(M1), np.cos(M1)
        M = M1[None, :] - self._theta[:, None]
        cos_th, sin_th = np.cos(self._theta)[:, None], np.sin(self._theta)[:, None]
        sM = s1 * cos_th - c1 * sin_th
        cM = c1 * cos_th + s1 * sin_th
        d = sM * ((e - e**3 / 8) + e**2 * cM + 3 * e**3 / 8 * (3 - 4 * sM * sM))
        for _ in range(30):
            E = M + d
            sE, cE = np.sin(E), np.cos(E)
            step = (d - e * sE) / (1 - e * cE)
            d -= step
            if np.max(np.abs(step), initial=0.0) < 1e-8:
                half_sq = 0.5 * step * step
                sE, cE = sE * (1 - half_sq) - cE * step, cE * (1 - half_sq) + sE * step
                return M + d, sE, cE
        raise RuntimeError("Kepler's equation did not converge")  # pragma: no cover

    def _state(self, t: np.ndarray):
        """Positions and velocities as component arrays ``X[k, xyz, n]``, ``V[k, xyz, n]``."""
        _, sE, cE = self._kepler(t)
        P, Q = self._P[:, :, None], self._Q[:, :, None]
        X = P * (cE - self.eccentricity)[:, None, :] + Q * sE[:, None, :]
        dE = self.mean_motion / (1 - self.eccentricity * cE)
        V = (Q * (cE * dE)[:, None, :]) - P * (sE * dE)[:, None, :]
        return X, V

    def _chunked_states(self, t, which: int) -> np.ndarray:
        t = as_times(t)
        out = np.empty((3, t.size, 3))
        for start in range(0, t.size, _CHUNK):
            sl = slice(start, start + _CHUNK)
            out[:, sl, :] = self._state(t[sl])[which].transpose(0, 2, 1)
        return out

    def positions(self, t) -> np.ndarray:
        """Heliocentric positions [m] in ecliptic axes, shape ``(3, n, 3)``."""
        return self._chunked_states(t, 0)

    def velocities(self, t) -> np.ndarray:
        """Heliocentric velocities [m/s], shape ``(3, n, 3)``."""
        return self._chunked_states(t, 1)

    # -- light travel times ----------------------------------------------------------

    @staticmethod
    def _dot(a, b):
        return np.einsum("ij,ij->j", a, b)

    def _solve_chunk(self, t: np.ndarray, rates: bool):
        """Light travel times (and rates) for one chunk of reception times."""
        X, V = self._state(t)  # (3 SC, 3 xyz, m)
        dot = self._dot
        # Keplerian acceleration and jerk of each spacecraft: VAJ[k] = (v_k, a_k, j_k).
        VAJ = np.empty((3, 3, 3, t.size))
        VAJ[:, 0] = V
        vv, va = [], []
        for k in range(3):
            r2 = dot(X[k], X[k])
            gm_r3 = GM_SUN / (r2 * np.sqrt(r2))
            np.multiply(-gm_r3, X[k], out=VAJ[k, 1])
            np.multiply(-gm_r3, V[k] - (3.0 * dot(X[k], V[k]) / r2) * X[k], out=VAJ[k, 2])
            vv.append(dot(V[k], V[k]))
            va.append(dot(V[k], VAJ[k, 1]))
        A, J = VAJ[:, 1], VAJ[:, 2]
        tau = np.empty((6, t.size))
        rate = np.empty((6, t.size)) if rates else None
        c2_light = C * C
        # d = x_i - x_j for the pair (i < j), its square, and its projections on the
        # emitter's V, A, J (the reversed link uses -d and the other spacecraft).
        pair_cache = {}
        for index, (i, j) in enumerate(zip(_RECEIVER, _EMITTER)):
            key = (min(i, j), max(i, j))
            if key not in pair_cache:
                d_key = X[key[0]] - X[key[1]]
                pair_cache[key] = (d_key, dot(d_key, d_key))
            d_key, c0 = pair_cache[key]
            sign = 1.0 if i == key[0] else -1.0
            proj = np.einsum("ij,kij->kj", d_key, VAJ[j])
            # |x_i(t) - x_j(t - tau)|^2 = c0 + c1 tau + c2 tau^2 + c3 tau^3 + O(1e-21 relative)
            c1 = (2.0 * sign) * proj[0]
            c2 = vv[j] - sign * proj[1]
            c3 = (sign / 3.0) * proj[2] - va[j]
            # start: exact root of the quadratic truncation c^2 tau^2 = c0 + c1 tau + c2 tau^2
            q = c2_light - c2
            x = (c1 + np.sqrt(c1 * c1 + 4.0 * q * c0)) / (2.0 * q)
            for _ in range(20):
                new = np.sqrt(c0 + x * (c1 + x * (c2 + x * c3))) / C
                change = np.max(np.abs(new - x), initial=0.0)
                x = new
                if change < 1e-13:
                    break
            else:  # pragma: no cover - contraction ~1e-4, converges in 1-2 steps
                raise RuntimeError("light-time iteration did not converge")
            tau[index] = x
            if rate is not None:  # rates asked for
                # c tau' = n.(v_i - v_j^e (1 - tau'))  =>  tau' = n.(v_i - v_j^e) / (c - n.v_j^e)
                r = sign * d_key + x * (V[j] - x * (0.5 * A[j] - x * J[j] / 6.0))
                vj_e = V[j] - x * (A[j] - 0.5 * x * J[j])
                inv_nr = 1.0 / np.sqrt(dot(r, r))
                n_ve = dot(r, vj_e) * inv_nr
                rate[index] = (dot(r, V[i]) * inv_nr - n_ve) / (C - n_ve)
        return tau, rate

    def _solve(self, t, rates: bool):
        t = as_times(t)
        tau = np.empty((6, t.size))
        rate = np.empty((6, t.size)) if rates else None
        for start in range(0, t.size, _CHUNK):
            sl = slice(start, start + _CHUNK)
            tau[:, sl], r = self._solve_chunk(t[sl], rates)
            if rate is not None:  # rates asked for
                rate[:, sl] = r
        return tau, rate

    def ltt(self, t) -> np.ndarray:
        """Light travel times [s], shape ``(6, n)``, from the light-time equation (class docstring)."""
        return self._solve(t, rates=False)[0]

    def ltt_rate(self, t) -> np.ndarray:
        r"""Exact derivatives of the light travel times [s/s], shape ``(6, n)``.

        Differentiating ``c tau = |x_i(t) - x_j(t - tau)|`` gives

            d tau / dt = n . (v_i(t) - v_j(t - tau)) / (c - n . v_j(t - tau)),

        with ``n`` the unit vector from emitter (at emission) to receiver (at reception).
        """
        return self._solve(t, rates=True)[1]

    def describe(self) -> dict:
        return {
            "type": "keplerian",
            "arm_length": self.arm_length,
            "t_init": self.t_init,
            "lambda1": self.lambda1,
            "m_init1": self.m_init1,
            "semi_major_axis": self.semi_major_axis,
            "delta": self.delta,
        }


# ---------------------------------------------------------------------------
# lisaorbits files
# ---------------------------------------------------------------------------


class OrbitFile(Orbit):
    """Delays and spacecraft states read from a lisaorbits orbit file (HDF5).

    The file layout is that of lisaorbits >= 2.0: root attributes ``t0``, ``dt``, ``size``
    define the time grid ``t_k = t0 + k dt`` (``k = 0 .. size-1``); ``tcb/ltt`` and
    ``tps/ppr`` have shape ``(size, 6)`` with columns in the link order
    ``12, 23, 31, 13, 32, 21``; ``tcb/x`` and ``tcb/v`` have shape ``(size, 3, 3)``
    (sample, spacecraft, x/y/z). Only h5py is used; lisaorbits is not needed.

    ``tcb/ltt`` are light travel times indexed by the reception time in TCB;
    ``tps/ppr`` (the default, what lisainstrument uses) are proper pseudo-ranges indexed by
    the receiving spacecraft's proper time (TPS) and include the TPS-TCB offsets. In both
    cases ``t`` passed to :meth:`ltt` is read on the file's grid (TCB resp. TPS).

    Between samples every column is interpolated by a B-spline of degree ``order``
    (default 5, quintic, not-a-knot-like end conditions, ``scipy.interpolate.make_interp_spline``):
    for orbital motion sampled every ``dt`` the error scales as ``dt^6 f^(6)``, e.g.
    ~1e-11 s for LTTs sampled every 1e5 s (lisaorbits' default). At the grid times the
    file's samples are returned exactly. Times outside ``[t_0, t_{size-1}]`` raise
    :class:`~ttlcore.errors.TelemetryError`.

    Parameters
    ----------
    path : str or os.PathLike
        The orbit file.
    dataset : {"tps/ppr", "tcb/ltt"}
        Which delays :meth:`ltt` returns.
    order : int
        Spline degree (1 to 5; lowered automatically for files with few samples).
    """

    def __init__(self, path, dataset: str = "tps/ppr", order: int = 5):
        self.path = os.fspath(path)
        self.dataset = str(dataset)
        if self.dataset not in ORBIT_FILE_DATASETS:
            raise ConfigError(f"orbit file dataset must be one of {', '.join(ORBIT_FILE_DATASETS)}, got {dataset!r}")
        try:
            order = int(order)
        except (TypeError, ValueError):
            raise ConfigError(f"orbit file interpolation 'order' must be an integer, got {order!r}") from None
        if not 1 <= order <= 5:
            raise ConfigError(f"orbit file interpolation 'order' must be between 1 and 5, got {order}")
        self.order = order
        self.name = f"file:{os.path.basename(self.path)}"
        self._splines: dict[str, object] = {}
        self._samples: dict[str, np.ndarray] = {}

        h5py = self._h5py()
        try:
            with h5py.File(self.path, "r") as f:
                attrs = {}
                for key in ("t0", "dt", "size"):
                    if key not in f.attrs:
                        raise TelemetryError(
                            self.path, f"missing time-grid attribute '{key}' (not a lisaorbits >= 2.0 orbit file?)", key
                        )
                    attrs[key] = f.attrs[key]
                self.generator = str(f.attrs.get("generator", ""))
                self.file_version = str(f.attrs.get("version", ""))
        except TelemetryError:
            raise
        except (OSError, ValueError) as exc:
            raise TelemetryError(self.path, f"cannot read orbit file ({exc})") from None
        try:
            self.t0 = float(np.asarray(attrs["t0"]).item())
            self.dt = float(np.asarray(attrs["dt"]).item())
            self.size = int(np.asarray(attrs["size"]).item())
        except (TypeError, ValueError) as exc:
            raise TelemetryError(self.path, f"bad time-grid attributes t0/dt/size ({exc})") from None
        if not (np.isfinite(self.t0) and np.isfinite(self.dt) and self.dt > 0 and self.size >= 2):
            raise TelemetryError(self.path, f"bad time grid t0={self.t0!r}, dt={self.dt!r}, size={self.size!r}", "dt")
        #: File time grid [s] (same expression as lisaorbits: ``t0 + arange(size) * dt``).
        self.times = self.t0 + np.arange(self.size) * self.dt
        # Read and validate the delay dataset now, so a bad file fails at construction.
        self._load(self.dataset, (6,))
        logger.info(
            "orbit file %s: %s, %d samples every %g s from t0 = %g s (%s %s)",
            self.path,
            self.dataset,
            self.size,
            self.dt,
            self.t0,
            self.generator or "unknown generator",
            self.file_version,
        )

    @staticmethod
    def _h5py():

        return h5py

    def _load(self, name: str, trailing: tuple[int, ...]) -> np.ndarray:
        """Read dataset ``name`` (shape ``(size, *trailing)``), cached, with clear errors."""
        if name in self._samples:
            return self._samples[name]
        h5py = self._h5py()
        try:
            with h5py.File(self.path, "r") as f:
                if name not in f:
                    raise TelemetryError(self.path, f"missing dataset '{name}'", name)
                obj = f[name]
                if not isinstance(obj, h5py.Dataset):
                    raise TelemetryError(self.path, f"'{name}' is a group, not a dataset", name)
                data = np.asarray(obj[()], dtype=float)
        except TelemetryError:
            raise
        except (OSError, ValueError, TypeError) as exc:
            raise TelemetryError(self.path, f"cannot read dataset '{name}' ({exc})", name) from None
        expected = (self.size, *trailing)
        if data.shape != expected:
            raise TelemetryError(self.path, f"dataset '{name}' has shape {data.shape}, expected {expected}", name)
        if not np.all(np.isfinite(data)):
            raise TelemetryError(self.path, f"dataset '{name}' contains non-finite values", name)
        self._samples[name] = data
        return data

    def _spline(self, name: str, trailing: tuple[int, ...]):
        if name not in self._splines:
            data = self._load(name, trailing)
            k = min(self.order, self.size - 1)
            self._splines[name] = make_interp_spline(self.times, data, k=k, axis=0)
        return self._splines[name]

    def _check_range(self, t: np.ndarray, name: str) -> None:
        if t.size == 0:
            return
        tmin, tmax = float(np.min(t)), float(np.max(t))
        if not (np.isfinite(tmin) and np.isfinite(tmax)):
            raise TelemetryError(self.path, "requested times are not finite", name)
        first, last = self.times[0], self.times[-1]
        if tmin < first or tmax > last:
            raise TelemetryError(
                self.path,
                f"requested times [{tmin:.9g}, {tmax:.9g}] s are outside the file's range [{first:.9g}, {last:.9g}] s",
                name,
            )

    def _evaluate(self, name: str, trailing: tuple[int, ...], t, nu: int = 0) -> np.ndarray:
        """Interpolate ``name`` (or its ``nu``-th derivative) at ``t``: shape ``(n, *trailing)``."""
        t = as_times(t)
        self._check_range(t, name)
        spline = self._spline(name, trailing)
        out = spline(t, nu=nu) if nu else spline(t)
        if nu == 0:
            # Exact file samples at the grid times.
            k = np.clip(np.rint((t - self.t0) / self.dt).astype(np.int64), 0, self.size - 1)
            on_grid = self.times[k] == t
            if np.any(on_grid):
                out[on_grid] = self._samples[name][k[on_grid]]
        return out

    def ltt(self, t) -> np.ndarray:
        """Delays from the file's ``dataset`` [s], shape ``(6, n)``, interpolated in time."""
        return np.ascontiguousarray(self._evaluate(self.dataset, (6,), t).T)

    def ltt_rate(self, t) -> np.ndarray:
        """Derivative of the interpolating spline of :meth:`ltt` [s/s], shape ``(6, n)``."""
        return np.ascontiguousarray(self._evaluate(self.dataset, (6,), t, nu=1).T)

    def positions(self, t) -> np.ndarray:
        """Positions from ``tcb/x`` [m], shape ``(3, n, 3)``, interpolated in TCB."""
        return np.ascontiguousarray(self._evaluate("tcb/x", (3, 3), t).transpose(1, 0, 2))

    def velocities(self, t) -> np.ndarray:
        """Velocities from ``tcb/v`` [m/s], shape ``(3, n, 3)``, interpolated in TCB."""
        return np.ascontiguousarray(self._evaluate("tcb/v", (3, 3), t).transpose(1, 0, 2))

    @property
    def t_range(self) -> tuple[float, float]:
        """First and last time of the file grid [s]."""
        return float(self.times[0]), float(self.times[-1])

    def describe(self) -> dict:
        return {"type": "file", "path": os.path.abspath(self.path), "dataset": self.dataset, "order": self.order}


# ---------------------------------------------------------------------------
# Factories
# ---------------------------------------------------------------------------

_KEPLERIAN_KEYS = ("arm_length", "t_init", "lambda1", "m_init1", "semi_major_axis", "delta")


def _check_kwargs(spec: str, kwargs: dict, allowed: Sequence[str]) -> None:
    unknown = sorted(set(kwargs) - set(allowed))
    if unknown:
        allowed_text = ", ".join(allowed) if allowed else "none"
        raise ConfigError(f"orbit {spec!r} does not take {', '.join(unknown)} (allowed: {allowed_text})")


def make_orbit(spec, **kwargs) -> Orbit:
    """Build an orbit from a short spec.

    Parameters
    ----------
    spec : str or os.PathLike
        ``"equal"`` (:func:`equal_arms`, optional ``arm_length``), ``"unequal"``
        (:func:`paper_unequal`), ``"keplerian"`` (:class:`KeplerianOrbit`, keyword
        parameters passed on), or the path of a lisaorbits orbit file, optionally suffixed
        ``":tps/ppr"`` or ``":tcb/ltt"`` (:class:`OrbitFile`; ``dataset`` and ``order``
        keywords also accepted). Names are case-insensitive. An :class:`Orbit` is
        returned as is and a dict is passed to :func:`from_description`.
    **kwargs
        Parameters of the chosen model.

    Raises
    ------
    ConfigError
        Unknown spec, nonexistent file or bad parameters.
    TelemetryError
        The file exists but is not a usable orbit file.
    """
    if isinstance(spec, Orbit):
        _check_kwargs(type(spec).__name__, kwargs, ())
        return spec
    if isinstance(spec, Mapping):
        _check_kwargs("description", kwargs, ())
        return from_description(spec)
    if not isinstance(spec, (str, os.PathLike)):
        raise ConfigError(f"orbit spec must be a string or path, got {type(spec).__name__} {spec!r}")
    text = os.fspath(spec).strip()
    key = text.lower()
    if key in ("equal", "equal_arms"):
        _check_kwargs(key, kwargs, ("arm_length",))
        return equal_arms(**kwargs)
    if key in ("unequal", "paper_unequal"):
        _check_kwargs(key, kwargs, ())
        return paper_unequal()
    if key == "keplerian":
        _check_kwargs(key, kwargs, _KEPLERIAN_KEYS)
        return KeplerianOrbit(**kwargs)
    return _orbit_file(text, kwargs)


def _orbit_file(text: str, kwargs: dict) -> Orbit:
    """The lisaorbits orbit file of spec ``text`` (``FILE`` or ``FILE:dataset``); ConfigError
    when the dataset named disagrees with ``kwargs`` or there is no such file."""
    path, dataset = text, None
    for name in ORBIT_FILE_DATASETS:
        if text.endswith(":" + name):
            path, dataset = text[: -len(name) - 1], name
            break
    _check_kwargs("file", kwargs, ("dataset", "order"))
    if dataset is not None and kwargs.get("dataset", dataset) != dataset:
        raise ConfigError(f"orbit spec {text!r} names dataset {dataset!r} but dataset={kwargs['dataset']!r} was given")
    if dataset is not None:
        kwargs["dataset"] = dataset
    if not path or not os.path.isfile(path):
        looks_like_path = os.sep in path or path.lower().endswith((".h5", ".hdf5"))
        reason = f"no such orbit file {path!r}" if looks_like_path else f"unknown orbit spec {text!r}"
        raise ConfigError(
            f"{reason}: expected 'equal', 'unequal', 'keplerian' or the path of a lisaorbits orbit file "
            f"(optionally suffixed ':tps/ppr' or ':tcb/ltt')"
        )
    return OrbitFile(path, **kwargs)


def from_description(d: Mapping) -> Orbit:
    """Rebuild an orbit from :meth:`Orbit.describe` output (inverse of ``describe``)."""
    if not isinstance(d, Mapping) or "type" not in d:
        raise ConfigError(f"orbit description must be a dict with a 'type' field, got {d!r}")
    kind = d["type"]
    rest = {k: v for k, v in d.items() if k != "type"}
    if kind == "static":
        _check_kwargs("static description", rest, ("ltt", "name"))
        if "ltt" not in rest:
            raise ConfigError("static orbit description needs an 'ltt' field")
        return StaticOrbit(rest["ltt"], name=rest.get("name", "static"))
    if kind == "keplerian":
        _check_kwargs("keplerian description", rest, _KEPLERIAN_KEYS)
        return KeplerianOrbit(**rest)
    if kind == "file":
        _check_kwargs("file description", rest, ("path", "dataset", "order"))
        if "path" not in rest:
            raise ConfigError("file orbit description needs a 'path' field")
        return OrbitFile(rest["path"], dataset=rest.get("dataset", "tps/ppr"), order=rest.get("order", 5))
    raise ConfigError(f"orbit description 'type' must be 'static', 'keplerian' or 'file', got {kind!r}")
