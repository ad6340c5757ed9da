"""Gated data: spans of the data down-weighted to zero (the ``gate`` effect).

docs/diagnostics.md, "Glitches and gates".  The A, E, T series of the data and of every
column are multiplied by the gate (:class:`ttlcore.effects.gate.Gate`; the taper of
:func:`ttlcore.effects.gate.gate`)

    g(t) = 0 inside [start, stop],  1/2 - 1/2 cos(pi d / taper) for the distance d < taper
           outside it,  1 beyond,

before the segments are windowed (:class:`GatedGrid`), so that the fit ignores the span
and no hard edge leaks.  A segment partly gated holds less noise: its spectra are divided
by ``sqrt(r_s)``, ``r_s = sum (w g)^2 / sum w_k^2``, ``w_k`` its taper ``w`` over the samples
kept (the spectra are normalised by the window's power there: only the ramps are left to
restore), so that its chi^2 keeps the expectation of an ungated segment; a segment keeping
less than ``MIN_KEPT`` of its whole taper's power, ``sum (w g)^2 / sum w^2``, is left out
(its remnant leaks the red noise below the band).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass, field, fields, replace

import numpy as np

from ..effects.gate import Gate, gate
from ..errors import ConfigError
from .columns import ColumnStore, regressor_columns
from .transients import data_gaps
from .whitened import MIN_KEPT, AnalysisGrid, WhitenedData, noise_digest

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class GatedGrid(AnalysisGrid):
    """:class:`~ttlcore.diagnose.whitened.AnalysisGrid` with spans gated out (module
    docstring).  Every decimated series is multiplied by ``gate``: the data's and the TTL
    regressors' (:class:`~ttlcore.diagnose.whitened.MeasuredTDI` ``data_series``,
    ``regressor_series``) once in :func:`gated_data`, every column's where it is decimated
    (:meth:`decimate`, the one path from an effect's TDI to its spectra), so that data and
    columns carry the same window and the time-domain residual (per-hour adequacy,
    transients) is tapered too, without a hard edge; each segment's spectra are multiplied
    by ``seg_scale`` (``1 / sqrt(r_s)``).  Inside a span (``gate == 0``) the samples are out
    of ``mask``.

    Attributes
    ----------
    gate : ndarray (n,)
        The gate ``g(t)`` on the decimated samples.
    seg_scale : ndarray (S,)
        ``1 / sqrt(r_s)`` of each kept segment.
    seg_variance : ndarray (S,)
        Each kept segment's variance factor over the untouched taper's
        (:func:`taper_variance`): above 1 where a gate or a gap cuts into the segment.  The
        power the gate takes is restored (``seg_scale``), the resolution it takes is not: the
        bins of a segment with a hole are more correlated than those of a whole one, and a
        fit that counted them as independent kept its sigmas as if nothing had been gated
        (a 22-min gate on a 12-h day moved the coefficients by 0.38 sigma RMS with the
        sigmas unchanged to 1e-3; :meth:`segment_kappa`, used by the covariances).
    gates : tuple of str
        The model's gates' effect specs; ``gate_spans`` their ``(start, stop)`` [s].
    gap_spans : tuple of (float, float)
        Runs of missing data [s] gated the same way (:func:`missing_data`): the data's, not
        the model's; reported as gaps, never advised.
    """

    gate: np.ndarray = field(default_factory=lambda: np.ones(0))
    seg_scale: np.ndarray = field(default_factory=lambda: np.ones(0))
    seg_variance: np.ndarray = field(default_factory=lambda: np.ones(0))
    gates: tuple[str, ...] = ()
    gate_spans: tuple[tuple[float, float], ...] = ()
    gap_spans: tuple[tuple[float, float], ...] = ()

    def spectra_of(self, x: np.ndarray, offset: int = 0, segments: range | None = None) -> np.ndarray:
        scale = self.seg_scale if segments is None else self.seg_scale[segments.start : segments.stop]
        return super().spectra_of(x, offset, segments) * scale[:, None, None, None]

    def segment_kappa(self) -> np.ndarray:
        return self.kappa * self.seg_variance

    def decimate(self, xyz: np.ndarray, is_aet: bool = False) -> np.ndarray:
        """The decimated A, E, T of columns (:meth:`AnalysisGrid.decimate`) times the gate;
        full-length series only (a stretch: decimate it ungated and gate it once placed)."""
        out = super().decimate(xyz, is_aet)
        if out.shape[-1] != self.gate.size:
            raise ConfigError(
                f"gated data: a series of {out.shape[-1]} decimated samples cannot be gated ({self.gate.size} expected)"
            )
        return out * self.gate


def taper_variance(w: np.ndarray) -> float:
    """``L sum w^4 / (sum w^2)^2`` of a segment's taper ``w`` (length ``L``): the variance
    of a fit statistic of the segment over the one computed with its bins independent
    (:func:`ttlcore.estimate.fit.variance_factor` without overlap)."""
    w2 = np.square(w)
    return float(w.size * np.sum(w2**2) / np.sum(w2) ** 2)


def missing_data(data: WhitenedData) -> list[tuple[float, float]]:
    """The runs of missing data [s] inside ``data``'s analysed span (NaN in the telemetry,
    grown by the TDI's reach; :func:`ttlcore.diagnose.transients.data_gaps`), which the
    diagnosis gates before it fits anything (:func:`gated_data`'s ``gaps``): a hard edge
    into a gap would leak the red noise below the band into every bin of its segment and
    read as an excess in the hours around it."""
    if isinstance(data.grid, GatedGrid):
        return list(data.grid.gap_spans)
    return data_gaps(data.tdi.data_series, data.grid.fs, data.grid.t0, data.grid.mask)


def gated_data(data: WhitenedData, gates: Iterable[Gate], gaps: Iterable[tuple[float, float]] = ()) -> WhitenedData:
    """``data`` with the spans of ``gates`` (:class:`Gate`) and the runs of missing data
    ``gaps`` (``(start, stop)`` [s], :func:`missing_data`) gated out (its grid a
    :class:`GatedGrid`); ``data`` itself when there is neither.  A gap is gated like a gate
    of the default taper (:data:`ttlcore.effects.gate.GATE_TAPER`) and recorded as the
    data's (``gap_spans``), not the model's.  The noise model is kept; the context is new,
    with an empty column store (columns built on ungated data do not apply)."""
    gates, gaps = list(gates), [(float(a), float(b)) for a, b in gaps]
    if not gates and not gaps:
        return data
    grid = data.grid
    if isinstance(grid, GatedGrid):
        raise ConfigError("these data are already gated")
    n = grid.mask.size
    g = np.ones(n)
    for e in [*gates, *(Gate(start=a, stop=b) for a, b in gaps)]:
        g = np.minimum(g, gate(n, grid.fs, grid.t0, [e.span], taper=float(e.options["taper"])))
    inside = g <= 0.0
    mask = grid.mask & ~inside
    if not mask.any():
        raise ConfigError("the gates leave no data")
    keep, scale, variance = [], [], []
    whole = float(np.sum(grid.win**2))
    whole_variance = taper_variance(grid.win)
    for s0 in grid.starts:
        w = grid.win * grid.mask[s0 : s0 + grid.L]
        wg2 = float(np.sum((w * g[s0 : s0 + grid.L]) ** 2))
        # against the whole taper, not the samples the data hold: a segment inside a gap
        # holds none, and 0 >= 0.6 x 0 kept it (a blind week's window over a 7-h gap: a
        # segment of zeros divided by 1e-150 read chi2/dof 16080)
        keep.append(wg2 >= MIN_KEPT * whole)
        # the spectra are normalised by the window's power over the samples kept
        # (``segment_fft`` of ``win * mask``, the span out of ``mask``): only the ramps'
        # share is left to restore.  Against the whole window, the span was restored twice:
        # a 30-min gate read chi2/dof 1.058 on a 12-h day (1.007 ungated)
        wk = grid.win * mask[s0 : s0 + grid.L]
        scale.append(1.0 / math.sqrt(max(wg2 / max(float(np.sum(wk**2)), 1e-300), 1e-300)))
        variance.append(taper_variance(w * g[s0 : s0 + grid.L]) / whole_variance if wg2 > 0 else 1.0)
    if not any(keep):
        raise ConfigError("the gates leave no FFT segment with data")
    idx = [i for i, k in enumerate(keep) if k]
    starts = tuple(grid.starts[i] for i in idx)
    w2 = np.stack([(grid.win * mask[s0 : s0 + grid.L] * g[s0 : s0 + grid.L]) ** 2 for s0 in starts])
    gated = GatedGrid(
        **{
            **{f.name: getattr(grid, f.name) for f in fields(AnalysisGrid)},
            "mask": mask,
            "starts": starts,
            "seg_t0": np.asarray(grid.seg_t0)[idx],
            "w2": w2 / w2.sum(axis=1, keepdims=True),
            "gate": g,
            "seg_scale": np.asarray(scale)[idx],
            "seg_variance": np.asarray(variance)[idx],
            "gates": tuple(e.spec() for e in gates),
            "gate_spans": tuple(e.span for e in gates),
            "gap_spans": tuple(gaps),
        }
    )
    # gated once; inside a span exactly zero (a gap's NaN there too); the regressors in
    # place (a day's are 100 MB: no second copy for the zeros)
    series = np.where(inside, 0.0, data.tdi.data_series * g)
    regs = data.tdi.regressor_series * g
    regs[..., inside] = 0.0
    d = gated.spectra(series[:, None, :])[..., 0]
    R = gated.spectra(regs)
    wd = np.matmul(data.noise.Lh, d[..., None])[..., 0]
    dd = np.zeros((len(starts), gated.G))
    for gi, (a, b) in enumerate(gated.slices):
        dd[:, gi] = np.sum(np.abs(wd[:, a:b]) ** 2, axis=(1, 2))
    out = WhitenedData(
        grid=gated,
        tdi=replace(data.tdi, data_series=series, regressor_series=regs, d=d),
        noise=replace(
            data.noise,
            wd=wd,
            dd=dd,
            key=noise_digest(data.noise.csd)
            + ":gated:"
            + ",".join([*gated.gates, *(f"gap:{a:.3f}-{b:.3f}" for a, b in gaps)]),
        ),
        context=replace(data.context, store=ColumnStore()),
    )
    out.context.store.put(("regressors",), out, regressor_columns(out, R))
    log.info(
        "gated %s and %d gap(s): %d of %d segments kept",
        ", ".join(gated.gates),
        len(gaps),
        len(starts),
        len(grid.starts),
    )
    return out


def in_gates(data, a: float, b: float) -> bool:
    """Whether ``[a, b]`` [s] lies inside one of ``data``'s gates or gated gaps (:class:`GatedGrid`),
    to a sample (a run of zeros found in the gated series ends one sample after the span:
    the gate is zero at both ends)."""
    spans = (*getattr(data.grid, "gate_spans", ()), *getattr(data.grid, "gap_spans", ()))
    tol = 1.0 / data.grid.fs + 1e-6
    return any(lo <= a + tol and b <= hi + tol for lo, hi in spans)


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
