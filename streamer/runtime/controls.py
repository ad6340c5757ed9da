"""A stage's control commands: handled on its main thread between segments, each recorded and
answered to its sender.

A command (``ttl/<run>/control/<stage>/<command>``) comes as a query from ``ttl control``
(or as a plain put, which gets no answer).  Between two segments the stage handles it
(:meth:`ControlDesk.handle`): the payload goes through the bounded parser of the segment
headers, then to :meth:`Stage.control`; the verdict (``accepted`` or ``rejected``, with the
reason) is recorded on the ``control`` topic, then sent back to the sender.

A stage busy inside one segment for long (the fitter's live diagnosis: minutes) takes its
commands at its checkpoints (:meth:`ControlDesk.defer`): each is recorded as ``queued`` and
the sender told so at once, and it is handled after the segment, in the order received.  A
stage killed in between loses nothing it said was queued: its successor reads the queued
commands without a verdict from the earlier recordings (:func:`due_controls`) and handles
them first.  A command is handled once: its id (the sender's UUID) is in every record.
"""

from __future__ import annotations

import json
import logging
import time
from collections import deque
from collections.abc import Callable, Iterable
from pathlib import Path

from ..bus.bounded_json import BoundedJSONError, load_bounded
from ..bus.keys import control_key
from ..bus.transport import Control, StageTransport
from ..recording.recording_reader import read_recording
from .ingest import PREVIEW_CHARS
from .stage_reports import earlier_recordings

__all__ = ["ControlDesk", "due_controls", "recorded_controls"]

#: Verdicts that end a command (``queued`` does not).
FINAL = ("accepted", "rejected")


def recorded_controls(run_dir: Path, stage: str, log: logging.Logger | logging.LoggerAdapter) -> list[dict]:
    """The ``control`` records of the earlier processes of ``stage`` (``<stage>.<n>.mcap``
    in ``run_dir``, oldest first; their segments are not decoded).  A damaged or unreadable
    file is skipped (warned): the others are used."""
    records: list[dict] = []
    for path in earlier_recordings(run_dir, stage):
        try:
            records += read_recording(path, keep=lambda topic, header: False, topics=("control",)).json("control")
        except Exception as exc:  # noqa: BLE001 - a damaged file: use what the others have
            log.warning("cannot read the control records of %s: %s", path, exc)
    return records


def due_controls(records: Iterable[dict]) -> list[Control]:
    """The commands an earlier process of a stage recorded as ``queued`` and gave no verdict
    (``control`` records, oldest first), in the order received; their payloads as recorded
    (the parsed JSON, written again)."""
    queued: dict[str, dict] = {}
    ended: set[str] = set()
    for r in records:
        cid = r.get("id")
        if not isinstance(cid, str):
            continue
        if r.get("state") == "queued":
            queued.setdefault(cid, r)
        elif r.get("state") in FINAL:
            ended.add(cid)
    return [
        Control(str(r.get("command")), b"" if r.get("payload") is None else json.dumps(r["payload"]).encode(), cid)
        for cid, r in queued.items()
        if cid not in ended
    ]


class ControlDesk:
    """The control commands of one stage (see the module docstring).

    Parameters
    ----------
    run, stage : str
        Run id and stage name.
    transport : StageTransport
        Where the commands come in.
    record : callable
        ``record(obj)`` writes a ``control`` record to the stage's recording and flushes it.
    apply : callable
        ``apply(command, payload)`` runs the command (:meth:`Stage.control`): raises to
        reject it, returns outputs to publish.
    publish, event, report_error : callable
        The stage's.
    log : logging.LoggerAdapter
    """

    def __init__(
        self,
        run: str,
        stage: str,
        transport: StageTransport,
        *,
        record: Callable[[dict], None],
        apply: Callable,
        publish: Callable,
        event: Callable,
        report_error: Callable,
        log: logging.LoggerAdapter | logging.Logger,
    ):
        self.run, self.stage, self.transport = run, stage, transport
        self.record, self.apply, self.publish = record, apply, publish
        self.event, self.report_error, self.log = event, report_error, log
        #: Commands received but not handled yet (queued at a checkpoint, or restored).
        self.deferred: deque[Control] = deque()

    def restore(self, controls: Iterable[Control]) -> None:
        """Commands an earlier process queued and did not handle: handled first."""
        for c in controls:
            self.log.info("restart: control %s (id %s) queued by the earlier process is handled now", c.command, c.id)
            self.deferred.append(c)

    def handle_pending(self) -> None:
        """Handle the deferred commands, then those come since (between two segments)."""
        while self.deferred:
            self.handle(self.deferred.popleft())
        for c in self.transport.pending_controls():
            self.handle(c)

    def defer(self, why: str = "busy") -> None:
        """Take the commands come so far without handling them (the stage is inside a
        segment): each is recorded ``queued`` and its sender told so; handled by the next
        :meth:`handle_pending`.  A payload the bounded parser refuses is rejected now."""
        for c in self.transport.pending_controls():
            try:
                shown = self._parse(c)
            except BoundedJSONError as exc:
                self._reject_unparsed(c, exc)
                continue
            self.record(self._record(c, "queued", payload=shown, message=why))
            self.deferred.append(c)
            if c.reply is not None:
                c.reply.answer(self._verdict(c, "queued", why), final=False)

    def handle(self, c: Control) -> None:
        """Check, run, record and answer one command; a rejected one changes nothing and is
        also reported on ``errors``."""
        try:
            # the bounded parser of the segment headers: a payload nested 500 deep, or with
            # a 5000-digit number, is refused here, before any parser or recorder walks it
            shown = self._parse(c)
        except BoundedJSONError as exc:
            self._reject_unparsed(c, exc)
            return
        try:
            outputs = list(self.apply(c.command, c.payload) or ())
        except Exception as exc:  # a bad command must not stop the stage
            self._reject(c, str(exc), self._record(c, "rejected", payload=shown, message=str(exc)))
            return
        self.record(self._record(c, "accepted", payload=shown))
        self.event("control", message=f"{c.command} accepted", id=c.id)
        if c.reply is not None:
            c.reply.answer(self._verdict(c, "accepted", f"{c.command} accepted"))
        for out in outputs:
            self.publish(out)

    # ------------------------------------------------------------------ parts
    @staticmethod
    def _parse(c: Control):
        return load_bounded(c.payload, root="payload") if c.payload.strip() else None

    def _record(self, c: Control, state: str, **fields) -> dict:
        rec = {"run": self.run, "stage": self.stage, "command": c.command, "time": time.time(), "id": c.id}
        rec["state"] = state
        if state in FINAL:
            rec["accepted"] = state == "accepted"
        return {**rec, **{k: v for k, v in fields.items() if v is not None or k == "payload"}}

    def _verdict(self, c: Control, state: str, message: str) -> dict:
        return {"stage": self.stage, "command": c.command, "id": c.id, "state": state, "message": message}

    def _reject_unparsed(self, c: Control, exc: Exception) -> None:
        text = c.payload[:PREVIEW_CHARS].decode("utf-8", errors="replace")
        self._reject(c, str(exc), self._record(c, "rejected", payload=text, message=str(exc)))

    def _reject(self, c: Control, message: str, record: dict) -> None:
        self.log.warning("control %s rejected: %s", c.command, message)
        self.record(record)
        self.report_error(
            "rejected",
            f"control message {c.command!r}: {message}",
            key=control_key(self.run, self.stage, c.command),
            field="payload",
        )
        if c.reply is not None:
            c.reply.answer(self._verdict(c, "rejected", message))
