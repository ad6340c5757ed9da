"""Subtraction of the fitted TTL model in the time domain (docs/physics.md, "Fit and subtraction").

TDI is linear, so subtracting the TTL model after TDI is the same as subtracting it from
``eta`` before::

    residual = TDI(data) - sum_k C_k TDI(regressor_k)          (= TDIData.data - TDIData.model(C))

for each channel of a :class:`~ttlcore.tdi.data.TDIData` (X2, Y2, Z2 or A, E, T).

With simulated data the truth file adds (all in TDI, fractional frequency):

- ``ttl_tdi = TDI(true TTL)``: the truth file's ``ttl`` series (the TTL term of each
  ``eta_ij``) through the same combinations, with the same delays;
- ``ttl_residual = TDI(true TTL) - model(C_fit)``: what the fitted model leaves of the TTL,
  that is the coefficient error times the jitter plus the DWS readout noise times the
  fitted coefficients (the model is built from the *noisy* DWS readouts);
- ``noise_without_ttl = TDI(eta) - TDI(true TTL) = TDI(eta - true TTL)``: the data as they
  would be without TTL coupling;
- ``residual_true = TDI(data) - model(C_true)``: the subtraction with the true
  coefficients.  For time-varying truth the *mean* of the true coefficients over the fit
  window is used (what a constant-coefficient fit estimates); for constant coefficients
  it is exact, and it leaves ``noise_without_ttl`` plus the DWS readout noise times
  ``C_true``.

:func:`analyse_subtraction` computes all of them into a :class:`SubtractionResult`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..tdi.combinations import AET, AET_MATRIX, DEFAULT_DELAY_ORDER, MICHELSON, XYZ
from ..tdi.data import TDIData, compute_tdi_arrays
from ..tdi.interpolation import DEFAULT_ORDER


def _coefficients(td: TDIData, coefficients) -> np.ndarray:
    """Coefficients as a vector in ``td.names`` order (accepts a vector or a name->value mapping)."""
    if isinstance(coefficients, dict):
        missing = [n for n in td.names if n not in coefficients]
        if missing:
            raise ValueError(f"coefficients: missing {', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''}")
        return np.array([float(coefficients[n]) for n in td.names])
    c = np.asarray(coefficients, dtype=float)
    if c.shape != (len(td.names),):
        raise ValueError(f"coefficients: expected {len(td.names)} values (one per regressor), got shape {c.shape}")
    return c


def subtract(td: TDIData, coefficients) -> np.ndarray:
    """Residual ``td.data - sum_k C_k td.regressors[:, k]``, shape (3, n), same channels as ``td``.

    ``coefficients`` [m/rad]: a vector in ``td.names`` order or a mapping name -> value.
    """
    return td.data - td.model(_coefficients(td, coefficients))


def to_xyz(series: np.ndarray, channels) -> np.ndarray:
    """X2, Y2, Z2 of a (3, ...) array in ``channels`` (the A, E, T matrix is orthonormal,
    so its inverse is its transpose)."""
    channels = tuple(channels)
    if channels == XYZ:
        return np.asarray(series)
    if channels == AET:
        return np.tensordot(AET_MATRIX.T, np.asarray(series), axes=(1, 0))
    raise ValueError(f"unknown channel set {channels!r}")


def to_aet(series: np.ndarray, channels) -> np.ndarray:
    """A, E, T of a (3, ...) array in ``channels``."""
    channels = tuple(channels)
    if channels == AET:
        return np.asarray(series)
    if channels == XYZ:
        return np.tensordot(AET_MATRIX, np.asarray(series), axes=(1, 0))
    raise ValueError(f"unknown channel set {channels!r}")


def residual_xyz(td: TDIData, coefficients) -> np.ndarray:
    """Residual in X2, Y2, Z2, shape (3, n), whatever the channels of ``td``."""
    return to_xyz(subtract(td, coefficients), td.channels)


def residual_aet(td: TDIData, coefficients) -> np.ndarray:
    """Residual in A, E, T, shape (3, n), whatever the channels of ``td``."""
    return to_aet(subtract(td, coefficients), td.channels)


def ttl_in_tdi(
    ttl_truth: np.ndarray,
    ltt: np.ndarray,
    fs: float,
    t0: float,
    *,
    history: int = 0,
    order: int = DEFAULT_ORDER,
    delay_order: int = DEFAULT_DELAY_ORDER,
    combinations=MICHELSON,
) -> np.ndarray:
    """TDI (X2, Y2, Z2) of the true TTL series of the six links, shape (3, n - history).

    ``ttl_truth`` (6, n) is the truth file's ``ttl`` (fractional frequency, the TTL term of
    each ``eta_ij``); ``ltt`` (6, n) the delays of the telemetry.  Uses the same TDI code
    as the data (:func:`ttlcore.tdi.data.compute_tdi_arrays` with no regressors), so with
    the same delays and orders the result is exactly the TTL part of ``TDI(eta)``.  The
    first ~70 s are NaN like the data's.
    """
    ttl_truth = np.asarray(ttl_truth, dtype=float)
    zeros = np.zeros_like(ttl_truth)
    td = compute_tdi_arrays(
        ttl_truth,
        zeros,
        zeros,
        ltt,
        fs,
        t0,
        history=history,
        names=(),
        order=order,
        delay_order=delay_order,
        combinations=combinations,
    )
    return td.data


def ttl_residual(ttl_tdi: np.ndarray, td: TDIData, coefficients) -> np.ndarray:
    """``TDI(true TTL) - model(C)``, in the channels of ``td`` (``ttl_tdi`` must be in the same)."""
    return np.asarray(ttl_tdi) - td.model(_coefficients(td, coefficients))


@dataclass
class SubtractionResult:
    """Time series of a subtraction, all (3, n) in ``channels``, fractional frequency.

    Attributes
    ----------
    t0, fs : float
        Time of the first sample [s] and sampling rate [Hz].
    channels : tuple of str
        ``("X2", "Y2", "Z2")`` or ``("A", "E", "T")``.
    data : ndarray
        TDI of the data (with TTL).
    residual : ndarray
        Data minus the model with the fitted coefficients.
    coefficients : ndarray (P,)
        The fitted coefficients used [m/rad].
    true_coefficients : ndarray (P,) or None
        The (mean) true coefficients [m/rad], if known.
    residual_true : ndarray or None
        Data minus the model with ``true_coefficients``.
    ttl_tdi : ndarray or None
        TDI of the true TTL (needs the truth TTL series: our truth files only).
    ttl_residual : ndarray or None
        ``ttl_tdi - model(coefficients)``.
    noise_without_ttl : ndarray or None
        ``data - ttl_tdi``.
    notes : list of str
        What could not be computed and why.
    """

    t0: float
    fs: float
    channels: tuple
    data: np.ndarray
    residual: np.ndarray
    coefficients: np.ndarray
    true_coefficients: np.ndarray | None = None
    residual_true: np.ndarray | None = None
    ttl_tdi: np.ndarray | None = None
    ttl_residual: np.ndarray | None = None
    noise_without_ttl: np.ndarray | None = None
    notes: list = field(default_factory=list)

    SERIES = ("data", "residual", "residual_true", "ttl_tdi", "ttl_residual", "noise_without_ttl")

    @property
    def size(self) -> int:
        return self.data.shape[-1]

    @property
    def t(self) -> np.ndarray:
        return self.t0 + np.arange(self.size) / self.fs

    def _convert(self, fn, channels) -> SubtractionResult:
        conv: dict = {
            k: (None if getattr(self, k) is None else fn(getattr(self, k), self.channels)) for k in self.SERIES
        }
        return replace(self, channels=channels, **conv)

    def xyz(self) -> SubtractionResult:
        """The same series in X2, Y2, Z2."""
        return self if self.channels == XYZ else self._convert(to_xyz, XYZ)

    def aet(self) -> SubtractionResult:
        """The same series in A, E, T."""
        return self if self.channels == AET else self._convert(to_aet, AET)

    def channel(self, name: str) -> dict:
        """``{series name: 1-D array}`` of one channel (``"X2"``, ``"X"``, ``"A"``, ...), present series only."""
        name = {"X": "X2", "Y": "Y2", "Z": "Z2"}.get(name, name)
        res = self.xyz() if name in XYZ else self.aet()
        k = res.channels.index(name)
        return {s: getattr(res, s)[k] for s in self.SERIES if getattr(res, s) is not None}


def analyse_subtraction(
    td: TDIData,
    coefficients,
    *,
    true_coefficients=None,
    ttl_truth=None,
    ltt=None,
    order: int = DEFAULT_ORDER,
    delay_order: int = DEFAULT_DELAY_ORDER,
) -> SubtractionResult:
    """All the subtraction series of :class:`SubtractionResult` for ``td`` (X2, Y2, Z2 or A, E, T).

    Parameters
    ----------
    td : TDIData
        TDI of the data and the regressors (undecimated, as :func:`~ttlcore.tdi.data.compute_tdi` gives).
    coefficients : array or mapping
        Fitted coefficients [m/rad].
    true_coefficients : array or mapping, optional
        True (mean) coefficients [m/rad]: adds ``residual_true``.
    ttl_truth : ndarray (6, n), optional
        The truth file's ``ttl`` series on the samples of ``td`` (same t0, fs and length):
        adds ``ttl_tdi``, ``ttl_residual`` and ``noise_without_ttl``.
    ltt : ndarray (6, n), optional
        The delays the data's TDI used (the telemetry's ``ltt``); needed with ``ttl_truth``.
    """
    C = _coefficients(td, coefficients)
    out = SubtractionResult(
        t0=td.t0, fs=td.fs, channels=tuple(td.channels), data=td.data, residual=td.data - td.model(C), coefficients=C
    )
    if true_coefficients is not None:
        Ct = _coefficients(td, true_coefficients)
        out.true_coefficients = Ct
        out.residual_true = td.data - td.model(Ct)
    else:
        out.notes.append("no true coefficients: residual with true coefficients not computed")
    if ttl_truth is not None:
        if ltt is None:
            raise ValueError("ttl_truth needs ltt (the delays of the data's TDI)")
        ttl_truth = np.asarray(ttl_truth)
        if ttl_truth.shape != (6, td.size):
            raise ValueError(f"ttl_truth: expected shape (6, {td.size}) to match the TDI data, got {ttl_truth.shape}")
        ttl_xyz = ttl_in_tdi(ttl_truth, ltt, td.fs, td.t0, order=order, delay_order=delay_order)
        ttl_tdi = ttl_xyz if tuple(td.channels) == XYZ else to_aet(ttl_xyz, XYZ)
        out.ttl_tdi = ttl_tdi
        out.ttl_residual = ttl_tdi - td.model(C)
        out.noise_without_ttl = td.data - ttl_tdi
    else:
        out.notes.append("no true TTL series: TTL residual and noise without TTL not computed")
    return out
