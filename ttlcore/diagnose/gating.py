"""Gated data: spans of the data down-weighted to zero (the ``gate`` effect).

docs/diagnostics.md, "Glitches and gates".  The A, E, T series of the data and of every
column are multiplied by the gate (:class:`ttlcore.effects.glitch.Gate`; the taper of
:func:`ttlcore.effects.glitch.gate`)

    g(t) = 0 inside [start, stop],  1/2 - 1/2 cos(pi d / taper) for the distance d < taper
           outside it,  1 beyond,

before the segments are windowed (:class:`GatedData`), so that the fit ignores the span
and no hard edge leaks.  A segment partly gated holds less noise: its spectra are divided
by ``sqrt(r_s)``, ``r_s = sum (w g)^2 / sum w^2`` over its taper ``w``, so that its chi^2
keeps the expectation of an ungated segment; a segment with ``r_s < MIN_KEPT`` is left out
(its remnant leaks the red noise below the band).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np

from ..effects.glitch import gate
from ..errors import ConfigError
from .columns import ColumnStore, regressor_columns
from .whitened import WhitenedData, noise_digest

log = logging.getLogger(__name__)

#: Segments keeping less than this share of their taper's power under a gate are left out:
#: a short remnant of a segment leaks the red noise below the band into it through the
#: gate's ramps (4-h simulated day, 58-min segments, a 55-min gate: keeping a remnant of
#: 0.3 read chi2/dof 1.43 and pull RMS 2.49; leaving it out, 0.993 and 0.88).
MIN_KEPT = 0.6


@dataclass(frozen=True, eq=False)
class GatedData(WhitenedData):
    """:class:`~ttlcore.diagnose.whitened.WhitenedData` with spans gated out (module
    docstring).  Every decimated series is multiplied by ``gate``: the data's and the TTL
    regressors' (``data_series``, ``regressor_series``) once here, every column's where it
    is decimated (:meth:`decimate`, the one path from an effect's TDI to its spectra), so
    that data and columns carry the same window and the time-domain residual (per-hour
    adequacy, transients) is tapered too, without a hard edge; each segment's spectra are
    multiplied by ``seg_scale`` (``1 / sqrt(r_s)``).  Inside a span (``gate == 0``) the
    samples are out of ``mask``."""

    gate: np.ndarray | None = None
    seg_scale: np.ndarray | None = None
    gates: tuple = ()
    #: ``((start, stop), ...)`` [s] of the gates
    gate_spans: tuple = ()

    def spectra(self, x: np.ndarray) -> np.ndarray:
        assert self.seg_scale is not None  # set with the gate (gate_data)
        return super().spectra(x) * self.seg_scale[:, None, None, None]

    def decimate(self, xyz: np.ndarray, is_aet: bool = False) -> np.ndarray:
        """The decimated A, E, T of columns (:meth:`WhitenedData.decimate`) times the gate;
        full-length series only (a stretch: decimate it ungated and gate it once placed)."""
        out = super().decimate(xyz, is_aet)
        assert self.gate is not None  # set with the gate (gate_data)
        if out.shape[-1] != self.gate.size:
            raise ConfigError(
                f"gated data: a series of {out.shape[-1]} decimated samples cannot be gated ({self.gate.size} expected)"
            )
        return out * self.gate


def gated_data(data: WhitenedData, gates) -> WhitenedData:
    """``data`` with the spans of ``gates`` (:class:`Gate`) gated out (:class:`GatedData`);
    ``data`` itself when there is none.  The noise model is kept; the column store is new
    (columns built on ungated data do not apply)."""
    gates = list(gates)
    if not gates:
        return data
    if isinstance(data, GatedData):
        raise ConfigError("these data are already gated")
    n = data.mask.size
    g = np.ones(n)
    for e in gates:
        g = np.minimum(g, gate(n, data.fs, data.t0, [e.span], taper=float(e.options["taper"])))
    inside = g <= 0.0
    mask = data.mask & ~inside
    if not mask.any():
        raise ConfigError("the gates leave no data")
    keep, scale = [], []
    for s0 in data.starts:
        w = data.win * data.mask[s0 : s0 + data.L]
        r = float(np.sum((w * g[s0 : s0 + data.L]) ** 2) / max(np.sum(w**2), 1e-300))
        keep.append(r >= MIN_KEPT)
        scale.append(1.0 / math.sqrt(max(r, 1e-300)))
    if not any(keep):
        raise ConfigError("the gates leave no FFT segment with data")
    idx = [i for i, k in enumerate(keep) if k]
    starts = tuple(data.starts[i] for i in idx)
    w2 = np.stack([(data.win * mask[s0 : s0 + data.L] * g[s0 : s0 + data.L]) ** 2 for s0 in starts])
    # gated once; inside a span exactly zero (a gap's NaN there too)
    series = np.where(inside, 0.0, data.data_series * g)
    regs = np.where(inside, 0.0, data.regressor_series * g)
    out = GatedData(
        **{
            **{k: getattr(data, k) for k in data.__dataclass_fields__},
            "mask": mask,
            "starts": starts,
            "seg_t0": np.asarray(data.seg_t0)[idx],
            "w2": w2 / w2.sum(axis=1, keepdims=True),
            "data_series": series,
            "regressor_series": regs,
            "store": ColumnStore(),
            "d": np.empty(0),
            "wd": np.empty(0),
            "dd": np.empty(0),
            "gate": g,
            "seg_scale": np.asarray(scale)[idx],
            "gates": tuple(e.spec() for e in gates),
            "gate_spans": tuple(e.span for e in gates),
        }
    )
    d = out.spectra(series[:, None, :])[..., 0]
    R = out.spectra(regs)
    wd = np.matmul(out.Lh, d[..., None])[..., 0]
    dd = np.zeros((len(starts), out.G))
    for gi, (a, b) in enumerate(out.slices):
        dd[:, gi] = np.sum(np.abs(wd[:, a:b]) ** 2, axis=(1, 2))
    out = replace(out, d=d, wd=wd, dd=dd, noise_key=noise_digest(out.noise_csd) + ":gated:" + ",".join(out.gates))
    out.store.put(("regressors",), out, regressor_columns(out, R))
    log.info("gated %s: %d of %d segments kept", ", ".join(out.gates), len(starts), len(data.starts))
    return out


def in_gates(data, a: float, b: float) -> bool:
    """Whether ``[a, b]`` [s] lies inside one of ``data``'s gates (:class:`GatedData`)."""
    return any(lo <= a + 1e-6 and b <= hi + 1e-6 for lo, hi in getattr(data, "gate_spans", ()))


def with_gates(model_json: dict, gates) -> dict:
    """A report's ``model`` part (:func:`ttlcore.diagnose.report.model_json`) with the
    model's gates listed among its effects (they change the data, not the columns) and
    under ``gates`` (``[start, stop]`` [s] each)."""
    gates = list(gates)
    if not gates:
        return model_json
    out = dict(model_json)
    out["effects"] = list(out["effects"]) + [g.spec() for g in gates]
    out["cli_effects"] = ",".join([out["cli_effects"]] + [g.cli_spec() for g in gates])
    out["gates"] = [list(g.span) for g in gates]
    return out
