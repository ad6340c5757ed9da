"""The segment streams of a run on Zenoh: publishers with caches, subscribers that catch
up, and a re-fetch of a damaged segment.

Segment data go through Zenoh's *advanced* publisher and subscriber (``zenoh.ext``,
marked unstable in zenoh-python 1.x):

* :class:`SegmentPublisher` publishes every segment of a topic on one key,
  ``ttl/<run>/<topic>`` (the segment index is in the message header), with congestion
  control BLOCK (the default DROP silently loses multi-megabyte messages), reliable
  reliability, a cache of the last ``cache`` segments, publisher detection and sporadic
  heartbeats.  One long-lived publisher per topic: an advanced publisher is bound to one
  key, and declaring one per segment key grew the memory of every subscriber and of the
  router with the number of segments (``bench/soak.py``).
* :func:`declare_segment_subscriber` declares an advanced subscriber on
  ``ttl/<run>/<topic>/**`` that, on declaration and whenever a publisher appears later,
  queries the caches (late joiners and restarted stages catch up), recovers a lost sample
  from the heartbeats, and reports what it could not recover to a miss callback.
* :func:`refetch_segment` asks the publishers' caches again for one segment, for a copy
  that arrived damaged (its payload does not match its header's checksum or size): after
  a consumer stalled longer than the BLOCK wait, a multi-megabyte segment has arrived
  whole in size but not in content (docs/operations.md); the codec refuses it, and the
  cached copy replaces it.  The query names the damaged copy's sequence number
  (``?_sn=<n>..<n>``: the advanced publisher's number, in the sample's ``source_info``), so
  that a cache answers with that one sample, not with every segment it holds (11.4 MB
  each for TDI: a flood of damaged headers made every query cost the whole cache, issue 33).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import zenoh
from zenoh import ext

from .codec import CodecError, decode, parse_header
from .keys import segment_key, stream_key

log = logging.getLogger(__name__)

#: Seconds a re-fetch of one segment from the publishers' caches waits for their replies.
REFETCH_TIMEOUT = 30.0
#: Default number of segments kept in a topic's publisher caches.
DEFAULT_CACHE = 4
#: Period of the sporadic heartbeat of segment publishers [s].
HEARTBEAT_PERIOD = 1.0


# ---------------------------------------------------------------------------- publishers


def declare_segment_publisher(
    session: zenoh.Session, key: str, cache: int = 1, heartbeat: float = HEARTBEAT_PERIOD
) -> ext.AdvancedPublisher:
    """An advanced publisher for segment data on one key.

    Congestion control BLOCK, reliable, a cache of the last ``cache`` samples (replied to
    history queries with BLOCK too), sample-miss detection with a sporadic heartbeat of
    period ``heartbeat`` [s], and publisher detection (a liveliness token that lets
    advanced subscribers declared earlier query the cache).
    """
    block = zenoh.CongestionControl.BLOCK
    return ext.declare_advanced_publisher(
        session,
        key,
        encoding=zenoh.Encoding.APPLICATION_OCTET_STREAM,
        congestion_control=block,
        reliability=zenoh.Reliability.RELIABLE,
        cache=ext.CacheConfig(
            max_samples=max(1, int(cache)), replies_config=ext.RepliesConfig(congestion_control=block)
        ),
        sample_miss_detection=ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=heartbeat),
        publisher_detection=True,
    )


class SegmentPublisher:
    """Publishes the segments of one topic on ``ttl/<run>/<topic>``.

    One advanced publisher (:func:`declare_segment_publisher`), declared on the first put,
    whose cache of the last ``cache`` segments answers late joiners.

    Parameters
    ----------
    session : zenoh.Session
    run, topic : str
    cache : int
        Number of segments kept for late joiners (memory: ``cache`` payloads).
    """

    def __init__(self, session: zenoh.Session, run: str, topic: str, cache: int = DEFAULT_CACHE):
        self.session = session
        self.run = run
        self.topic = topic
        self.cache = max(1, int(cache))
        self.key = stream_key(run, topic)
        self._publisher: ext.AdvancedPublisher | None = None

    def put(self, index: int, payload, attachment) -> str:
        """Publish segment ``index`` (blocks while the transport is congested).

        The header in ``attachment`` carries the index; returns the segment's name
        ``ttl/<run>/<topic>/<index>``.
        """
        name = segment_key(self.run, self.topic, index)
        if self._publisher is None:
            self._publisher = declare_segment_publisher(self.session, self.key, cache=self.cache)
        self._publisher.put(payload, attachment=attachment)
        return name

    def undeclare(self) -> None:
        """Undeclare the publisher (its cache goes with it)."""
        if self._publisher is not None:
            self._publisher.undeclare()
            self._publisher = None


def refetch_segment(
    session: zenoh.Session,
    key_expr: str,
    index: int,
    header: bytes | None,
    on_sample: Callable[[zenoh.Sample], None],
    *,
    on_done: Callable[[int], None] | None = None,
    timeout: float = REFETCH_TIMEOUT,
    sn: int | None = None,
) -> None:
    """Ask every publisher cache of the stream ``key_expr`` (``ttl/<run>/<topic>``) again
    for segment ``index`` with the header ``header`` (the damaged message's, byte for byte:
    its payload was damaged, not its header); returns at once.

    The advanced publishers' caches answer on ``<key_expr>/@adv/pub/<zid>/<eid>`` with the
    samples as published (key ``key_expr``, the header in the attachment).  Each reply with
    that header whose payload matches it (size and checksum) goes to
    ``on_sample``, the callback a subscriber's samples go to, on a Zenoh thread; other
    cached messages (other segments, other copies of this one) are not handed on again.  When the query is over (all caches
    answered, or ``timeout`` seconds), ``on_done(n)`` gets the number of copies handed on:
    0 when no cache holds the segment any more (a cache keeps the last ``cache`` segments
    of its publisher).  ``header=None``: any intact copy of segment ``index`` (a segment
    announced but never received, e.g. a late joiner's history query lost under load).
    ``sn``: the sequence number of the damaged copy (``sample.source_info.source_sn``): the
    caches answer with the sample of that number only (Zenoh's ``_sn`` selector parameter);
    None: with everything they hold (a fetch of an announced segment, whose number is not
    known: fits, a few kB each).
    """
    found = [0]

    def on_reply(reply) -> None:
        sample = reply.ok
        if sample is None or sample.attachment is None:
            return
        try:
            raw = sample.attachment.to_bytes()
            if (header is not None and raw != header) or parse_header(raw, key_expr).index != index:
                return
            decode(sample.payload, sample.attachment, key=key_expr)  # intact this time
        except CodecError:
            return
        found[0] += 1
        on_sample(sample)

    def done() -> None:
        if on_done is not None:
            on_done(found[0])

    session.get(
        f"{key_expr}/@adv/pub/**" + (f"?_sn={int(sn)}..{int(sn)}" if sn is not None else ""),
        zenoh.handlers.Callback(on_reply, done),
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
        accept_replies=zenoh.ReplyKeyExpr.ANY,  # the caches reply on the stream key, not the query's
        congestion_control=zenoh.CongestionControl.BLOCK,
        timeout=timeout,
    )


# ---------------------------------------------------------------------------- subscribers


class Undeclarable(Protocol):
    """A Zenoh entity (subscriber, miss listener) that can be undeclared."""

    def undeclare(self) -> None: ...


@dataclass
class SegmentSubscription:
    """An advanced subscriber and its miss listener; :meth:`undeclare` removes both."""

    subscriber: Undeclarable | None
    miss_listener: Undeclarable | None = None

    def undeclare(self) -> None:
        if self.miss_listener is not None:
            self.miss_listener.undeclare()
            self.miss_listener = None
        if self.subscriber is not None:
            self.subscriber.undeclare()
            self.subscriber = None


def declare_segment_subscriber(
    session: zenoh.Session,
    key_expr: str,
    callback: Callable[[zenoh.Sample], None],
    *,
    history: int | None = None,
    on_miss: Callable[[str, int], None] | None = None,
) -> SegmentSubscription:
    """Subscribe to segment data with history and recovery.

    Parameters
    ----------
    session : zenoh.Session
    key_expr : str
        Usually ``ttl/<run>/<topic>/**`` (:func:`streamer.bus.keys.topic_pattern`).
    callback : callable(zenoh.Sample)
        Called on a Zenoh thread for every sample: keep it short (queue the sample).
    history : int or None
        Samples to query from each matching publisher's cache (the last ``history`` of a
        key), on declaration and when a publisher appears later; None: all it holds; 0: no
        history.
    on_miss : callable(source: str, count: int), optional
        Called when samples were lost beyond recovery; default logs a warning.
    """
    if history is None:
        hist = ext.HistoryConfig(detect_late_publishers=True)
    elif history > 0:
        hist = ext.HistoryConfig(detect_late_publishers=True, max_samples=int(history))
    else:
        hist = None
    sub = ext.declare_advanced_subscriber(
        session,
        key_expr,
        callback,
        history=hist,
        recovery=ext.RecoveryConfig(periodic_queries=None, heartbeat=True),
        subscriber_detection=True,
    )

    def missed(miss) -> None:
        if on_miss is not None:
            on_miss(str(miss.source), int(miss.nb))
        else:
            log.warning("%s: %d sample(s) missed from %s", key_expr, miss.nb, miss.source)

    return SegmentSubscription(sub, sub.sample_miss_listener(missed))
