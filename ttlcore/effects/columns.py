"""What effects build their regressor columns from, and what they return.

An effect's column is a sum of *parts* (:class:`Part`): a witness series built from the
telemetry (DWS readouts, time, delays, fitted coefficients) placed on a link, either
undelayed (``extra=()``, the Rx placement) or after the delay ``D_link`` (``extra=(link,)``,
the Tx placement).  :class:`EffectInput` holds the series they are built from: the DWS
readouts and fitted coefficients in the diagnosis, the true angular velocities and
coefficients of a chunk in the simulator.

Witness convention: ``w[m, a] = -DWS_a[m] / c`` (rad/s over m/s), so that a coefficient in
m/rad times ``w`` is fractional frequency (docs/physics.md, units).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..conventions import (
    COEFFICIENT_NAMES,
    MOSAS,
    C,
)
from ..errors import ConfigError


@dataclass
class Part:
    """One witness series placed on a link.

    Attributes
    ----------
    link : str
        Link ``ij`` (received at SC i) whose ``eta`` the series enters.
    series : ndarray, shape (n,)
        The series [fractional frequency per unit of the column's parameter].
    delayed : bool
        False: enters ``eta_ij`` as is (Rx placement).  True: enters as ``D_ij series``
        (Tx placement, the series belongs to the transmitting MOSA ``ji``).
    """

    link: str
    series: np.ndarray | None  # None in the columns of names only (EffectInput.names_only)
    #: False/0: undelayed; True/1: ``D_link series``; an integer n: n delays of the link
    #: (``D_link ... D_link series``, the witness library's "delayed nL")
    delayed: bool | int = False
    #: ``(mosa, angle)`` if the series is the plain witness ``-DWS/c`` of that channel: the
    #: diagnosis then includes its readout noise in the errors-in-variables correction
    channel: tuple | None = None
    #: with ``channel``: the series is ``modulation * witness`` for a slowly varying factor
    #: (a drift's ``(t - t_ref) / day``, a step's ``H(t - t_step)``, same samples), and the
    #: readout noise enters modulated alike
    modulation: np.ndarray | None = None

    @property
    def extra(self) -> tuple:
        return (self.link,) * int(self.delayed)


@dataclass
class Column:
    """One regressor column: ``name`` (unique, ``<effect>.<detail>``), its parts, its unit
    and the prior scale of its parameter (standard deviation of the zero-mean Gaussian prior
    of the exact linear-Gaussian Bayes factor, :func:`ttlcore.diagnose.diagnoser.log_bayes_factor`)."""

    name: str
    parts: list
    unit: str = ""
    prior_scale: float = 1.0
    #: optional frequency response ``f [Hz] -> complex (m,)`` of a filter applied to the
    #: column's witness before it enters the link (a frequency-dependent coupling); the
    #: diagnosis multiplies the column's spectrum, and its readout noise, by it (a linear
    #: time-invariant filter commutes with TDI up to the arms' rate of change, ~1e-8)
    response: Callable[[np.ndarray], np.ndarray] | None = None
    #: columns of one effect with the same ``base`` share their parts (only the response
    #: differs): their TDI is computed once
    base: str = ""


@dataclass
class EffectInput:
    """What effects build their columns from.

    In the diagnosis: the telemetry's DWS readouts (with readout noise) and the fitted
    linear coefficients.  In the simulator: the true angular velocities of a chunk with
    ``history`` leading samples and the true coefficients.

    Attributes
    ----------
    t : ndarray (n,)
        Sample times [s].
    fs : float
        Sampling rate [Hz].
    phi_dot, eta_dot : ndarray (6, n)
        Angular velocities [rad/s] of the six MOSAs (MOSA order).
    ltt : ndarray (6, n)
        Light travel times [s] (LINKS order).
    coefficients : ndarray (24,) or (24, n), optional
        Linear TTL coefficients [m/rad] (fitted, or true in the simulator).
    angle0 : ndarray (2, 6)
        Angles [rad] just before the first sample (phi, eta): the integration constant of
        :attr:`angles`.
    t_ref : float
        Reference time of time-modulated effects [s] (the middle of the data in the
        diagnosis, the effect's own ``t_ref`` in the simulator).
    """

    t: np.ndarray
    fs: float
    phi_dot: np.ndarray
    eta_dot: np.ndarray
    ltt: np.ndarray
    coefficients: np.ndarray | None = None
    angle0: np.ndarray = field(default_factory=lambda: np.zeros((2, 6)))
    t_ref: float = 0.0
    #: only the column names are wanted (effects may skip options they need for values)
    names_only: bool = False
    _angles: tuple | None = None

    @property
    def n(self) -> int:
        return self.t.size

    def velocity(self, angle: str) -> np.ndarray:
        return {"phi": self.phi_dot, "eta": self.eta_dot}[angle]

    def witness(self, mosa: str, angle: str) -> np.ndarray:
        """``-DWS_angle[mosa] / c`` (the TTL witness)."""
        return -self.velocity(angle)[MOSAS.index(mosa)] / C

    @property
    def angles(self) -> tuple[np.ndarray, np.ndarray]:
        """``(phi, eta)`` angles [rad], (6, n) each: running integral of the velocities
        (rectangle rule, as the simulator's truth angles) from :attr:`angle0`."""
        if self._angles is None:
            self._angles = tuple(
                self.angle0[i][:, None] + np.cumsum(v, axis=1) / self.fs
                for i, v in enumerate((self.phi_dot, self.eta_dot))
            )
        return self._angles

    def coefficient(self, name: str) -> np.ndarray | float:
        """Coefficient ``name`` [m/rad] (scalar or series); ConfigError if none are known."""
        if self.coefficients is None:
            raise ConfigError("this effect needs the linear TTL coefficients (fit linear-ttl first)")
        return np.asarray(self.coefficients)[COEFFICIENT_NAMES.index(name)]


def names_only_input() -> EffectInput:
    """A tiny input with ``names_only=True``: enough for an effect to name its columns."""
    t = np.arange(64.0)
    z = np.zeros((6, 64))
    return EffectInput(t=t, fs=1.0, phi_dot=z, eta_dot=z, ltt=z + 8.3, coefficients=np.zeros(24), names_only=True)
