"""Monitor stage: ASDs, coefficient trends, model adequacy and alerts, drawn in Rerun.

Inputs ``ttl/<run>/telemetry/<i>``, ``tdi/<i>``, ``fit/<i>`` and ``residual/<i>``; it draws
whatever it receives, so it may start late (it then draws from the publishers' caches on)
or miss a topic.  A message that does not fit is rejected by the stage base (reported on
``errors``); an exception while drawing one is reported as that segment's failure; the
monitor goes on in both cases.

What it draws (the numbers come from :mod:`ttlcore.estimate.monitoring`)
------------------------------------------------------------------------
* ASD of X2 per segment (Welch, Hann, log-averaged 20 per decade, in displacement
  m/sqrt(Hz)): the data (with TTL), the residual, the TTL model, the expected secondary
  noise for the segment's mean arms and the LISA requirement; and per segment the in-band
  (fit band) median of residual / expected, a one-number adequacy check beside the fit's
  chi^2/dof.
* Coefficient trends: every fit's 24 coefficients with +-1 sigma, at the centre of its
  window (the estimate is the window's average); when the telemetry meta names a truth
  (a truth file, or a simulation's coefficient model), the true coefficients averaged over
  the same window (:mod:`stages.monitor.truth`).
* The model timeline (:mod:`stages.monitor.timeline`): which model was in force over which
  fits (a lane per effect), each change (what, by whom, chi^2/dof per band and the residual's
  ASD before and after), the gaps and the hours left out of the fit as shaded spans.
* Step and drift alerts from :class:`ttlcore.diagnose.trends.TrendMonitor` (thresholds and their
  false-alarm reasoning in :mod:`ttlcore.diagnose.trends`), within a model epoch (meta ``model``;
  :mod:`stages.monitor.epochs`).  Each alert is logged as a Rerun text entry, written to the
  MCAP recording as JSON (topic ``alerts``, schema ``ttl.Alert``) and published with the
  fit's index on ``ttl/<run>/monitor/<i>``.

Output ``ttl/<run>/monitor/<i>``, one per segment, once the segment is drawn: its TDI, and
its fit and residual from a fitter / subtractor that reports progress or is alive (they are
waited for until that stage has passed the segment, for as long as it is alive: a loaded
machine may take minutes; a stage that is skipped or not started blocks nothing).  A
segment whose fit or residual could not be drawn, or will not come (its producer gone for
``settle_timeout`` = 60 s, or a sample lost beyond recovery and ``settle_timeout`` passed),
is a recorded failure (``failed`` error, ``failed`` in the progress: ``ttl run`` exits 1),
never a silently incomplete "done" (the bookkeeping: :mod:`stages.monitor.settling`).  An
input its producer announced that does not come (a monitor restarted after the caches moved
on) is caught up as every stage's (:mod:`streamer.runtime.catch_up`): the producer's cache, then its
recordings, else the segment fails with an ``input-lost`` warning.  The
segment is then done for the progress protocol (:mod:`streamer.runtime.progress`), so the replayer
paces on the monitor too and ``ttl run`` stops it only once it has drawn everything.
Arrays ``drift_rate`` (24,) [mm/rad/day] and ``drift_significance`` (24,) of the latest
trend evaluation (0 where not yet defined, see meta ``drift_windows``); meta ``names``,
``alerts`` (the alerts raised since the previous monitor message, each
:meth:`ttlcore.diagnose.trends.Alert.to_json` with the index of the fit that raised it),
``drifting``, ``drift_windows``, ``model_epoch``, ``residual_over_expected`` (latest in-band
median ASD ratio, its segment), ``fit`` (index, chi2_dof, window of the latest fit), ``segments_total``
(:mod:`stages.monitor.status`).  The same goes to the recording on ``monitor/summary``.

Rerun recording ``<recordings>/<run>/monitor.rrd`` (an existing one is kept as
``monitor.<n>.rrd``, like the MCAP files), its rows gathered and written a chunk per entity
every 60 s of wall clock (:class:`streamer.tools.viewer.LiveFanout`), and closed with its RRD
footer however the monitor ends, then its chunks merged (a week: ~210 chunks, not ~17,600); a
blueprint shows everything at once: the views, their entities and the drawing functions
are in :mod:`stages.monitor.views`.  The web viewer ingests what arrives for ~10 ms per
frame, and a frame drawn in software at 1920x1080 takes ~0.5-2 s, so every chunk, the
blueprint's included, costs load time: each entity is one chunk (a time series' style goes
with its earliest row: :class:`stages.monitor.views.SeriesLog`), and the blueprint sets no
view property that its default already gives.  Besides the plots, a run summary (progress, every
alert) and the live diagnosis of the fit messages (meta ``diagnosis``: ``text``,
``recommendation``) are text documents.  Timelines: ``mission_time`` (duration, seconds of mission
time) and ``segment`` (sequence).  A fit that did not converge is a WARN entry of the
alerts log here, and a ``warnings`` message in the fitter's MCAP file (``ttl inspect``).

Live viewing (option ``live``, :mod:`streamer.tools.viewer`): ``"spawn"`` starts the ``rerun``
viewer binary on 127.0.0.1 on a free (or ``viewer_port``) port and streams to it as well
(the window outlives the monitor); ``"serve"`` starts a headless ``rerun`` gRPC server on
127.0.0.1 (stopped with the monitor); a ``rerun+http://`` URL streams to a viewer already
running there.  A viewer that cannot start (no display), is unreachable or goes away is
dropped with a warning and the file goes on.

Options (``StageConfig.options`` or the command line): ``rrd`` (path), ``live``,
``viewer_port``, ``rerun_binary``, ``trends`` (:class:`ttlcore.diagnose.trends.TrendSettings`
fields), ``asd_per_decade`` (20), ``band`` ([fmin, fmax], default the fit band),
``settle_timeout`` (60 s: how long a gone producer is waited for), ``trend_spacing`` (3600 s: the trends get at most one fit per
hour of window end, so that their cost per segment stays bounded with short segments).
"""

from __future__ import annotations

import json
import math
import os
import queue
import time
from collections import deque
from pathlib import Path
from typing import TypeVar

import numpy as np

from streamer.bus.codec import Expect
from streamer.bus.fit_record import FitMessage
from streamer.bus.keys import ERRORS, topic_pattern
from streamer.bus.message_schema import to_jsonable
from streamer.bus.residual_record import ResidualMessage
from streamer.bus.segment_record import segment_meta
from streamer.runtime.pipeline_stage import PipelineStage
from streamer.runtime.processes import stop_process
from streamer.runtime.stage import Output, set_aside, stage_main
from streamer.tools.viewer import LiveFanout, compact_rrd, start_live
from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.diagnose.trends import Alert, TrendMonitor

from . import views
from .epochs import ModelEpochs, trend_estimate
from .noise import NoiseCurves
from .options import MonitorOptions, add_options, options
from .settling import Settling
from .status import UNITS, drift_arrays, status_meta
from .timeline import ModelTimeline
from .truth import FitTruth

P = len(COEFFICIENT_NAMES)
#: Application id of the Rerun recording.
APPLICATION_ID = "ttl_monitor"
T = TypeVar("T")


def _opened(part: T | None, what: str) -> T:
    """``part`` of the monitor that :meth:`Monitor.setup` opens; a RuntimeError before."""
    if part is None:
        raise RuntimeError(f"monitor: {what} is used before the stage's setup()")
    return part


class Monitor(PipelineStage[MonitorOptions]):
    """Draws ASDs, coefficient trends, chi^2/dof and alerts in Rerun (module docstring)."""

    name = "monitor"
    options_type = MonitorOptions
    inputs = ("telemetry", "tdi", "fit", "residual")
    follow = ("tdi_builder", "fitter", "subtractor")
    # no gap reports on arrival: the monitor needs no order, and settles each segment from its
    # producers' progress (Settling.waiting_for); an arrival order says nothing (a forged fit 9 ahead
    # of the stream recorded "fit segments 1..8 missing" for fits that came later)
    reorders = inputs

    def __init__(self, config):
        super().__init__(config)
        o = self.options
        self.live = o.live
        self.per_decade = o.asd_per_decade
        self.band = o.band
        self.trends = TrendMonitor(settings=o.trends)
        self._rec: LiveFanout | None = None  # the Rerun recording (:meth:`open_recording`)
        self._rrd: Path | None = None  # its file (:meth:`setup`)
        self.viewer = None
        self.viewer_url: str | None = None
        self.noise = NoiseCurves(self.band, self.per_decade)  # the noise view's curves
        self._timeline: ModelTimeline | None = None  # the model timeline, gaps, left-out hours
        # the truth beside the fits, and the fits' windows (redrawn when a truth becomes known later)
        self.truth = FitTruth(warn=lambda message: self.text("log", message, "WARN"))
        self.epochs = ModelEpochs()  # where the model changed, as drawn
        self._series: views.SeriesLog | None = None  # the time series' rows (styles with their earliest)
        self._now = 0.0  # mission time [s] the recording is at
        self._errors: queue.Queue = queue.Queue()
        self._pending_alerts: list[Alert] = []
        self._last_fit: dict | None = None
        self._ratio: tuple | None = None
        self._segment_time: dict[int, tuple[float, float]] = {}
        # what was drawn, refused, could not be handled; when a segment is done
        self.settling = Settling(self.inputs, o.settle_timeout)
        self.trend_spacing = o.trend_spacing
        self._trend_t: deque = deque(maxlen=64)  # window ends given to the trends lately
        self._alert_lines: list[str] = []  # every alert so far, for the run summary
        self._band_labels: list[str] = []  # the adequacy bands, for the run summary's key
        self._drawn_to: tuple[int, float] | None = None  # latest segment drawn and its end [s]

    # ------------------------------------------------------------------ what setup() opens
    @property
    def rrd(self) -> Path:
        """The Rerun recording's file (chosen by :meth:`setup`)."""
        return _opened(self._rrd, "the recording's file")

    @rrd.setter
    def rrd(self, path: Path) -> None:
        self._rrd = path

    @property
    def rec(self) -> LiveFanout:
        """The Rerun recording (opened by :meth:`setup`)."""
        return _opened(self._rec, "the Rerun recording")

    @property
    def timeline(self) -> ModelTimeline:
        """The model timeline view (opened by :meth:`setup`)."""
        return _opened(self._timeline, "the model timeline")

    @property
    def series(self) -> views.SeriesLog:
        """The time series' rows (opened by :meth:`setup`)."""
        return _opened(self._series, "the time series")

    # ------------------------------------------------------------------ lifecycle
    def setup(self) -> None:
        super().setup()
        rrd = self.options.rrd or Path(self.config.recordings) / self.run_id / "monitor.rrd"
        self._rrd = set_aside(Path(rrd))
        self._rrd.parent.mkdir(parents=True, exist_ok=True)
        # no display, no binary, nothing listening: the file is still written
        self.viewer, self.viewer_url, viewer_problem = start_live(
            self.live, self.options.viewer_port, self.options.rerun_binary
        )
        if viewer_problem:
            self.log.warning("%s", viewer_problem)
        self.open_recording()
        self.text(
            "log",
            f"monitor of run {self.run_id} started; recording {self.rrd}"
            + (f", live viewer {self.viewer_url}" if self.viewer_url else ""),
        )
        if viewer_problem:
            self.text("log", viewer_problem, "WARN")
        self.live_bus.subscriber(topic_pattern(self.run_id, ERRORS), self._on_error)
        self.flush()
        self.log.info("rerun recording %s%s", self.rrd, f", live {self.viewer_url}" if self.viewer_url else "")

    def open_recording(self) -> None:
        """The Rerun recording (file ``self.rrd``, and the live viewer at ``self.viewer_url``),
        its blueprint and static parts, and the text panels at mission time 0."""
        self._rec = LiveFanout.open(
            APPLICATION_ID,
            f"{self.run_id}-{os.getpid()}-{int(time.time())}",
            self.rrd,
            self.viewer_url,
            views.blueprint(self.band),
            on_live_failure=self._live_failed,
        )
        self.rec.send_recording_name(f"ttl {self.run_id}")
        self._series = views.SeriesLog(self.rec)
        self._timeline = ModelTimeline(self.rec, self._time, self.band)
        views.static_styles(self.rec, self.band)
        self._time(0.0, 0)
        views.first_texts(self.rec)

    def _live_failed(self, exc) -> None:
        self.log.warning("live viewer %s lost (%s): writing the file only", self.viewer_url, exc)
        self.text("log", f"live viewer {self.viewer_url} lost: {exc}", "WARN")

    def teardown(self) -> None:
        self._drain_errors()
        self._close_recording("monitor stopped")
        if self.viewer is not None and self.live == "serve":
            stop_process(self.viewer, 5.0)  # the headless server; a spawned viewer window stays for the user

    def run(self) -> int:
        """The stage's run, and the Rerun file closed on every way out: a stop (control
        message, SIGINT, SIGTERM) goes through :meth:`teardown`; an exception that ends the
        loop does not, and would leave the file without its last batch and its footer."""
        try:
            return super().run()
        finally:
            self._close_recording("monitor ended abnormally")

    def _close_recording(self, message: str) -> None:
        """Write the last batch and the RRD footer, then merge the file's chunks (once; the
        viewer then opens the file from its manifest instead of scanning it)."""
        if self._rec is None or self._rec.closed:
            return
        try:
            self.text("log", message)
        finally:
            self.rec.disconnect()
        started = time.monotonic()
        problem = compact_rrd(self.rrd, self.options.rerun_binary)
        if problem:
            self.log.warning("%s: %s (the file is complete, its chunks not merged)", self.rrd, problem)
        else:
            self.log.info("rerun recording %s: chunks merged in %.1f s", self.rrd, time.monotonic() - started)

    def tick(self):
        self._drain_errors()
        self.fetch_announced()  # announced, not come: the caches, the recordings (streamer.runtime.catch_up)
        self._settle()
        return ()

    def flush(self) -> None:
        if self._rec is not None:
            self._rec.flush()

    # ------------------------------------------------------------------ inputs
    def expect(self, topic, index):
        specs: dict[str, dict[str, tuple[str | None, tuple | None]]] = {
            "telemetry": {"ltt": ("<f8", (6, None))},
            "tdi": {"data": ("<f8", (3, None))},
            "fit": {"coefficients": ("<f8", (P,)), "sigma": ("<f8", (P,))},
            "residual": {"residual": ("<f8", (3, None)), "ttl_model": ("<f8", (3, None))},
        }
        return Expect(run=self.run_id, index=index, arrays=specs[topic], allow_nonfinite=topic != "fit")

    def handle(self, header, arrays):
        self.note_meta(header.meta)
        topic = header.topic
        try:
            out = getattr(self, f"on_{topic}")(header, arrays)
            self.settling.drawn[topic].add(header.index)
        except Exception:
            if topic == "tdi":
                self.mark_failed(header.index)
            else:  # the segment is settled as failed, not waited for (the error is recorded)
                self.settling.unhandled[topic].add(header.index)
            raise
        finally:
            self._drain_errors()
            self.flush()
        self._settle()
        return out

    def withdraw(self, topic, index, held):
        """Conflicting copies: not drawn if still held, not waited for; a TDI segment (what the
        monitor's progress counts) not drawn is given up (failed)."""
        drawn = self.settling.drawn
        self.settling.refused[topic].add(index)
        if topic == "tdi" and index not in drawn["tdi"] and index not in self.done | self.failed:
            self.mark_failed(index)
        return index not in drawn[topic]

    # ------------------------------------------------------------------ catching up (streamer.runtime.catch_up)
    def announced_inputs(self):
        return self.settling.announced(self.board)

    def still_needed(self, topic: str, index: int) -> bool:
        return self.settling.needed(topic, index)

    def settle_lost(self, topic: str, index: int, why: str) -> None:
        """A lost TDI segment is given up (failed); a lost fit or residual is not waited for:
        its segment fails once its TDI is drawn (:meth:`Settling.ready`), with the reason."""
        if topic != "tdi":
            self.settling.unhandled[topic].add(index)
            self.report_error("failed", f"segment {index}: its {topic} did not come: {why}", index=index)
        elif index not in self.done | self.failed:
            self.mark_failed(index)

    # ------------------------------------------------------------------ progress
    def _settle(self) -> None:
        """Publish the status of every drawn segment that waits for nothing more, mark it
        done; fail a segment whose input could not be handled or will not come
        (:meth:`stages.monitor.settling.Settling.ready`); give up segments upstream gave up."""
        board = self.board.snapshot()
        changed = False
        handled = self.done | self.failed
        for i, outcome, waiting, why in self.settling.ready(
            board, handled, self.alive_peers, self.last_miss, time.monotonic()
        ):
            changed = True
            if outcome == "gone":
                self.report_error(
                    "failed",
                    f"segment {i}: its {waiting} did not come: {why}",
                    index=i,
                    details={"waiting_for": waiting},
                )
                self.text("log", f"segment {i}: its {waiting} did not come: {why}", "WARN")
            if outcome != "done":  # will not come, or could not be drawn (error recorded): failed
                self._forget(i)
                self.mark_failed(i)
                continue
            self.publish(self.status(i))
            self.mark_done(i)  # after the output is out (progress protocol)
            self._forget(i)
        tdi = board.get(self.upstream) if self.upstream is not None else None
        if tdi is not None:
            for i in sorted(tdi.failed - self.done - self.failed - self.settling.drawn["tdi"]):
                if i in tdi.gaps:
                    self.draw_gap(i)
                (self.mark_gap if i in tdi.gaps else self.mark_failed)(i)
        self.check_complete()
        if changed:
            self.flush()

    def draw_gap(self, i: int) -> None:
        """Segment ``i`` reported as a gap upstream: a shaded span of the model timeline, over
        the segment's span in the run's plan (else extrapolated from the segments drawn)."""
        plan = self.validator.plan
        span = None
        if plan is not None and 0 <= i < plan.segments_total:
            t0, n = plan.segment(i)
            span = (t0, t0 + n / plan.fs)
        self.timeline.gap(i, span)

    def _forget(self, i: int) -> None:
        """Segment ``i`` is settled: its bookkeeping goes (memory flat in a long run)."""
        self.settling.forget(i)
        self._segment_time.pop(i, None)

    def pending(self) -> int:
        return self.settling.pending(self.done | self.failed)

    def _time(self, t: float, index: int) -> None:
        self._now = float(t)
        self.rec.set_time("mission_time", duration=float(t))
        self.rec.set_time("segment", sequence=int(index))

    def text(self, entity: str, message: str, level: str = "INFO") -> None:
        import rerun as rr

        self.rec.log(entity, rr.TextLog(message, level=level))

    def _on_error(self, sample) -> None:  # Zenoh thread: queue, log in the main thread
        try:
            self._errors.put_nowait(bytes(sample.payload.to_bytes()))
        except Exception:
            pass

    def _drain_errors(self) -> None:

        while True:
            try:
                raw = self._errors.get_nowait()
            except queue.Empty:
                return
            try:
                e = json.loads(raw)
                msg = f"error from {e.get('stage')}: {e.get('kind')} segment {e.get('index')}: {e.get('message')}"
            except (ValueError, RecursionError, AttributeError):  # not JSON, nested too deep, not an object
                msg = f"unreadable error message ({len(raw)} bytes)"
            if self._rec is not None:
                self.text("log", msg, "ERROR")

    # ------------------------------------------------------------------ telemetry
    def on_telemetry(self, header, arrays):
        self.noise.telemetry(header.index, arrays["ltt"])
        meta = segment_meta(header)
        truth = meta.truth
        if self.truth.is_new(truth):
            self.truth.source = truth
            self._time(header.t0, header.index)
            try:
                self.truth.load(truth, block=float(meta.segment_duration or 3600.0))
                if isinstance(truth, dict):  # a simulation on the fly: its coefficient model
                    self.text("log", "simulated on the fly: the simulation's true coefficients drawn beside the fits")
                else:
                    self.text("log", f"truth file {truth}: true coefficients drawn beside the fits")
                # fits drawn before the truth was known (a late joiner), drawn again with it
                for index, centre, coefficients, sigma, window_truth in self.truth.redraw():
                    self._time(centre, index)
                    views.fit_point(self.series, coefficients, sigma, centre, window_truth)
            except Exception as exc:  # a bad truth file must not stop the monitor
                self.truth.truth = None
                self.text("log", f"truth file {truth} unusable: {exc}", "WARN")
                self.report_error("truth", f"{truth}: {exc}", index=header.index)
        return ()

    # ------------------------------------------------------------------ ASDs
    def on_tdi(self, header, arrays):
        self._segment_time[header.index] = (header.t0, header.fs)
        self._time(header.t0, header.index)
        self.noise.tdi(self.rec, header, arrays["data"])
        end = header.t0 + arrays["data"].shape[-1] / header.fs
        self.timeline.segment(header.index, header.t0, end - header.t0)
        if self._drawn_to is None or header.index > self._drawn_to[0]:
            self._drawn_to = (header.index, end)
            self._summary()
        return ()

    def _summary(self) -> None:
        """The run summary document (progress, every alert, the bands' key), at the current time."""
        total = self.segments_total
        if self._drawn_to is None:
            progress = "no segment drawn yet"
        else:
            i, end = self._drawn_to
            progress = (
                f"Drawn to segment {i}" + (f" of {total - 1}" if total else "") + f", mission time {views.days(end)}"
            )
        views.summary_document(self.rec, progress, self._alert_lines, self._band_labels, self.epochs.lines)

    def on_residual(self, header, arrays):
        self._time(header.t0, header.index)
        meta = ResidualMessage.from_header(header.meta, f"residual {header.index}")
        f, asd, ratio = self.noise.residual(self.rec, header, arrays, meta.effects or ())
        if np.isfinite(ratio) and ratio > 0:
            self.series.log("adequacy/log10_residual_over_expected", math.log10(ratio), self._now)
        self._ratio = (header.index, ratio if math.isfinite(ratio) else None)
        self.timeline.residual(header.index, meta.fit_index, f, asd, ratio)
        return ()

    # ------------------------------------------------------------------ fits and trends
    def on_fit(self, header, arrays):
        meta = FitMessage.from_header(header.meta, f"fit {header.index}")
        names = meta.names or COEFFICIENT_NAMES
        if names != COEFFICIENT_NAMES:
            raise ValueError(f"meta.names: expected the 24 canonical coefficient names, got {list(names)[:3]}...")
        C = arrays["coefficients"]
        S = arrays["sigma"]
        t_start, t_stop = meta.t_start, meta.t_stop
        if not (isinstance(t_start, (int, float)) and isinstance(t_stop, (int, float)) and t_stop > t_start):
            raise ValueError(f"meta t_start/t_stop: the fitted window is needed, got {t_start!r}, {t_stop!r}")
        centre = 0.5 * (t_start + t_stop)
        model = list(meta.model) if meta.model is not None else None
        change, style = self.epochs.fit(header.index, model, centre, t_stop), None
        # the model timeline: lanes, the change (who, what), left-out hours, before and after
        said = self.timeline.fit(header.index, meta, centre, change.t_break if change else None, t_stop)
        if change is not None:  # at the change's time (where the lanes switch)
            self._time(change.t_break if change.t_break is not None else centre, header.index)
            self.text("model/log", change.message + (f"; {said}" if said else ""))
            self._summary()
        self._time(centre, header.index)
        if change is not None and change.t_break is not None:  # the lines broken between the two models
            self._time(change.t_break, header.index)
            views.break_series(self.rec)
            style = views.epoch_style(change.number)
            self._time(centre, header.index)
        # the fit and, in the same row, the truth averaged over its window (when known)
        views.fit_point(self.series, C, S, centre, self.truth.mean(t_start, t_stop), style)
        self.truth.add_fit(header.index, t_start, t_stop, C, S)
        chi2 = meta.chi2_dof
        chi2 = float(chi2) if chi2 is not None and math.isfinite(chi2) else None
        if chi2 is not None:
            self.series.log("adequacy/chi2_dof", chi2, centre)
        if meta.converged is False:  # the fitter records it in its MCAP too (warnings)
            self.text("alerts", f"fit {header.index}: did not converge", "WARN")
        self.draw_model(header.index, meta)

        # at most one fit per trend_spacing of window end (10-min segments: six near-equal windows an hour)
        near = [t for t in self._trend_t if abs(t - t_stop) < self.trend_spacing - 1e-6]
        if not near:
            self._trend_t.append(float(t_stop))
            C_t, S_t = trend_estimate(meta, C, S)
            alerts = self.trends.add(header.index, float(t_start), float(t_stop), C_t, S_t, model)
        else:
            alerts = []
        self._time(t_stop, header.index)
        for a in alerts:
            self.text("alerts", a.message, "WARN")
            raised = a.t_detected if math.isfinite(a.t_detected) else t_stop
            self._alert_lines.append(f"raised at {views.days(raised)}: {a.message}")
            self.live_recorder.write_json("alerts", {"run": self.run_id, **a.to_json()}, schema="ttl.Alert")
            self.log.warning("alert: %s", a.message)
        if alerts:
            self._summary()
        self._pending_alerts.extend(alerts)
        self._last_fit = {"index": header.index, "chi2_dof": chi2, "t_start": t_start, "t_stop": t_stop}
        return ()

    def draw_model(self, index: int, meta: FitMessage) -> None:
        """Adequacy against the instrument noise model, model changes and candidates of a fit."""
        adequacy = meta.adequacy
        if adequacy is not None and adequacy.chi2_dof is not None:
            self.series.log("adequacy/instrument/chi2_dof", float(adequacy.chi2_dof), self._now)
            bands = [b.to_json() for b in adequacy.bands]
            views.band_series(self.series, bands, self._now)
            labels = [views.band_label(b) for b in bands]
            if labels and labels != self._band_labels:
                self._band_labels = labels
                self._summary()
            if adequacy.fails:
                self.text(
                    "model/log",
                    f"fit {index}: the model fails against the instrument noise model: " + "; ".join(adequacy.summary),
                    "WARN",
                )
        # the live diagnosis, when there is one
        views.diagnosis_document(self.rec, index, meta.diagnosis)
        views.model_change(self.rec, index, meta.model_change)
        views.candidate_ranking(self.rec, index, meta.candidates)

    def status(self, index: int) -> Output:
        """The ``monitor/<i>`` message of segment ``i`` (:mod:`stages.monitor.status`): trend
        state and the alerts raised since the last one."""
        arrays = drift_arrays(self.trends)
        alerts, self._pending_alerts = self._pending_alerts, []
        t0, fs = self._segment_time.get(index, (0.0, 1.0))
        meta = status_meta(self.trends, alerts, self._ratio, self._last_fit, self.segments_total, f"monitor {index}")
        return Output(
            self.output_topic,
            arrays,
            index=index,
            fields={"t0": t0, "fs": fs, "units": UNITS, "meta": meta.to_header()},
            summary=to_jsonable({"run": self.run_id, "index": index, **meta.summary_fields(), **arrays}),
        )


# ---------------------------------------------------------------------------- entry point


def check(config) -> str:
    m = Monitor(config)
    return (
        f"monitor of run {config.run}: recording {Path(config.recordings) / config.run / 'monitor.rrd'}, "
        f"live {m.live or 'off'}, band {m.band}, trends {m.trends.settings}"
    )


def main(argv=None) -> int:
    return stage_main(Monitor, argv, add_options, options, check)
