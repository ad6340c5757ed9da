"""What a stage does with a message before its :meth:`~streamer.runtime.stage.Stage.handle` sees it:
validation, hold-back and gap detection.

* :meth:`Ingest.take` decodes the message with the codec (:func:`streamer.bus.codec.decode`)
  against the stage's :meth:`~streamer.runtime.stage.Stage.expect`, checks it against the plan
  (:class:`streamer.runtime.plan.Validator`), ignores an identical copy of a processed segment, and
  holds an accepted one ``hold`` seconds (:class:`streamer.runtime.plan.Holdback`; a different copy
  arriving meanwhile keeps both out), or hands it to the stage at once when ``hold`` is 0.
  A copy damaged on the way (payload size or checksum not those of its header) is asked
  for again from its producer's cache (``refetch``) when
  :class:`streamer.runtime.refetch_policy.RefetchBudget` allows it (an index of the plan and of the
  window, not processed yet, the topic's producer, at most 3 times per segment and a
  bounded rate per producer): the intact copy then goes through the same checks.
  Whatever a message holds, this does not raise:
  a message that does not fit is reported (kind ``rejected``, or the validator's kind) and
  the stage goes on; only an ``OSError`` (the recording's disk) escapes.  The reports of one
  cause from one producer are recorded one by one up to a limit, then counted
  (:class:`streamer.runtime.refetch_policy.ReportLimiter`, :meth:`Ingest.suppressed`).
* :class:`GapWatch` notes the indices an arrival skips and reports those that do not come
  within ``gap_grace`` seconds.
"""

from __future__ import annotations

import time
import traceback
from collections.abc import Callable

from ..bus.codec import CodecError, Expect, decode, parse_header
from ..bus.keys import KeyExprError, parse_stream_key, segment_key
from .plan import Holdback, Rejected, Validator
from .rangeset import RangeSet
from .refetch_policy import RefetchBudget, ReportLimiter, refetch_refusal, sender, topic_owner

#: Characters of a rejected attachment kept in the error report.
PREVIEW_CHARS = 2000
#: Codec fields at fault in a copy damaged on the way (asked for again).
DAMAGED = ("payload", "checksum")


def preview(attachment) -> str:
    """The start of an attachment, as text, for an error report."""
    if attachment is None:
        return ""
    raw = attachment.to_bytes() if hasattr(attachment, "to_bytes") else bytes(attachment)
    return raw[:PREVIEW_CHARS].decode("utf-8", errors="replace")


class GapWatch:
    """Indices skipped on arrival, reported when they have not come within ``gap_grace`` s.

    Parameters
    ----------
    gap_grace : float
        Seconds a skipped index has to arrive before it is a gap [s] (messages of different
        keys may arrive out of order).
    reorders : tuple of str
        Topics not watched (the stage puts them back in order itself).

    Memory: one entry per gap, whatever its length.
    """

    def __init__(self, gap_grace: float, reorders: tuple[str, ...] = ()):
        self.gap_grace = gap_grace
        self.reorders = tuple(reorders)
        self._highest: dict[str, int] = {}
        # suspected gaps, in ranges: topic -> [[first, last, since, revealed by], ...]
        self._suspected: dict[str, list[list]] = {}

    def arrived(self, topic: str, index: int) -> None:
        """Note segment ``index`` of ``topic``: the indices it skips become suspected gaps,
        and a suspected index that comes is no longer one."""
        if topic in self.reorders:
            return
        gaps = self._suspected.setdefault(topic, [])
        for k, (first, last, since, revealed) in enumerate(gaps):
            if first <= index <= last:  # a suspected index came: split the range
                parts = [[a, b, since, revealed] for a, b in ((first, index - 1), (index + 1, last)) if a <= b]
                gaps[k : k + 1] = parts
                break
        highest = self._highest.get(topic)
        if highest is not None and index > highest + 1:
            gaps.append([highest + 1, index - 1, time.monotonic(), index])
        if highest is None or index > highest:
            self._highest[topic] = index

    def due(self) -> list[tuple[str, int, int, int]]:
        """The gaps not filled within ``gap_grace``, as (topic, first, last, revealed by);
        taken out."""
        now = time.monotonic()
        out = []
        for topic, gaps in self._suspected.items():
            due = [g for g in gaps if now - g[2] >= self.gap_grace]
            out += [(topic, first, last, revealed) for first, last, _, revealed in due]
            if due:
                gaps[:] = [g for g in gaps if now - g[2] < self.gap_grace]
        return out


class Ingest:
    """The checks an input message goes through (module docstring).

    Parameters
    ----------
    run : str
        Run id.
    validator : Validator
        The plan's checks.
    held : Holdback
        The hold-back of accepted segments.
    expect : callable
        ``expect(topic, index)``: what a message must fit (:meth:`streamer.runtime.stage.Stage.expect`).
    withdraw : callable
        ``withdraw(topic, index, held)``: keep the first of two conflicting copies out
        (:meth:`streamer.runtime.stage.Stage.withdraw`).
    report : callable
        Reports an error (:meth:`streamer.runtime.stage.Stage.report_error`).
    event : callable
        Records an event (:meth:`streamer.runtime.stage.Stage.event`).
    use : callable
        ``use(key, header, arrays, payload)``: hand an accepted segment to the stage.
    log : logging.LoggerAdapter
        The stage's logger.
    refetch : callable, optional
        ``refetch(stream_key, index, header, sn)``: ask the publishers' caches again for the
        sample ``sn`` of segment ``index``, whose copy arrived damaged (``sn`` None: a sample
        without a sequence number, a plain put: every cached sample, filtered by its header;
        :func:`streamer.bus.segment_stream.refetch_segment`); None: do not.
    """

    def __init__(
        self,
        run: str,
        validator: Validator,
        held: Holdback,
        *,
        expect: Callable[[str, int], Expect],
        withdraw: Callable[[str, int, bool], bool],
        report: Callable[..., object],
        event: Callable[..., None],
        use: Callable[[str, object, dict, bytes], None],
        log,
        refetch: Callable[[str, int, bytes, int | None], None] | None = None,
    ):
        self.run = run
        self.validator = validator
        self.held = held
        self.expect = expect
        self.withdraw = withdraw
        self.report = report
        self.event = event
        self.use = use
        self.log = log
        self.refetch = refetch
        #: Which damaged copies are asked for again (per segment, per producer).
        self.budget = RefetchBudget()
        #: Which refusals are recorded one by one.
        self.limiter = ReportLimiter()
        #: Messages refused (codec errors excepted: those are reports only).
        self.rejections = 0
        #: Segment indices processed, per topic.
        self.done: dict[str, RangeSet] = {}

    def take(self, key: str, payload, attachment, sn: int | None = None) -> None:
        """Validate one message that came on Zenoh key ``key``, and hold it or use it (or
        refuse it).

        Data come on the stream key ``ttl/<run>/<topic>``, the index in the header; from
        the header on, the segment is named ``ttl/<run>/<topic>/<index>``.  Nothing a
        message holds can stop the stage: an exception that escapes the checks (a bug met
        by an unforeseen message) is a recorded rejection of that message (``field:
        message``), and the stage goes on.  An ``OSError`` (the recording's disk) is not the
        message's doing and still stops the stage.
        """
        try:
            self._take(key, payload, attachment, sn)
        except OSError:
            raise
        except Exception as exc:  # noqa: BLE001 - the loop must outlive any message
            self.rejections += 1
            self.log.exception("%s: unexpected failure while checking a message", key)
            self.report(
                "rejected",
                f"unexpected {type(exc).__name__} while checking the message: {exc}",
                key=key,
                field="message",
                details={"traceback": traceback.format_exc(limit=8), "attachment": preview(attachment)},
            )

    def _take(self, key: str, payload, attachment, sn: int | None = None) -> None:
        """The body of :meth:`take`."""
        payload = payload.to_bytes() if hasattr(payload, "to_bytes") else bytes(payload or b"")
        try:
            topic = parse_stream_key(key)
        except KeyExprError as exc:
            self.report("rejected", str(exc), key=key, field="key")
            return
        index = None
        producer = None
        stream = key
        try:
            claimed = parse_header(attachment, key)
            index, producer = claimed.index, claimed.producer
            key = segment_key(self.run, topic, index)
            header, arrays = decode(payload, attachment, self.expect(topic, index), key=key)
        except CodecError as exc:
            details = {"payload_bytes": len(payload), "attachment": preview(attachment)}
            if exc.field in DAMAGED and index is not None:
                raw = attachment.to_bytes() if hasattr(attachment, "to_bytes") else bytes(attachment)
                details["refetch"], why = self._ask_again(stream, topic, index, producer, raw, sn)
                if why:
                    details["refetch_refused"] = why
            self._refused(topic, producer, "rejected", exc.what, index=index, key=key, field=exc.field, details=details)
            return
        at = claimed.index  # the segment's index (the header parsed above holds it)
        try:
            verdict = self.validator.check(topic, header, arrays)
        except Rejected as exc:
            self.rejections += 1
            details = {"producer": header.producer, "t0": header.t0, "fs": header.fs, "checksum": header.checksum}
            what = exc.what
            if exc.kind == "conflict" and exc.field == "payload":  # the first conflicting copy: the other goes too
                held = self.held.withdraw(topic, at)
                kept_out = self.withdraw(topic, at, held)
                details["first_copy"] = "withdrawn" if kept_out else "used"
                what += (
                    "; the first copy is withdrawn, the segment is missing"
                    if kept_out
                    else "; the first copy had been used already"
                )
            self._refused(topic, header.producer, exc.kind, what, index=at, key=key, field=exc.field, details=details)
            return
        done = self.done.setdefault(topic, RangeSet())
        if verdict == "duplicate" or at in done:
            self.log.info("%s: identical copy of a processed segment, ignored", key)
            self.event("duplicate", index=at, message=f"{key} already processed (identical copy)")
            return
        self.validator.accepted(topic, header)  # from now on a different copy is a conflict
        if not self.held.put(topic, at, (key, header, arrays, payload), time.monotonic()):
            self.use(key, header, arrays, payload)

    def _refused(self, topic: str, producer, kind: str, what: str, **fields) -> None:
        """Report a refused message, unless its cause has been recorded often enough
        (:class:`streamer.runtime.refetch_policy.ReportLimiter`: then it is counted)."""
        owner = topic_owner(topic, self.validator.plan)
        if self.limiter.admit(sender(producer, owner), kind, fields.get("field")):
            self.report(kind, what, **fields)

    def suppressed(self, final: bool = False) -> list[tuple[str, str, str, int]]:
        """The refusals counted and not recorded since last asked, ``(producer, kind, field,
        count)`` per cause (:meth:`streamer.runtime.refetch_policy.ReportLimiter.due`)."""
        return self.limiter.due(final)

    def _ask_again(
        self, stream: str, topic: str, index: int, producer, header: bytes, sn: int | None
    ) -> tuple[int, str]:
        """Ask the producer's cache again for the copy of segment ``index`` of ``stream``
        with the damaged copy's ``header`` (bytes), if the plan, the window and the budget
        allow it (:mod:`streamer.runtime.refetch_policy`); returns the attempt number (0 when not
        asked) and why not."""
        if self.refetch is None:
            return 0, ""
        v = self.validator
        plan = v.plan
        owner = topic_owner(topic, plan)
        ceiling = v.highest + v.window if v.highest >= 0 or plan is None else None
        why = refetch_refusal(
            index,
            str(producer),
            owner,
            total=v.segments_total,
            floor=v.floor,
            ceiling=max(ceiling, v.window) if ceiling is not None else None,
            done=index in self.done.get(topic, ()),
        )
        if why:
            return 0, why
        # the budget's key: the topic's producer (without a plan, any name the sender writes
        # would open a new budget: one for the topic then)
        attempt = self.budget.take(stream, index, owner or topic, v.floor)
        if not attempt:
            return 0, f"re-fetches of segment {index} or of producer {producer!r} used up"
        self.log.warning("%s: segment %d arrived damaged, asking the producer's cache again", stream, index)
        self.refetch(stream, index, header, sn)
        return attempt, ""

    def due(self) -> list[tuple]:
        """The held segments whose wait is over (no conflicting copy came), to use now."""
        return self.held.due(time.monotonic())
