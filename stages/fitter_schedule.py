"""When the fitter diagnoses its window: the cadence, the sustained excess that brings the
diagnosis forward, and the run's last segment (``docs/diagnostics.md``, "A model that lives
for weeks").  A state object with no bus in it: the stage records what it decides."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["MIN_FIRST", "SUSTAINED_OUTLIERS", "DiagnosisSchedule"]

#: FFT segments in a row left out of the rolling fit as outliers that make a sustained excess.
SUSTAINED_OUTLIERS = 3
#: The first diagnosis at half the cadence only when that many segments or more are in the
#: window by then (a short cadence is its own first diagnosis).
MIN_FIRST = 6


@dataclass
class DiagnosisSchedule:
    """The live diagnosis' schedule.

    Parameters
    ----------
    every : int
        ``--diagnose-every``: the window is diagnosed every ``every`` segments, counted by
        index (0: never), and the first time at half of it when that is :data:`MIN_FIRST`
        segments or more: with 1-h segments and the default 24, at 12 h (a model adopted then
        is fitted and subtracted for the rest of a one-day file), then at the end of every day.
    sustained : int
        Outliers in a row that bring the diagnosis forward (:meth:`outlier`).

    Attributes
    ----------
    outlier_run : int
        FFT segments in a row the rolling fit left out as outliers, up to now.
    """

    every: int
    sustained: int = SUSTAINED_OUTLIERS
    outlier_run: int = 0

    def due(self, index: int, *, last: bool, new_model: bool) -> bool:
        """Whether segment ``index`` is diagnosed: on the cadence above, on the first
        segment of a new model or a sustained excess (``new_model``: the model's own flag),
        and on the run's ``last`` segment (its advice stands in the recordings)."""
        if self.every <= 0:
            return False
        return (
            new_model
            or (index + 1) % self.every == 0
            or (self.every // 2 >= MIN_FIRST and index + 1 == self.every // 2)
            or last
        )

    def outlier(self, excluded: dict | None) -> bool:
        """Count a fit's left-out FFT segment (the rolling fit's ``extra["excluded"]``: an
        outlier carries its ``z``; a gate or a gap does not, and ends the run of outliers).
        True once, when the run reaches :attr:`sustained`: a sustained excess - a coupling
        that switched on, a noise change, a long chirp - is no transient, and the window is
        diagnosed now instead of at its slot."""
        self.outlier_run = self.outlier_run + 1 if excluded and "z" in excluded else 0
        return self.outlier_run == self.sustained
