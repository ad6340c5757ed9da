"""The fitter's window of telemetry: the segments of the rolling window, for the model's refits.

The rolling fit keeps the window's spectra; the window refit, the live diagnosis and the
rolling model's columns need the window's telemetry itself.  :class:`TelemetryWindow` keeps
it, segment by segment in index order, for one window duration; a missing segment is held
as NaN readouts (the light travel times held), and the window joins into one series as
``ttl refit`` builds it from the recorded segments (:meth:`TelemetryWindow.joined`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from dataclasses import replace

import numpy as np

from streamer.bus.messages import concatenate_telemetry
from ttlcore.diagnose.settings import DiagnoseSettings
from ttlcore.diagnose.whitened import WhitenedData, whiten_telemetry
from ttlcore.io.telemetry import Telemetry, bridged_ltt


class TelemetryWindow:
    """The telemetry of the segments of a rolling window, ``(index, Telemetry)`` in index order.

    Parameters
    ----------
    duration : float
        The window [s]: a segment that starts more than ``duration`` (+1 s) before the newest
        one ends goes.
    """

    def __init__(self, duration: float):
        self.duration = float(duration)
        self.segments: deque[tuple[int, Telemetry]] = deque()
        #: indices of the segments that did not come (:meth:`add_gap`)
        self._gaps: set[int] = set()
        #: (source, settings, effect modules) -> the window joined and whitened, while the
        #: window stays as it is (:meth:`whitened`)
        self._whitened: tuple[tuple, Telemetry, WhitenedData] | None = None

    def __iter__(self) -> Iterator[tuple[int, Telemetry]]:
        return iter(self.segments)

    def __len__(self) -> int:
        return len(self.segments)

    @property
    def telemetry(self) -> list[Telemetry]:
        """The segments' telemetry, oldest first."""
        return [tm for _, tm in self.segments]

    @property
    def first(self) -> int:
        """Index of the oldest segment."""
        return self.segments[0][0]

    @property
    def last(self) -> int:
        """Index of the newest segment."""
        return self.segments[-1][0]

    @property
    def t_start(self) -> float:
        """Start [s] of the oldest segment."""
        return float(self.segments[0][1].t0)

    @property
    def t_stop(self) -> float:
        """End [s] of the newest segment."""
        tm = self.segments[-1][1]
        return float(tm.t0 + tm.size / tm.fs)

    def clear(self) -> None:
        """Forget every segment (a discontinuity: the window restarts)."""
        self.segments.clear()
        self._gaps.clear()
        self._whitened = None

    def add(self, index: int, tm: Telemetry) -> None:
        """Segment ``index`` joins the window; the segments now out of it go."""
        self._whitened = None
        self.segments.append((index, tm))
        self._gaps.discard(index)
        end = tm.t0 + tm.size / tm.fs
        while self.segments and self.segments[0][1].t0 < end - self.duration - 1.0:
            self._gaps.discard(self.segments.popleft()[0])

    def add_gap(self, index: int, t0: float, fs: float, n: int) -> None:
        """Segment ``index`` will not come: ``n`` samples of NaN readouts from ``t0``, the
        last light travel times held (nothing when the window is empty)."""
        if not self.segments:
            return
        self._whitened = None
        prev = self.segments[-1][1]
        blank = np.full((6, n), np.nan)
        gap = Telemetry(
            t0=t0,
            fs=fs,
            eta=blank,
            dws_phi=blank,
            dws_eta=blank,
            ltt=np.repeat(prev.ltt[:, -1:], n, axis=1),
            source=prev.source,
        )
        self.segments.append((index, gap))
        self._gaps.add(index)

    def joined(self, source: str) -> Telemetry:
        """The window's telemetry, one series (:func:`streamer.bus.messages.concatenate_telemetry`:
        the same as ``ttl refit`` builds from the recorded segments); the light travel times
        of the segments that did not come bridged between those around them
        (:func:`ttlcore.io.telemetry.bridged_ltt`: held, they step at the gap's end and spoil
        the TDI of the hours after it)."""
        tm = concatenate_telemetry(self.telemetry, source=source)
        missing = np.concatenate([np.full(seg.size, index in self._gaps) for index, seg in self.segments])
        if not missing.any():
            return tm
        return replace(tm, ltt=bridged_ltt(tm.ltt, missing))

    def whitened(
        self, source: str, settings: DiagnoseSettings, effect_modules=(), *, keep: bool = True
    ) -> tuple[Telemetry, WhitenedData]:
        """The window joined (:meth:`joined`) and its whitened data
        (:func:`ttlcore.diagnose.whitened.whiten_telemetry`: the TDI of the data and the 24
        regressors, their spectra, the instrument noise model), built once while the window
        and ``settings`` stay as they are: the window refit and the live diagnosis of one
        segment share them (a day's: 3.5 s of CPU built once, not twice).  ``keep`` False: the
        window lets them go (the caller's are the last references), as :meth:`release` does."""
        key = (source, settings, tuple(effect_modules))
        if self._whitened is None or self._whitened[0] != key:
            self._whitened = None  # the old window's freed before the new one is built
            tm = self.joined(source)
            self._share(tm)
            self._whitened = (key, tm, whiten_telemetry(tm, settings, effect_modules))
        _, tm, data = self._whitened
        if not keep:
            self._whitened = None
        return tm, data

    def _share(self, tm: Telemetry) -> None:
        """The segments become views of the joined window ``tm``: the window's telemetry is
        held once through a diagnosis, not twice (a day's: 66 MB).  The old series go when
        nothing else holds them; a later join copies from the views, the same numbers."""
        a = 0
        for i, (index, seg) in enumerate(self.segments):
            b = a + seg.size
            self.segments[i] = (
                index,
                replace(
                    seg, eta=tm.eta[:, a:b], dws_phi=tm.dws_phi[:, a:b], dws_eta=tm.dws_eta[:, a:b], ltt=tm.ltt[:, a:b]
                ),
            )
            a = b

    def release(self) -> None:
        """Let the whitened window of :meth:`whitened` go (after the segment that used it)."""
        self._whitened = None
