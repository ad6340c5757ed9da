"""When the monitor is done with a segment: waiting for alive producers, and giving up.

The monitor's output of segment ``i`` (``monitor/<i>``) goes once its TDI is drawn and its
fit and residual are drawn too, or will not come.  They are waited for only from a fitter /
subtractor that reports progress or is alive (its liveliness token): a stage that is skipped
or not started blocks nothing.  A wait ends without the input only when its producer has
been gone for ``settle_timeout`` seconds, or a sample was lost beyond recovery (a ``missed``
error) and ``settle_timeout`` has passed since; an input that could not be drawn, or whose
copies conflicted, is not waited for.  :class:`Settling` keeps what was drawn, refused and
could not be handled, and says for each segment whether it is done, failed or still waits
(:meth:`Settling.ready`); the monitor publishes, records and marks progress.
"""

from __future__ import annotations

from collections.abc import Iterator

from streamer.runtime.rangeset import RangeSet

#: Producer of each topic the monitor waits for.
PRODUCERS = {"fit": "fitter", "residual": "subtractor"}
#: Producer of each input topic the monitor catches up when it does not come
#: (:meth:`Settling.announced`: the cache, then the producer's recordings).
RECORDED = {"tdi": "tdi_builder", "fit": "fitter", "residual": "subtractor"}


class Settling:
    """The monitor's bookkeeping of which segments are settled (module docstring).

    Parameters
    ----------
    inputs : sequence of str
        The monitor's input topics.
    settle_timeout : float
        How long [s] a gone producer, or a sample lost beyond recovery, is waited for.

    Attributes
    ----------
    drawn, refused, unhandled : dict of str to set of int
        Per topic, the segments drawn, withdrawn (conflicting copies: not waited for) and
        whose drawing raised (the error recorded: not waited for).
    since : dict of int to float
        When (monotonic [s]) each segment began to wait with its producer gone or a loss seen.
    """

    def __init__(self, inputs, settle_timeout: float = 60.0):
        self.settle_timeout = float(settle_timeout)
        self.drawn: dict[str, set[int]] = {t: set() for t in inputs}
        self.refused: dict[str, set[int]] = {t: set() for t in inputs}
        self.unhandled: dict[str, set[int]] = {t: set() for t in inputs}
        self.since: dict[int, float] = {}

    def waiting_for(self, i: int, board: dict, alive: set[str]) -> str | None:
        """What segment ``i`` (its TDI drawn) still waits for before it is done, or None.

        The fit and the residual of ``i`` are waited for only from a fitter / subtractor
        that reports progress (``board``) or is alive (``alive``), so a skipped or not
        started stage blocks nothing: until it has passed ``i``, and then for what it
        published (the subtractor's residual, the fitter's fit if it made one, ``fits`` of
        its progress).  A stage that is alive but has not reported yet (a fitter still on its
        first segment) is waited for: the monitor would otherwise settle the first segments
        without their fits and residuals.
        """
        for stage, topic, made in (
            ("fitter", "fit", lambda p: p.extra.get("fits", set())),
            ("subtractor", "residual", lambda p: p.done),
        ):
            peer = board.get(stage)
            if peer is None:
                if stage in alive and i not in self.refused[topic]:
                    return topic
                continue
            settled = self.drawn[topic] | self.refused[topic] | self.unhandled[topic]
            if i in made(peer) and i not in settled:
                return topic
            if not peer.complete and i not in peer.handled:
                return topic
        return None

    def give_up(self, waiting: str, since: float, now: float, alive: set[str], last_miss: float | None) -> str | None:
        """Why a segment waiting since ``since`` stops waiting for its ``waiting`` input, or None
        to go on.

        Never while the producer is alive and nothing was lost (a loaded machine may take
        minutes; the publisher's cache and Zenoh's recovery deliver it): only when the
        producer's liveliness token has been gone for ``settle_timeout`` seconds, or when a
        sample was lost beyond recovery (``last_miss``, a ``missed`` error) since the wait
        began and ``settle_timeout`` has passed since.
        """
        stage = PRODUCERS[waiting]
        if now - since < self.settle_timeout:
            return None
        if stage not in alive:
            return f"{stage} gone for {self.settle_timeout:g} s"
        if last_miss is not None and last_miss >= since - self.settle_timeout:
            return f"lost beyond recovery ({self.settle_timeout:g} s after a missed-samples report)"
        return None

    def ready(
        self, board: dict, handled: RangeSet | set[int], alive: set[str], last_miss: float | None, now: float
    ) -> Iterator[tuple[int, str, str | None, str | None]]:
        """The drawn segments not ``handled`` yet that wait for nothing more, in index order:
        ``(i, "done", None, None)``; ``(i, "unhandled", None, None)`` when its fit or residual
        could not be drawn (a failed segment, the error recorded); ``(i, "gone", waiting,
        why)`` when its ``waiting`` input will not come (:meth:`give_up`).  A segment whose
        producer is there and nothing was lost waits on, its wait starting again."""
        for i in sorted(self.drawn["tdi"] - handled):
            waiting = self.waiting_for(i, board, alive)
            if waiting is not None:
                since = self.since.setdefault(i, now)
                if PRODUCERS[waiting] in alive and last_miss is None:
                    self.since[i] = now  # the producer is there: the wait is not over
                    continue
                why = self.give_up(waiting, since, now, alive, last_miss)
                if why is not None:
                    yield i, "gone", waiting, why
                continue
            if any(i in self.unhandled[t] for t in ("fit", "residual")):
                yield i, "unhandled", None, None
                continue
            yield i, "done", None, None

    def announced(self, board) -> dict[str, tuple[str, RangeSet]]:
        """Per input topic the monitor catches up when a segment does not come
        (:meth:`streamer.runtime.pipeline_stage.PipelineStage.fetch_announced`): its producer and what
        the producer's progress on ``board`` says it published (the fitter's ``fits``)."""
        out: dict[str, tuple[str, RangeSet]] = {}
        for topic, stage in RECORDED.items():
            peer = board.get(stage)
            if peer is not None and topic in self.drawn:
                out[topic] = (stage, peer.extra.get("fits", RangeSet()) if topic == "fit" else peer.done)
        return out

    def needed(self, topic: str, i: int) -> bool:
        """Whether segment ``i`` of ``topic`` is still waited for: neither drawn, refused nor
        failed to draw here."""
        return i not in self.drawn[topic] and i not in self.refused[topic] and i not in self.unhandled[topic]

    def forget(self, i: int) -> None:
        """Segment ``i`` is settled: its bookkeeping goes (memory flat in a long run)."""
        self.since.pop(i, None)
        for topic in ("fit", "residual"):
            self.unhandled[topic].discard(i)

    def pending(self, handled: RangeSet | set[int]) -> int:
        """Segments drawn and not yet ``handled``."""
        return len(self.drawn["tdi"] - handled)
