"""Rolling-window fit for streaming operations: the same estimator as the batch analysis.

:class:`RollingFit` takes TDI outputs one telemetry segment at a time (as the streaming
TDI builder produces them), and keeps, for the last ``window_duration`` seconds, the
band-limited spectra of fixed FFT segments.  Each new FFT segment triggers a refit with
:func:`ttlcore.estimate.fit.fit_spectra` over the window -- the very function the batch
:func:`ttlcore.estimate.fit.fit_tdi` calls -- so a window covering exactly the span of a batch
analysis (same settings) gives the same result to rounding.

To make that hold sample for sample, the streaming path reproduces the batch
preprocessing exactly:

- A, E, T from X2, Y2, Z2;
- the anti-alias low-pass and decimation of :meth:`ttlcore.tdi.data.TDIData.decimated`
  (same causal FIR, outputs on the same global sample grid, the filter's memory carried
  between segments, outputs touched by invalid input marked invalid);
- FFT segments on the same grid (every ``segment_duration`` of decimated samples from
  the first one), spectra by :func:`ttlcore.estimate.fit.spectra_of_segment`;
- the mean light travel times of the window (segment means, equal-length segments).

Update cost
-----------
Two kinds of refit (``FitResult.extra["update"]``):

- **full**: :func:`ttlcore.estimate.fit.fit_spectra` over the window's stored spectra - the batch
  estimator, noise CSD re-estimated and iterated; its cost grows with the window.
- **incremental**: the new FFT segment's normal equations and sandwich scores with the
  weights (inverse noise CSD) and notches of the last full refit are added to per-segment
  sums, those of the segment leaving the window subtracted, and the sums solved - the work
  of one segment whatever the window's length.  The estimate is the GLS estimate of the
  window with weights lagging by up to ``full_every``: unbiased, within a small fraction of
  sigma of the full refit (weights change slowly), its covariance the sandwich of the sums
  (each segment's scores taken at the estimate when it entered the window).

A full refit runs when the window's end lies a multiple of ``full_every`` seconds after the
start of the stream (default 6 h: at the end of every day of data, so that a window
covering exactly a day equals the batch fit of that day to rounding), while the window
holds fewer than 6 FFT segments, and whenever the weights no longer fit (another frequency
grid); ``full_every=None`` makes every refit full.  ``bench/rolling.py`` measures, on a
Keplerian day and a half (1-h FFT segments, one-day window), the CPU time of both kinds of
update and how far the incremental estimates are from full refits of the same windows
(measured: 0.041 s against 0.39 s for a full refit, medians; within 0.31 sigma once the
window holds half a day, 0.38 sigma while it fills; sigmas within 1.9 %).  No time series of the window are kept or re-transformed.

A full refit hands its per-segment sums to the incremental updates from the spectra its
last pass whitened (``fit_spectra(..., per_segment=True)``), and the errors-in-variables
term of a set of weights is taken once (:func:`ttlcore.estimate.sums.eiv_bands`): a
stream of 36 one-hour segments (1.5 Keplerian days, one-day window, a gate) took 7.06 s of
CPU before and 6.09 s after, the same estimates to 5e-13 sigma (docs/operations.md, "A
mission week").
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, replace

import numpy as np
from scipy import signal

from ..conventions import COEFFICIENT_NAMES
from ..tdi.combinations import AET
from ..tdi.data import TDIData, lowpass_taps
from .fit import (
    FitResult,
    FitSettings,
    NormalEquations,
    SegmentSpectra,
    _result,
    accumulate,
    fit_spectra,
    score_matrix,
    solve,
    spectra_of_segment,
)
from .gls import sandwich, set_apart, sigma_ratio
from .whitening import Whitener, whiten

log = logging.getLogger(__name__)


class StreamingDecimator:
    """Causal FIR low-pass and decimation by ``factor`` of consecutive blocks.

    Output ``k`` is ``sum_j h[j] x[factor * k - j]`` on the global input index, exactly as
    the batch filter; inputs that are not finite are taken as zero and every output whose
    filter span touches one is set to NaN.
    """

    def __init__(self, taps: np.ndarray, factor: int):
        self.h = np.asarray(taps, dtype=float)
        self.factor = int(factor)
        self.n_in = 0  # global index of the next input sample
        self._tail: np.ndarray | None = None  # last len(h) - 1 inputs (zeros before the start)
        self._bad_tail: np.ndarray | None = None

    def keep_rows(self, rows) -> None:
        """Keep the filter history of the rows ``rows`` (axis -2) only: the next blocks have those."""
        if self._tail is not None:
            self._tail = self._tail[..., rows, :]

    def push(self, x: np.ndarray) -> np.ndarray:
        """Filter the block ``x`` (shape ``(..., m)``); returns its decimated outputs."""
        x = np.asarray(x, dtype=float)
        m = x.shape[-1]
        L = self.h.size
        bad = ~np.isfinite(x).reshape(-1, m).all(axis=0)
        x = np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)
        if self._tail is None or self._bad_tail is None:
            self._tail = np.zeros(x.shape[:-1] + (L - 1,))
            self._bad_tail = np.zeros(L - 1, dtype=bool)
        ext = np.concatenate([self._tail, x], axis=-1)
        bad_ext = np.concatenate([self._bad_tail, bad])
        y = signal.oaconvolve(ext, self.h.reshape((1,) * (x.ndim - 1) + (-1,)), mode="valid", axes=-1)
        spoiled = np.convolve(bad_ext.astype(float), np.ones(L), mode="valid") > 0
        first = (-self.n_in) % self.factor  # first output on the global decimation grid
        y = y[..., first :: self.factor]
        spoiled = spoiled[first :: self.factor]
        y[..., spoiled] = np.nan
        self._tail = ext[..., -(L - 1) :]
        self._bad_tail = bad_ext[-(L - 1) :]
        self.n_in += m
        return y


@dataclass
class _Pending:
    data: list
    regressors: list
    n: int = 0


class _Sums:
    """One FFT segment's sums in the window: its normal equations ``neq`` and sandwich
    scores ``scores`` under the kept weights, and (taken when first asked for, then kept:
    the outlier test asks for every segment of the window at every push)
    :attr:`own_chi2_dof`."""

    __slots__ = ("neq", "scores", "_own")

    def __init__(self, neq: NormalEquations, scores: np.ndarray):
        self.neq, self.scores = neq, scores
        self._own: float | None = None

    def __iter__(self):  # unpacks as the ``(neq, scores)`` pair it was
        return iter((self.neq, self.scores))

    def __getitem__(self, k: int):
        return (self.neq, self.scores)[k]

    @property
    def own_chi2_dof(self) -> float:
        """chi^2/dof of the segment at its own least-squares fit (:func:`_own_fit_chi2_dof`)."""
        if self._own is None:
            self._own = _own_fit_chi2_dof(self.neq)[0]
        return self._own


def _own_fit_chi2_dof(neq: NormalEquations) -> tuple[float, float]:
    """chi^2/dof of the normal equations at their own least-squares solution (no
    errors-in-variables term), and the degrees of freedom."""
    N, b, dd = neq.total(eiv=False)
    dof = float(neq.dof_per_band().sum() - len(b))
    return max(2.0 * (dd - _explained(N, b)), 0.0) / dof, dof


def _explained(N: np.ndarray, b: np.ndarray) -> float:
    """``b^T N^+ b``: what the least-squares fit of normal equations ``N C = b`` takes of
    ``dd``, summed over the eigen-directions of ``N`` scaled to unit diagonal that the data
    determine (eigenvalue above ``1e-12`` of the largest, as :func:`~ttlcore.estimate.gls.inverse`;
    a column without information: none).  Each direction adds ``(v . b)^2 / w >= 0``, so the
    chi^2 left is at most ``dd``.  ``dd - b @ solve(N, b)`` is not bounded so where columns are
    nearly collinear with next to no information in one FFT segment (after their times,
    glitches on one test mass are each a constant velocity step, which TDI nearly cancels):
    ``solve`` follows rounding there (a null direction a hair negative, ``b`` a hair off the
    range of ``N``), and the live merger-and-glitches day, three glitches on test mass 21 in
    its model, left the hour 22-23 h out at chi^2/dof 1e16."""
    d = np.real(np.diag(N))
    live = d > 0.0
    if not live.any():
        return 0.0
    scale = 1.0 / np.sqrt(d[live])
    w, V = np.linalg.eigh(np.real(N[np.ix_(live, live)]) * np.outer(scale, scale))
    keep = w > 1e-12 * w.max()
    proj = V[:, keep].T @ (np.real(b[live]) * scale)
    return float(np.sum(proj**2 / w[keep]))


class RollingFit:
    """Rolling one-day (by default) TTL fit fed with TDI segments.

    Parameters
    ----------
    settings : FitSettings
        As for the batch fit; ``segment_duration`` is the FFT segment (a refit follows
        each completed one) and should divide the telemetry segments' length.
    window_duration : float
        Length of the window [s] (default one day).
    names : sequence of str
        Regressor names (default the 24 coefficients).
    full_every : float or None
        Mission-time period [s] of the full refits (module docstring); None: always full.
    eiv_extra : dict or None
        For regressors beyond the 24 (a model's columns), the DWS readouts whose noise each
        carries (:func:`ttlcore.estimate.fit.eiv_parts`), for the errors-in-variables term.
    outlier_z : float or None
        A new FFT segment whose residual at its own best fit is an outlier among the
        window's (:meth:`outlier`: more than ``outlier_z`` standard deviations of chi^2/dof
        above their median) is left out of the window: a glitch or a merger does not pull
        the fit.  None: every segment is kept.
    prior_scale : dict or None
        Regressor name -> the expected size of its coefficient (a model column's
        :attr:`ttlcore.effects.Column.prior_scale`): a regressor the window determines worse
        than that (a glitch whose FFT segments were left out) gets coefficient 0 and infinite
        variance (:func:`ttlcore.estimate.gls.set_apart`); regressors not named, never.

    Example
    -------
    >>> rf = RollingFit(FitSettings(segment_duration=3600))
    >>> for td in tdi_segments:          # TDIData of consecutive telemetry segments
    ...     result = rf.push(td)          # FitResult over the window, or None
    """

    #: Full refits while the window holds fewer FFT segments than this.
    MIN_INCREMENTAL = 6

    def __init__(
        self,
        settings: FitSettings | None = None,
        window_duration: float = 86400.0,
        names=COEFFICIENT_NAMES,
        full_every: float | None = 21600.0,
        eiv_extra: dict | None = None,
        outlier_z: float | None = 10.0,
        prior_scale: dict | None = None,
    ):
        self.settings = settings or FitSettings(segment_duration=3600.0)
        self.eiv_extra = eiv_extra
        #: per regressor, the scale below which the data must determine it (``inf``: any)
        self.prior_scale = (
            None if not prior_scale else np.array([float(prior_scale.get(n, np.inf)) for n in names], dtype=float)
        )
        self.outlier_z = outlier_z
        #: the FFT segments left out as outliers (:meth:`outlier`) or gated, oldest first
        self.excluded: list[dict] = []
        #: spans ``(start, stop)`` [s] of mission time whose FFT segments are left out (:meth:`set_gates`)
        self.gates: tuple = ()
        self.window_duration = float(window_duration)
        self.names = tuple(names)
        if full_every is not None and not full_every > 0:
            raise ValueError(f"full_every must be positive or None, got {full_every}")
        self.full_every = full_every
        self.reset()

    def reset(self) -> None:
        """Forget everything (after a gap in the data)."""
        self._decimator: StreamingDecimator | None = None
        self._fs_in: float | None = None
        self._t0_out: float | None = None  # time of decimated output sample 0
        self._n_out = 0  # decimated samples produced so far
        self._pending = _Pending([], [])
        self._spectra: deque[SegmentSpectra] = deque()
        self._ltt: deque[np.ndarray] = deque()
        self._ltt_blocks: list = []
        self._sums: deque[_Sums] = deque()  # per segment, lagged weights
        self._weights: dict | None = None  # internals of the last full refit
        self.last: FitResult | None = None
        self.last_decimated: TDIData | None = None

    @property
    def n_segments(self) -> int:
        """FFT segments currently in the window."""
        return len(self._spectra)

    def push(self, td: TDIData, ltt_mean: np.ndarray | None = None) -> FitResult | None:
        """Add one TDI segment; refit if an FFT segment was completed.

        Parameters
        ----------
        td : TDIData
            TDI outputs of the next telemetry segment (X2/Y2/Z2 or A/E/T).
        ltt_mean : ndarray (6,), optional
            Mean light travel times over this segment (default ``td.ltt_mean``).

        Returns
        -------
        FitResult or None
            The fit over the current window, or None when no FFT segment completed.
        """
        s = self.settings
        td = td.to_aet()
        if self._decimator is None:
            self._fs_in = td.fs
            factor = int(round(td.fs / 2.0)) if (s.decimate and td.fs > 2.0) else 1
            taps = lowpass_taps(td.fs) if factor > 1 else np.ones(1)
            self._decimator = StreamingDecimator(taps, factor)
            self._factor = factor
            self._t0_out = td.t0 - (taps.size - 1) / 2 / td.fs
        elif td.fs != self._fs_in:
            raise ValueError(f"segment at t0={td.t0}: fs {td.fs} differs from {self._fs_in}")
        assert self._fs_in is not None and self._t0_out is not None  # set with the decimator
        stacked = np.concatenate([td.data[:, None, :], td.regressors], axis=1)  # (3, 1 + P, n)
        out = self._decimator.push(stacked)
        fs_out = self._fs_in / self._factor
        ltt_seg = np.asarray(ltt_mean if ltt_mean is not None else td.ltt_mean)
        #: the segment low-passed and decimated (A, E, T; NaN where the filter saw invalid input)
        self.last_decimated = TDIData(
            t0=self._t0_out + (self._n_out + self._pending.n) / fs_out,
            fs=fs_out,
            channels=AET,
            data=out[:, 0],
            regressors=out[:, 1:],
            names=td.names,
            ltt_mean=ltt_seg,
        )
        self._pending.data.append(out[:, 0])
        self._pending.regressors.append(out[:, 1:])
        self._pending.n += out.shape[-1]
        self._ltt_blocks.append((ltt_seg, td.size))
        return self._complete_segments()

    def flush(self) -> FitResult | None:
        """Close the FFT segment in progress at the end of the stream and refit.

        The last telemetry segment of a file is often shorter than the others (a
        lisainstrument day loses its first samples to the eta reduction), so its samples
        never complete an FFT segment and no fit would cover it.  The FFT segment in progress
        is completed with NaN (a gap at its end: masked and tapered like any gap,
        :func:`ttlcore.estimate.fit.spectra_of_segment`, and left out when less than half of
        it holds data) and handled as :meth:`push` handles a completed one.  Call it once,
        after the last segment: the FFT grid does not continue past it.

        Returns
        -------
        FitResult or None
            The fit over the window with that FFT segment; the standing fit flagged
            (``extra["excluded"]``) when it was left out; None when nothing was pending.
        """
        if self._decimator is None or self._pending.n == 0 or self._fs_in is None:
            return None
        fs_out = self._fs_in / self._factor
        pad = int(round(self.settings.segment_duration * fs_out)) - self._pending.n
        if pad > 0:
            data, regs = self._pending.data[-1], self._pending.regressors[-1]
            self._pending.data.append(np.full(data.shape[:-1] + (pad,), np.nan))
            self._pending.regressors.append(np.full(regs.shape[:-1] + (pad,), np.nan))
            self._pending.n += pad
        return self._complete_segments()

    def _complete_segments(self) -> FitResult | None:
        """Spectra of every FFT segment the pending samples complete, each refitted (or left
        out); the last result."""
        s = self.settings
        assert self._fs_in is not None and self._t0_out is not None  # set with the decimator
        fs_out = self._fs_in / self._factor
        L = int(round(s.segment_duration * fs_out))
        result = None
        while self._pending.n >= L:
            data = np.concatenate(self._pending.data, axis=-1)
            regs = np.concatenate(self._pending.regressors, axis=-1)
            t0 = self._t0_out + self._n_out / fs_out
            sp = spectra_of_segment(data[:, :L], regs[:, :, :L], t0, fs_out, s.band, s.window)
            self._n_out += L
            self._pending = _Pending([data[:, L:]], [regs[:, :, L:]], data.shape[-1] - L)
            weights = np.array([n for _, n in self._ltt_blocks], dtype=float)
            self._ltt.append(np.average(np.stack([m for m, _ in self._ltt_blocks]), axis=0, weights=weights))
            self._ltt_blocks = []
            if sp is None:
                log.info("FFT segment at t0=%.1f has less than half valid samples: skipped", t0)
                self._ltt.pop()  # this segment's light travel times: it is not in the window
                if self.last is not None:  # the window is unchanged: its fit stands, flagged
                    gap = {"t_start": float(t0), "t_stop": float(t0 + L / fs_out), "gap": True}
                    result = replace(self.last, extra={**self.last.extra, "excluded": gap})
                continue
            outlier = self.gated(sp) or self.outlier(sp)
            if outlier is not None:
                self.excluded.append(outlier)
                self._ltt.pop()  # this segment's light travel times: it is not in the window
                if "gate" in outlier:
                    log.info("FFT segment at t0=%.1f left out: it overlaps the gate %s", t0, outlier["gate"])
                else:
                    log.info(
                        "FFT segment at t0=%.1f left out: chi2/dof at its own best fit %.3f, %.1f sigma above "
                        "the window's median %.3f",
                        t0,
                        outlier["chi2_dof"],
                        outlier["z"],
                        outlier["reference"],
                    )
                if self.last is not None:  # the window is unchanged: its fit stands
                    result = replace(self.last, extra={**self.last.extra, "excluded": outlier})
                continue
            self._spectra.append(sp)
            while (
                self._spectra
                and self._spectra[-1].t0 + self._spectra[-1].duration - self._spectra[0].t0
                > self.window_duration + 1e-6
            ):
                self._spectra.popleft()
                if len(self._sums) > len(self._spectra) - 1:
                    self._sums.popleft()
            while len(self._ltt) > len(self._spectra):
                self._ltt.popleft()
            result = self._refit()
        return result

    def drop(self, names) -> FitResult | None:
        """Drop the regressors ``names`` (a transient's columns out of the window, an effect
        removed): the FFT segments keep the other spectra, the window of a fit that never had
        them but for the outliers and weights decided with them; refitted in full now, and
        returned (None: no FFT segment).  A rebuild from the telemetry took 15-20 s."""
        gone = set(names)
        keep = [j for j, n in enumerate(self.names) if n not in gone]
        if len(keep) == len(self.names):
            return self.last
        self.names = tuple(self.names[j] for j in keep)
        if self.prior_scale is not None:
            ps = self.prior_scale[keep]
            self.prior_scale = ps if np.isfinite(ps).any() else None
        if self.eiv_extra is not None:
            self.eiv_extra = {k: v for k, v in self.eiv_extra.items() if k not in gone} or None
        self._spectra = deque(replace(sp, R=sp.R[:, :, keep]) for sp in self._spectra)
        self._pending = _Pending(self._pending.data, [r[:, keep] for r in self._pending.regressors], self._pending.n)
        if self._decimator is not None:  # its rows: the data, then the regressors
            self._decimator.keep_rows([0, *(1 + j for j in keep)])
        if self.last_decimated is not None:
            ld = self.last_decimated
            self.last_decimated = replace(ld, regressors=ld.regressors[:, keep], names=self.names)
        self._sums.clear()
        self._weights = None
        self.last = self._refit() if self._spectra else None
        return self.last

    def set_gates(self, spans) -> None:
        """Leave out the FFT segments that overlap any of ``spans`` (``(start, stop)`` [s] of
        mission time: a model's ``gate`` effects): those in the window now (the next fit is a
        full refit) and those to come."""
        spans = tuple(sorted((float(a), float(b)) for a, b in spans))
        if spans == self.gates:
            return
        self.gates = spans
        keep = [k for k, sp in enumerate(self._spectra) if self.gated(sp) is None]
        if len(keep) < len(self._spectra):
            for sp in self._spectra:
                gate = self.gated(sp)
                if gate is not None:  # those not kept
                    self.excluded.append(gate)
            self._spectra = deque(self._spectra[k] for k in keep)
            self._ltt = deque(self._ltt[k] for k in keep if k < len(self._ltt))
            self._sums.clear()
            self._weights = None  # the next fit is a full refit of what is left

    def gated(self, sp: SegmentSpectra) -> dict | None:
        """``{t_start, t_stop, gate}`` when the FFT segment ``sp`` overlaps a gate."""
        for a, b in self.gates:
            if sp.t0 < b and sp.t0 + sp.duration > a:
                return {"t_start": float(sp.t0), "t_stop": float(sp.t0 + sp.duration), "gate": [a, b]}
        return None

    def outlier(self, sp: SegmentSpectra) -> dict | None:
        """Whether the FFT segment ``sp`` is an outlier among the window's, and by how much.

        The statistic is the segment's chi^2/dof at its own least-squares fit of all the
        regressors, under the weights of the last full refit: a change of the coefficients
        (a drift, a step) is fitted away, what no coefficient can take (a glitch, a merger,
        a noise burst) is not.  The segment is an outlier when the statistic exceeds the
        median of the window's segments by more than ``outlier_z`` of its standard
        deviation ``sqrt(2 / dof)`` relative (1-h segments at 2 Hz: ~1 %, so the default
        10 is an excess of ~10 %).  Not tested before the window holds
        :data:`MIN_INCREMENTAL` segments.  Returns None or ``{t_start, t_stop, chi2_dof,
        reference, z}``.
        """
        w = self._weights
        if (
            self.outlier_z is None
            or w is None
            or len(self._sums) < self.MIN_INCREMENTAL - 1
            or sp.f.size != w["f_size"]
        ):
            return None
        ref = float(np.median([sums.own_chi2_dof for sums in self._sums]))
        r, dof = _own_fit_chi2_dof(
            accumulate([self._masked(sp)], w["weights"], w["band_edges"], self.names, prepared=w["plain"])
        )
        z = (r / ref - 1.0) / np.sqrt(2.0 / dof)
        if not z > self.outlier_z:
            return None
        return {
            "t_start": float(sp.t0),
            "t_stop": float(sp.t0 + sp.duration),
            "chi2_dof": float(r),
            "reference": ref,
            "z": float(z),
        }

    def _full_due(self) -> bool:
        if self.full_every is None or self._weights is None or len(self._spectra) < self.MIN_INCREMENTAL:
            return True
        if len(self._sums) != len(self._spectra) - 1 or self._spectra[-1].f.size != self._weights["f_size"]:
            return True
        # FFT segments tile the time from the first output sample of the stream (t0 of the
        # telemetry minus the low-pass delay): count from there
        assert self._t0_out is not None  # set with the first segment
        elapsed = self._spectra[-1].t0 + self._spectra[-1].duration - self._t0_out
        return abs(elapsed / self.full_every - round(elapsed / self.full_every)) * self.full_every < 1e-3

    def _refit(self) -> FitResult:
        ltt_mean = np.mean(np.stack(self._ltt), axis=0)
        if self._full_due():
            res, internals = fit_spectra(
                list(self._spectra),
                ltt_mean,
                self.settings,
                self.names,
                eiv_extra=self.eiv_extra,
                prior_scale=self.prior_scale,
                per_segment=self.full_every is not None,
            )
            res.extra["update"] = "full"
            if self.full_every is not None:
                self._keep_weights(internals)
        else:
            res = self._update()
        self.last = res
        return res

    # ---------------------------------------------------------------- incremental updates
    def _kept(self) -> dict:
        """The weights of the last full refit (the incremental updates need one)."""
        if self._weights is None:
            raise RuntimeError("no full refit yet: no weights to update with")
        return self._weights

    def _masked(self, sp: SegmentSpectra) -> SegmentSpectra:
        keep = self._kept()["notch"]
        if keep is None:
            return sp
        return SegmentSpectra(sp.t0, sp.duration, sp.f[keep], sp.d[keep], sp.R[keep], sp.valid_fraction)

    def _segment_sums(self, sp: SegmentSpectra, C: np.ndarray) -> _Sums:
        """Normal equations and sandwich scores of one segment with the kept weights."""
        w = self._kept()
        sp = self._masked(sp)
        prepared = w["whitener"]
        _, wd, wR = whiten(w["weights"], sp.d[None], sp.R[None], Lh=prepared.Lh)
        neq = accumulate([sp], w["weights"], w["band_edges"], self.names, prepared=prepared, whitened=(wd, wR))
        return _Sums(neq, score_matrix([sp], w["weights"], C, whitened=(wd, wR)))

    def _keep_weights(self, internals: dict) -> None:
        """After a full refit: its weights, and the per-segment sums of the window with them
        (``internals["segment_sums"]``: summed from the spectra the refit whitened with its
        last weights; whitening and summing every segment again here took a third of the
        fitter's rolling updates)."""
        self._weights = {
            k: internals[k] for k in ("weights", "notch", "eiv_response", "dws_psd", "band_edges", "variance_factor")
        }
        self._weights["f_size"] = self._spectra[-1].f.size
        # the weights' Cholesky factor, whitened readout-noise responses and their
        # errors-in-variables term, taken once for every segment summed with them
        prepared = internals["whitener"]
        self._weights["whitener"] = prepared
        self._weights["plain"] = Whitener(prepared.Lh)  # the outlier test's sums: no readout-noise term
        self._sums = deque(_Sums(neq, M) for neq, M in internals["segment_sums"])

    def _update(self) -> FitResult:
        """GLS of the window from the per-segment sums with the lagged weights (one segment's work)."""
        s, w = self.settings, self._kept()
        C_prev = self.last.coefficients if self.last is not None else np.zeros(len(self.names))
        self._sums.append(self._segment_sums(self._spectra[-1], C_prev))
        total = self._sums[0].neq
        M = self._sums[0].scores
        for sums in list(self._sums)[1:]:
            total, M = total + sums.neq, M + sums.scores
        C, cov = solve(total, eiv=s.eiv, prior_scale=self.prior_scale)
        kappa = w["variance_factor"]
        cov_model = kappa * cov
        N, _, _ = total.total(s.eiv)
        cov_robust = kappa * sandwich(set_apart(N, self.prior_scale), M)
        chi2 = total.chi2_per_band(C, eiv=s.eiv)
        res = _result(
            self.names,
            C,
            cov_robust if s.robust_covariance else cov_model,
            chi2,
            total,
            s,
            "gls",
            s.eiv,
            0,
            True,
            list(self._spectra),
        )
        res.extra.update(
            update="incremental",
            variance_factor=kappa,
            covariance_model_based=cov_model.tolist(),
            sigma_ratio_robust_to_model=sigma_ratio(cov_robust, cov_model),
        )
        return res
