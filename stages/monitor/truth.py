"""The truth the monitor draws beside the fits: the true coefficients averaged over each window.

When the telemetry meta names a truth (a truth file, or a simulation's coefficient model:
:func:`ttlcore.estimate.monitoring.window_truth`), every fit is drawn with the true
coefficients averaged over the window it fitted.  :class:`FitTruth` holds that truth and the
windows of the fits drawn so far, so that the fits drawn before the truth became known (a
late joiner) are drawn again with it (:meth:`FitTruth.redraw`).  A truth that fails to give
a window's average is dropped: no more truth is drawn.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping

import numpy as np

from ttlcore.estimate.monitoring import FileTruth, ModelTruth, window_truth


class FitTruth:
    """The truth named by the telemetry, and the windows of the fits drawn.

    Parameters
    ----------
    warn : callable
        Called with a message when the truth fails (the monitor's log in the recording).

    Attributes
    ----------
    truth : ModelTruth or FileTruth or None
        The truth (:mod:`ttlcore.estimate.monitoring`), None while none is known or usable.
    source : str or dict or None
        What the telemetry meta named last (a file, or a simulation's coefficient model).
    windows : dict of int to (float, float, ndarray, ndarray)
        Fit index -> the window drawn [s] and its coefficients and sigma [m/rad].
    """

    def __init__(self, warn: Callable[[str], None]):
        self.warn = warn
        self.truth: ModelTruth | FileTruth | None = None
        self.source: str | Mapping | None = None
        self.windows: dict[int, tuple[float, float, np.ndarray, np.ndarray]] = {}

    def is_new(self, named) -> bool:
        """True when the telemetry meta names a truth other than the last one named."""
        return bool(named) and named != self.source

    def load(self, named, block: float) -> None:
        """Take the truth ``named`` (a file, or a simulation's coefficient model) with time
        blocks of ``block`` [s]; an exception when it is unusable."""
        self.truth = window_truth(named, block=block)

    def add_fit(self, index: int, t_start: float, t_stop: float, coefficients, sigma) -> None:
        """A fit drawn: its window kept, to be drawn again when a truth becomes known later."""
        self.windows[index] = (float(t_start), float(t_stop), np.array(coefficients, float), np.array(sigma, float))

    def mean(self, t_start: float, t_stop: float):
        """The true coefficients [m/rad] averaged over a fit window, or None (no truth known,
        none for that window, or the truth failed: then no more truth is drawn)."""
        if self.truth is None:
            return None
        try:
            return self.truth.mean(t_start, t_stop)
        except Exception as exc:
            self.warn(f"truth file {self.truth.path}: {exc}; no more truth drawn")
            self.truth = None
            return None

    def redraw(self) -> Iterator[tuple[int, float, np.ndarray, np.ndarray, np.ndarray]]:
        """The fits drawn so far, in index order, with the truth averaged over their windows:
        ``(index, centre of the window [s], coefficients, sigma, truth)``; none once the truth
        fails."""
        for index, (t_start, t_stop, coefficients, sigma) in sorted(self.windows.items()):
            if self.truth is None:
                return
            truth = self.mean(t_start, t_stop)
            if truth is None:
                continue
            yield index, 0.5 * (t_start + t_stop), coefficients, sigma, truth
