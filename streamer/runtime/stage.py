"""The stage base: one process that turns input segments into output segments.

A stage subclass sets :attr:`Stage.name` and :attr:`Stage.inputs` and implements
:meth:`Stage.handle`; the base does the rest:

* opens the Zenoh session (:class:`~streamer.bus.session.SessionSettings`) and declares the
  liveliness token ``ttl/<run>/alive/<stage>``;
* subscribes to ``ttl/<run>/<topic>/*`` for each input topic with the advanced subscriber
  (history from the publishers' caches, recovery, miss reports);
* validates every message with the codec (:func:`streamer.bus.codec.decode`) and the stage's
  :meth:`Stage.expect`; a message that does not fit is reported on
  ``ttl/<run>/errors/<index>`` and in the recording, and the stage goes on;
* processes each segment index once per topic: a duplicate is ignored (an event is
  recorded), a gap in the indices is reported on the errors topic;
* holds every accepted segment ``hold`` seconds before using it: a different copy of it
  arriving meanwhile keeps both out (:class:`streamer.runtime.plan.Holdback`; a later one withdraws
  the first from the stage if it can, :meth:`Stage.withdraw`);
* calls :meth:`Stage.handle` inside ``try``: an exception is reported as an error of that
  segment, not a crash;
* publishes the returned :class:`Output` objects with the codec (BLOCK, cached for late
  joiners) and records inputs and outputs in ``<recordings>/<run>/<stage>.mcap``;
* stops gracefully on SIGINT, SIGTERM or ``ttl/<run>/control/stop`` (or
  ``.../control/<stage>/stop``): recording closed with its summary, entities undeclared,
  session closed, :meth:`Stage.run` returns 0.

Source stages (no inputs, e.g. the replayer) implement :meth:`Stage.tick`, called whenever
no message is waiting.

The parts (each its own module): :mod:`streamer.bus.transport` (queues and publishers),
:mod:`streamer.runtime.ingest` (validation, hold-back, gaps), :mod:`streamer.runtime.stage_reports` (the
recording's errors, warnings and events), :mod:`streamer.runtime.lifecycle` (signals, the launcher,
the full disk), :mod:`streamer.runtime.stage_config` and :mod:`streamer.runtime.stage_cli` (configuration and
command line); :class:`Stage` composes them and runs the loop.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import threading
import time
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..bus.codec import Expect, Header
from ..bus.keys import (
    KeyExprError,
    control_pattern,
    parse_segment_key,
    parse_stream_key,
    segment_key,
    stage_control_pattern,
    stream_key,
    topic_pattern,
)
from ..bus.session import Bus
from ..bus.transport import Output, StageTransport, output_fields, recorded_part
from ..recording.recorder import Recorder, mission_ns
from .controls import ControlDesk, due_controls, recorded_controls
from .ingest import PREVIEW_CHARS, GapWatch, Ingest
from .ingest import preview as _preview
from .lifecycle import LAUNCHER, LauncherWatch, OrphanWatchdog, disk_full, install_signal_flag
from .plan import Holdback, Plan, Validator
from .processes import SignalFlag
from .rangeset import RangeSet
from .refetch_policy import topic_owner
from .stage_cli import add_common_options, config_from_args, stage_arguments, stage_main
from .stage_config import StageConfig
from .stage_reports import StageReports, recording_path, set_aside
from .stagelog import JsonFormatter, StageLogger, configure_logging

__all__ = [  # the names stage programs import from here (their parts live in the modules above)
    "LAUNCHER",
    "PREVIEW_CHARS",
    "JsonFormatter",
    "Output",
    "Stage",
    "StageConfig",
    "StageLogger",
    "_preview",
    "add_common_options",
    "config_from_args",
    "configure_logging",
    "disk_full",
    "recording_path",
    "set_aside",
    "stage_arguments",
    "stage_main",
]


class Stage:
    """Base class of the stage programs (see the module docstring).

    Subclasses set :attr:`name` and :attr:`inputs`, implement :meth:`handle`, and may
    override :meth:`expect`, :meth:`setup`, :meth:`teardown` and :meth:`tick`.
    """

    #: Default stage name (liveliness token, recording file, producer field).
    name: ClassVar[str] = "stage"
    #: Input topics whose gaps are not reported on arrival: the stage puts them back in
    #: order itself (and reports a segment once it is really given up) or does not need
    #: them in order.  History from several publisher caches, after a restart or a late
    #: join, arrives in any order without anything missing.
    reorders: ClassVar[tuple[str, ...]] = ()
    #: Input topics.
    inputs: ClassVar[tuple[str, ...]] = ()
    #: Poll interval [s] when neither the command line nor the configuration file sets one.
    default_poll_interval: ClassVar[float] = StageConfig.poll_interval
    #: The control commands :meth:`control` knows (stop excepted): a restarted stage with
    #: any reads the commands its earlier process queued and did not handle.
    commands: ClassVar[tuple[str, ...]] = ()

    def __init__(self, config: StageConfig):
        self.stage_name = config.stage or self.name
        if config.zenoh.credentials is not None and not config.zenoh.identity:  # this stage's certificate
            config = dataclasses.replace(config, zenoh=dataclasses.replace(config.zenoh, identity=self.stage_name))
        self.config = config
        self.run_id = config.run
        self.log = StageLogger(
            logging.getLogger(f"streamer.runtime.stage.{self.stage_name}"),
            {"run": self.run_id, "stage": self.stage_name},
        )
        self.recording_path: Path | None = None
        self._stop = threading.Event()
        self._signals = SignalFlag(())  # replaced by the installed one in run()
        #: Errors, warnings, events; the bus and the recorder while running.
        self.reports = StageReports(self.run_id, self.stage_name, self.log)
        #: Queues filled by the Zenoh callbacks; output publishers.
        self.transport = StageTransport(self.run_id, self.stage_name, config.cache, self._stop, self.log)
        #: Control commands: handled between segments, recorded, answered (:mod:`.controls`).
        self.controls = ControlDesk(
            self.run_id,
            self.stage_name,
            self.transport,
            record=lambda obj: self.live_recorder.write_json("control", obj),
            apply=lambda command, payload: self.control(command, payload),
            publish=lambda out: self.publish(out),
            event=lambda kind, **kw: self.event(kind, **kw),
            report_error=lambda *a, **kw: self.report_error(*a, **kw),
            log=self.log,
        )
        #: Validation and hold-back of input messages.
        self.ingest = Ingest(
            self.run_id,
            Validator(Plan.from_dict(config.plan) if config.plan else None),
            Holdback(config.hold),
            expect=lambda topic, index: self.expect(topic, index),
            withdraw=lambda topic, index, held: self.withdraw(topic, index, held),
            report=lambda *a, **k: self.report_error(*a, **k),
            event=lambda *a, **k: self.event(*a, **k),
            use=lambda *item: self._use(*item),
            log=self.log,
            refetch=lambda key, index, header, sn: self.transport.refetch(self.live_bus, key, index, header, sn),
        )
        #: Indices skipped on arrival (not for the topics in :attr:`reorders`).
        self.gap_watch = GapWatch(config.gap_grace, self.reorders)
        #: Whether the launcher that started the stage is gone.
        self.launcher_watch = LauncherWatch(config.launcher_pid, config.orphan_grace)
        #: Stages of the run whose liveliness token is present (updated from a Zenoh thread).
        self.alive_peers: set[str] = set()
        self.exit_reason: str | None = None
        #: When a sample was last lost beyond recovery (``missed``), monotonic [s], or None.
        self.last_miss: float | None = None

    # ------------------------------------------------------------------ the parts' state
    @property
    def bus(self) -> Bus | None:
        return self.reports.bus

    @bus.setter
    def bus(self, bus: Bus | None) -> None:
        self.reports.bus = bus

    @property
    def recorder(self) -> Recorder | None:
        return self.reports.recorder

    @recorder.setter
    def recorder(self, recorder: Recorder | None) -> None:
        self.reports.recorder = recorder

    @property
    def live_bus(self) -> Bus:
        """The bus while the stage runs (inside :meth:`run`); a RuntimeError outside it."""
        if self.reports.bus is None:
            raise RuntimeError(f"stage {self.stage_name}: the bus is used outside run()")
        return self.reports.bus

    @property
    def live_recorder(self) -> Recorder:
        """The recorder while the stage runs (inside :meth:`run`); a RuntimeError outside it."""
        if self.reports.recorder is None:
            raise RuntimeError(f"stage {self.stage_name}: the recorder is used outside run()")
        return self.reports.recorder

    @property
    def disk_full(self) -> str | None:
        """Why the stage stopped on a full disk, or None."""
        return self.reports.disk_full

    @property
    def validator(self) -> Validator:
        return self.ingest.validator

    @property
    def held(self) -> Holdback:
        return self.ingest.held

    @property
    def rejections(self) -> int:
        return self.ingest.rejections

    # ------------------------------------------------------------------ to override
    def handle(self, header: Header, arrays: dict[str, np.ndarray]) -> Sequence[Output]:
        """Process one validated input segment; return the outputs to publish.

        ``header.topic`` says which input it came on.  Raise to report the segment as
        failed (the stage keeps running).
        """
        raise NotImplementedError

    def expect(self, topic: str, index: int) -> Expect:
        """What an input message on ``topic`` with header index ``index`` must fit.

        Default: this run, that index, finite values.  Override to require arrays,
        dtypes and shapes.
        """
        return Expect(run=self.run_id, index=index)

    def setup(self) -> None:
        """Called once the session is open and before inputs are subscribed."""

    def teardown(self) -> None:
        """Called on shutdown, before the recording and the session are closed."""

    def withdraw(self, topic: str, index: int, held: bool) -> bool:
        """Copies of segment ``index`` of ``topic`` conflict: keep the first one out too.

        ``held``: the first copy was still held (:attr:`StageConfig.hold`) and is dropped;
        otherwise :meth:`handle` has had it.  Treat the index as missing from now on and
        return True if the first copy has changed no output, False if it has (too late).
        Default: True when it was held.  Override in stages that keep segments before using
        them (a reorder buffer) and in stages that must account for every index.
        """
        return held

    def tick(self) -> Sequence[Output]:
        """Called when no input is waiting (every ``poll_interval`` at most); source stages
        return the outputs to publish now."""
        return ()

    # ------------------------------------------------------------------ lifecycle
    def stop(self) -> None:
        """Ask the stage to stop (thread-safe; not from a signal handler: SIGINT and SIGTERM
        go through :class:`streamer.runtime.processes.SignalFlag`)."""
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set() or bool(self._signals)

    def run(self) -> int:
        """Run until stopped; returns the exit code (0 after a graceful stop)."""
        cfg = self.config
        self.recording_path = recording_path(cfg.recordings, self.run_id, self.stage_name)
        restore = None
        watchdog = OrphanWatchdog(self.launcher_watch, self.log)
        try:
            with (
                Bus.open(cfg.zenoh) as bus,
                Recorder(
                    self.recording_path,
                    metadata={
                        "run": self.run_id,
                        "stage": self.stage_name,
                        "class": type(self).__qualname__,
                        "config": json.dumps(cfg.to_dict()),
                    },
                ) as recorder,
            ):
                # only now: zenoh.open blocks (up to 30 s for a client whose router is gone)
                # without returning to Python, where a handler would run; until then a
                # signal's default action ends the process, which has nothing to close yet
                self._signals = install_signal_flag()
                restore = self._signals.restore
                watchdog.start()  # a segment still computing 30 s after the launcher is gone: exit
                self.bus, self.recorder = bus, recorder
                bus.subscriber(control_pattern(self.run_id), self.transport.on_control)
                bus.queryable(stage_control_pattern(self.run_id, self.stage_name), self.transport.on_control_query)
                # alive once it takes commands: a sender that waits for the token and then
                # sends is not lost to a subscriber not yet declared (declarations reach the
                # router in order; a fresh clone's make test lost four control messages so)
                bus.declare_alive(self.run_id, self.stage_name)
                bus.watch_alive(self.run_id, self._on_alive)
                if self.commands:  # commands an earlier process queued and did not handle: first
                    self.controls.restore(
                        due_controls(recorded_controls(cfg.recordings / self.run_id, self.stage_name, self.log))
                    )
                self.setup()
                for topic in self.inputs:
                    bus.segment_subscriber(
                        topic_pattern(self.run_id, topic),
                        self.transport.on_sample,
                        history=cfg.history,
                        on_miss=self.transport.on_miss,
                    )
                self.event("start", message=f"inputs {list(self.inputs)}")
                self.log.info("running (inputs %s, recording %s)", list(self.inputs), self.recording_path)
                try:
                    self._loop()
                except OSError as exc:
                    if not disk_full(exc):
                        raise
                    self.reports.note_disk_full(exc, self.recording_path.parent if self.recording_path else "?")
                if self._signals:
                    self.log.info("received %s", self._signals.name)
                if self.exit_reason is None and (
                    why := self.launcher_watch.orphaned_by_signal(bool(self._signals))
                ):  # a signal sent because the launcher died (die-with-parent): say so
                    self.exit_reason = why
                    self.log.error("%s: stopping (exit status 3)", why)
                    self.report_error("orphaned", f"{why}: stage stops")
                watchdog.disarm()
                self.log.info("stopping")
                self.reports.last_words(self.teardown)
                self.reports.last_words(lambda: self._report_suppressed(final=True))
                self.reports.last_words(
                    lambda: self.event(
                        "stop",
                        message=self.disk_full or self.exit_reason or "",
                        orphaned=bool(self.exit_reason),
                        disk_full=self.disk_full is not None,
                        rejections=self.rejections,
                    )
                )
        except OSError as exc:
            if not self.reports.closing_failed(exc):
                raise
        finally:
            watchdog.disarm()
            self.bus = self.recorder = None
            if restore is not None:
                restore()
        self.log.info("stopped")
        return 4 if self.disk_full else 3 if self.exit_reason else 0

    def _on_alive(self, stage: str, alive: bool) -> None:  # Zenoh thread
        if stage == LAUNCHER:
            self.launcher_watch.token(alive)
        else:
            (self.alive_peers.add if alive else self.alive_peers.discard)(stage)

    def orphaned(self) -> str | None:
        """Why this stage has lost its launcher, or None (:meth:`streamer.runtime.lifecycle.LauncherWatch.orphaned`)."""
        return self.launcher_watch.orphaned()

    def _check_orphaned(self) -> None:
        why = self.launcher_watch.check()
        if why:
            self.exit_reason = why
            self.log.error("%s: stopping (exit status 3)", why)
            self.report_error("orphaned", f"{why}: stage stops")
            self._stop.set()

    def _loop(self) -> None:
        while not self.stopping:
            self._check_orphaned()
            self._release_held()
            self._report_suppressed()
            if self.controls_ready():
                self.controls.handle_pending()
            item = self.transport.next(self.config.poll_interval)
            if item is None:
                self._run_tick()
                continue
            if item[0] == "miss":
                _, source, count = item
                self.last_miss = time.monotonic()
                self.report_error("missed", f"{count} sample(s) lost beyond recovery from publisher {source}")
            elif item[0] == "refetched":
                self._refetched(*item[1:])
            elif item[0] == "fetched":
                _, key, index, copies = item
                self.event("fetched", index=index, message=f"{copies} cached copy(ies) of {key} segment {index}")
                self.fetched(parse_stream_key(key), index, copies)
            else:
                self.ingest.take(*item[1:])

    def _report_suppressed(self, final: bool = False) -> None:
        """One ``suppressed`` warning per cause of refusals counted, not recorded one by one
        (:class:`streamer.runtime.refetch_policy.ReportLimiter`), with their count."""
        for producer, kind, field, count in self.ingest.suppressed(final):
            self.warn(
                "suppressed",
                f"{count} more message(s) from {producer} refused ({kind}, {field}): counted, not recorded "
                f"one by one (the first {self.ingest.limiter.limit} of this cause were)",
                producer=producer,
                cause=kind,
                refused_field=field,
                count=count,
            )

    def fetch(self, topic: str, index: int) -> bool:
        """Ask the producer's cache for segment ``index`` of ``topic`` (any intact copy): for
        a segment announced on the progress board that never came (a late joiner's history
        query lost under load).  What comes is taken as any sample; a ``fetched`` event
        records how many copies came.  Asked only for an index of the plan and the window
        not processed yet, within the producer's re-fetch budget
        (:mod:`streamer.runtime.refetch_policy`); returns whether it was asked."""
        v = self.validator
        total = v.segments_total
        if (
            index < max(v.floor, 0)
            or (total is not None and index >= total)
            or index in self.ingest.done.get(topic, ())
        ):
            return False
        owner = topic_owner(topic, v.plan) or topic
        if not self.ingest.budget.take(stream_key(self.run_id, topic), index, owner, v.floor):
            return False
        self.transport.fetch(self.live_bus, stream_key(self.run_id, topic), index)
        return True

    def fetched(self, topic: str, index: int, copies: int) -> None:
        """The cache query of :meth:`fetch` for segment ``index`` of ``topic`` is over:
        ``copies`` came (override; the default does nothing more)."""

    def _refetched(self, key: str, index: int, copies: int) -> None:
        """A re-fetch of a damaged segment is over: record it.  With no copy found, a warning
        (another copy may still come on the stream; if none does, the gap or the unhandled
        segment is reported as any other)."""
        topic = parse_stream_key(key)
        if copies:
            self.event("refetched", index=index, message=f"{copies} intact cached copy(ies) of {key} segment {index}")
        elif index not in self.ingest.done.get(topic, ()):
            self.warn(
                "refetch-empty",
                f"{segment_key(self.run_id, topic, index)} arrived damaged and no publisher cache holds an intact copy",
                index=index,
            )

    def controls_ready(self) -> bool:
        """Whether control commands can be handled now (override: a restarted fitter waits
        until it knows its first segment, from which a model change applies)."""
        return True

    def control(self, command: str, payload: bytes):
        """A control command for this stage (override; may return outputs to publish).

        Raise to reject it (the message names what is wrong); the default knows none.
        """
        raise ValueError(f"stage {self.stage_name} has no command {command!r}")

    def _run_tick(self) -> None:
        self._report_gaps()
        try:
            outputs = list(self.tick() or ())
            for out in outputs:
                self.publish(out)
        except OSError as exc:
            if disk_full(exc):
                raise
            self.log.exception("tick failed")
            self.report_error(
                "failed", f"{type(exc).__name__}: {exc}", details={"traceback": traceback.format_exc(limit=8)}
            )
        except Exception as exc:
            self.log.exception("tick failed")
            self.report_error(
                "failed", f"{type(exc).__name__}: {exc}", details={"traceback": traceback.format_exc(limit=8)}
            )

    # ------------------------------------------------------------------ processing
    def _release_held(self) -> None:
        """Use the held segments whose wait is over (no conflicting copy came)."""
        for key, header, arrays, payload in self.ingest.due():
            try:
                self._use(key, header, arrays, payload)
            except OSError:
                raise
            except Exception as exc:  # noqa: BLE001 - as in Ingest.take: the loop goes on
                self.log.exception("%s: unexpected failure while using a held segment", key)
                self.report_error(
                    "failed",
                    f"unexpected {type(exc).__name__}: {exc}",
                    index=header.index,
                    key=key,
                    details={"traceback": traceback.format_exc(limit=8)},
                )

    def _use(self, key: str, header: Header, arrays: dict, payload: bytes) -> None:
        """Record an accepted input segment and hand it to :meth:`handle`."""
        seg = parse_segment_key(key)
        index = seg.index
        if index is None:  # only ttl/<run>/errors/unknown has none, never an input
            raise KeyExprError(key, "an input segment key without a segment index")
        done = self.ingest.done.setdefault(seg.topic, RangeSet())
        self.gap_watch.arrived(seg.topic, index)
        if self.config.record_inputs:
            self.live_recorder.write_segment(seg.topic, header, payload)
        else:  # a reference: the payload is in the producer's recording, named by its checksum
            self.live_recorder.write_json(
                f"{seg.topic}/input", header.to_dict(), schema="ttl.SegmentHeader", log_time=mission_ns(header.t0)
            )
        try:
            outputs = list(self.handle(header, arrays) or ())
            for out in outputs:
                self.publish(out, source=header)
        except OSError as exc:
            if disk_full(exc):
                raise
            self._handle_failed(key, index, exc)
            return
        except Exception as exc:
            self._handle_failed(key, index, exc)
            return
        done.add(index)
        self.log.info("%s: processed, %d output(s)", key, len(outputs))

    def _handle_failed(self, key: str, index: int, exc: Exception) -> None:
        self.log.exception("%s: processing failed", key)
        self.report_error(
            "failed",
            f"{type(exc).__name__}: {exc}",
            index=index,
            key=key,
            details={"traceback": traceback.format_exc(limit=8)},
        )
        self.input_failed(parse_segment_key(key).topic, index, f"{type(exc).__name__}: {exc}")

    def input_failed(self, topic: str, index: int, why: str) -> None:
        """Input segment ``index`` of ``topic`` came intact and :meth:`handle` raised (``why``;
        reported as ``failed``).  It is not marked received: a good copy is still taken.
        Override to settle it when none comes (the default does nothing more)."""

    def _report_gaps(self) -> None:
        grace = self.gap_watch.gap_grace
        for topic, first, last, revealed in self.gap_watch.due():
            missing = f"{first}" if first == last else f"{first}..{last}"
            self.report_error(
                "gap",
                f"{topic} segment(s) {missing} missing before {revealed} (not received within {grace:g} s)",
                index=revealed,
                details={"topic": topic, "first_missing": first, "last_missing": last},
            )

    # ------------------------------------------------------------------ outputs and reports
    def publish(self, out: Output, source: Header | None = None) -> str:
        """Encode, publish and record one output; returns its key."""
        index, fields = output_fields(out, self.run_id, self.stage_name, source)
        key, header, payload = self.transport.put(self.live_bus, out, index, fields)
        if self.config.record_outputs:
            part = recorded_part(out, fields, header)
            self.live_recorder.write_segment(out.topic, *(part or (header, payload)))
        if out.summary is not None:
            self.live_recorder.write_json(
                f"{out.topic}/summary", out.summary, schema=out.summary_schema, log_time=mission_ns(header["t0"])
            )
        return key

    def report_error(
        self,
        kind: str,
        message: str,
        *,
        index: int | None = None,
        key: str | None = None,
        field: str | None = None,
        details: dict | None = None,
    ) -> dict:
        """Publish an error on ``ttl/<run>/errors/<index>``, record it, log it; returns it
        (:meth:`StageReports.error`; its keywords typed here, so that callers are checked)."""
        return self.reports.error(kind, message, index=index, key=key, field=field, details=details)

    def warn(self, kind: str, message: str, *, index: int | None = None, **details) -> None:
        """Log and record a warning (topic ``warnings``): not an error, but for the operator's eyes."""
        self.reports.warn(kind, message, index=index, **details)

    def event(self, kind: str, *, index: int | None = None, message: str = "", **details) -> None:
        """Record a lifecycle or bookkeeping event in the recording."""
        self.reports.event(kind, index=index, message=message, **details)
