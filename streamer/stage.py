"""The stage base: one process that turns input segments into output segments.

A stage subclass sets :attr:`Stage.name` and :attr:`Stage.inputs` and implements
:meth:`Stage.handle`; the base does the rest:

* opens the Zenoh session (:class:`~streamer.session.SessionSettings`) and declares the
  liveliness token ``ttl/<run>/alive/<stage>``;
* subscribes to ``ttl/<run>/<topic>/*`` for each input topic with the advanced subscriber
  (history from the publishers' caches, recovery, miss reports);
* validates every message with the codec (:func:`streamer.codec.decode`) and the stage's
  :meth:`Stage.expect`; a message that does not fit is reported on
  ``ttl/<run>/errors/<index>`` and in the recording, and the stage goes on;
* processes each segment index once per topic: a duplicate is ignored (an event is
  recorded), a gap in the indices is reported on the errors topic;
* holds every accepted segment ``hold`` seconds before using it: a different copy of it
  arriving meanwhile keeps both out (:class:`streamer.plan.Holdback`; a later one withdraws
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
"""

from __future__ import annotations

import argparse
import dataclasses
import errno
import json
import logging
import os
import queue
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ttlcore.errors import TTLError

from . import allocator
from .codec import CodecError, Expect, Header, decode, encode, parse_header
from .keys import (
    KeyExprError,
    SegmentKey,
    check_name,
    control_key,
    control_pattern,
    errors_key,
    parse_control_key,
    parse_segment_key,
    parse_stream_key,
    segment_key,
    topic_pattern,
)
from .plan import Holdback, Plan, RangeSet, Rejected, Validator
from .processes import SignalFlag, set_parent_death_signal
from .recorder import Recorder, mission_ns, stage_record, stop_note_path
from .session import DEFAULT_CACHE, Bus, SessionSettings

log = logging.getLogger(__name__)

#: Name of the launcher's liveliness token (``ttl/<run>/alive/launcher``).
LAUNCHER = "launcher"
#: Characters of a rejected attachment kept in the error report.
PREVIEW_CHARS = 2000


@dataclass
class StageConfig:
    """Configuration of one stage process.

    Attributes
    ----------
    run : str
        Run identifier (a key chunk: letters, digits, ``.``, ``_``, ``-``).
    stage : str
        Stage name (default: the class's :attr:`Stage.name`).
    zenoh : SessionSettings
        How to open the session (default: peer on loopback, no multicast scouting).
    recordings : Path
        Recordings directory; the stage writes ``<recordings>/<run>/<stage>.mcap``.
    cache : int
        Segments kept per output topic for late joiners.
    history : int or None
        Segments asked from each input topic's publisher cache at start and on publisher
        appearance (the last ``history``); None: everything the cache holds.
    record_inputs : bool
        Record input segments whole (header and payload) in the MCAP file; when False
        (``ttl run``: the producer's file holds the payload) only their headers, on
        ``<topic>/input``, whose checksum refers to the payload in the producer's file.
    record_outputs : bool
        Record output segments (header and payload, see :attr:`Output.record_arrays`).
    poll_interval : float
        Longest wait for a message before checking for shutdown and calling :meth:`Stage.tick` [s].
    gap_grace : float
        A segment index skipped on arrival is reported as a gap only if it has not come
        within this many seconds [s] (segments of different keys may arrive out of order).
    hold : float
        Seconds an accepted input segment waits before the stage uses it [s]: a different
        copy of the same segment arriving meanwhile keeps both out (``docs/operations.md``).
        0: used at once (a conflicting copy then refuses only the later one).
    options : dict
        Stage-specific options.
    plan : dict, optional
        The run's plan (:class:`streamer.plan.Plan`); every input message is checked
        against it (:class:`streamer.plan.Validator`).  None: learned from the messages.
    launcher_pid : int, optional
        Process id of the launcher that started this stage: the stage stops (exit status
        3, recording closed) as soon as its parent is no longer that process.
    progress_from : {"stages", "launcher"}
        Whose progress messages a pipeline stage follows: the stages' own
        (``control/progress/<stage>``), or, in a run of ``ttl run``, the launcher's verified
        board (``control/board/<stage>``: only what the launcher believed).
    orphan_grace : float
        Once the launcher's liveliness token ``ttl/<run>/alive/launcher`` has been seen, the
        stage stops when it has been gone this long [s] (a launcher on another host).
    """

    run: str
    stage: str = ""
    zenoh: SessionSettings = field(default_factory=SessionSettings)
    recordings: Path = Path("recordings")
    cache: int = DEFAULT_CACHE
    history: int | None = None
    record_inputs: bool = True
    record_outputs: bool = True
    poll_interval: float = 0.2
    gap_grace: float = 10.0
    hold: float = 1.0
    options: dict = field(default_factory=dict)
    plan: dict | None = None
    launcher_pid: int | None = None
    orphan_grace: float = 60.0
    progress_from: str = "stages"

    def to_dict(self) -> dict:
        return {
            "run": self.run,
            "stage": self.stage,
            "zenoh": self.zenoh.to_dict(),
            "recordings": str(self.recordings),
            "cache": self.cache,
            "history": self.history,
            "record_inputs": self.record_inputs,
            "record_outputs": self.record_outputs,
            "poll_interval": self.poll_interval,
            "gap_grace": self.gap_grace,
            "hold": self.hold,
            "options": self.options,
            "plan": self.plan,
            "launcher_pid": self.launcher_pid,
            "orphan_grace": self.orphan_grace,
            "progress_from": self.progress_from,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> StageConfig:
        d = dict(d)
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"stage configuration: unknown field {sorted(unknown)[0]!r}")
        if "run" not in d:
            raise ValueError("stage configuration: field 'run' missing")
        d["zenoh"] = SessionSettings.from_dict(d.get("zenoh"))
        if "recordings" in d:
            d["recordings"] = Path(d["recordings"])
        return cls(**d)


@dataclass
class Output:
    """A segment message to publish.

    Attributes
    ----------
    topic : str
        Output topic (``tdi``, ``fit``, ...).
    arrays : ndarray or mapping of str to ndarray
        The arrays (see :func:`streamer.codec.encode`).
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
        Name in :data:`streamer.recorder.SCHEMAS` or a JSON schema.
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


class StageLogger(logging.LoggerAdapter):
    """Attaches ``run`` and ``stage`` (and any ``extra``) to the records of a stage."""

    def process(self, msg, kwargs):
        kwargs["extra"] = {**self.extra, **kwargs.get("extra", {})}
        return msg, kwargs


class JsonFormatter(logging.Formatter):
    """One JSON object per line: time, level, logger, message, and run/stage/index if set."""

    def format(self, record: logging.LogRecord) -> str:
        out = {
            "time": round(record.created, 6),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        for name in ("run", "stage", "index"):
            if hasattr(record, name):
                out[name] = getattr(record, name)
        if record.exc_info:
            out["exception"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


def configure_logging(level: str | int = "INFO", json_lines: bool = False, stream=None) -> None:
    """Set up the root logger of a stage process (plain text or JSON lines on stderr)."""
    handler = logging.StreamHandler(stream or sys.stderr)
    handler.setFormatter(
        JsonFormatter() if json_lines else logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
    )
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)


def set_aside(path: Path) -> Path:
    """``path``, free to write: an existing file is first renamed ``<stem>.<n><suffix>``
    (the lowest ``n`` free), so that a restarted process keeps its predecessor's recording
    (and its stop note, :func:`streamer.recorder.stop_note_path`)."""
    path = Path(path)
    if path.exists():
        n = 1
        while (old := path.with_name(f"{path.stem}.{n}{path.suffix}")).exists():
            n += 1
        path.rename(old)
        note = stop_note_path(path)
        if note.exists():
            note.rename(stop_note_path(old))
        log.info("kept the previous recording as %s", old)
    return path


def recording_path(recordings: Path, run: str, stage: str) -> Path:
    """``<recordings>/<run>/<stage>.mcap``; an existing file is first renamed ``<stage>.<n>.mcap``."""
    return set_aside(Path(recordings) / run / f"{stage}.mcap")


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

    def __init__(self, config: StageConfig):
        self.stage_name = config.stage or self.name
        if config.zenoh.credentials is not None and not config.zenoh.identity:  # this stage's certificate
            config = dataclasses.replace(config, zenoh=dataclasses.replace(config.zenoh, identity=self.stage_name))
        self.config = config
        self.run_id = config.run
        self.log = StageLogger(
            logging.getLogger(f"streamer.stage.{self.stage_name}"), {"run": self.run_id, "stage": self.stage_name}
        )
        self.bus: Bus | None = None
        self.recorder: Recorder | None = None
        self.recording_path: Path | None = None
        self._queue: queue.Queue = queue.Queue()
        self._controls: queue.Queue = queue.Queue()  # handled before queued segments
        self._stop = threading.Event()
        self._signals = SignalFlag(())  # replaced by the installed one in run()
        self._publishers: dict = {}
        self._done: dict[str, RangeSet] = {}
        self._highest: dict[str, int] = {}
        # suspected gaps, in ranges: topic -> [[first, last, since, revealed by], ...]
        self._suspected: dict[str, list[list]] = {}
        self.validator = Validator(Plan.from_dict(config.plan) if config.plan else None)
        self.held = Holdback(config.hold)
        self.rejections = 0
        self._launcher_seen = False
        self._launcher_gone_at: float | None = None
        #: Stages of the run whose liveliness token is present (updated from a Zenoh thread).
        self.alive_peers: set[str] = set()
        self.exit_reason: str | None = None
        #: When a sample was last lost beyond recovery (``missed``), monotonic [s], or None.
        self.last_miss: float | None = None
        #: Why the stage stopped on a full disk (:meth:`_on_disk_full`), or None.
        self.disk_full: str | None = None

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
        go through :class:`streamer.processes.SignalFlag`)."""
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set() or bool(self._signals)

    def run(self) -> int:
        """Run until stopped; returns the exit code (0 after a graceful stop)."""
        cfg = self.config
        self.recording_path = recording_path(cfg.recordings, self.run_id, self.stage_name)
        restore = None
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
                restore = self._install_signal_handlers()
                self.bus, self.recorder = bus, recorder
                bus.declare_alive(self.run_id, self.stage_name)
                bus.subscriber(control_pattern(self.run_id), self._on_control)
                bus.watch_alive(self.run_id, self._on_alive)
                self.setup()
                for topic in self.inputs:
                    bus.segment_subscriber(
                        topic_pattern(self.run_id, topic), self._on_sample, history=cfg.history, on_miss=self._on_miss
                    )
                self.event("start", message=f"inputs {list(self.inputs)}")
                self.log.info("running (inputs %s, recording %s)", list(self.inputs), self.recording_path)
                try:
                    self._loop()
                except OSError as exc:
                    if not disk_full(exc):
                        raise
                    self._on_disk_full(exc)
                if self._signals:
                    self.log.info("received %s", self._signals.name)
                if self.exit_reason is None and (why := self._orphaned_by_signal()):
                    # a signal sent because the launcher died (die-with-parent): say so
                    self.exit_reason = why
                    self.log.error("%s: stopping (exit status 3)", why)
                    self.report_error("orphaned", f"{why}: stage stops")
                self.log.info("stopping")
                self._last_words(self.teardown)
                self._last_words(
                    lambda: self.event(
                        "stop",
                        message=self.disk_full or self.exit_reason or "",
                        orphaned=bool(self.exit_reason),
                        disk_full=self.disk_full is not None,
                        rejections=self.rejections,
                    )
                )
        except OSError as exc:
            if self.disk_full is None or not disk_full(exc):
                raise
            self.log.error("could not close the recording on the full disk: %s", exc)
        finally:
            self.bus = self.recorder = None
            if restore is not None:
                restore()
        self.log.info("stopped")
        return 4 if self.disk_full else 3 if self.exit_reason else 0

    def _on_disk_full(self, exc: OSError) -> None:
        """The recording's disk is full: free the recorder's reserve, leave the stop note
        beside the file (``ttl inspect`` names the cause), report it on the bus; the stage
        then stops (exit status 4)."""
        where = self.recording_path.parent if self.recording_path else "?"
        self.disk_full = f"disk full: {exc.strerror or exc} (writing under {where})"
        self.log.error("%s: stopping (exit status 4)", self.disk_full)
        if self.recorder is not None:
            self.recorder.release_reserve()
            try:
                self.recorder.note_stop(
                    "disk-full", self.disk_full, run=self.run_id, stage=self.stage_name, errno=exc.errno
                )
            except OSError as again:
                self.log.error("could not write the stop note: %s", again)
        self._last_words(lambda: self.report_error("disk-full", f"{self.disk_full}: stage stops"))

    def _last_words(self, write) -> None:
        """Call ``write``; once the disk is full, a failure to write is logged, not raised."""
        if self.disk_full is None:
            write()
            return
        try:
            write()
        except OSError as exc:
            self.log.error("on the full disk: %s", exc)

    def _on_alive(self, stage: str, alive: bool) -> None:  # Zenoh thread
        if stage != LAUNCHER:
            (self.alive_peers.add if alive else self.alive_peers.discard)(stage)
            return
        if alive:
            self._launcher_seen, self._launcher_gone_at = True, None
        elif self._launcher_seen:
            self._launcher_gone_at = time.monotonic()

    def orphaned(self) -> str | None:
        """Why this stage has lost its launcher, or None: its parent process is no longer the
        launcher that started it, or the launcher's liveliness token has been gone for
        ``orphan_grace`` seconds."""
        pid = self.config.launcher_pid
        if pid is not None and os.getppid() != pid:
            return f"the launcher (pid {pid}) is gone"
        gone = self._launcher_gone_at
        if gone is not None and time.monotonic() - gone >= self.config.orphan_grace:
            return f"the launcher's liveliness token has been gone for {self.config.orphan_grace:g} s"
        return None

    def _orphaned_by_signal(self, wait: float = 2.0) -> str | None:
        """:meth:`orphaned`, after a signal that may be the launcher's death (die-with-parent).

        Linux sends that signal when the launcher's thread that started this process exits;
        the other threads of a killed launcher may still be going, and this process is
        reparented only once the last has: ``getppid()`` is then still the launcher's pid
        for a moment.  So a signal with the launcher seemingly alive is given ``wait``
        seconds to show whether the launcher is going.
        """
        why = self.orphaned()
        if why or not self._signals or self.config.launcher_pid is None:
            return why
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            time.sleep(0.05)
            if os.getppid() != self.config.launcher_pid:
                return self.orphaned()
        return None

    def _check_orphaned(self) -> None:
        now = time.monotonic()
        if now - self._orphan_checked < 0.5:
            return
        self._orphan_checked = now
        why = self.orphaned()
        if why:
            self.exit_reason = why
            self.log.error("%s: stopping (exit status 3)", why)
            self.report_error("orphaned", f"{why}: stage stops")
            self._stop.set()

    def _loop(self) -> None:
        self._orphan_checked = 0.0
        while not self.stopping:
            self._check_orphaned()
            self._release_held()
            while not self._controls.empty():
                self._control(*self._controls.get_nowait())
            try:
                item = self._queue.get(timeout=self.config.poll_interval)
            except queue.Empty:
                self._run_tick()
                continue
            if item[0] == "miss":
                _, source, count = item
                self.last_miss = time.monotonic()
                self.report_error("missed", f"{count} sample(s) lost beyond recovery from publisher {source}")
            else:
                self._process(*item[1:])

    def _control(self, command: str, payload: bytes) -> None:
        """Handle ``ttl/<run>/control/<stage>/<command>`` on the main thread: record it, call
        :meth:`control`; a rejected command is reported on ``errors`` and changes nothing."""
        key = control_key(self.run_id, self.stage_name, command)
        text = payload.decode("utf-8", errors="replace")
        try:
            shown = json.loads(text) if text.strip() else None
        except (ValueError, RecursionError):  # RecursionError: nested too deep for the parser
            shown = text
        record = {
            "run": self.run_id,
            "stage": self.stage_name,
            "command": command,
            "payload": shown,
            "time": time.time(),
        }
        try:
            outputs = list(self.control(command, payload) or ())
        except Exception as exc:  # a bad command must not stop the stage
            self.log.warning("control %s rejected: %s", command, exc)
            self.recorder.write_json("control", {**record, "accepted": False, "message": str(exc)})
            self.report_error("rejected", f"control message {command!r}: {exc}", key=key, field="payload")
            return
        self.recorder.write_json("control", {**record, "accepted": True})
        self.event("control", message=f"{command} accepted")
        for out in outputs:
            self.publish(out)

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

    def _install_signal_handlers(self):
        """SIGINT and SIGTERM stop the loop through a flag (no lock, no logging in the
        handler: :class:`streamer.processes.SignalFlag`); returns the function restoring the
        previous handlers."""
        self._signals = SignalFlag().install()
        return self._signals.restore

    # ------------------------------------------------------------------ callbacks (Zenoh threads)
    def _on_sample(self, sample) -> None:
        self._queue.put(("sample", str(sample.key_expr), sample.payload, sample.attachment))

    def _on_miss(self, source: str, count: int) -> None:
        self._queue.put(("miss", source, count))

    def _on_control(self, sample) -> None:
        try:
            _, parts = parse_control_key(str(sample.key_expr))
        except KeyExprError:
            return
        if parts in (("stop",), (self.stage_name, "stop")):
            self.log.info("stop requested on %s", sample.key_expr)
            self._stop.set()
        elif len(parts) == 2 and parts[0] == self.stage_name:
            payload = sample.payload.to_bytes() if sample.payload is not None else b""
            self._controls.put((parts[1], payload))

    # ------------------------------------------------------------------ processing
    def _process(self, key: str, payload, attachment) -> None:
        """Validate one message that came on Zenoh key ``key`` and use it (or refuse it).

        Data come on the stream key ``ttl/<run>/<topic>``, the index in the header; from
        the header on, the segment is named ``ttl/<run>/<topic>/<index>``.  Nothing a
        message holds can stop the stage: an exception that escapes the checks (a bug met
        by an unforeseen message) is a recorded rejection of that message (``field:
        message``), and the stage goes on.  An ``OSError`` (the recording's disk) is not the
        message's doing and still stops the stage.
        """
        try:
            self._check_and_use(key, payload, attachment)
        except OSError:
            raise
        except Exception as exc:  # noqa: BLE001 - the loop must outlive any message
            self.rejections += 1
            self.log.exception("%s: unexpected failure while checking a message", key)
            self.report_error(
                "rejected",
                f"unexpected {type(exc).__name__} while checking the message: {exc}",
                key=key,
                field="message",
                details={"traceback": traceback.format_exc(limit=8), "attachment": _preview(attachment)},
            )

    def _check_and_use(self, key: str, payload, attachment) -> None:
        """The body of :meth:`_process`."""
        payload = payload.to_bytes() if hasattr(payload, "to_bytes") else bytes(payload or b"")
        try:
            topic = parse_stream_key(key)
        except KeyExprError as exc:
            self.report_error("rejected", str(exc), key=key, field="key")
            return
        index = None
        try:
            index = parse_header(attachment, key).index
            key = segment_key(self.run_id, topic, index)
            header, arrays = decode(payload, attachment, self.expect(topic, index), key=key)
        except CodecError as exc:
            self.report_error(
                "rejected",
                exc.what,
                index=index,
                key=key,
                field=exc.field,
                details={"payload_bytes": len(payload), "attachment": _preview(attachment)},
            )
            return
        seg = SegmentKey(self.run_id, topic, index)
        try:
            verdict = self.validator.check(seg.topic, header, arrays)
        except Rejected as exc:
            self.rejections += 1
            details = {"producer": header.producer, "t0": header.t0, "fs": header.fs, "checksum": header.checksum}
            what = exc.what
            if exc.kind == "conflict" and exc.field == "payload":  # the first conflicting copy: the other goes too
                held = self.held.withdraw(seg.topic, seg.index)
                kept_out = self.withdraw(seg.topic, seg.index, held)
                details["first_copy"] = "withdrawn" if kept_out else "used"
                what += (
                    "; the first copy is withdrawn, the segment is missing"
                    if kept_out
                    else "; the first copy had been used already"
                )
            self.report_error(exc.kind, what, index=seg.index, key=key, field=exc.field, details=details)
            return
        done = self._done.setdefault(seg.topic, RangeSet())
        if verdict == "duplicate" or seg.index in done:
            self.log.info("%s: identical copy of a processed segment, ignored", key)
            self.event("duplicate", index=seg.index, message=f"{key} already processed (identical copy)")
            return
        self.validator.accepted(seg.topic, header)  # from now on a different copy is a conflict
        if not self.held.put(seg.topic, seg.index, (key, header, arrays, payload), time.monotonic()):
            self._use(key, header, arrays, payload)

    def _release_held(self) -> None:
        """Use the held segments whose wait is over (no conflicting copy came)."""
        for key, header, arrays, payload in self.held.due(time.monotonic()):
            try:
                self._use(key, header, arrays, payload)
            except OSError:
                raise
            except Exception as exc:  # noqa: BLE001 - as in _process: the loop goes on
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
        done = self._done.setdefault(seg.topic, RangeSet())
        self._check_gap(seg.topic, seg.index)
        if self.config.record_inputs:
            self.recorder.write_segment(seg.topic, header, payload)
        else:  # a reference: the payload is in the producer's recording, named by its checksum
            self.recorder.write_json(
                f"{seg.topic}/input", header.to_dict(), schema="ttl.SegmentHeader", log_time=mission_ns(header.t0)
            )
        try:
            outputs = list(self.handle(header, arrays) or ())
            for out in outputs:
                self.publish(out, source=header)
        except OSError as exc:
            if disk_full(exc):
                raise
            self._handle_failed(key, seg.index, exc)
            return
        except Exception as exc:
            self._handle_failed(key, seg.index, exc)
            return
        done.add(seg.index)
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

    def _check_gap(self, topic: str, index: int) -> None:
        """Note the indices an arrival skips, as ranges; :meth:`_report_gaps` reports those
        that do not come within ``gap_grace`` (messages of different keys may arrive out of
        order).  Memory: one entry per gap, whatever its length."""
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

    def _report_gaps(self) -> None:
        now = time.monotonic()
        for topic, gaps in self._suspected.items():
            due = [g for g in gaps if now - g[2] >= self.config.gap_grace]
            for first, last, _, revealed in due:
                missing = f"{first}" if first == last else f"{first}..{last}"
                self.report_error(
                    "gap",
                    f"{topic} segment(s) {missing} missing before {revealed} "
                    f"(not received within {self.config.gap_grace:g} s)",
                    index=revealed,
                    details={"topic": topic, "first_missing": first, "last_missing": last},
                )
            if due:
                gaps[:] = [g for g in gaps if now - g[2] < self.config.gap_grace]

    # ------------------------------------------------------------------ outputs and reports
    def publish(self, out: Output, source: Header | None = None) -> str:
        """Encode, publish and record one output; returns its key."""
        index = out.index if out.index is not None else (source.index if source else None)
        if index is None:
            raise ValueError(f"output on {out.topic!r}: no index and no input segment to take it from")
        fields = {"index": index}
        if source is not None:
            fields.update(t0=source.t0, fs=source.fs)
        fields.update(out.fields)
        fields.update(run=self.run_id, producer=self.stage_name)
        payload, attachment = encode(out.arrays, fields, allow_nonfinite=out.allow_nonfinite)
        publisher = self._publishers.get(out.topic)
        if publisher is None:
            publisher = self.bus.segment_publisher(self.run_id, out.topic, cache=self.config.cache)
            self._publishers[out.topic] = publisher
        key = publisher.put(index, payload, attachment)
        header = json.loads(attachment)
        if self.config.record_outputs:
            self._record_output(out, fields, header, payload)
        if out.summary is not None:
            self.recorder.write_json(
                f"{out.topic}/summary", out.summary, schema=out.summary_schema, log_time=mission_ns(header["t0"])
            )
        return key

    def _record_output(self, out: Output, fields: dict, header: dict, payload) -> None:
        """Record an output, whole or with the arrays of :attr:`Output.record_arrays` only."""
        arrays = out.arrays if isinstance(out.arrays, Mapping) else None
        if out.record_arrays is None or arrays is None or set(out.record_arrays) >= set(arrays):
            self.recorder.write_segment(out.topic, header, payload)
            return
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
        self.recorder.write_segment(out.topic, json.loads(attachment), part)

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
        """Publish an error on ``ttl/<run>/errors/<index>``, record it, log it; returns it."""
        error = stage_record(
            self.run_id, self.stage_name, kind, message, index=index, details=details, key=key, field=field
        )
        self.log.warning(
            "%s%s%s: %s",
            kind,
            f" {key}" if key else "",
            f" field {field!r}" if field else "",
            message,
            extra={"index": index},
        )
        if self.bus is not None:
            try:
                self.bus.put_json(errors_key(self.run_id, index), error)
            except Exception:
                self.log.exception("could not publish the error")
        if self.recorder is not None:
            self.recorder.write_json("errors", error)
        return error

    def warn(self, kind: str, message: str, *, index: int | None = None, **details) -> None:
        """Log and record a warning (topic ``warnings``): not an error, but for the operator's eyes."""
        self.log.warning("%s: %s", kind, message, extra={"index": index})
        if self.recorder is not None:
            self.recorder.write_json(
                "warnings", stage_record(self.run_id, self.stage_name, kind, message, index=index, details=details)
            )

    def event(self, kind: str, *, index: int | None = None, message: str = "", **details) -> None:
        """Record a lifecycle or bookkeeping event in the recording."""
        if self.recorder is not None:
            self.recorder.write_json(
                "events", stage_record(self.run_id, self.stage_name, kind, message, index=index, details=details)
            )


def disk_full(exc: BaseException) -> bool:
    """True for the error of a write to a full disk (or a full quota)."""
    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT)


def _preview(attachment) -> str:
    if attachment is None:
        return ""
    raw = attachment.to_bytes() if hasattr(attachment, "to_bytes") else bytes(attachment)
    return raw[:PREVIEW_CHARS].decode("utf-8", errors="replace")


def stage_arguments(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """Command-line options common to all stages."""
    p = parser or argparse.ArgumentParser()
    p.add_argument("--config", type=Path, help="stage configuration (JSON, StageConfig fields)")
    p.add_argument("--run", help="run id")
    p.add_argument("--name", help="stage name (default: the stage's)")
    p.add_argument("--connect", action="append", default=None, help="Zenoh endpoint to connect to (repeatable)")
    p.add_argument("--listen", action="append", default=None, help="Zenoh endpoint to listen on (repeatable)")
    p.add_argument(
        "--mode",
        choices=("peer", "client"),
        help="Zenoh mode (default: client when --connect is given without --listen, as behind "
        "the router of `ttl run`; else peer)",
    )
    p.add_argument("--zenoh-config", type=Path, help="Zenoh configuration file (JSON5)")
    p.add_argument(
        "--credentials",
        type=Path,
        metavar="DIR",
        help="credentials directory: mutual TLS with DIR/<stage>.pem (endpoints tls/...)",
    )
    p.add_argument("--recordings", type=Path, help="recordings directory")
    p.add_argument("--log-level", default="INFO")
    p.add_argument("--log-json", action="store_true", help="log JSON lines")
    return p


def config_from_args(args: argparse.Namespace) -> StageConfig:
    """A :class:`StageConfig` from ``--config`` and the options overriding it."""
    d = json.loads(args.config.read_text()) if args.config else {}
    for key, value in (("run", args.run), ("stage", args.name), ("recordings", args.recordings)):
        if value:
            d[key] = str(value)
    z = dict(d.get("zenoh") or {})
    for key, value in (
        ("connect", args.connect),
        ("listen", args.listen),
        ("config_file", args.zenoh_config),
        ("credentials", getattr(args, "credentials", None)),
        ("mode", getattr(args, "mode", None)),
    ):
        if value:
            z[key] = value if isinstance(value, list) else str(value)
    if args.connect and not args.listen and not z.get("mode") and not z.get("config_file"):
        z["mode"] = "client"  # a router routes between its clients, not between peers
    d["zenoh"] = z
    return StageConfig.from_dict(d)


def add_common_options(p: argparse.ArgumentParser) -> None:
    """Options of a stage process that override :class:`StageConfig` fields, besides
    :func:`stage_arguments`."""
    p.add_argument("--cache", type=int, help="segments kept per output topic for late joiners")
    p.add_argument(
        "--history", type=int, help="segments asked from each input topic's publisher cache (default: all it holds)"
    )
    p.add_argument("--no-record-inputs", action="store_true", help="do not record input payloads")
    p.add_argument("--poll-interval", type=float, help="longest wait before checking timers [s]")


def stage_main(
    stage_class: type[Stage],
    argv: Sequence[str] | None = None,
    add_options: Callable[[argparse.ArgumentParser], None] | None = None,
    options: Callable[[argparse.Namespace], dict] | None = None,
    check: Callable[[StageConfig], str] | None = None,
) -> int:
    """Entry point of a stage process.

    Parses :func:`stage_arguments`, :func:`add_common_options` and the stage's own
    (``add_options``; ``options(args)`` returns the stage options they set, overriding the
    ``--config`` file's), sets up logging and runs the stage.  With ``--check`` the options
    are validated by ``check(config)`` (which returns a one-line description) and nothing
    runs.  Errors: one line naming the problem on stderr, exit status 2.
    """
    parser = stage_arguments(
        argparse.ArgumentParser(
            prog=f"ttl stage {stage_class.name}", description=(stage_class.__doc__ or "").split("\n\n")[0]
        )
    )
    add_common_options(parser)
    if check is not None:
        parser.add_argument("--check", action="store_true", help="validate the options and exit")
    if add_options is not None:
        add_options(parser)
    args = parser.parse_args(argv)
    configure_logging(args.log_level, args.log_json)
    # before the stage allocates anything or starts threads: freed multi-megabyte blocks go
    # back to the system (streamer/allocator.py; docs/operations.md, Measured)
    allocator.configure()
    try:
        if not args.config and not args.run:
            raise ValueError("--run (or --config with a 'run' field) is required")
        config = config_from_args(args)
        if args.cache is not None:
            config.cache = args.cache
        if args.history is not None:
            config.history = args.history
        if args.no_record_inputs:
            config.record_inputs = False
        if args.poll_interval is not None:
            config.poll_interval = args.poll_interval
        elif not (args.config and "poll_interval" in json.loads(args.config.read_text())):
            config.poll_interval = stage_class.default_poll_interval
        if options is not None:
            config.options = {**config.options, **{k: v for k, v in options(args).items() if v is not None}}
        check_name(config.run, "run id")
        if check is not None and args.check:
            print(check(config))
            return 0
        if config.launcher_pid is not None:
            # die with the launcher: SIGTERM when it dies, so the stage closes its recording at
            # once (Stage.run then says "orphaned"); a launcher already gone is noticed by
            # Stage.orphaned on the first turn of the loop
            set_parent_death_signal(signal.SIGTERM)
        stage = stage_class(config)
    except Exception as exc:  # noqa: BLE001 - one line, no traceback, for user errors
        print(f"ttl stage {stage_class.name}: error: {exc}", file=sys.stderr)
        return 2
    try:
        return stage.run()
    except (TTLError, OSError, ValueError) as exc:
        log.debug("stage failed", exc_info=True)
        print(f"ttl stage {stage_class.name}: error: {exc}", file=sys.stderr)
        return 2
