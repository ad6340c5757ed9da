"""Analytic one-sided amplitude spectral densities (ASDs) of the simulated noises.

Every model is a plain module-level function of the Fourier frequency ``f`` [Hz]
(``f > 0``; array in, array out) returning a one-sided ASD.  The shapes and levels are
those of the appendix "Jitters and noises used in our analysis" of the paper
(``app:noise_and_jitter`` in the paper) and of ``docs/physics.md``; where
the two differ ``docs/physics.md`` wins (see :func:`test_mass`).

Units (``docs/physics.md``, "Units"):

- the interferometric noises (:func:`laser`, :func:`oms`, :func:`backlink`,
  :func:`telescope`, :func:`test_mass`) are ASDs of fractional frequency ``y``
  [1/sqrt(Hz)], the unit of the ``eta_ij`` variables;
- :func:`oms_displacement` is a displacement ASD [m/sqrt(Hz)];
- the jitters and the DWS readout noise (:func:`sc_jitter`, :func:`mosa_jitter_phi`,
  :func:`mosa_jitter_eta`, :func:`dws_readout`) are angle ASDs [rad/sqrt(Hz)];
  :func:`as_velocity` turns one into the ASD of the angular velocity [rad/s/sqrt(Hz)],
  which is what the simulator generates (as lisainstrument does; DWS readouts are
  angular velocities).

:data:`MODELS` maps the names of the simulator's noise series to their ASD functions.
All entries are picklable (module-level functions or :class:`functools.partial`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np

from ..conventions import NU0, acceleration_to_ffd_asd, displacement_to_ffd_asd

__all__ = [
    "OMS_SCI",
    "OMS_TMI",
    "OMS_REF",
    "OMS_LINK",
    "BACKLINK",
    "BACKLINK_LINK",
    "TELESCOPE_IN",
    "TELESCOPE_OUT",
    "TELESCOPE_CORR",
    "TELESCOPE_LINK",
    "laser",
    "oms_displacement",
    "oms",
    "backlink",
    "telescope",
    "test_mass",
    "secondary_single_link",
    "sc_jitter",
    "mosa_jitter_phi",
    "mosa_jitter_eta",
    "dws_readout",
    "as_velocity",
    "MODELS",
]

# ---------------------------------------------------------------------------
# Levels (paper appendix)
# ---------------------------------------------------------------------------

#: Readout noise of the inter-satellite (science) interferometer [m/sqrt(Hz)].
OMS_SCI = 6.35e-12
#: Readout noise of the test-mass interferometer [m/sqrt(Hz)].
OMS_TMI = 1.42e-12
#: Readout noise of the reference interferometer [m/sqrt(Hz)].
OMS_REF = 3.32e-12
#: Link-averaged effective OMS level of one ``eta_ij`` variable [m/sqrt(Hz)],
#: ``sqrt(sci^2 + ref^2 + tmi^2 / 2)`` = 7.23 pm/sqrt(Hz) (see :func:`oms`).
OMS_LINK = float(np.sqrt(OMS_SCI**2 + OMS_REF**2 + 0.5 * OMS_TMI**2))
#: Backlink (fibre) noise of one MOSA [m/sqrt(Hz)].
BACKLINK = 3e-12
#: Effective backlink level of one ``eta_ij`` variable, ``BACKLINK / sqrt(2)`` [m/sqrt(Hz)].
BACKLINK_LINK = float(BACKLINK / np.sqrt(2.0))
#: Telescope path-length noise of the incoming light [m/sqrt(Hz)].
TELESCOPE_IN = 1e-15
#: Telescope path-length noise of the outgoing light [m/sqrt(Hz)].
TELESCOPE_OUT = 2e-15
#: Correlated part of the telescope path-length noise [m/sqrt(Hz)].
TELESCOPE_CORR = 1.5e-15
#: Quadrature sum of the three telescope terms [m/sqrt(Hz)].
TELESCOPE_LINK = float(np.sqrt(TELESCOPE_IN**2 + TELESCOPE_OUT**2 + TELESCOPE_CORR**2))

#: Corner frequency of the OMS-type (readout, backlink) noises [Hz].
OMS_FKNEE = 2e-3
#: Break frequency [Hz] above which the test-mass acceleration noise rises as ``(f / fbreak)^2``
#: in ASD (:func:`test_mass`).
TM_FBREAK = 8e-3
#: Corner frequency of the jitters [Hz].
JITTER_FKNEE = 0.8e-3


def _freq(f) -> np.ndarray:
    return np.asarray(f, dtype=float)


# ---------------------------------------------------------------------------
# Interferometric noises (fractional frequency)
# ---------------------------------------------------------------------------


def laser(f, asd_hz: float = 30.0, fknee: float = 2e-3):
    """Laser frequency noise of one free-running laser, in fractional frequency.

    ``S^{1/2}(f) = asd_hz * sqrt(1 + (fknee / f)^4) / nu0`` with 30 Hz/sqrt(Hz) and a
    2 mHz corner (paper appendix, "Laser noise"; ``docs/physics.md``, measurement model ``p_i``).

    Parameters
    ----------
    f : array_like
        Frequency [Hz], ``f > 0``.
    asd_hz : float
        High-frequency level [Hz/sqrt(Hz)].
    fknee : float
        Corner frequency [Hz].

    Returns
    -------
    ndarray
        ASD [1/sqrt(Hz)].
    """
    f = _freq(f)
    return asd_hz * np.sqrt(1.0 + (fknee / f) ** 4) / NU0


def oms_displacement(f, asd: float, fknee: float = OMS_FKNEE):
    """Readout (OMS) noise of one interferometer as a displacement ASD.

    ``S^{1/2}(f) = asd * sqrt(1 + (fknee / f)^4)`` (paper appendix, "Readout noises"),
    with ``asd`` one of :data:`OMS_SCI` (6.35 pm/sqrt(Hz)), :data:`OMS_TMI` (1.42) or
    :data:`OMS_REF` (3.32), or the fibre level :data:`BACKLINK` (3 pm/sqrt(Hz)).

    Parameters
    ----------
    f : array_like
        Frequency [Hz], ``f > 0``.
    asd : float
        High-frequency level [m/sqrt(Hz)].
    fknee : float
        Corner frequency [Hz], 2 mHz by default.

    Returns
    -------
    ndarray
        ASD [m/sqrt(Hz)].
    """
    f = _freq(f)
    return asd * np.sqrt(1.0 + (fknee / f) ** 4)


def oms(f):
    """Effective OMS readout noise of one ``eta_ij`` variable, in fractional frequency.

    Derivation.  In the standard intermediary-variable reduction (pytdi ``intervar``)

    - ``xi_12  = sci_12 + ref_12/2 + D ref_21/2 - tmi_12/2 - D tmi_21/2``
    - ``eta_12 = xi_12 + D (ref_21 - ref_23)/2``  (likewise 23, 31)
    - ``eta_13 = xi_13 + (ref_12 - ref_13)/2``    (likewise 32, 21)

    so an independent readout noise in each interferometer (levels ``sci``, ``ref``,
    ``tmi``: the paper appendix's 6.35, 3.32 and 1.42 pm/sqrt(Hz)) enters ``eta_ij``
    with variance ``sci^2 + 1.5 ref^2 + 0.5 tmi^2`` for ``ij`` in 12, 23, 31 (``ref_21``
    appears twice, with total weight 1, ``ref_12`` and ``ref_23`` with 1/2) and
    ``sci^2 + 0.5 ref^2 + 0.5 tmi^2`` for 13, 32, 21 (``ref_13`` cancels).  The
    eta-level simulator draws one independent noise per link with the link-averaged
    level ``sqrt(sci^2 + ref^2 + tmi^2/2)`` = 7.23 pm/sqrt(Hz) (:data:`OMS_LINK`); it
    neglects the correlations between links that the shared reference-interferometer
    noises would create.  The shape is ``sqrt(1 + (2 mHz / f)^4)``, and the displacement
    ASD is converted to fractional frequency by ``2 pi f / c``
    (:func:`ttlcore.conventions.displacement_to_ffd_asd`).

    Parameters
    ----------
    f : array_like
        Frequency [Hz], ``f > 0``.

    Returns
    -------
    ndarray
        ASD [1/sqrt(Hz)].
    """
    f = _freq(f)
    return displacement_to_ffd_asd(oms_displacement(f, OMS_LINK), f)


def backlink(f):
    """Effective backlink (fibre) noise of one ``eta_ij`` variable, in fractional frequency.

    The backlink noise of a MOSA enters its reference and test-mass interferometers
    identically, so it cancels in every ``ref - tmi`` difference of the
    intermediary variables (see :func:`oms`); it survives only in the two
    reference-interferometer terms of weight 1/2 (``D (ref_21 - ref_23)/2`` in
    ``eta_12``, ``(ref_12 - ref_13)/2`` in ``eta_13``).  With independent noises per
    MOSA the per-link level is ``sqrt(1/2) * 3 pm/sqrt(Hz)`` (:data:`BACKLINK_LINK`,
    paper appendix "Fiber (or back-link) noise"), shape ``sqrt(1 + (2 mHz / f)^4)``,
    converted to fractional frequency by ``2 pi f / c``.

    Parameters
    ----------
    f : array_like
        Frequency [Hz], ``f > 0``.

    Returns
    -------
    ndarray
        ASD [1/sqrt(Hz)].
    """
    f = _freq(f)
    return displacement_to_ffd_asd(oms_displacement(f, BACKLINK_LINK), f)


def telescope(f):
    """Telescope path-length noise of one link, in fractional frequency.

    ``S^{1/2}(f) = (2 pi f / c) * sqrt(A_in^2 + A_out^2 + A_corr^2)`` with
    ``A_in = 1``, ``A_out = 2`` and ``A_corr = 1.5`` fm/sqrt(Hz) (paper appendix,
    "Telescope path length noise"; the paper's expression already includes the
    ``2 pi f / c`` conversion, so it is a fractional-frequency ASD).  The three terms
    are added in quadrature into one noise per link (:data:`TELESCOPE_LINK`).

    Parameters
    ----------
    f : array_like
        Frequency [Hz], ``f > 0``.

    Returns
    -------
    ndarray
        ASD [1/sqrt(Hz)].
    """
    f = _freq(f)
    return displacement_to_ffd_asd(TELESCOPE_LINK * np.ones_like(f), f)


def test_mass(f, asd: float = 2.4e-15, fknee: float = 0.4e-3, fbreak: float = TM_FBREAK):
    """Acceleration noise of ONE test mass, as a fractional-frequency (velocity / c) ASD.

    ``S^{1/2}(f) = asd / (2 pi f c) * sqrt(1 + (fknee / f)^2) * sqrt(1 + (f / fbreak)^4)``
    with 2.4 fm/s^2/sqrt(Hz), 0.4 mHz and 8 mHz.

    The paper's appendix prints the last factor as ``sqrt(1 + (8 mHz / f)^4)``; that is a
    typo: ``docs/physics.md`` (requirement shape ``(1 + (f / 8 mHz)^4)``) and lisainstrument
    (``NoiseDefTestMass``, "original" shape) use ``(f / fbreak)^4``, and so does this
    function.

    Parameters
    ----------
    f : array_like
        Frequency [Hz], ``f > 0``.
    asd : float
        Acceleration level [m/s^2/sqrt(Hz)].
    fknee : float
        Low-frequency corner [Hz].
    fbreak : float
        High-frequency break [Hz].

    Returns
    -------
    ndarray
        ASD [1/sqrt(Hz)].
    """
    f = _freq(f)
    shape = np.sqrt(1.0 + (fknee / f) ** 2) * np.sqrt(1.0 + (f / fbreak) ** 4)
    return acceleration_to_ffd_asd(asd * shape, f)


def secondary_single_link(f):
    """Single-link secondary-noise PSDs ``(S_oms, S_acc)`` in fractional frequency.

    ``S_oms = oms^2 + backlink^2 + telescope^2`` (all readout-like noises of one
    ``eta_ij``) and ``S_acc = test_mass^2`` (one test mass), the two inputs of the
    analytic TDI PSD of ``docs/physics.md``,
    ``S_X2 = 64 sin^2(x) sin^2(2x) [S_oms + (3 + cos 2x) S_acc]``.

    Parameters
    ----------
    f : array_like
        Frequency [Hz], ``f > 0``.

    Returns
    -------
    tuple of ndarray
        ``(S_oms, S_acc)``, one-sided PSDs [1/Hz] (not ASDs).
    """
    f = _freq(f)
    s_oms = oms(f) ** 2 + backlink(f) ** 2 + telescope(f) ** 2
    s_acc = test_mass(f) ** 2
    return s_oms, s_acc


# ---------------------------------------------------------------------------
# Jitters and DWS readout (angles)
# ---------------------------------------------------------------------------


def _jitter(f, asd: float, fknee: float):
    f = _freq(f)
    return asd * np.sqrt(1.0 + (fknee / f) ** 4)


def sc_jitter(f, asd: float = 5e-9, fknee: float = JITTER_FKNEE):
    """Spacecraft angular jitter (each of phi, eta, theta), angle ASD.

    ``S^{1/2}(f) = 5 nrad/sqrt(Hz) * sqrt(1 + (0.8 mHz / f)^4)`` (paper appendix,
    eq. ``SC_jitter``; ``docs/physics.md``).

    Parameters
    ----------
    f : array_like
        Frequency [Hz], ``f > 0``.
    asd : float
        High-frequency level [rad/sqrt(Hz)].
    fknee : float
        Corner frequency [Hz].

    Returns
    -------
    ndarray
        ASD [rad/sqrt(Hz)].
    """
    return _jitter(f, asd, fknee)


def mosa_jitter_phi(f, asd: float = 2e-9, fknee: float = JITTER_FKNEE):
    """MOSA jitter in phi (yaw), angle ASD.

    ``S^{1/2}(f) = 2 nrad/sqrt(Hz) * sqrt(1 + (0.8 mHz / f)^4)`` (paper appendix,
    eq. ``MOSA_phi_jitter``).

    Parameters
    ----------
    f : array_like
        Frequency [Hz], ``f > 0``.
    asd : float
        High-frequency level [rad/sqrt(Hz)].
    fknee : float
        Corner frequency [Hz].

    Returns
    -------
    ndarray
        ASD [rad/sqrt(Hz)].
    """
    return _jitter(f, asd, fknee)


def mosa_jitter_eta(f, asd: float = 1e-9, fknee: float = JITTER_FKNEE):
    """MOSA jitter in eta (pitch), angle ASD.

    ``S^{1/2}(f) = 1 nrad/sqrt(Hz) * sqrt(1 + (0.8 mHz / f)^4)`` (paper appendix,
    eq. ``MOSA_eta_jitter``).

    Parameters
    ----------
    f : array_like
        Frequency [Hz], ``f > 0``.
    asd : float
        High-frequency level [rad/sqrt(Hz)].
    fknee : float
        Corner frequency [Hz].

    Returns
    -------
    ndarray
        ASD [rad/sqrt(Hz)].
    """
    return _jitter(f, asd, fknee)


def dws_readout(f, asd: float = 70e-9 / 335):
    """DWS readout noise, white in angle: ``70/335 nrad/sqrt(Hz)`` (paper appendix).

    Parameters
    ----------
    f : array_like
        Frequency [Hz].
    asd : float
        Level [rad/sqrt(Hz)].

    Returns
    -------
    ndarray
        ASD [rad/sqrt(Hz)], same shape as ``f``.
    """
    f = _freq(f)
    return asd * np.ones_like(f)


def _velocity_asd(asd_angle_func: Callable, f):
    f = _freq(f)
    return 2.0 * np.pi * f * np.asarray(asd_angle_func(f), dtype=float)


def as_velocity(asd_angle_func: Callable) -> Callable:
    """Angular-velocity ASD function ``f -> 2 pi f * asd_angle_func(f)``.

    The simulator generates angular velocities (as lisainstrument does), and the DWS
    readouts are in rad/s (``docs/physics.md``, units), so the angle ASDs of the appendix are
    multiplied by ``2 pi f``.

    Parameters
    ----------
    asd_angle_func : callable
        Angle ASD [rad/sqrt(Hz)] as a function of frequency [Hz].

    Returns
    -------
    callable
        Picklable function of ``f`` returning the ASD [rad/s/sqrt(Hz)].
    """
    return functools.partial(_velocity_asd, asd_angle_func)


# ---------------------------------------------------------------------------
# Registry
# ---------------------------------------------------------------------------

#: ASD models of the simulator's noise series, by name (all picklable).
MODELS: dict[str, Callable] = {
    "laser": laser,
    "oms": oms,
    "backlink": backlink,
    "telescope": telescope,
    "test_mass": test_mass,
    "sc_jitter_velocity": as_velocity(sc_jitter),
    "mosa_jitter_phi_velocity": as_velocity(mosa_jitter_phi),
    "mosa_jitter_eta_velocity": as_velocity(mosa_jitter_eta),
    "dws_velocity": as_velocity(dws_readout),
}

# ``test_mass`` is a model, not a test: keep pytest from collecting it when a test module
# imports it by name.
test_mass.__test__ = False  # type: ignore[attr-defined]  # an attribute pytest reads, set on a function
