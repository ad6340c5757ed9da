"""What a stage does about a damaged copy, and about many refused ones (issue 33).

A copy whose payload does not match its header (size, checksum) is asked for again from
its producer's cache (:func:`streamer.bus.segment_stream.refetch_segment`).  The header is the
sender's word, and a sender with a producer's key can send thousands of them: each re-fetch
costs the producer one segment's bytes, so a re-fetch is asked only when
:class:`RefetchBudget` allows it:

* the index exists in the run's plan (``0 <= index < segments_total``) and lies within the
  stage's index window (``floor .. highest + window`` of :class:`streamer.runtime.plan.Validator`),
  and the stage has not processed it already (a damaged copy of a used segment needs
  nothing);
* the header names the topic's producer (the plan's);
* at most :data:`MAX_REFETCHES` per segment, and per producer a budget of
  :data:`REFETCH_BURST` re-fetches that grows back by one every :data:`REFETCH_PERIOD`
  seconds: a bounded rate, whatever indices the copies name.  The per-segment counts are
  kept for the indices still inside the window (a copy below it is refused as too late by
  the validator before it could be asked for), so none is forgotten while it could count.

:class:`ReportLimiter` bounds what the refused copies leave in the recording: the first
:data:`REPORTS_PER_CAUSE` reports of one cause (kind and field) from one producer are
recorded as they come; further ones are counted and recorded as one ``suppressed`` warning
per cause and producer, with the count, every :data:`SUPPRESSED_EVERY` seconds and when the
stage stops.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

from ..bus.topology import PRODUCERS

#: Re-fetches of one segment at most.
MAX_REFETCHES = 3
#: Re-fetches one producer's damaged copies may cause at once (the budget's size).
REFETCH_BURST = 8
#: Seconds for one re-fetch of a producer's budget to grow back.
REFETCH_PERIOD = 5.0
#: Refused messages of one cause from one producer recorded one by one; beyond, counted.
REPORTS_PER_CAUSE = 500
#: Seconds between two ``suppressed`` records of one cause.
SUPPRESSED_EVERY = 10.0


def refetch_refusal(
    index: int,
    producer: str,
    owner: str | None,
    *,
    total: int | None,
    floor: int,
    ceiling: int | None,
    done: bool,
) -> str | None:
    """Why segment ``index`` of a damaged copy from ``producer`` is not asked for again, or
    None when it may be (module docstring).

    Parameters
    ----------
    index : int
        The index the damaged copy's header names.
    producer, owner : str
        The header's producer, and the topic's (None: not known, anything goes).
    total : int or None
        Segments of the run (the plan), None when not known yet.
    floor, ceiling : int
        The stage's index window: copies below ``floor`` are refused as too late, above
        ``ceiling`` (None: no segment accepted yet) as too far ahead.
    done : bool
        The stage has processed segment ``index`` already.
    """
    if owner is not None and producer != owner:
        return f"producer {producer!r} is not the topic's ({owner!r})"
    if index < 0 or (total is not None and index >= total):
        return f"segment {index} is not in the run's plan ({total} segments)"
    if index < floor or (ceiling is not None and index > ceiling):
        return f"segment {index} is outside the index window {max(floor, 0)}..{ceiling}"
    if done:
        return f"segment {index} was processed already"
    return None


@dataclass
class RefetchBudget:
    """Per-segment and per-producer limits of the re-fetches (module docstring).

    ``clock``: the time source [s] (tests pass their own).
    """

    per_index: int = MAX_REFETCHES
    burst: int = REFETCH_BURST
    period: float = REFETCH_PERIOD
    clock: Callable[[], float] = time.monotonic
    #: Re-fetches asked per (stream key, index), for indices at or above the window's floor.
    asked: dict[tuple[str, int], int] = field(default_factory=dict)
    #: Producer -> (budget left, when it was last counted).
    _budget: dict[str, tuple[float, float]] = field(default_factory=dict)
    #: Re-fetches refused by the budget, per producer.
    refused: dict[str, int] = field(default_factory=dict)

    def take(self, stream: str, index: int, producer: str, floor: int) -> int:
        """Count one re-fetch of segment ``index`` of ``stream`` from ``producer``: returns
        its attempt number (1, 2, ...), or 0 when the segment's attempts or the producer's
        budget are used up (nothing counted then).  ``floor``: the lowest index still in the
        stage's window (counts below it are dropped: no copy that old is asked for)."""
        tries = self.asked.get((stream, index), 0)
        if tries >= self.per_index:
            return 0
        now = self.clock()
        left, then = self._budget.get(producer, (float(self.burst), now))
        left = min(float(self.burst), left + (now - then) / self.period)
        if left < 1.0:
            self._budget[producer] = (left, now)
            self.refused[producer] = self.refused.get(producer, 0) + 1
            return 0
        self._budget[producer] = (left - 1.0, now)
        self.asked[(stream, index)] = tries + 1
        if len(self.asked) > 4 * self.burst and any(i < floor for _, i in self.asked):
            self.asked = {k: n for k, n in self.asked.items() if k[1] >= floor}
        return tries + 1


def topic_owner(topic: str, plan) -> str | None:
    """The producer of ``topic`` in the run's plan (:data:`streamer.bus.topology.PRODUCERS` for
    a topic the plan does not name); None without a plan (a stage run on its own trusts the
    first producer it meets, :class:`streamer.runtime.plan.Validator`: anything goes here)."""
    if plan is None:
        return None
    return plan.producers.get(topic, PRODUCERS.get(topic))


#: The producer of a refused message that does not name its topic's (or names none).
OTHER_SENDER = "(not the topic's producer)"


def sender(producer: object, owner: str | None) -> str:
    """The producer a refused message is counted under: the topic's own when it names it,
    else :data:`OTHER_SENDER` (a sender picks the name it writes: counting by that name would
    let it make a new cause of every message)."""
    return producer if isinstance(producer, str) and producer == owner else OTHER_SENDER


class ReportLimiter:
    """Bounds the records of refused messages: per (producer, kind, field), the first
    ``limit`` go through, the others are counted (module docstring)."""

    def __init__(
        self,
        limit: int = REPORTS_PER_CAUSE,
        every: float = SUPPRESSED_EVERY,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.limit = limit
        self.every = every
        self.clock = clock
        self.seen: dict[tuple[str, str, str], int] = {}
        #: Cause -> (counted since the last ``suppressed`` record, when that record was made).
        self.pending: dict[tuple[str, str, str], tuple[int, float]] = {}

    def admit(self, producer: str, kind: str, field: str | None) -> bool:
        """Whether to record this report one by one (False: it is counted).  ``producer``:
        the topic's producer when the message names it, else one name for all others
        (:func:`sender`): the causes are as few as the code's kinds and fields."""
        cause = (producer, kind, str(field))
        n = self.seen.get(cause, 0) + 1
        self.seen[cause] = n
        if n <= self.limit:
            return True
        count, last = self.pending.get(cause, (0, self.clock()))
        self.pending[cause] = (count + 1, last)
        return False

    def due(self, final: bool = False) -> list[tuple[str, str, str, int]]:
        """Causes with suppressed reports to record now, ``(producer, kind, field, count)``;
        all of them when ``final``."""
        now = self.clock()
        out = []
        for cause, (count, last) in list(self.pending.items()):
            if count and (final or now >= last + self.every):
                out.append((*cause, count))
                self.pending[cause] = (0, now)
        return out
