"""Analytic secondary-noise PSDs in TDI and the LISA requirement curve (docs/physics.md).

Equal arms, second-generation Michelson (docs/physics.md, "Analytic secondary-noise PSD"):

    S_X2(f) = 64 sin^2(x) sin^2(2x) [S_oms(f) + (3 + cos 2x) S_acc(f)],   x = 2 pi f L / c,

with ``S_oms`` the single-link OMS PSD and ``S_acc`` the PSD of one test mass, both in
fractional frequency.  For arbitrary static (unequal) arms, and for the cross-spectra
between X, Y, Z (or A, E, T), :func:`tdi_noise_csd` pushes every independent single-link
source through the combinations' exact frequency responses
(:func:`ttlcore.tdi.combinations.link_responses`): an OMS-type noise ``o_ij`` enters link ``ij`` only; a
test-mass noise ``delta_ij`` enters ``eta_ij`` directly and ``eta_ji`` delayed by ``D_ji``.
For equal arms this reproduces the closed form above (checked in the tests).

The "LISA requirement" curve uses 15 pm/sqrt(Hz) OMS with shape ``1 + (2 mHz/f)^4`` and
3 fm/s^2/sqrt(Hz) test-mass acceleration with shape
``(1 + (0.4 mHz/f)^2)(1 + (f/8 mHz)^4)`` (SciRD).
"""

from __future__ import annotations

import numpy as np

from ..conventions import (
    ARM_LENGTH,
    LINKS,
    C,
    acceleration_to_ffd_asd,
    displacement_to_ffd_asd,
    ffd_to_displacement_asd,
)
from ..sim import noise_models
from ..tdi.combinations import AET_MATRIX, MICHELSON, link_responses

#: Requirement levels (SciRD): OMS [m/sqrt(Hz)], test-mass acceleration [m/s^2/sqrt(Hz)].
REQUIREMENT_OMS = 15e-12
REQUIREMENT_ACC = 3e-15


def requirement_single_link(f) -> tuple[np.ndarray, np.ndarray]:
    """Requirement single-link PSDs ``(S_oms, S_acc)`` in fractional frequency [1/Hz]."""
    f = np.asarray(f, dtype=float)
    s_oms = displacement_to_ffd_asd(REQUIREMENT_OMS, f) ** 2 * (1 + (2e-3 / f) ** 4)
    s_acc = acceleration_to_ffd_asd(REQUIREMENT_ACC, f) ** 2 * (1 + (0.4e-3 / f) ** 2) * (1 + (f / 8e-3) ** 4)
    return s_oms, s_acc


def simulated_single_link(f) -> tuple[np.ndarray, np.ndarray]:
    """Single-link PSDs ``(S_oms, S_acc)`` of the simulator's secondary noises (paper appendix)."""
    return noise_models.secondary_single_link(f)


def x2_psd_equal_arms(f, s_oms, s_acc, arm_length: float = ARM_LENGTH) -> np.ndarray:
    """``S_X2 = 64 sin^2 x sin^2 2x [S_oms + (3 + cos 2x) S_acc]``, ``x = 2 pi f L / c``."""
    x = 2 * np.pi * np.asarray(f, dtype=float) * arm_length / C
    return 64 * np.sin(x) ** 2 * np.sin(2 * x) ** 2 * (s_oms + (3 + np.cos(2 * x)) * s_acc)


def requirement_x2(f, arm_length: float = ARM_LENGTH) -> np.ndarray:
    """Requirement PSD of X2 in fractional frequency [1/Hz] (equal arms)."""
    return x2_psd_equal_arms(f, *requirement_single_link(f), arm_length=arm_length)


def requirement_x2_displacement_asd(f, arm_length: float = ARM_LENGTH) -> np.ndarray:
    """Requirement ASD of X2 in displacement [m/sqrt(Hz)], for plots."""
    return ffd_to_displacement_asd(np.sqrt(requirement_x2(f, arm_length)), f)


def tdi_noise_csd(f, ltt, s_oms=None, s_acc=None, combinations=MICHELSON, aet: bool = True) -> np.ndarray:
    """Cross-spectral matrix of the secondary noises in TDI, for static delays.

    Parameters
    ----------
    f : ndarray, shape (m,)
        Frequencies [Hz].
    ltt : dict or array_like
        Light travel times [s] (``{link: tau}``, six values, or (6, n) series -> mean).
    s_oms, s_acc : ndarray, shape (m,), optional
        Single-link OMS PSD (independent per link) and single test-mass PSD, fractional
        frequency; default: the simulator's (paper appendix) levels.
    combinations : sequence of Combination
        Default X2, Y2, Z2.
    aet : bool
        Return the CSD of A, E, T (default) instead of X, Y, Z.

    Returns
    -------
    ndarray, shape (m, k, k), complex
        ``S[f, a, b] = E[x_a(f) x_b(f)^*]`` as a one-sided PSD [1/Hz].
    """
    f = np.asarray(f, dtype=float)
    if s_oms is None or s_acc is None:
        s_oms, s_acc = simulated_single_link(f)
    h = np.stack([link_responses(c, f, ltt) for c in combinations])  # (k, 6 links, m)
    if not isinstance(ltt, dict):
        arr = np.asarray(ltt, dtype=float)
        arr = arr.mean(axis=-1) if arr.ndim == 2 else arr
        ltt = dict(zip(LINKS, arr))
    csd = np.einsum("alm,blm->mab", h, h.conj()) * np.asarray(s_oms)[:, None, None]
    for k, link in enumerate(LINKS):  # test mass of MOSA ij: eta_ij + D_ji onto eta_ji
        rev = LINKS.index(link[::-1])
        g = h[:, k, :] + h[:, rev, :] * np.exp(-2j * np.pi * f * ltt[link[::-1]])
        csd += np.einsum("am,bm->mab", g, g.conj()) * np.asarray(s_acc)[:, None, None]
    if aet:
        csd = np.einsum("ia,mab,jb->mij", AET_MATRIX, csd, AET_MATRIX)
    return csd
