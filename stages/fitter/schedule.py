"""When the fitter diagnoses its window: the cadence, the sustained excess that brings the
diagnosis forward, and the run's last segment (``docs/diagnostics.md``, "A model that lives
for weeks").  A state object with no bus in it: the stage records what it decides."""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["MIN_FIRST", "SUSTAINED_OUTLIERS", "TRANSIENT_SPACING", "DiagnosisSchedule"]

#: FFT segments in a row left out of the rolling fit as outliers that make a sustained excess.
SUSTAINED_OUTLIERS = 3
#: The first diagnosis at half the cadence only when that many segments or more are in the
#: window by then (a short cadence is its own first diagnosis).
MIN_FIRST = 6
#: A model that only gained transients (gates, glitches) is diagnosed this many segments after
#: its first, not on it: an excess that goes on to the window's end (a coupling that switched
#: on an hour ago) was otherwise gated again at every segment, each time by a diagnosis of
#: several minutes (bench/mission.py: segments 72-74 of a week took 2, 5.5 and 8+ min).
#: Only when a transient added reaches the window's last that many segments: one seen whole
#: inside the window waits for the next slot.
TRANSIENT_SPACING = 3


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
    pending_from : int or None
        A diagnosis put off to this segment (:meth:`later`).
    last_done : int or None
        The segment of the last diagnosis (:meth:`done`).
    previous, current : int or None
        The segment before the one in hand, and the one in hand (:meth:`arrive`): a slot that
        fell in between (in a gap, or segments stepped over) is kept at the first segment after.
    since_done : set of int
        The segments in hand since the last diagnosis (:meth:`arrive`, :meth:`done`).
    """

    every: int
    sustained: int = SUSTAINED_OUTLIERS
    outlier_run: int = 0
    pending_from: int | None = None
    last_done: int | None = None
    previous: int | None = None
    current: int | None = None
    since_done: set[int] = field(default_factory=set)

    def arrive(self, index: int) -> None:
        """Segment ``index`` is in hand (once per segment, before :meth:`due` is asked)."""
        if index != self.current:
            self.previous, self.current = self.current, index
        if self.every > 0:
            self.since_done.add(index)

    def later(self, index: int) -> None:
        """Diagnose at segment ``index`` (or at the slot before it): a model that only gained
        transients waits :data:`TRANSIENT_SPACING` segments."""
        self.pending_from = index if self.pending_from is None else min(self.pending_from, index)

    def done(self, index: int, first: int | None = None) -> list[int]:
        """A diagnosis ran at segment ``index`` on a window from segment ``first``: what was
        put off is done.  Returns the segments in hand since the previous diagnosis that the
        window no longer held: they were in no diagnosed window (a slot that fell in a gap is
        taken at the first segment after it, whose window starts after them)."""
        missed = sorted(i for i in self.since_done if first is not None and i < first)
        self.since_done.clear()
        self.pending_from = None
        self.last_done = index
        return missed

    def due(self, index: int, *, last: bool, new_model: bool) -> bool:
        """Whether segment ``index`` is diagnosed: on the cadence above (a slot passed since
        the previous segment in hand, in a gap or segments stepped over, falls on this one), on
        the first segment of a new model or a sustained excess (``new_model``: the model's own
        flag), from a segment put off to (:meth:`later`), and on the run's ``last`` segment when
        half a cadence or more has passed since the last diagnosis (its advice stands in the
        recordings; a short run is not diagnosed at its end)."""
        if self.every <= 0:
            return False
        before = self.previous if self.current == index and self.previous is not None else index - 1
        half = self.every // 2
        return (
            new_model
            or (index + 1) // self.every > (before + 1) // self.every
            or (half >= MIN_FIRST and before + 1 < half <= index + 1)
            or (self.pending_from is not None and index >= self.pending_from)
            or (last and index - (-1 if self.last_done is None else self.last_done) >= max(1, self.every // 2))
        )

    def outlier(self, excluded: dict | None) -> bool:
        """Count a fit's left-out FFT segment (the rolling fit's ``extra["excluded"]``: an
        outlier carries its ``z``; a gate or a gap does not, and ends the run of outliers).
        True once, when the run reaches :attr:`sustained`: a sustained excess - a coupling
        that switched on, a noise change, a long chirp - is no transient, and the window is
        diagnosed now instead of at its slot."""
        self.outlier_run = self.outlier_run + 1 if excluded and "z" in excluded else 0
        return self.outlier_run == self.sustained
