"""Pipeline stages: stages that report progress, and stages that handle segments in index order.

A :class:`PipelineStage` is a :class:`streamer.runtime.stage.Stage` that publishes its progress
after every segment it handles (published or given up) and follows the progress of the stages
it names in :attr:`PipelineStage.follow` (:mod:`streamer.runtime.progress`).  An
:class:`OrderedStage` puts its input back in index order (:class:`InOrder`) before processing
it, as TDI with history and the rolling fit need.  The stage programs (:mod:`stages`) subclass
these; what a stage publishes and whom it follows comes from :mod:`streamer.bus.topology`.
"""

from __future__ import annotations

import itertools
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import ClassVar, Generic, TypeVar, cast

import zenoh

from ..bus.keys import board_key, progress_key, progress_pattern, segment_key, stream_key, to_ranges
from ..bus.segment_record import segments_total_of
from ..bus.segment_stream import declare_segment_publisher
from ..bus.topology import OUTPUT_TOPIC, PRODUCERS, UPSTREAM
from ..recording.recorded_inputs import recorded_copies, wire_copy
from ..recording.recording_reader import RecordedSegment
from .catch_up import ANNOUNCED_FETCH_AFTER, CatchUp
from .lifecycle import StageStopping, disk_full
from .memtrace import MemoryTrace
from .plan import MAX_SEGMENTS
from .progress import Progress, ProgressBoard, key_stage
from .rangeset import RangeSet
from .stage import Stage, StageConfig
from .stage_options import OrderedOptions, StageOptions

__all__ = ["ANNOUNCED_FETCH_AFTER", "InOrder", "OrderedStage", "PipelineStage"]


class InOrder:
    """Reorder buffer: hands out items in index order.

    The first index is 0 if it arrives first; otherwise (a stage joining late or restarted,
    whose history comes from several publisher caches in any order) the lowest index
    received within ``settle`` seconds of the first arrival, or :attr:`start_at` when lower
    (a restarted stage: the segments after its earlier process's may be in no cache).  A missing index is skipped when
    ``skip(index)`` says it will not come (the producer gave it up), or after
    ``gap_timeout`` seconds while later indices wait, and at once when it was withdrawn
    (:meth:`withdraw`).
    """

    def __init__(self, settle: float = 1.0, gap_timeout: float = 60.0):
        self.settle = float(settle)
        self.gap_timeout = float(gap_timeout)
        self.pending: dict[int, object] = {}
        self.next: int | None = None
        self._first_arrival: float | None = None
        self._gap_since: float | None = None
        self.skipped_reason = ""
        self.withdrawn: dict[int, str] = {}  # index -> why it is skipped
        #: The first index to hand out when known before any arrives (a restarted stage: the
        #: first its earlier process did not handle); None: the lowest received (docstring).
        self.start_at: int | None = None

    def withdraw(self, index: int, reason: str) -> bool:
        """Skip ``index`` (dropping its item if buffered) when its turn comes; False when it
        was handed out already.  A withdrawn index counts as arrived for the queue's start:
        a stream whose every segment is withdrawn still goes through them in order."""
        if self.next is not None and index < self.next:
            return False
        if self._first_arrival is None:
            self._first_arrival = time.monotonic()
        self.pending.pop(index, None)
        self.withdrawn[index] = reason
        return True

    def add(self, index: int, item) -> bool:
        """Buffer ``item``; False when ``index`` is behind the current position (stale)."""
        if self.next is not None and index < self.next:
            return False
        if self._first_arrival is None:
            self._first_arrival = time.monotonic()
        self.pending[index] = item
        return True

    def ready(self, skip: Callable[[int], bool] = lambda i: False, total: int | None = None):
        """Yield ``(index, item)`` in order; ``item`` is None for an index given up, with
        ``self.skipped_reason`` saying why."""
        now = time.monotonic()
        if not self._started(now):
            return
        while (index := self.next) is not None:
            if index in self.withdrawn:
                self.skipped_reason = self.withdrawn.pop(index)
                item = None
            elif index in self.pending:
                self._gap_since = None
                item = self.pending.pop(index)
            elif total is not None and index >= total:
                return
            else:
                why = self._given_up(index, skip, now)
                if why is None:
                    return  # wait for it
                self.skipped_reason, item = why, None
            self.next = index + 1
            yield index, item

    def _started(self, now: float) -> bool:
        """Whether the first index to hand out is known (set now when it is settled)."""
        if self.next is not None:
            return True
        if not self.pending and not self.withdrawn:
            return False
        first = self._first_arrival
        if first is None:  # set by the add() or withdraw() of the first index
            raise RuntimeError("in-order queue: segments pending with no arrival time")
        if 0 not in self.pending and 0 not in self.withdrawn and now - first < self.settle:
            return False
        self.next = min(self.pending.keys() | self.withdrawn.keys())
        if self.start_at is not None and self.start_at < self.next:
            self.next = self.start_at  # waited for (caught up, or skipped after gap_timeout)
        return True

    def _given_up(self, index: int, skip: Callable[[int], bool], now: float) -> str | None:
        """Why the missing ``index`` is skipped now (``skip`` says it will not come, or later
        segments waited ``gap_timeout`` for it), or None to wait for it."""
        if skip(index):
            return "given up upstream"
        if not self.pending:
            return None
        if self._gap_since is None:
            self._gap_since = now
        if now >= self._gap_since + self.gap_timeout:
            self._gap_since = None
            return f"not received within {self.gap_timeout:g} s while later segments waited"
        return None


O = TypeVar("O", bound=StageOptions)
OO = TypeVar("OO", bound=OrderedOptions)


class PipelineStage(Stage, Generic[O]):
    """A :class:`streamer.runtime.stage.Stage` that reports progress and completion (module docstring).

    Subclasses call :meth:`mark_done` / :meth:`mark_failed` for every segment they handle,
    set :attr:`segments_total` from the input meta, and may list in :attr:`follow` the
    stages whose progress they need (``"*"`` for all); :attr:`board` then holds it.
    They publish on :attr:`output_topic` and handle the segments of :attr:`upstream`.
    """

    #: Stages whose progress messages this stage subscribes to ("*": all).
    follow: ClassVar[tuple[str, ...]] = ()
    #: Per input topic, ``f(run_dir, segment) -> (payload, attachment)``: the published copy of a
    #: segment recorded in part (``Output.record_arrays``), bit for bit, or a ValueError.
    rebuilds: ClassVar[dict[str, Callable[[Path, RecordedSegment], tuple[bytes, bytes]]]] = {}
    #: Default poll interval of the pipeline stages [s].
    default_poll_interval: ClassVar[float] = 0.05
    #: The stage's options: a frozen dataclass (:mod:`streamer.runtime.stage_options`).
    options_type: ClassVar[type[StageOptions]] = StageOptions

    def __init__(self, config: StageConfig):
        super().__init__(config)
        #: The stage's options, parsed once: an unknown or bad option stops the stage at start.
        self.options: O = cast(O, self.options_type.parse(config.options, self.name))
        #: This process's progress (what it published and gave up), published after every segment.
        self.progress = Progress(
            self.stage_name, segments_total=self.validator.plan.segments_total if self.validator.plan else None
        )
        self.board = ProgressBoard()
        self._progress_pub = None
        #: Announced input segments not received: the cache, the recordings, lost (:mod:`streamer.runtime.catch_up`).
        self.late_inputs = CatchUp()
        #: Memory per segment, logged when ``TTL_MEMTRACE`` is set (:mod:`streamer.runtime.memtrace`).
        self.memtrace = MemoryTrace.from_env(self.log)

    @property
    def done(self) -> RangeSet:
        """Segments whose output this process published."""
        return self.progress.done

    @property
    def failed(self) -> RangeSet:
        """Segments this process gave up (gaps included)."""
        return self.progress.failed

    @property
    def gaps(self) -> RangeSet:
        """Segments given up for lack of data upstream."""
        return self.progress.gaps

    @property
    def segments_total(self) -> int | None:
        """Segments of the run, once known (the plan, or the inputs' meta)."""
        return self.progress.segments_total

    @segments_total.setter
    def segments_total(self, total: int | None) -> None:
        self.progress.segments_total = total

    @property
    def output_topic(self) -> str:
        """The topic this stage publishes (:data:`streamer.bus.topology.OUTPUT_TOPIC`)."""
        return OUTPUT_TOPIC[self.name]

    @property
    def upstream(self) -> str | None:
        """The stage whose segments this stage handles (:data:`streamer.bus.topology.UPSTREAM`):
        its progress says which segments were given up before reaching this one."""
        return UPSTREAM.get(self.name)

    # ------------------------------------------------------------------ lifecycle
    def setup(self) -> None:
        bus = self.live_bus
        self._progress_pub = bus.track(
            declare_segment_publisher(bus.session, progress_key(self.run_id, self.stage_name), cache=1)
        )
        if self.follow:
            pattern = progress_pattern(self.run_id, board=self.config.progress_from == "launcher")
            bus.segment_subscriber(pattern, self._on_progress, history=1)

    def refresh_progress(self, stage: str) -> None:
        """Ask the cache of ``stage``'s progress (the launcher's board of it, when the stage
        follows the board) for its latest message again; returns at once, the reply goes to
        the board as any progress message.  For a stage that waits on another's progress and
        hears nothing: a late joiner's history query can be lost on a loaded machine, and a
        stage that has finished publishes no more progress."""
        if self.bus is None:
            return
        key = (board_key if self.config.progress_from == "launcher" else progress_key)(self.run_id, stage)

        def on_reply(reply) -> None:
            if reply.ok is not None:
                self._on_progress(reply.ok)

        self.bus.session.get(
            f"{key}/@adv/pub/**",
            zenoh.handlers.Callback(on_reply, lambda: None),
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            accept_replies=zenoh.ReplyKeyExpr.ANY,  # the cache replies on the progress key
            timeout=10.0,
        )

    def _on_progress(self, sample) -> None:
        stage = key_stage(str(sample.key_expr))
        if "*" in self.follow or stage in self.follow or stage == self.stage_name:
            plan = self.validator.plan
            self.board.feed(sample, self.run_id, plan.segments_total if plan is not None else None)

    def announced_inputs(self) -> dict[str, tuple[str, RangeSet]]:
        """Per input topic caught up when a segment does not come (:meth:`fetch_announced`): its
        producer and the segments the producer's progress says it published.  Default: the
        :attr:`upstream` stage's output; a stage with more inputs it waits for adds them."""
        up = self.upstream
        peer = self.board.get(up) if up is not None else None
        topic = OUTPUT_TOPIC.get(up or "")
        if up is None or peer is None or topic is None or topic not in self.inputs:
            return {}
        return {topic: (up, peer.done)}

    def fetch_announced(self, now: float | None = None) -> list[tuple[str, int]]:
        """Catch up the input segments the producers' progress says they published that have
        not come (:meth:`announced_inputs`; not received, not handled or given up here or by
        an earlier process of this stage, at or above the validator's floor), by the rule of
        :mod:`streamer.runtime.catch_up`: after :data:`ANNOUNCED_FETCH_AFTER` seconds asked of the
        producer's cache once (:meth:`streamer.runtime.stage.Stage.fetch` applies the re-fetch
        budget), then read from its recordings (:meth:`take_recorded`), else given up
        (:meth:`input_lost`).  Nothing else tells a stage that its history query was lost, or
        that its producer restarted since: the segment would be waited for until the run
        times out.  Returns the ``(topic, index)`` asked of the cache now."""
        now = time.monotonic() if now is None else now
        floor = max(self.validator.floor, 0)
        own = self.board.get(self.stage_name)  # an earlier process of this stage handled those
        handled = self.done | self.failed | (own.handled if own is not None else RangeSet())
        published = {topic: announced for topic, (_, announced) in self.announced_inputs().items()}
        missing: dict[str, set[int]] = {}
        for topic, announced in published.items():
            got = self.ingest.done.get(topic, RangeSet())
            missing[topic] = {
                i
                for i in announced - handled - got
                if i >= floor and (topic, i) not in self.validator.digests and self.still_needed(topic, i)
            }
        ask, read = self.late_inputs.step(missing, now)
        for topic, index, why in self.late_inputs.unusable(published, self.ingest.done, now):
            if index not in handled:
                self.input_lost(
                    topic,
                    index,
                    f"the copy that came failed here ({why}) and no good copy came within "
                    f"{self.late_inputs.fetch_after:g} s",
                )
        asked = []
        for topic, i in ask:
            sent = self.fetch(topic, i)
            self.late_inputs.asked(topic, i, sent, now)
            if sent:
                asked.append((topic, i))
        if read:
            self.read_recorded(read)
        return asked

    def still_needed(self, topic: str, index: int) -> bool:
        """Whether input segment ``index`` of ``topic``, announced and not received, is still
        waited for here (override: the default, always)."""
        return True

    def input_failed(self, topic: str, index: int, why: str) -> None:
        """A segment that came and failed here: given up by :meth:`fetch_announced` when no
        good copy follows (:meth:`streamer.runtime.catch_up.CatchUp.unusable`)."""
        self.late_inputs.failed_here(topic, index, why, time.monotonic())

    def fetched(self, topic: str, index: int, copies: int) -> None:
        """The cache query for an announced segment is over (:meth:`fetch_announced`)."""
        self.late_inputs.answered(topic, index, copies)

    def read_recorded(self, wanted: dict[str, set[int]]) -> None:
        """Take the segments ``wanted`` (per topic) from their producers' recordings in the run
        directory, each through the checks of a copy from the bus (:meth:`take_recorded`); one
        no recording holds is lost (:meth:`input_lost`)."""
        run_dir = Path(self.config.recordings) / self.run_id
        producers = {t: p for t, (p, _) in self.announced_inputs().items()}
        for topic, indices in sorted(wanted.items()):
            producer = producers.get(topic) or PRODUCERS.get(topic, topic)
            copies = recorded_copies(run_dir, producer, topic, indices)
            for i in sorted(indices - copies.keys()):
                self.input_lost(
                    topic,
                    i,
                    f"{producer} published it, it did not come, no cache holds it (its producer restarted "
                    f"or moved on) and no recording in {run_dir} holds it",
                )
            if not copies:
                continue
            self.event(
                "recovered",
                message=f"{len(copies)} {topic} segment(s) read back from {producer}'s recordings "
                "(published, never received, in no cache)",
                topic=topic,
                indices=to_ranges(sorted(copies)),
            )
            for i in sorted(copies):
                self.take_recorded(topic, copies[i])

    def take_recorded(self, topic: str, seg: RecordedSegment) -> None:
        """Hand recorded segment ``seg`` to the stage as if it had come on the bus: the same
        checks, recording and handling (a copy recorded in part made whole by :attr:`rebuilds`).
        A copy the checks refuse (reported) leaves the segment lost, not waited for."""
        index = seg.header.index
        try:
            payload, attachment = wire_copy(seg, self.rebuilds.get(topic), Path(self.config.recordings) / self.run_id)
        except ValueError as exc:
            self.input_lost(topic, index, f"its recorded copy is unusable: {exc}")
            return
        self.ingest.take(stream_key(self.run_id, topic), payload, attachment)
        if (topic, index) not in self.validator.digests and index not in self.ingest.done.get(topic, ()):
            self.input_lost(topic, index, "its recorded copy was refused (the rejection is reported)")

    def input_lost(self, topic: str, index: int, why: str) -> None:
        """Input segment ``index`` of ``topic`` will not come (:mod:`streamer.runtime.catch_up`): an
        ``input-lost`` warning, and the stage settles the segment without it
        (:meth:`settle_lost`)."""
        self.warn("input-lost", f"{segment_key(self.run_id, topic, index)} given up: {why}", index=index, topic=topic)
        self.settle_lost(topic, index, why)

    def settle_lost(self, topic: str, index: int, why: str) -> None:
        """Go on without input segment ``index`` of ``topic`` (override; the default gives up
        segment ``index`` here, as failed: ``ttl run`` then exits 1)."""
        if index not in self.done | self.failed:
            self.mark_failed(index)

    def pending(self) -> int:
        """Segments received but not yet handled (override in buffering stages)."""
        return 0

    def handled_before(self, index: int) -> bool:
        """True when an earlier process of this stage already handled ``index`` (its output is
        out): a restarted stage processes it again to rebuild its state, publishes nothing."""
        if index in self.done or index in self.failed:
            return False
        own = self.board.get(self.stage_name)
        return own is not None and index in own.handled

    # ------------------------------------------------------------------ bookkeeping
    def note_meta(self, meta: dict) -> None:
        """Take ``segments_total`` from an input's meta."""
        if self.validator.plan is not None:
            return  # the plan says it
        total = segments_total_of(meta)
        if total is not None and total <= MAX_SEGMENTS:
            self.segments_total = total

    def mark_done(self, index: int, **extra) -> None:
        """Segment ``index`` is handled (its output published); publish progress."""
        self.done.add(index)
        self.failed.discard(index)
        self._after(index, extra)

    def mark_failed(self, index: int, **extra) -> None:
        """Segment ``index`` is given up (the error was reported); publish progress."""
        if index not in self.done:
            self.failed.add(index)
        self._after(index, extra)

    def mark_gap(self, index: int, **extra) -> None:
        """Segment ``index`` has no data (a gap upstream, reported): given up, as a gap."""
        if index not in self.done:
            self.gaps.add(index)
        self.mark_failed(index, **extra)

    def _after(self, index: int, extra: dict) -> None:
        self.progress.extra.update(extra)
        self.check_complete(publish=False)
        self.publish_progress(index)
        self.memtrace.segment(index)

    def check_complete(self, publish: bool = True) -> bool:
        """Record the ``complete`` event once the last segment is handled and nothing waits."""
        total = self.segments_total
        handled = self.done | self.failed
        if not self.progress.complete and total is not None and (total - 1) in handled and self.pending() == 0:
            self.progress.complete = True
            missing = sorted(set(range(total)) - handled)
            self.event(
                "complete",
                index=total - 1,
                message=f"handled {len(handled)} of {total} segments in this process",
                done=to_ranges(self.done),
                failed=to_ranges(self.failed),
                missing=to_ranges(missing),
            )
            self.log.info(
                "complete: last segment %d handled (%d done, %d failed in this process)",
                total - 1,
                len(self.done),
                len(self.failed),
            )
            if publish:
                self.publish_progress(None)
        return self.progress.complete

    def publish_progress(self, index: int | None) -> None:
        if self._progress_pub is None:
            return
        msg = self.progress.message(self.run_id, pid=os.getpid(), index=index)
        try:
            self._progress_pub.put(json.dumps(msg).encode())
        except Exception:
            self.log.exception("could not publish progress")


class OrderedStage(PipelineStage[OO]):
    """A pipeline stage that processes its input segments one by one in index order.

    Subclasses implement :meth:`process` (one segment -> an output or None) and may
    override :meth:`restart` (forget the state carried between segments, after a segment
    was skipped or failed) and :meth:`progress_fields` (extras of the progress messages).
    :meth:`handle` validates an input into an item and passes it to :meth:`enqueue`;
    segments are buffered (:class:`InOrder`, options ``settle`` and ``gap_timeout``) and
    processed as soon as they are next in order, or skipped when :attr:`upstream` gave them
    up or they do not come within ``gap_timeout`` while later ones wait.
    """

    options_type: ClassVar[type[StageOptions]] = OrderedOptions

    def __init__(self, config: StageConfig):
        super().__init__(config)
        self.queue = InOrder(settle=self.options.settle, gap_timeout=self.options.gap_timeout)

    def process(self, header, item):
        """Process the next segment in order; returns an :class:`streamer.runtime.stage.Output` or None."""
        raise NotImplementedError

    def restart(self) -> None:
        """Forget the state carried from segment to segment (after a skip or a failure)."""

    def fill_gap(self, index: int) -> None:
        """Segment ``index`` will not come (a gap): carry the state over it.  Default:
        :meth:`restart`; the fitter keeps its window instead."""
        self.restart()

    def progress_fields(self) -> dict:
        """Extra fields of the progress messages (sets are sent as index ranges)."""
        return {}

    def withdraw(self, topic: str, index: int, held: bool) -> bool:
        """Conflicting copies: a segment not processed yet is skipped in its turn (a
        failed segment, reported)."""
        return self.queue.withdraw(index, "conflicting copies of it were received (both kept out)")

    def published(self, index: int) -> None:
        """Segment ``index`` produced an output, now published."""

    def settle_lost(self, topic: str, index: int, why: str) -> None:
        """An input segment that will not come is skipped in its turn (a failed segment,
        reported), so that the state carried from segment to segment sees it in order."""
        self.queue.withdraw(index, f"lost ({why})")

    def pending(self) -> int:
        return len(self.queue.pending)

    def enqueue(self, header, item) -> None:
        """Buffer a validated input segment and process what is ready."""
        self.note_meta(header.meta)
        if not self.queue.add(header.index, (header, item)):
            self.event(
                "stale",
                index=header.index,
                message=f"{header.topic} segment {header.index} arrived after "
                f"the stream moved past it (next is {self.queue.next}); ignored",
            )
            return
        self.drain()

    def tick(self):
        self.drain()
        self.fetch_announced()
        self.check_complete()
        return ()

    def upstream_failed(self, index: int) -> bool:
        peer = self.board.get(self.upstream)
        return peer is not None and index in peer.failed

    def _resume_point(self) -> None:
        """A restarted stage (its earlier process's progress on the board) starts its queue at
        the first segment that process did not handle, not at the lowest received: the
        segments in between may be in no cache (their producer restarted too) and come from
        its recordings (:meth:`fetch_announced`), else are skipped after ``gap_timeout``."""
        if self.queue.next is None and self.queue.start_at is None:
            own = self.board.get(self.stage_name)
            if own is not None and own.handled:
                self.queue.start_at = next(i for i in itertools.count() if i not in own.handled)

    def _start_on_upstream_losses(self) -> None:
        """A queue that has not started, with nothing buffered, starts on the segments its
        upstream gave up: from the first one not handled here, as many in a row as the
        upstream failed (each skipped in its turn).  Otherwise a stage whose every input was
        given up upstream (nothing ever comes) waits until the run's timeout."""
        if self.queue.next is not None or self.queue.pending:
            return
        peer = self.board.get(self.upstream)
        if peer is None or not peer.failed:
            return
        own = self.board.get(self.stage_name)
        handled = self.done | self.failed | (own.handled if own is not None else RangeSet())
        index = self.queue.start_at if self.queue.start_at is not None else 0
        while index in handled:
            index += 1
        while index in peer.failed and index not in self.queue.withdrawn:
            self.queue.withdraw(index, "given up upstream")
            index += 1

    def drain(self, limit: int = 1) -> None:
        """Process up to ``limit`` segments that are next in order (or give up missing ones);
        one at a time by default, so that control messages are handled between segments."""
        done = 0
        self._resume_point()
        self._start_on_upstream_losses()
        for index, entry in self.queue.ready(self.upstream_failed, self.segments_total):
            done += 1
            if entry is None:
                self.report_error(
                    "gap", f"{self.inputs[0]} segment {index} skipped: {self.queue.skipped_reason}", index=index
                )
                self.fill_gap(index)
                peer = self.board.get(self.upstream)
                if peer is not None and index in peer.gaps:
                    self.mark_gap(index, **self.progress_fields())
                else:
                    self.mark_failed(index, **self.progress_fields())
                continue
            header, item = entry
            try:
                again = self.handled_before(index)
                out = self.process(header, item)
                if again:
                    why = "processed again to rebuild the state after a restart; its output was out already"
                    self.event("replayed", index=index, message=f"segment {index} {why}")
                elif out is not None:
                    self.publish(out, source=header)
                    self.published(index)
            except Exception as exc:
                if disk_full(exc):  # not the segment's doing: the stage stops (Stage.run)
                    raise
                if isinstance(exc, StageStopping):  # left unhandled, for the successor
                    return self.log.info("segment %d left unhandled: %s", index, exc)
                self.log.exception("segment %d failed", index)
                self.report_error("failed", f"{type(exc).__name__}: {exc}", index=index, key=header.key)
                self.fill_gap(index)
                self.mark_failed(index, **self.progress_fields())
                continue
            self.mark_done(index, **self.progress_fields())
            if done >= limit:
                return
