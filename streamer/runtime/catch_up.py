"""Input segments a producer announced that never came: its cache, then its recordings, then lost.

A stage learns from its producers' progress (:mod:`streamer.runtime.progress`) which segments they
published.  One announced there that has not come may never come on its own: a late
joiner's history query lost under load, or a stage restarted after its producer's cache
moved on.  A publisher's cache keeps the last ``cache`` segments *of its process*
(:mod:`streamer.bus.segment_stream`): a producer restarted since loses everything its earlier
process published, however recent.  A monitor restarted after the fitter had been
restarted waited for fits no cache held, as long as the fitter lived (issue 33: the chaos
run with model changes never ended).

:class:`CatchUp` is the rule every pipeline stage follows for such a segment
(:meth:`streamer.runtime.pipeline_stage.PipelineStage.fetch_announced` drives it):

1. missing for :data:`ANNOUNCED_FETCH_AFTER` seconds: asked of the producer's cache, once
   (:meth:`streamer.runtime.stage.Stage.fetch`, within the re-fetch budget);
2. still missing when the cache query is over with no copy, when it could not be asked
   (the budget, the index window), or :data:`CACHE_ANSWER_WITHIN` seconds after it was
   asked: read from the producer's recordings in the run directory
   (:func:`streamer.recording.recorded_inputs.recorded_copies`), the copy of last resort, and handed to
   the stage as if it had arrived (a ``recovered`` event);
3. in no recording either (a producer on another host): given up, once, with an
   ``input-lost`` warning naming the segment and why; the stage settles the segment without
   it (:meth:`streamer.runtime.pipeline_stage.PipelineStage.input_lost`: a failed segment, so ``ttl
   run`` does not exit 0).

A segment that *came*, passed the checks of its copy and then failed here (the stage's
``handle`` raised: reported as ``failed``) is neither missing nor handled: the cache and the
recordings hold the same copy, which would fail again.  It waits :data:`ANNOUNCED_FETCH_AFTER`
seconds for a good copy (a forged copy can come before the real one), and once its producer's
progress has it as published, it is given up as in step 3 (:meth:`CatchUp.unusable`).  Before,
a stage whose ``handle`` failed on every segment held the run until it timed out: nothing
was missing, nothing was handled, and an ordered stage's queue never started.

It holds the bookkeeping only (no bus, no file): the caller says what is missing now, and
what happened to the questions it asked.
"""

from __future__ import annotations

from collections.abc import Container, Mapping
from dataclasses import dataclass

__all__ = ["ANNOUNCED_FETCH_AFTER", "CACHE_ANSWER_WITHIN", "CatchUp"]

#: An input segment its producer's progress announced (published) that has not come after
#: this long [s] is asked for from its cache, once: a late joiner's history query can be lost
#: on a loaded machine (CI, 2026-11-28: six tdi segments never reached a subtractor started
#: half-way through the replay, and the run timed out waiting for them).
ANNOUNCED_FETCH_AFTER = 10.0
#: After this long [s] without the cache query's end, a segment asked for that has still not
#: come is read from the recordings (the query's own timeout is 30 s:
#: :data:`streamer.bus.segment_stream.REFETCH_TIMEOUT`).
CACHE_ANSWER_WITHIN = 40.0


@dataclass
class _Missing:
    """One announced segment not received: since when [monotonic s], when it was asked of the
    cache (None: not yet), whether the cache could be asked, the copies the query brought (None:
    not over), whether the recordings were read for it."""

    since: float
    asked_at: float | None = None
    asked: bool = False
    copies: int | None = None
    recorded: bool = False


@dataclass
class _Unusable:
    """A segment that came and failed here: since when [monotonic s] and why."""

    since: float
    why: str


class CatchUp:
    """Which missing announced segments to ask of the cache and which to read from the
    recordings, and when (module docstring).

    Parameters
    ----------
    fetch_after : float
        Seconds a segment is missing before its cache is asked.
    answer_within : float
        Seconds after the question before the recordings are read without its answer.
    """

    def __init__(self, fetch_after: float = ANNOUNCED_FETCH_AFTER, answer_within: float = CACHE_ANSWER_WITHIN):
        self.fetch_after = float(fetch_after)
        self.answer_within = float(answer_within)
        self._missing: dict[tuple[str, int], _Missing] = {}
        self._unusable: dict[tuple[str, int], _Unusable] = {}

    def step(self, missing: dict[str, set[int]], now: float) -> tuple[list[tuple[str, int]], dict[str, set[int]]]:
        """What to do now about the segments ``missing`` (per topic: announced by the producer,
        neither received nor handled): ``(ask, read)``, the ``(topic, index)`` to ask of the
        cache (report each with :meth:`asked`) and, per topic, the indices to read from the
        recordings (each read once).  A segment no longer missing is forgotten; one seen
        missing again later starts afresh."""
        now = float(now)
        wanted = {(t, i) for t, indices in missing.items() for i in indices}
        self._missing = {k: self._missing.get(k) or _Missing(now) for k in wanted}
        ask: list[tuple[str, int]] = []
        read: dict[str, set[int]] = {}
        for (topic, index), m in sorted(self._missing.items()):
            if m.recorded:
                continue
            if m.asked_at is None:
                if now >= m.since + self.fetch_after:  # deadlines, not differences: exact at the deadline
                    ask.append((topic, index))
                continue
            if not m.asked or m.copies == 0 or now >= m.asked_at + self.answer_within:
                m.recorded = True
                read.setdefault(topic, set()).add(index)
        return ask, read

    def asked(self, topic: str, index: int, sent: bool, now: float) -> None:
        """Segment ``index`` of ``topic`` was asked of the cache (``sent``), or could not be
        (the re-fetch budget, the index window: the recordings are next)."""
        m = self._missing.get((topic, index))
        if m is not None:
            m.asked_at, m.asked = float(now), bool(sent)

    def answered(self, topic: str, index: int, copies: int) -> None:
        """The cache query for segment ``index`` of ``topic`` is over: ``copies`` came."""
        m = self._missing.get((topic, index))
        if m is not None and m.asked:
            m.copies = int(copies)

    def waiting(self) -> int:
        """Segments missing and not yet read from the recordings."""
        return sum(not m.recorded for m in self._missing.values())

    def failed_here(self, topic: str, index: int, why: str, now: float) -> None:
        """Segment ``index`` of ``topic`` came and failed here (``why``): waited for a good copy
        from now (the first failure), then given up (:meth:`unusable`)."""
        key = (topic, index)
        if key in self._unusable:
            self._unusable[key].why = why
        else:
            self._unusable[key] = _Unusable(float(now), why)

    def unusable(
        self, published: Mapping[str, Container[int]], arrived: Mapping[str, Container[int]], now: float
    ) -> list[tuple[str, int, str]]:
        """The segments that failed here to give up now, ``(topic, index, why)``, each once.

        A segment a good copy of which has since been handled (in ``arrived``, per topic) is
        forgotten.  One is given up :attr:`fetch_after` seconds after its first failure, when
        its producer's progress has it (``published``, per topic: a forged copy ahead of the real
        segment is not a reason to give the real one up); a topic with no producer known here
        is given up on time alone.
        """
        out = []
        for key, u in sorted(self._unusable.items()):
            topic, index = key
            if index in arrived.get(topic, ()):
                del self._unusable[key]
            elif now >= u.since + self.fetch_after and (topic not in published or index in published[topic]):
                del self._unusable[key]
                out.append((topic, index, u.why))
        return out
