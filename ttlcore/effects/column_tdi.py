"""TDI of effect columns: the code path of the 24 TTL regressors.

Each column is the sum of its parts placed on their links, through the block engine
:func:`ttlcore.tdi.engine.tdi_columns` (:func:`columns_tdi`, :func:`tdi_in_blocks`); the
diagnosis builds its columns from the telemetry's DWS readouts
(:func:`effect_input_from_telemetry`); :class:`TelemetryRegressors` builds the 24
regressors' TDI again from a telemetry on demand.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..conventions import COEFFICIENT_NAMES, LINKS
from ..tdi.combinations import MICHELSON, aet
from ..tdi.engine import Part as EnginePart
from ..tdi.engine import tdi_columns
from .columns import Column, EffectInput
from .linear_ttl import LinearTTL

if TYPE_CHECKING:
    from ..io.telemetry import Telemetry


def effect_input_from_telemetry(tm, coefficients=None) -> EffectInput:
    """:class:`EffectInput` from a :class:`~ttlcore.io.telemetry.Telemetry` (DWS readouts).

    A gap in the readouts (NaN) is zero here, as the data's gap is in the spectra: a filtered
    column (a resonance, a pole) would otherwise carry the NaN over its whole length, and every
    candidate built on a witness of a gapped day was skipped ("a regressor column is not
    finite inside the analysed span").  Data without a gap are passed as they are."""
    t = tm.t0 + np.arange(tm.size) / tm.fs
    phi, eta = np.asarray(tm.dws_phi), np.asarray(tm.dws_eta)
    if not (np.isfinite(phi).all() and np.isfinite(eta).all()):
        phi, eta = np.nan_to_num(phi, nan=0.0), np.nan_to_num(eta, nan=0.0)
    return EffectInput(
        t=t,
        fs=tm.fs,
        phi_dot=phi,
        eta_dot=eta,
        ltt=np.asarray(tm.ltt),
        coefficients=coefficients,
        t_ref=float(t[0] + t[-1]) / 2,
    )


def tdi_in_blocks(
    ltt: np.ndarray,
    fs: float,
    columns=(),
    eta: np.ndarray | None = None,
    *,
    order: int,
    delay_order: int,
    block: int = 43200,
) -> tuple:
    """TDI (X2, Y2, Z2) of regressor columns (:func:`columns_tdi`) and optionally of ``eta``,
    by the block engine :func:`ttlcore.tdi.engine.tdi_columns` (each block with the history
    its delays reach back to; memory does not grow with the data).  The first ~70 s are NaN.

    Parameters
    ----------
    ltt : ndarray, shape (6, n)
        Light travel times [s].
    fs : float
        Sampling rate [Hz].
    columns : list of Column
        Parts sampled like ``ltt``.
    eta : ndarray, shape (6, n), optional
        Link readouts.
    order, delay_order : int
        Lagrange orders of the data and of the delay interpolation.
    block : int
        Kept for callers; the engine chooses its own blocks (~2.2 h at 4 Hz), which bound
        the memory, so the result equals the one-call :func:`columns_tdi` exactly.

    Returns
    -------
    data : ndarray (3, n) or None
        TDI of ``eta``.
    regressors : ndarray (3, len(columns), n)
    """
    parts = _engine_parts(columns, first=1)
    if eta is not None:
        parts += [EnginePart(0, link, (), np.asarray(eta)[k]) for k, link in enumerate(LINKS)]
    out = tdi_columns(parts, 1 + len(columns), ltt, fs, combinations=MICHELSON, order=order, delay_order=delay_order)
    return (None if eta is None else out[:, 0]), out[:, 1:]


def _engine_parts(columns, first: int = 0) -> list:
    """The parts of ``columns`` as :class:`ttlcore.tdi.engine.Part` (column ``first + j``)."""
    return [EnginePart(first + j, p.link, p.extra, p.series) for j, col in enumerate(columns) for p in col.parts]


def columns_tdi(columns: list[Column], built) -> np.ndarray:
    """TDI (the combinations of ``built``, :func:`ttlcore.tdi.combinations.build`) of
    regressor columns: each column is the sum of its parts placed on their links, through
    the block engine :func:`ttlcore.tdi.engine.tdi_columns` - the code path of the 24 TTL
    regressors.

    Returns
    -------
    ndarray, shape (len(built), len(columns), n)
    """
    b = built[0]
    return tdi_columns(
        _engine_parts(columns),
        len(columns),
        b.ltt,
        b.fs,
        history=b.history,
        combinations=[x.combination for x in built],
        order=b.order,
        delay_order=b.delay_order,
    )


@dataclass(frozen=True)
class TelemetryRegressors:
    """The input-rate A, E, T of the 24 TTL regressors of a telemetry, built on demand
    (:meth:`ttlcore.diagnose.whitened.MeasuredTDI.input_regressors`): the TDI of their columns
    by the block engine with the diagnosis' Lagrange orders - the numbers of
    :func:`tdi_in_blocks`, as :func:`ttlcore.diagnose.whitened.whiten_telemetry` builds them,
    to the bit."""

    tm: Telemetry
    order: int
    delay_order: int

    def __call__(self, names: tuple[str, ...], weights=None) -> np.ndarray:
        """A, E, T (3, k, n) of the regressors ``names``; with ``weights`` (k,) the one
        column ``sum_k w_k R_k`` (3, 1, n), built as the TDI of the weighted witnesses (TDI
        is linear: one column's work instead of k, equal to rounding)."""
        columns = dict(zip(COEFFICIENT_NAMES, LinearTTL().columns(effect_input_from_telemetry(self.tm))))
        missing = [n for n in names if n not in columns]
        if missing:
            raise KeyError(f"not a TTL regressor of the telemetry: {', '.join(missing)}")
        if weights is None:
            parts = _engine_parts([columns[n] for n in names])
        else:
            parts = _weighted_parts([columns[n] for n in names], weights)
        # the columns alone (no data column), turned into A, E, T in place one column at a
        # time: the TDI of 8 regressors of a day (66 MB) took 271 MB at its peak, a copy for
        # the data column's slice and one for A, E, T beside the X, Y, Z
        out = tdi_columns(
            parts,
            len(names) if weights is None else 1,
            self.tm.ltt,
            self.tm.fs,
            combinations=MICHELSON,
            order=self.order,
            delay_order=self.delay_order,
        )
        for k in range(out.shape[1]):
            out[:, k] = aet(out[:, k])
        return out


def _weighted_parts(columns, weights) -> list:
    """The parts of ``columns`` scaled by ``weights`` as one column (0), those on the same
    link after the same delays summed (one series for the engine to transform)."""
    summed: dict = {}
    for w, col in zip(np.asarray(weights, dtype=float), columns, strict=True):
        for p in col.parts:
            key = (p.link, p.extra)
            summed[key] = w * p.series if key not in summed else summed[key] + w * p.series
    return [EnginePart(0, link, extra, series) for (link, extra), series in summed.items()]
