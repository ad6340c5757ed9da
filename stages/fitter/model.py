"""The fitter's model changes and restarts: what may change its model, when, and how a
restarted fitter gets back the state of the uninterrupted run.

A change (a control message ``ttl/<run>/control/fitter/model``, the adoption of the live
diagnosis' recommendation, a transient that left the window) is checked completely when it
is asked for - a refused one changes nothing, is never recorded as a ``model`` event, and its
reason goes back to the sender (``ttl control`` prints it) - then recorded (a ``model`` event
with the segment it applies from) and queued: it takes effect at the next segment boundary,
never in the middle of a segment (:class:`stages.fitter.live_model.LiveModel`).

A restarted fitter queues again the recorded changes (:meth:`FitterModel.restore_model`),
rebuilds its window from the replayer's recorded telemetry (:meth:`FitterModel.catch_up`),
each segment with the model that was in force for it, and records again the fits an earlier
process published but did not get to record before it was killed
(:meth:`FitterModel.record_again`): ``ttl inspect`` shows every fit the subtractor used.
"""

from __future__ import annotations

import json
import shlex
from typing import TYPE_CHECKING

from streamer.bus.codec import encode
from streamer.bus.keys import to_ranges
from streamer.bus.message_schema import to_jsonable
from streamer.bus.segment_record import segment_meta
from streamer.bus.transport import Output, output_fields
from streamer.recording.recorder import mission_ns
from streamer.runtime.lifecycle import StageStopping
from ttlcore.errors import ConfigError

from .recordings import pushed_again, recorded_models, recorded_telemetry
from .schedule import TRANSIENT_SPACING

if TYPE_CHECKING:  # the mixin is checked as the ordered stage it is mixed into
    from collections.abc import Callable

    from streamer.bus.segment_record import SegmentMeta
    from streamer.runtime.pipeline_stage import OrderedStage
    from ttlcore.estimate.fit import FitSettings
    from ttlcore.estimate.rolling import RollingFit

    from .live_model import LiveModel
    from .rolling_model import RollingModel
    from .schedule import DiagnosisSchedule
    from .window import TelemetryWindow

    _Stage = OrderedStage
else:
    _Stage = object


class FitterModel(_Stage):
    """The model-change and restart part of :class:`stages.fitter.fitter.Fitter` (a mixin: it uses
    the stage's ``model``, ``queue``, ``schedule``, ``window_tm``, recorder and events)."""

    #: ``ttl control fitter model '{"effects": [...]}'`` (:meth:`control`)
    commands = ("model",)
    #: the fitter's state this part works on (set by :class:`stages.fitter.fitter.Fitter`)
    model: LiveModel
    schedule: DiagnosisSchedule
    window_tm: TelemetryWindow
    rolling: RollingFit | None
    rolling_model: RollingModel
    window_duration: float
    settings: Callable[[SegmentMeta], FitSettings]
    _catching_up: bool
    _caught_up: bool
    _restarted: bool

    #: segments an earlier process of this stage recorded a fit of (a restarted fitter), and
    #: those whose summary it recorded too (what ``ttl inspect`` lists)
    recorded_fits: set[int]
    summarised_fits: set[int]

    def change_model(self, new: list[str], *, diagnose: bool = True, report: bool = True, **why) -> None:
        """The model ``new`` (validated) from the next segment on: queued (it takes effect
        when that segment is processed) and recorded as a ``model`` event saying why; its
        first segment diagnosed unless ``diagnose`` is False, and its first fit a window refit
        of both models (``model_change``) unless ``report`` is False.  The model already
        planned for the next segment changes nothing (no event)."""
        start = self.queue.next if self.queue.next is not None else 0
        # never before a change already queued (the order asked is the order in force), nor
        # on a segment an earlier process handled or recorded a fit of (a restarted fitter
        # replaying it: its fit is out): a change applies from a segment still to be published.
        # (The chaos test, seed 825968289: a fitter published and recorded fit 139 and went
        # with its launcher before the board learned of it; its successor, told of a change
        # while at 138, made it from 139: two fits 139 with two models.)
        start = max([start, *(c["from_index"] for c in self.model.pending)])
        while self.handled_before(start) or start in self.recorded_fits:
            start += 1
        before = self.model.planned
        until = self.model.transients_added_until(new) if diagnose else None
        if until is not None:  # transients alone: diagnosed a little later, or at the next slot
            diagnose = False
            if self.transient_at_window_end(until):
                self.schedule.later(start + TRANSIENT_SPACING)
        if not self.model.request(new, start, diagnose=diagnose, report=report):
            self.log.info("model %s already planned from segment %d: nothing to change", ",".join(new), start)
            return
        self.log.info("model change: %s -> %s from segment %d", ",".join(before), ",".join(new), start)
        self.event(
            "model",
            index=start,
            message=f"model {','.join(new)} from segment {start} on",
            effects=new,
            before=before,
            from_index=start,
            diagnose=diagnose,
            report=report,
            **why,
        )

    def diagnosis_done(self, index: int) -> None:
        """The live diagnosis of segment ``index`` ran (:meth:`DiagnosisSchedule.done`).  The
        segments after the previous diagnosis that its window no longer held - a slot that
        fell in a gap is taken after it, on a window that starts after them - are an
        ``undiagnosed`` warning with the command that looks at them offline."""
        missed = to_ranges(self.schedule.done(index, first=self.window_tm.first))
        if not missed:
            return
        run, model = shlex.quote(str(self.config.recordings / self.run_id)), shlex.quote(",".join(self.model.effects))
        spans = ", ".join(f"{a}-{b}" if b > a else f"{a}" for a, b in missed)
        commands = "; ".join(f"ttl refit {run} --segments {a}:{b} --effects {model}" for a, b in missed)
        self.warn(
            "undiagnosed",
            f"fit {index}: segment(s) {spans} in no diagnosed window (this diagnosis came late - its slot fell in "
            f"a gap, or the ones before could not run - on a window from segment {self.window_tm.first}); "
            f"look at them offline: {commands}",
            index=index,
            segments=missed,
        )

    def transient_at_window_end(self, until: float) -> bool:
        """Whether a transient whose span ends at ``until`` [s] reaches the last
        :data:`~stages.fitter.schedule.TRANSIENT_SPACING` segments of the window: an excess
        that may go on past the window's end (a coupling switched on an hour ago, gated as a
        transient), diagnosed again a little later.  One inside the window was seen whole and
        waits for the next slot (the mission week: five diagnoses of ~70 s of CPU each, after
        glitches adopted half a day back, found nothing new)."""
        if not len(self.window_tm):
            return True
        newest = self.window_tm.telemetry[-1]
        return until > self.window_tm.t_stop - TRANSIENT_SPACING * newest.size / newest.fs

    def control(self, command: str, payload: bytes):
        """``model``: ``{"effects": [...]}`` changes the model from the next segment on, once
        checked completely (its columns built on the newest telemetry of the window); a model
        refused raises ValueError with the reason, which the stage reports to the sender."""
        if command != "model":
            return super().control(command, payload)
        newest = self.window_tm.telemetry[-1] if len(self.window_tm) else None
        self.change_model(self.model.parse_control(payload, window=newest), by="control")
        return ()

    def restore_model(self) -> None:
        """A restarted fitter: the model changes an earlier process of this stage accepted
        (``model`` events of ``<stage>.<n>.mcap``, oldest file first) are queued again, each
        from its own segment; a change's ``model_change`` is still due when no fit was
        recorded from the segment it applies from on
        (:meth:`stages.fitter.live_model.LiveModel.restore`).  A damaged or unreadable file is
        skipped (warned)."""
        models, fits, summaries = recorded_models(self.config.recordings / self.run_id, self.stage_name, self.log)
        self.recorded_fits, self.summarised_fits = set(fits), set(summaries)
        try:
            restored = self.model.restore(models, fits)
        except (KeyError, TypeError, ValueError, ConfigError) as exc:
            self.report_error(
                "failed",
                f"restart: the recorded model change cannot be restored ({exc}); "
                f"the configured model {','.join(self.model.effects)} stays",
                field="model",
            )
            return
        if restored is None:
            return
        start, due = restored
        effects = self.model.planned
        self.event(
            "model-restored",
            index=start,
            message=f"model {','.join(effects)} restored from the earlier "
            f"process (in force from segment {start}"
            f"{'; its model change is still to be reported' if due else ''})",
            effects=effects,
            from_index=start,
            change_due=due,
        )
        self.log.info("restart: model %s restored (from segment %d)", ",".join(effects), start)

    def catch_up(self, first: int) -> None:
        """A restarted fitter whose first segment is ``first`` > 0: rebuild the rolling window
        and the telemetry window by pushing again the segments before it, their TDI computed
        again from the replayer's recorded telemetry (``<recordings>/<run>/replayer*.mcap``;
        the same TDI stream as the TDI builder's, from the run's first segment), never from
        the publishers' caches alone.  From the start of the run when the recordings have it,
        so that the state (window, weights of the full refits) is the uninterrupted run's;
        each segment with the model in force for it (the queued changes take effect at their
        own segments).  Control commands come meanwhile are queued (recorded, their senders
        told) and handled once it has caught up.  Told to stop, it leaves the segment (and
        any later one: the window half rebuilt) to its successor (``StageStopping``)."""
        if first == 0:  # the run's first segment: nothing before it
            self._caught_up = True
            return
        if self.stopping:
            raise StageStopping(f"stopping before the window is rebuilt (segment {first})")
        segments = recorded_telemetry(self.config.recordings / self.run_id, first, self.log)
        start = first
        while start - 1 in segments:
            start -= 1
        if start > 0:
            self.report_error(
                "window-shortened",
                f"restart: telemetry segments before {start} are not in the "
                f"recordings; the window restarts at {start} instead of the run's start",
                index=first,
                details={"recorded": to_ranges(sorted(segments))},
            )
        self._catching_up = True
        try:
            for header, item in pushed_again(segments, start, first):
                if self.stopping:  # minutes of pushing: a stage told to stop leaves now
                    raise StageStopping(f"stopping while rebuilding the window (at segment {header.index})")
                self.controls.defer(f"rebuilding its window after a restart, segment {header.index} of {first - 1}")
                self.process(header, item)
        finally:
            self._catching_up = False
        self._caught_up = True
        self.event(
            "restored",
            index=first,
            message=f"window rebuilt from the replayer's recorded telemetry: segments "
            f"{start}..{first - 1} pushed again",
            first=start,
            last=first - 1,
        )
        self.log.info("restart: window rebuilt from segments %d..%d of the recordings", start, first - 1)

    def unrecorded(self, index: int) -> bool:
        """Whether segment ``index`` was handled by an earlier process (its fit published,
        its progress says so) that was killed before its fit (or its summary) reached its
        recording."""
        return self._restarted and index not in self.summarised_fits and self.handled_before(index)

    def record_again(self, index: int, out: Output, source) -> None:
        """Record the fit ``out`` of segment ``index`` that an earlier process published and
        did not record (killed in between), without publishing it again: the fit recomputed
        by the same state is the one published (``fit-recorded-again`` event).  Its summary
        only when the earlier process recorded the fit message itself."""
        _, fields = output_fields(out, self.run_id, self.stage_name, source)
        payload, attachment = encode(out.arrays, fields, allow_nonfinite=out.allow_nonfinite)
        header = json.loads(attachment)
        if index not in self.recorded_fits:
            self.live_recorder.write_segment(out.topic, header, payload)
        if out.summary is not None:
            self.live_recorder.write_json(
                f"{out.topic}/summary", out.summary, schema=out.summary_schema, log_time=mission_ns(header["t0"])
            )
        self.recorded_fits.add(index)
        self.summarised_fits.add(index)
        self.event(
            "fit-recorded-again",
            index=index,
            message=f"fit {index} was published by the earlier process, which was killed before recording "
            "it: recomputed and recorded (not published again)",
        )

    def drop_columns(self, header, gone: list[str]) -> None:
        """The columns ``gone`` dropped from the rolling fit, its window kept
        (:meth:`ttlcore.estimate.rolling.RollingFit.drop`): a model change that only removes
        effects (a transient that left with the window, an effect removed by hand) needs no
        rebuild of the window (:func:`stages.fitter.rolling_model.dropped_columns`)."""
        assert self.rolling is not None  # a change of the rolling fit's columns
        self.rolling.drop(gone)
        self.event(
            "rolling-reduced",
            index=header.index,
            message=f"rolling fit: the columns {', '.join(gone)} dropped, its window of "
            f"{self.rolling.n_segments} FFT segments kept",
            dropped=list(gone),
        )

    def rebuild_rolling(self, header, names: tuple) -> None:
        """A new rolling fit for the regressors ``names``, rebuilt from the window's telemetry
        (:meth:`stages.fitter.rolling_model.RollingModel.rebuilt`): when a model change adds or
        alters the rolling model's columns."""
        window = self.window_tm.telemetry
        self.rolling = self.rolling_model.rebuilt(
            self.settings(segment_meta(header)), self.window_duration, names, window
        )
        self.event(
            "rolling-rebuilt",
            index=header.index,
            message=f"rolling fit rebuilt for {len(names)} regressors from the window's {len(window)} "
            f"telemetry segments",
            names=list(names),
            segments=len(window),
        )

    def drop_expired(self, index: int) -> None:
        """Transients of the model (glitches, gates) whose span has left the window leave the
        model from the next segment on (a ``model`` event ``by: window`` with the specs
        ``removed``; the recordings keep them for offline refits of their span), so that the
        model's size stays bounded over any run; a coupling switched on before the window
        becomes the plain coupling (``settled``: ``{old: new}``).  A removal alone is not
        reported by a window refit (``report`` False in its event)."""
        model = self.model
        if self._catching_up or not len(self.window_tm) or not model.extended or model.change_due or model.pending:
            return  # (a change still to be reported or queued first: the transients go at the next segment)
        gone = model.expired(self.window_tm.t_start)
        settled = model.settled(self.window_tm.t_start)
        if not gone and not settled:
            return
        kept = [settled.get(e, e) for e in model.effects if e not in gone]
        why: dict[str, object] = {"removed": gone} if gone else {}
        if settled:  # switched on before the window: the plain coupling from here on
            why["settled"] = settled
        # a removal alone is not reported by a window refit: the effects gone are zero over
        # the window, both models the same on it (a refit of the window per transient was
        # ~25 s of the fitter's CPU, ten of them in the mission week); the rolling fit drops
        # their columns and keeps its window (RollingFit.drop)
        self.change_model(kept, diagnose=False, report=bool(settled), by="window", decided_at=index, **why)


def adoption_refused(out: dict, exc: Exception) -> None:
    """A recommendation the live model refuses (a limit, a gate over the window): not adopted,
    the reason in the diagnosis' ``adoption``."""
    out["adoption"]["adopted"] = False
    out["adoption"]["reason"] = f"not adopted: {exc}"
    out["adoption"]["refused"] = to_jsonable(str(exc))
