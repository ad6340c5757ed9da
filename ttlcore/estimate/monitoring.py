"""What a monitor of the subtraction computes: noise curves of a segment and the truth over a fit's window.

The streaming pipeline's monitor (``stages/monitor/monitor.py``) draws these; ``ttl inspect`` reads
the truth the same way.  Nothing here draws or talks to a bus.

Noise curves (per segment of TDI X2, in displacement, :mod:`ttlcore.estimate.spectra`):

* :func:`channel_asd`: the log-averaged Welch ASD of one channel over its longest finite
  stretch;
* :func:`reference_curves`: the expected secondary noise of X2 for the segment's mean arms
  (:func:`ttlcore.estimate.noise_psd.tdi_noise_csd`) and the LISA requirement, averaged on the
  same bins as the data;
* :func:`band_ratio`: the median of one curve over another in a band, the one-number
  adequacy check (residual over expected noise) beside the fit's chi^2/dof.

The truth over a fit's window (the estimate is the window's average, so the truth to
compare with is the same average): :class:`ModelTruth` for a simulation on the fly (its
coefficient model), :class:`FileTruth` for a truth file, :func:`window_truth` to pick one
from what the telemetry's meta says.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from pathlib import Path

import numpy as np

from ..conventions import COEFFICIENT_NAMES
from ..io.truth import read_truth
from ..sim.coefficients import CoefficientModel
from .noise_psd import requirement_x2, tdi_noise_csd
from .spectra import displacement_asd, log_displacement_asd, longest_run

#: Fewest finite samples a segment's ASD is computed from.
MIN_SAMPLES = 64


def channel_asd(x: np.ndarray, fs: float, per_decade: int = 20):
    """Log-averaged displacement ASD of one TDI channel in fractional frequency, over its
    longest finite stretch (:func:`ttlcore.estimate.spectra.displacement_asd`).

    Returns
    -------
    f : ndarray
        Frequencies [Hz] of the bins with power.
    asd : ndarray
        Displacement ASD [m/sqrt(Hz)] there.
    f_welch : ndarray
        The Welch grid without DC (for :func:`reference_curves`).

    Raises
    ------
    ValueError
        If fewer than :data:`MIN_SAMPLES` samples are finite in a row.
    """
    x = np.asarray(x, dtype=float)
    x = x[longest_run(np.isfinite(x))]
    if x.size < MIN_SAMPLES:
        raise ValueError(f"too few finite samples ({x.size}) for an ASD")
    f, asd, f_welch = displacement_asd(x, fs, per_decade=per_decade)
    good = asd > 0
    return f[good], asd[good], f_welch


def reference_curves(f_welch: np.ndarray, ltt, per_decade: int = 20) -> dict:
    """Expected secondary noise of X2 for the arms ``ltt`` (six values [s]) and the
    requirement, log-averaged like the data: ``{name: (f, asd [m/sqrt(Hz)])}``."""
    expected = np.real(tdi_noise_csd(f_welch, ltt, aet=False)[:, 0, 0])
    out = {}
    for name, psd in (("expected", expected), ("requirement", requirement_x2(f_welch))):
        fc, asd = log_displacement_asd(f_welch, psd, per_decade)
        good = asd > 0
        out[name] = (fc[good], asd[good])
    return out


def band_ratio(f, a, f_ref, ref, band) -> float:
    """Median of ``a / ref`` over ``band`` = (fmin, fmax) [Hz] (``ref`` interpolated in
    log-log onto ``f``); NaN when no frequency of ``f`` is in the band."""
    sel = (f >= band[0]) & (f <= band[1])
    if not sel.any():
        return float("nan")
    r = np.interp(np.log10(f[sel]), np.log10(f_ref), np.log10(ref))
    return float(np.median(a[sel] / 10**r))


class ModelTruth:
    """True coefficients of a simulation on the fly, averaged over time spans from its
    coefficient model (:meth:`ttlcore.sim.coefficients.CoefficientModel.mean`)."""

    path = "simulation"

    def __init__(self, model: CoefficientModel):
        self.model = model

    def mean(self, t_start: float, t_stop: float) -> np.ndarray:
        """Average true coefficients over ``[t_start, t_stop]`` [m/rad], shape (24,)."""
        return self.model.mean(t_start, t_stop)


class FileTruth:
    """True coefficients averaged over time spans, read block by block from a truth file.

    The file is read in blocks of ``block`` seconds (:func:`ttlcore.io.truth.read_truth`): a
    block's sum is kept for good (24 numbers), and the running sums of its samples for the
    last :attr:`RECENT` blocks read, so that a span's partial edges inside those come from
    memory.  Under a window sliding by a block at a time a block is read at most twice: as
    the window's newest block, and again as its oldest when the window is longer than
    :attr:`RECENT` blocks (before, every span read both of its partial edges again).
    """

    #: Blocks whose running sums are kept (a sliding window's two edges, and a block's worth of margin).
    RECENT = 4

    def __init__(self, path, block: float = 3600.0):
        self.path = Path(path)
        head = read_truth(self.path, 0, 1)
        self.t0, self.fs = float(head.t0), float(head.fs)
        self.block = max(1, int(round(block * self.fs)))
        self._sums: dict[int, tuple[np.ndarray, int]] = {}
        self._running: OrderedDict[int, np.ndarray] = OrderedDict()

    def _block(self, k: int) -> np.ndarray:
        """Running sums of block ``k``'s coefficients, shape (24, n + 1) (n samples in the
        file's block, fewer at its end)."""
        if k in self._running:
            self._running.move_to_end(k)
            return self._running[k]
        c = read_truth(self.path, k * self.block, (k + 1) * self.block).coefficients
        running = np.zeros((len(COEFFICIENT_NAMES), c.shape[1] + 1))
        np.cumsum(c, axis=1, out=running[:, 1:])
        self._running[k] = running
        self._sums[k] = (running[:, -1].copy(), c.shape[1])
        while len(self._running) > self.RECENT:
            self._running.popitem(last=False)
        return running

    def _span(self, k: int, a: int, b: int) -> tuple[np.ndarray, int]:
        """Sum and count of samples ``[a, b)`` of the file, within block ``k``."""
        lo, hi = a - k * self.block, b - k * self.block
        if lo == 0 and hi == self.block and k in self._sums:
            return self._sums[k]
        running = self._block(k)
        n = running.shape[1] - 1
        lo, hi = min(lo, n), min(hi, n)
        return running[:, hi] - running[:, lo], hi - lo

    def mean(self, t_start: float, t_stop: float) -> np.ndarray | None:
        """Average true coefficients over ``[t_start, t_stop)`` [m/rad], shape (24,); None
        if the span holds no sample of the file."""
        a = max(0, int(math.ceil((t_start - self.t0) * self.fs - 1e-9)))
        b = int(math.ceil((t_stop - self.t0) * self.fs - 1e-9))
        total, count = np.zeros(len(COEFFICIENT_NAMES)), 0
        for k in range(a // self.block, -(-b // self.block)) if b > a else ():
            s, n = self._span(k, max(a, k * self.block), min(b, (k + 1) * self.block))
            total, count = total + s, count + n
        return total / count if count else None


def window_truth(truth, block: float = 3600.0) -> ModelTruth | FileTruth:
    """The truth a telemetry message's meta names (``meta.truth``): a coefficient model
    description ``{"coefficients": ...}`` (a simulation on the fly) or the path of a truth
    file, read in blocks of ``block`` seconds.

    Raises
    ------
    ConfigError, TelemetryError
        If the description or the file is unusable (the message names it).
    """
    if isinstance(truth, dict):
        return ModelTruth(CoefficientModel.from_description(truth["coefficients"]))
    return FileTruth(truth, block=block)
