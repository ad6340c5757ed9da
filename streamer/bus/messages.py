"""The pipeline's segment messages as :mod:`ttlcore` objects.

A ``telemetry`` message (arrays ``eta``, ``dws_phi``, ``dws_eta``, ``ltt``, each (6, n)) is a
:class:`ttlcore.io.telemetry.Telemetry`; a ``tdi`` message (arrays ``data`` (3, n) and
``regressors`` (3, P, n), meta ``names`` and ``ltt_mean``) is a
:class:`ttlcore.tdi.data.TDIData`.  Used by the stages on live messages and by the offline
tools (``ttl refit``) on recorded ones.
"""

from __future__ import annotations

import numpy as np

from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.io.telemetry import Telemetry
from ttlcore.tdi.combinations import XYZ
from ttlcore.tdi.data import TDIData

from .codec import Expect
from .segment_record import segment_meta

#: Arrays of a telemetry message.
TELEMETRY_ARRAYS = ("eta", "dws_phi", "dws_eta", "ltt")
#: Coefficients of the linear TTL model: the regressors of a ``tdi`` message, the
#: coefficients of a ``fit``.
P = len(COEFFICIENT_NAMES)


def tdi_expect(run: str, index: int) -> Expect:
    """What a ``tdi`` message must fit (NaN allowed: first samples of a stream, gaps): X2, Y2,
    Z2 of the data and of the 24 regressors, and the telemetry they were computed from."""
    return Expect(
        run=run,
        index=index,
        channels=XYZ,
        allow_nonfinite=True,
        arrays={
            "data": ("<f8", (3, None)),
            "regressors": ("<f8", (3, P, None)),
            **{k: ("<f8", (6, None)) for k in TELEMETRY_ARRAYS},
        },
    )


def telemetry_of(header, arrays) -> Telemetry:
    """The :class:`~ttlcore.io.telemetry.Telemetry` of a ``telemetry`` message."""
    return Telemetry(
        t0=header.t0,
        fs=header.fs,
        source=str(segment_meta(header).source or "bus"),
        **{k: arrays[k] for k in TELEMETRY_ARRAYS},
    )


def concatenate_telemetry(parts, source: str = "bus") -> Telemetry:
    """Contiguous telemetry segments as one :class:`~ttlcore.io.telemetry.Telemetry` (the
    first segment's t0 and rate): the live fitter's window and ``ttl refit``'s input are
    built by this one function, so that both fit the same numbers."""
    parts = list(parts)
    if not parts:
        raise ValueError("no telemetry segments to join")

    def joined(name: str) -> np.ndarray:  # one of TELEMETRY_ARRAYS
        return np.concatenate([getattr(p, name) for p in parts], axis=1)

    return Telemetry(
        t0=parts[0].t0,
        fs=parts[0].fs,
        eta=joined("eta"),
        dws_phi=joined("dws_phi"),
        dws_eta=joined("dws_eta"),
        ltt=joined("ltt"),
        source=source,
    )


def tdi_of(header, arrays) -> TDIData:
    """The :class:`~ttlcore.tdi.data.TDIData` of a ``tdi`` message (errors name the field)."""
    meta = segment_meta(header)
    names = meta.names or COEFFICIENT_NAMES
    if len(names) != arrays["regressors"].shape[1]:
        raise ValueError(f"meta.names has {len(names)} names for {arrays['regressors'].shape[1]} regressors")
    ltt = np.asarray(meta.ltt_mean if meta.ltt_mean is not None else [np.nan] * 6, dtype=float)
    if ltt.shape != (6,):
        raise ValueError(f"meta.ltt_mean: expected 6 values, got shape {ltt.shape}")
    return TDIData(
        t0=header.t0,
        fs=header.fs,
        channels=tuple(header.channels),
        data=arrays["data"],
        regressors=arrays["regressors"],
        names=names,
        ltt_mean=ltt,
    )
