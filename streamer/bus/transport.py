"""A stage's traffic on the bus: what comes in (segments, misses, control commands) is
queued for the main thread; what goes out (:class:`Output`) is encoded and published.

The Zenoh callbacks (:meth:`StageTransport.on_sample`, :meth:`~StageTransport.on_miss`,
:meth:`~StageTransport.on_control`) run on Zenoh's threads: they only queue.  Control
commands have their own queue, emptied before the next segment.
"""

from __future__ import annotations

import json
import logging
import queue
import re
import threading
import uuid
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from .codec import Header, encode
from .keys import KeyExprError, parse_control_key
from .session import Bus


@dataclass
class Output:
    """A segment message to publish.

    Attributes
    ----------
    topic : str
        Output topic (``tdi``, ``fit``, ...).
    arrays : ndarray or mapping of str to ndarray
        The arrays (see :func:`streamer.bus.codec.encode`).
    fields : dict
        Header fields (``channels``, ``units``, ``channel_axis``, ``meta``, ``t0``,
        ``fs``...); ``run``, ``producer`` are set by the stage, ``index``, ``t0`` and
        ``fs`` default to the input segment's.
    index : int, optional
        Segment index (default: the input's).
    summary : dict, optional
        JSON record of this output (a fit, a diagnosis) written to the recording on
        ``<topic>/summary`` with schema ``summary_schema``.
    summary_schema : str or dict
        Name in :data:`streamer.recording.recorder.SCHEMAS` or a JSON schema.
    allow_nonfinite : bool
        Allow NaN/inf in the arrays (consumers must then expect them too).
    record_arrays : tuple of str, optional
        Arrays kept in the recording (default all): derived arrays a reader can rebuild
        from other recorded payloads are left out; the recorded header then carries
        ``meta.recorded`` with the arrays kept and the published checksum and size.
    """

    topic: str
    arrays: Any
    fields: dict = field(default_factory=dict)
    index: int | None = None
    summary: dict | None = None
    summary_schema: Any = "ttl.Object"
    allow_nonfinite: bool = False
    record_arrays: tuple | None = None


def output_fields(out: Output, run: str, producer: str, source: Header | None = None) -> tuple[int, dict]:
    """The segment index of ``out`` (its own, else ``source``'s) and its header fields:
    index, t0 and fs from ``source`` unless ``out`` sets them, then ``run`` and ``producer``."""
    index = out.index if out.index is not None else (source.index if source else None)
    if index is None:
        raise ValueError(f"output on {out.topic!r}: no index and no input segment to take it from")
    fields: dict[str, Any] = {"index": index}
    if source is not None:
        fields.update(t0=source.t0, fs=source.fs)
    fields.update(out.fields)
    fields.update(run=run, producer=producer)
    return index, fields


def recorded_part(out: Output, fields: dict, header: dict) -> tuple[dict, bytes] | None:
    """The copy of a published output to record when :attr:`Output.record_arrays` leaves
    arrays out: (header, payload) with ``meta.recorded``; None: record it whole."""
    arrays = out.arrays if isinstance(out.arrays, Mapping) else None
    if out.record_arrays is None or arrays is None or set(out.record_arrays) >= set(arrays):
        return None
    kept = {name: arrays[name] for name in out.record_arrays}
    meta = dict(fields.get("meta") or {})
    meta["recorded"] = {
        "arrays": list(kept),
        "published_checksum": header["checksum"],
        "published_bytes": header["payload_bytes"],
        "published_arrays": [a["name"] for a in header["arrays"]],
    }
    units = fields.get("units")
    sub = {**fields, "meta": meta}
    if isinstance(units, Mapping):
        sub["units"] = {k: v for k, v in units.items() if k in kept}
    part, attachment = encode(kept, sub, allow_nonfinite=out.allow_nonfinite)
    return json.loads(attachment), part


#: Characters of a sender's control id (``ttl control`` sends a UUID); another is replaced.
_CONTROL_ID = re.compile(r"[A-Za-z0-9_.:-]{1,64}")


def control_id(attachment) -> str:
    """The sender's id of a control command (its attachment: ``ttl control`` sends a UUID),
    else a new one: the id names the command in the stage's records
    (``control`` topic), which a restarted stage reads to finish what it queued."""
    try:
        text = attachment.to_bytes().decode("ascii") if attachment is not None else ""
    except (UnicodeDecodeError, AttributeError):
        text = ""
    return text if _CONTROL_ID.fullmatch(text) else uuid.uuid4().hex


class ControlReply:
    """The query a control command came on: the stage's answers go back to the sender.

    :meth:`answer` sends a verdict (a JSON object with ``state``: ``queued``, then
    ``accepted`` or ``rejected``); the final one ends the query.  A sender gone (its query
    timed out) loses the answer, never the command: the stage records every verdict.
    """

    def __init__(self, query):
        self.query = query

    def answer(self, verdict: dict, final: bool = True) -> None:
        if self.query is None:
            return
        try:
            self.query.reply(self.query.key_expr, json.dumps(verdict, default=str).encode())
        except Exception as exc:  # noqa: BLE001 - the sender has gone: the record stays
            logging.getLogger(__name__).info("control answer not delivered: %s", exc)
        if final:
            try:
                self.query.drop()
            finally:
                self.query = None


@dataclass
class Control:
    """One control command for a stage: ``ttl/<run>/control/<stage>/<command>``.

    Attributes
    ----------
    command : str
        The command (``model``...).
    payload : bytes
        Its payload (JSON; parsed by the stage with the bounded parser).
    id : str
        The sender's id (:func:`control_id`).
    reply : ControlReply, optional
        Where the verdict goes (None: put on the bus, or restored from a recording).
    """

    command: str
    payload: bytes
    id: str
    reply: ControlReply | None = None


def sequence_number(sample) -> int | None:
    """The advanced publisher's sequence number of ``sample`` (None: a sample of a plain
    ``put``, which has none)."""
    info = getattr(sample, "source_info", None)
    sn = getattr(info, "source_sn", None) if info is not None else None
    return int(sn) if isinstance(sn, int) else None


class StageTransport:
    """The queues a stage's Zenoh callbacks fill, and its output publishers.

    Parameters
    ----------
    run, stage : str
        Run id and stage name (control keys, output keys).
    cache : int
        Segments kept per output topic for late joiners.
    stop : threading.Event
        Set by a stop command (``control/stop`` or ``control/<stage>/stop``).
    log : logging.LoggerAdapter
        The stage's logger.
    """

    def __init__(self, run: str, stage: str, cache: int, stop: threading.Event, log):
        self.run = run
        self.stage = stage
        self.cache = cache
        self.stop = stop
        self.log = log
        #: ("sample", key, payload, attachment, sn), ("miss", source, count) and ("refetched",
        #: key, index, copies), in arrival order.
        self.inbox: queue.Queue = queue.Queue()
        #: :class:`Control` of ``control/<stage>/<command>``: handled before queued segments.
        self.controls: queue.Queue = queue.Queue()
        self._publishers: dict = {}

    # ------------------------------------------------------------------ Zenoh threads
    def on_sample(self, sample) -> None:
        self.inbox.put(("sample", str(sample.key_expr), sample.payload, sample.attachment, sequence_number(sample)))

    def on_miss(self, source: str, count: int) -> None:
        self.inbox.put(("miss", source, count))

    def refetch(self, bus: Bus, key: str, index: int, header: bytes, sn: int | None) -> None:
        """Ask the publishers' caches of stream ``key`` again for segment ``index`` (the copy
        with ``header``, bytes, and sequence number ``sn``): the copies come in as samples, then
        ("refetched", key, index, copies)."""
        bus.refetch(
            key, index, header, self.on_sample, on_done=lambda n: self.inbox.put(("refetched", key, index, n)), sn=sn
        )

    def fetch(self, bus: Bus, key: str, index: int) -> None:
        """Ask the publishers' caches of stream ``key`` for segment ``index``, any intact copy
        (one announced but never received): the copies come in as samples, then
        ("fetched", key, index, copies)."""
        bus.refetch(key, index, None, self.on_sample, on_done=lambda n: self.inbox.put(("fetched", key, index, n)))

    def on_control(self, sample) -> None:
        """A command put on the bus (no answer goes back: the launcher's stop, old senders)."""
        try:
            _, parts = parse_control_key(str(sample.key_expr))
        except KeyExprError:
            return
        if parts in (("stop",), (self.stage, "stop")):
            self.log.info("stop requested on %s", sample.key_expr)
            self.stop.set()
        elif len(parts) == 2 and parts[0] == self.stage:
            payload = sample.payload.to_bytes() if sample.payload is not None else b""
            self.controls.put(Control(parts[1], payload, control_id(sample.attachment)))

    def on_control_query(self, query) -> None:
        """A command asked as a query (``ttl control``): its verdict goes back on the query
        (:class:`ControlReply`); a stop is answered at once."""
        try:
            _, parts = parse_control_key(str(query.key_expr))
        except KeyExprError:
            query.drop()
            return
        if len(parts) != 2 or parts[0] != self.stage:
            query.drop()
            return
        reply = ControlReply(query)
        if parts[1] == "stop":
            self.log.info("stop requested on %s", query.key_expr)
            self.stop.set()
            reply.answer({"stage": self.stage, "command": "stop", "state": "accepted", "message": "stopping"})
            return
        payload = query.payload.to_bytes() if query.payload is not None else b""
        self.controls.put(Control(parts[1], payload, control_id(query.attachment), reply))

    # ------------------------------------------------------------------ main thread
    def pending_controls(self):
        """The control commands queued so far (:class:`Control`), in order (taken out)."""
        while not self.controls.empty():
            yield self.controls.get_nowait()

    def next(self, timeout: float):
        """The next queued sample or miss, or None after ``timeout`` seconds."""
        try:
            return self.inbox.get(timeout=timeout)
        except queue.Empty:
            return None

    def put(self, bus: Bus, out: Output, index: int, fields: dict) -> tuple[str, dict, bytes]:
        """Encode and publish ``out`` as segment ``index`` with header ``fields``; returns its
        key, header and payload."""
        payload, attachment = encode(out.arrays, fields, allow_nonfinite=out.allow_nonfinite)
        publisher = self._publishers.get(out.topic)
        if publisher is None:
            publisher = bus.segment_publisher(self.run, out.topic, cache=self.cache)
            self._publishers[out.topic] = publisher
        key = publisher.put(index, payload, attachment)
        return key, json.loads(attachment), payload
