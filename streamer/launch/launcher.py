"""The launcher of ``ttl run``: starts the five stages as processes, supervises them, stops them.

Process model
-------------
* The launcher starts a Zenoh **router** process (``ttl router``, log in
  ``<recordings>/<run>/router.log``) listening on ``tls/127.0.0.1:<free port>`` (or
  ``--listen``), multicast scouting off, and talks to it as a client itself.
* Security (:mod:`streamer.bus.security`): unless ``--insecure``, every session of the run uses
  mutual TLS with a certificate of the run's CA, taken from ``--credentials DIR`` or made on
  first use in ``<recordings>/<run>/credentials`` (keys mode 0600); the router enforces an
  access-control list (each stage publishes only its own topics, the launcher the
  commands).  Peers refused by the router and publications it dropped are read back from
  its log, reported and written to ``<recordings>/<run>/security.jsonl``.
* Each stage is a separate process, ``python -m stages.<name> --config
  <recordings>/<run>/<name>.config.json``, a Zenoh **client** of the router: every message
  goes through the router, and a stage whose link closed (a stall beyond
  :data:`streamer.bus.session.BLOCK_WAIT_BEFORE_CLOSE`) reconnects and catches up from the
  publishers' caches.  (Peers would talk directly, but Zenoh does not re-establish a closed
  peer-to-peer link, and the router does not route between peers.)  Nothing listens on
  anything but 127.0.0.1 unless configured (``--listen``, ``--zenoh-config``).
* Stage logs go to ``<recordings>/<run>/<name>.log``, recordings to
  ``<recordings>/<run>/<name>.mcap`` (and ``monitor.rrd``).

Progress and completion
-----------------------
The pipeline stages publish cumulative progress on ``ttl/<run>/control/progress/<stage>``
(:mod:`streamer.runtime.progress`); the replayer's carries ``segments_total``.  The launcher keeps,
per stage, a :class:`streamer.runtime.progress.Progress`: the union of the indices handled over all
its processes (a restarted stage starts afresh), of the messages it believed (a stage may
not claim a segment its upstream has not handled, :data:`streamer.bus.topology.UPSTREAM`).  It
republishes it on ``ttl/<run>/control/board/<stage>`` for the stages to follow, and shows
``done/total`` per stage, with liveliness (``ttl/<run>/alive/<stage>``).  When every stage
has handled every segment, the launcher sends ``ttl/<run>/control/stop``; the stages close
their recordings and exit 0, and so does ``ttl run`` unless segments were lost: a segment
outside the gaps in the data without a fit or a residual makes it exit 3
(:mod:`streamer.launch.run_verdict`, which also names them in the summary line).

Supervision
-----------
A stage that exits before the stop is reported (exit status, last line of its log); with
``restart`` > 0 it is restarted (up to that many times per stage) and catches up from the
publishers' caches (the replayer stays within ``window`` segments of the slowest stage and
the caches hold ``cache`` > ``window`` + 1 segments); otherwise the run is stopped and
``ttl run`` exits 1.  ``external`` stages are expected but run elsewhere (``ttl stage``
on another host, or started later: late joiners catch up from the caches).

Ctrl-C: the router and the stages run in process groups of their own, so the terminal's
SIGINT reaches the launcher alone; it records the interrupt (``interrupted``), passes SIGINT
on to the stages (each closes its recording), waits for them, stops the router last, and
exits 130 (docs/operations.md, "Ctrl-C").

The Zenoh router is supervised too: when it dies, it is started again on the same endpoints
(up to ``restart`` times); the stages and the launcher, its clients, reconnect by themselves
and recover what was published meanwhile from the publishers' caches.

Journal and resuming
--------------------
The launcher appends what it does to ``<recordings>/<run>/launcher.jsonl`` (one JSON object
a line: ``start`` (with the router's endpoint and credentials), ``stage-died``,
``stage-restarted``, ``router-died``, ``router-restarted``, ``resume``, ``interrupted``,
``end``; ``ttl inspect`` lists them) and keeps the board
it believes in ``<recordings>/<run>/board.json``.  A launcher that died (SIGKILL: its stages
and router stop with it) is replaced by the same command with ``--resume``: every segment
before the first one some stage lacks (``m``) counts as handled, the stages go on as
restarted ones do, and from ``m`` on all is processed again.  The input files must be those
the run was planned with (the pins of ``plan.json``, :mod:`streamer.launch.input_pins`): a file
changed since is refused before anything starts.  A live launcher holds
``launcher.lock``: a second one of the run is refused.

Parts
-----
:mod:`streamer.launch.launch_plan` (options, their checks, the stages' configurations),
:mod:`streamer.launch.run_router` (router process and credentials), :mod:`streamer.launch.supervision`
(stage processes: start, restart, stop), :mod:`streamer.launch.run_journal` (``launcher.jsonl``,
``board.json``), :mod:`streamer.launch.run_verdict` (the final report and the exit status);
:class:`Launcher` composes them with the progress board.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import signal
import socket
import sys
import time
from pathlib import Path

from tqdm import tqdm

from ..bus import security
from ..bus.keys import (
    ERRORS,
    board_key,
    errors_key,
    progress_key,
    progress_pattern,
    to_ranges,
    topic_pattern,
)
from ..bus.reach import zenoh_error_text
from ..bus.segment_stream import declare_segment_publisher, declare_segment_subscriber
from ..bus.session import Bus, SessionSettings, loopback_endpoint
from ..bus.topology import UPSTREAM
from ..recording.recorder import stage_record
from ..runtime.lifecycle import LAUNCHER
from ..runtime.processes import SignalFlag
from ..runtime.progress import Progress, key_stage, parse_progress
from ..runtime.rangeset import RangeSet
from .launch_plan import (
    LaunchError,
    RunOptions,
    cache_size,
    check_replayer,
    expected_stages,
    stage_config,
    stage_module_exists,
)
from .run_journal import append_journal, check_resumed_inputs, cut_board, lock_run, read_board, save_board
from .run_router import Router, make_credentials
from .run_verdict import conflicts, report
from .supervision import Child, Supervisor

__all__ = ["HOLD_PROGRESS", "Child", "LaunchError", "Launcher", "RunOptions", "run", "stage_module_exists"]

log = logging.getLogger(__name__)

#: Seconds a progress message claiming more than its upstream waits for the upstream's progress.
HOLD_PROGRESS = 30.0


class Launcher:
    """Runs one pipeline (see the module docstring); :meth:`run` returns the exit status."""

    def __init__(self, opts: RunOptions, out=None):
        self.opts = opts
        self.out = out or sys.stderr
        self.expected: list[str] = []
        self.alive: dict[str, bool] = {}
        self.progress: dict[str, Progress] = {}  # stage -> what the launcher believed of it
        self.errors: list[dict] = []
        self.events: queue.Queue = queue.Queue()
        self._t0 = time.monotonic()
        self._last_line = ""
        self._last_print = 0.0
        self._live: tqdm | None = None  # the status line, in place on a terminal
        self.endpoint = ""
        self.listen: tuple = ()
        self.run_dir = Path(opts.recordings) / opts.run_id
        self.run_plan: dict | None = None
        self.refused_progress: list[dict] = []  # progress messages refused (forged or inconsistent)
        self._held: list[tuple[dict, float]] = []
        self._boards: dict = {}
        self.credentials: Path | None = None
        #: The stage processes.
        self.stages = Supervisor(opts, self.say, self.journal)
        #: The router process (made in :meth:`run`, once the credentials are known).
        self.router: Router | None = None
        self.resumed_from: int | None = None  # --resume: the first segment handled again
        self._interrupted = False
        self.signals = SignalFlag(())  # SIGINT and SIGTERM noted while the run goes (run)

    @property
    def children(self) -> dict[str, Child]:
        return self.stages.children

    @property
    def refused(self) -> list[dict]:
        """Peers and publications the router refused."""
        return self.router.refused if self.router is not None else []

    # ------------------------------------------------------------------ output
    def say(self, text: str, *, status: bool = False) -> None:
        """A line on standard output; ``--quiet`` leaves out a ``status`` line (docs/cli.md)."""
        if status and self.opts.quiet:
            return
        msg = f"ttl run {self.opts.run_id}: {text}"
        if self._live is not None:  # above the status line, which stays at the bottom
            self._live.write(msg, file=self.out)
        else:
            print(msg, file=self.out, flush=True)

    # ------------------------------------------------------------------ planning
    def plan(self) -> None:
        self.expected = expected_stages(self.opts, self.say)

    @property
    def cache(self) -> int:
        return cache_size(self.opts)

    def stage_config(self, name: str) -> dict:
        return stage_config(self.opts, self.expected, name, self.session_settings(name).to_dict(), self.run_plan)

    def session_settings(self, identity: str) -> SessionSettings:
        """How ``identity`` (a stage, the launcher) connects to the run's router."""
        return SessionSettings(
            mode="client",
            connect=(self.endpoint,),
            credentials=self.credentials,
            identity=identity if self.credentials is not None else None,
        )

    def check_replayer(self) -> None:
        """Validate the source options in a child (``stages.replayer --check``)."""
        if "replayer" in self.opts.external:
            return
        self.run_plan, line = check_replayer(self.opts, self.stage_config("replayer"))
        self.say(f"replay: {line}", status=True)

    # ------------------------------------------------------------------ journal, board, resume
    def journal(self, kind: str, message: str, **details) -> None:
        """Append a record to ``launcher.jsonl`` (module docstring; ``ttl inspect`` reads it)."""
        append_journal(self.run_dir, kind, message, **details)

    def save_board(self) -> None:
        """Write the board to ``board.json`` (:func:`streamer.launch.run_journal.save_board`)."""
        save_board(self.run_dir, self.opts.run_id, self.progress)

    def load_board(self) -> None:
        """``--resume``: the progress of the earlier launcher (``board.json``), cut at the first
        segment some expected stage has not handled, so that every stage goes on from the
        same segment (the publishers' caches of the earlier processes are gone with them)."""
        path = self.run_dir / "board.json"
        total = self.run_plan["segments_total"] if self.run_plan else None
        try:
            progress = read_board(path, self.expected, total)
        except (OSError, ValueError) as exc:
            raise LaunchError(f"--resume: {path}: unreadable ({exc})") from None
        if progress is None:
            self.say(f"--resume: no {path}: the run starts from its first segment", status=True)
            progress = {}
        first, cut = cut_board(progress, self.expected, total)
        self.resumed_from = first
        if first == 0:
            self.journal("resume", "resumed from segment 0 (nothing handled by every stage)", first=0)
            return
        self.progress.update(cut)
        self.say(f"--resume: going on from segment {first} (0..{first - 1} handled by every stage)", status=True)
        self.journal(
            "resume", f"resumed: segments 0..{first - 1} handled by every stage; going on from {first}", first=first
        )

    # ------------------------------------------------------------------ router
    def watch_refusals(self) -> None:
        """Report peers and publications the router refused (from its log)."""
        if self.router is not None:
            self.router.watch_refusals()

    # ------------------------------------------------------------------ bus callbacks
    def _on_progress(self, sample) -> None:
        msg = parse_progress(sample.payload)
        if msg is None:
            return
        stage = key_stage(str(sample.key_expr))
        if msg["stage"] != stage:  # the key is what the access-control list vouches for
            self.events.put(
                (
                    "error",
                    {
                        "stage": stage,
                        "kind": "forged-progress",
                        "key": str(sample.key_expr),
                        "message": f"progress of {msg['stage']!r} published as {stage!r}",
                    },
                )
            )
            return
        self.events.put(("progress", msg))

    def _on_alive(self, stage: str, alive: bool) -> None:
        self.events.put(("alive", stage, alive))

    def _on_error(self, sample) -> None:
        try:
            self.events.put(("error", json.loads(sample.payload.to_bytes())))
        except (ValueError, RecursionError):  # RecursionError: nested too deep for the parser
            self.events.put(("error", {"message": "unreadable error message", "key": str(sample.key_expr)}))

    def _drain_events(self) -> bool:
        changed = False
        while True:
            try:
                ev = self.events.get_nowait()
            except queue.Empty:
                return changed
            changed = True
            if ev[0] == "progress":
                msg, since = ev[1], (ev[2] if len(ev) > 2 else time.monotonic())
                why = self.progress_refused(msg)
                if why and "has not handled" in why and time.monotonic() - since < HOLD_PROGRESS:
                    self._held.append((msg, since))
                    continue
                if why:
                    self.refuse_progress(msg, why)
                    continue
                self.progress.setdefault(msg["stage"], Progress(msg["stage"])).update(
                    msg, self.run_plan["segments_total"] if self.run_plan else None
                )
                self.publish_board(msg["stage"])
            elif ev[0] == "alive":
                _, stage, alive = ev
                if stage in self.expected and self.alive.get(stage) != alive:
                    log.info("%s %s", stage, "alive" if alive else "gone")
                self.alive[stage] = alive
            elif ev[0] == "error":
                err = ev[1]
                self.errors.append(err)
                where = f" segment {err.get('index')}" if err.get("index") is not None else ""
                self.say(f"error from {err.get('stage', '?')}{where}: {err.get('kind', '')}: {err.get('message', '')}")

    def progress_refused(self, msg: dict) -> str | None:
        """Why a progress message is not believed, or None.  A stage started here must report
        with its own process id; ``segments_total`` must be the plan's; a stage may not claim
        a segment its upstream has not handled (progress of a stage started here is checked
        against the one before it in the pipeline)."""
        stage = msg["stage"]
        if stage not in self.expected:
            return f"progress of unknown stage {stage!r}"
        child = self.children.get(stage)
        if child is not None and child.proc is not None and msg.get("pid") not in child.pids:
            return f"pid {msg.get('pid')!r} is not the {stage} process started by this launcher"
        if self.run_plan and msg.get("segments_total") not in (None, self.run_plan["segments_total"]):
            return f"segments_total {msg.get('segments_total')!r} differs from the plan's {self.run_plan['segments_total']}"
        upstream = UPSTREAM.get(stage)
        if upstream in self.expected:
            claims = Progress(stage)
            claims.update(msg, self.run_plan["segments_total"] if self.run_plan else None)
            beyond = claims.handled - self.handled(upstream)
            if beyond:
                return f"claims segment(s) {to_ranges(beyond)[:5]} that {upstream} has not handled"
        return None

    def _recheck_held(self) -> None:
        """Progress held back for claiming more than its upstream: believed once the upstream's
        progress catches up (messages of different keys may arrive out of order), refused after
        ``HOLD_PROGRESS`` seconds."""
        held, self._held = self._held, []
        for msg, since in held:
            self.events.put(("progress", msg, since))

    def publish_board(self, stage: str) -> None:
        """Publish what the launcher believes of ``stage``'s progress (the union over its
        processes of the messages it accepted) on ``ttl/<run>/control/board/<stage>``: the
        pipeline stages of a launched run follow these, not the stages' own messages."""
        pub = self._boards.get(stage)
        if pub is None:
            pub = self._boards[stage] = self.bus.track(
                declare_segment_publisher(self.bus.session, board_key(self.opts.run_id, stage), cache=1)
            )
        pub.put(json.dumps(self.progress[stage].message(self.opts.run_id)).encode())
        self.save_board()

    def refuse_progress(self, msg: dict, why: str) -> None:
        """Record a refused progress message (shown, kept for the report, put on errors)."""
        err = stage_record(
            self.opts.run_id,
            LAUNCHER,
            "forged",
            f"progress message refused: {why}",
            details={"pid": msg.get("pid")},
            key=progress_key(self.opts.run_id, msg["stage"]),
            field="progress",
        )
        self.refused_progress.append(err)
        if len(self.refused_progress) <= 20:
            self.say(err["message"])
        try:
            self.bus.put_json(errors_key(self.opts.run_id, None), err)
        except Exception:  # noqa: BLE001 - the session may be closing
            pass

    # ------------------------------------------------------------------ state
    @property
    def total(self) -> int | None:
        if self.run_plan:
            return self.run_plan["segments_total"]
        totals = [p.segments_total for p in self.progress.values() if p.segments_total]
        return max(totals) if totals else None

    def handled(self, stage: str) -> RangeSet:
        p = self.progress.get(stage)
        return p.handled if p is not None else RangeSet()

    def stage_done(self, stage: str) -> bool:
        """``stage`` has handled every segment of the run."""
        p = self.progress.get(stage)
        return p is not None and p.covers(self.total)

    def status_line(self) -> str:
        total = self.total
        parts = []
        for s in self.expected:
            n = len(self.handled(s))
            mark = "" if self.alive.get(s) else " (down)" if s in self.alive else " (not up)"
            parts.append(f"{s} {n}/{total if total is not None else '?'}{mark}")
        return " | ".join(parts) + f"  [{time.monotonic() - self._t0:.1f} s]"

    def show(self, force: bool = False) -> None:
        """The stages' progress: one line updated in place on a terminal, a new line at most
        every second when it changed in a log (``force``: the final state, printed to stay)."""
        if self.opts.quiet:
            return
        line = self.status_line()
        if self._live is not None or (hasattr(self.out, "isatty") and self.out.isatty()):
            if self._live is None:
                self._live = tqdm(total=None, file=self.out, bar_format="{desc}", leave=True, dynamic_ncols=True)
            self._live.set_description_str(f"ttl run {self.opts.run_id}: {line}")
            if force:
                self.end_status_line()
            return
        now = time.monotonic()
        core = line.rsplit("  [", 1)[0]
        if force or (core != self._last_line and now - self._last_print >= 1.0):
            self._last_line, self._last_print = core, now
            self.say(line)

    def end_status_line(self) -> None:
        """Leave the in-place status line as it is and go on below it."""
        if self._live is not None:
            self._live.close()
            self._live = None

    # ------------------------------------------------------------------ the run
    def run(self) -> int:
        o = self.opts
        self.plan()
        listen = tuple(o.listen) or (loopback_endpoint(protocol="tcp" if o.insecure else "tls"),)
        self.endpoint = next((e for e in listen if "127.0.0.1" in e or "localhost" in e), listen[0])
        self.listen = listen
        # the source is checked before the run directory is made: a refused run leaves nothing
        self.check_replayer()
        if o.resume:  # the input files as the run was planned with them (plan.json)
            check_resumed_inputs(self.run_dir, self.run_plan)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._lock = lock_run(self.run_dir)  # a second launcher of the run is refused here
        if self.run_plan is not None:
            (self.run_dir / "plan.json").write_text(json.dumps(self.run_plan, indent=2))
        self.credentials = make_credentials(
            o, self.run_dir, self.expected, listen, lambda t: self.say(t, status=True), self.say
        )
        self.router = Router(o, self.run_dir, self.credentials, self.say, self.journal)
        # where the run is reached while it lasts (ttl inspect tells a live run by these)
        self.journal(
            "start",
            f"ttl run started (pid {os.getpid()})" + (" with --resume" if o.resume else ""),
            resume=bool(o.resume),
            host=socket.gethostname(),
            router=self.endpoint,
            credentials=None if self.credentials is None else str(self.credentials),
        )
        if o.resume:
            self.load_board()
        # Ctrl-C, SIGTERM: a flag until the stages are told to stop (a KeyboardInterrupt raised
        # in an at-fork hook while a child started was ignored: docs/operations.md, "Ctrl-C")
        self.signals = SignalFlag().install()
        try:
            try:
                self.router.start(listen)
                try:
                    bus = Bus.open(self.session_settings("launcher"))
                except Exception as exc:
                    raise LaunchError(
                        f"cannot reach the run's router at {self.endpoint}: {zenoh_error_text(exc)}"
                    ) from None
                with bus:
                    status = self._run_on(bus)
            except KeyboardInterrupt:  # before the stages started, or again while they stop
                self.interrupted()
                self.end_status_line()
                self.say("run stopped: interrupted")
                status = 130
            self.journal("end", f"ttl run ended (exit status {status})", status=status)
            return status
        finally:
            self.signals.restore()
            self.router.stop()
            self.watch_refusals()
            if self.router.watcher is not None and self.credentials is not None:
                security.dump(self.refused, self.run_dir / "security.jsonl")

    def _run_on(self, bus: Bus) -> int:
        o = self.opts
        self.bus = bus
        bus.track(declare_segment_subscriber(bus.session, progress_pattern(o.run_id), self._on_progress, history=1))
        bus.watch_alive(o.run_id, self._on_alive)
        # the stages stop when this token goes (streamer.runtime.stage.Stage.orphaned)
        bus.declare_alive(o.run_id, LAUNCHER)
        bus.subscriber(topic_pattern(o.run_id, ERRORS), self._on_error)
        for stage in list(self.progress):  # --resume: the board of the earlier launcher, cut
            self.publish_board(stage)
        security_note = "" if self.credentials is None else f" (mutual TLS, credentials {self.credentials})"
        self.say(
            f"router on {', '.join(self.listen)}{security_note}; stages: {', '.join(self.expected)}"
            + (f" (external: {', '.join(o.external)})" if o.external else "")
            + f"; recordings in {self.run_dir}",
            status=True,
        )
        return self._supervise_loop()

    def start_stages(self) -> None:
        """Write each stage's configuration and start it: consumers first, the replayer last."""
        for name in reversed(self.expected):
            if name in self.opts.external:
                continue
            cfg = self.run_dir / f"{name}.config.json"
            cfg.write_text(json.dumps(self.stage_config(name), indent=2))
            self.stages.add(name, cfg, self.run_dir / f"{name}.log")

    def interrupted(self) -> None:
        """Ctrl-C: recorded in the journal at once, before any child is reaped."""
        if not self._interrupted:
            self._interrupted = True
            self.journal("interrupted", "ttl run interrupted (SIGINT, Ctrl-C): stopping the stages", signal="SIGINT")

    def _supervise_loop(self) -> int:
        o = self.opts
        deadline = time.monotonic() + o.timeout if o.timeout else None
        abort = None
        try:
            self.start_stages()  # a Ctrl-C while they start stops those started
            while True:
                if self.signals:  # before any child is reaped
                    abort = "interrupted" if self.signals.received == signal.SIGINT else "terminated"
                    break
                self._drain_events()
                self._recheck_held()
                self.watch_refusals()
                abort = self.stages.supervise()
                if not abort and self.router is not None and self.router.died():
                    abort = self.router.restart()
                if abort:
                    break
                self.show()
                if self.total is not None and all(self.stage_done(s) for s in self.expected):
                    self.show(force=True)
                    self.say("every stage has handled every segment: stopping", status=True)
                    break
                if deadline is not None and time.monotonic() > deadline:
                    abort = f"timed out after {o.timeout:g} s"
                    break
                time.sleep(0.1)
        finally:  # a second Ctrl-C while the stages stop: KeyboardInterrupt (caught in run)
            self.signals.restore()
        if abort == "interrupted":
            self.interrupted()
        self.stages.stop_all(self.bus, signal.SIGINT if abort == "interrupted" else None)
        self._drain_events()
        return self.report(abort)

    def conflicts(self) -> list[str]:
        """The segments of which a stage reported conflicting copies (:func:`streamer.launch.run_verdict.conflicts`)."""
        return conflicts(self.errors)

    def report(self, abort: str | None) -> int:
        """The final report and the exit status (:func:`streamer.launch.run_verdict.report`)."""
        return report(self, abort)


def run(opts: RunOptions, out=None) -> int:
    """Run a pipeline (``ttl run``); returns the exit status."""
    return Launcher(opts, out).run()
