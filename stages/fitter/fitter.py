"""Fitter stage: rolling one-day fit of the 24 TTL coefficients, refit on every new segment.

Input ``ttl/<run>/tdi/<i>`` (tdi_builder).  The TDI segments go, in index order, into
:class:`ttlcore.estimate.rolling.RollingFit` -- the batch estimator of :func:`ttlcore.estimate.fit.fit_tdi`
over a rolling window (default one day) of FFT segments.  The FFT segment defaults to the
telemetry segment length (``segment_duration`` of the input meta), so every new segment
completes one FFT segment and triggers a refit; a longer FFT segment refits less often.

Output ``ttl/<run>/fit/<i>`` when segment ``i`` produced a fit: arrays ``coefficients``
(24,) [m/rad], ``sigma`` (24,), ``covariance`` (24, 24); meta ``names``, ``chi2_dof``,
``t_start``, ``t_stop`` (the window fitted), ``segments`` (FFT segments in it), ``band``,
``converged``, plus ``chi2``, ``dof``, ``iterations``, ``method``, ``segments_total``.  The
full :meth:`ttlcore.estimate.fit.FitResult.to_json` goes into the recording on ``fit/summary``
(schema ``ttl.Fit``: the schema's fields, and the whole result under ``fit``).

The progress messages carry ``fits_ranges``: the segments that produced a fit, so that the
subtractor knows, for each segment, which fit is the latest one covering it.

Model, adequacy and the live loop (``docs/diagnostics.md``, "The loop in the live pipeline")
----------------------------------------------------------------------------------------
The model is a list of effects (option ``effects``, default ``linear-ttl``; plugins from the
stage's configuration only), held by :class:`stages.fitter.live_model.LiveModel`.  An extended model
is fitted two ways: the rolling update (its columns of the new segment appended to the 24
regressors, :class:`stages.fitter.rolling_model.RollingModel`) and the window refit every
``adequacy_every`` segments and on a model change (the window's telemetry refitted as ``ttl
refit`` does, with its adequacy, :mod:`stages.fitter.window_refit`).  The fit message carries each
other effect's X2, Y2, Z2 of the newest segment (``model_parts``) for the subtractor.

The window is diagnosed as ``ttl diagnose`` would (meta ``diagnosis``,
:mod:`stages.fitter.live_diagnosis`) on the schedule of :mod:`stages.fitter.schedule` (the first
half-cadence, every ``diagnose_every`` segments, a new model, a sustained excess, the last
segment); with ``adopt`` ``auto`` a recommendation :func:`stages.fitter.live_diagnosis.adoptable`
becomes the model from the next segment on.  A control message
``ttl/<run>/control/fitter/model`` (``{"effects": [...]}``) does the same by hand.  Every
change is a ``model`` event (``by``: ``control``, ``adopt auto``, or ``window`` for the
transients - glitches, gates - that leave the model once their span has left the window), and
its first fit message carries ``model_change`` (both models refitted on the window).  A change
is checked completely when asked for (a refused one is never recorded, its reason goes back to
the sender), then queued and applied at the start of the segment it applies from, never within
a segment (:mod:`stages.fitter.model`).  A restarted fitter queues the recorded changes again,
each from its own segment (:meth:`FitterModel.restore_model`), rebuilds its window from the
replayer's recorded telemetry (:meth:`FitterModel.catch_up`) and records the fits its
predecessor published but did not record.  A fit that took in no new data carries ``stale``
(``no_data`` and a warning when its window holds none).  The
run's last segment, often short, closes its FFT segment with a gap (``RollingFit.flush``): every
segment gets its fit, and one that gets none is a ``no-fit`` warning naming it and why.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from threadpoolctl import threadpool_limits

from stages.tdi_builder import rebuilt_copy
from streamer.bus.fit_record import FitMessage
from streamer.bus.message_schema import to_jsonable
from streamer.bus.messages import tdi_expect, tdi_of, telemetry_of
from streamer.bus.segment_record import SegmentMeta, segment_meta
from streamer.runtime.memtrace import release_free_memory
from streamer.runtime.pipeline_stage import OrderedStage
from streamer.runtime.rangeset import RangeSet
from streamer.runtime.stage import Output, stage_main
from streamer.tools.refit import refit_settings
from ttlcore.diagnose.diagnoser import diagnose
from ttlcore.diagnose.whitened import WhitenedData
from ttlcore.errors import ConfigError, TTLError
from ttlcore.estimate.fit import FitSettings
from ttlcore.estimate.rolling import RollingFit
from ttlcore.io.telemetry import Telemetry
from ttlcore.tdi.data import TDIData

from .live_diagnosis import DiagnosisStopped, control_command, diagnosis_meta, stop_check
from .live_model import LiveModel
from .message import UNITS, fit_meta, fit_summary, notices, rolling_estimate
from .model import FitterModel, adoption_refused
from .options import FitterOptions, add_options, options
from .rolling_model import RollingModel, dropped_columns, rolling_outputs
from .schedule import DiagnosisSchedule
from .window import TelemetryWindow
from .window_refit import window_refit, window_refit_meta


class Fitter(FitterModel, OrderedStage[FitterOptions]):
    """Rolling-window fit of the TTL coefficients (ttlcore.estimate.rolling.RollingFit), and
    of any extended model on the window's telemetry (ttlcore.diagnose.diagnoser.refit).

    Its parts: the model in force (:attr:`model`, :class:`stages.fitter.live_model.LiveModel`), the
    columns the rolling fit carries for it (:attr:`rolling_model`,
    :class:`stages.fitter.rolling_model.RollingModel`), the window refit
    (:mod:`stages.fitter.window_refit`), the live diagnosis (:mod:`stages.fitter.live_diagnosis`) and the
    fit message (:mod:`stages.fitter.message`); what a restart reads is
    :mod:`stages.fitter.recordings`."""

    name = "fitter"
    inputs = ("tdi",)
    rebuilds = {"tdi": rebuilt_copy}  # a tdi segment read back from the recordings lacks its regressors
    follow = ("tdi_builder",)
    reorders = ("tdi",)
    options_type = FitterOptions

    def __init__(self, config):
        super().__init__(config)
        o = self.options  # parsed and checked (FitterOptions)
        self.fit_segment = o.fit_segment
        self.window_duration = o.window_duration
        self.band = o.band
        self.rolling: RollingFit | None = None
        #: the rolling fit's model columns: effect spec -> its columns' names
        self._owners: dict[str, tuple] = {}
        self.fits = RangeSet()
        self._next_t0: float | None = None
        self.effect_modules = o.effect_modules
        try:
            self.model = LiveModel(o.effects, self.effect_modules, self.window_duration)
        except (ValueError, ConfigError) as exc:
            raise ConfigError(f"fitter --effects: {exc}") from None
        self.adequacy_every = o.adequacy_every
        self.candidates_every = o.candidates_every
        self.diagnose_every = o.diagnose_every
        self.diagnosis_workers = o.diagnosis_workers
        self.rolling_model = RollingModel(o.model_update, self.band, self.effect_modules)
        self.adopt = o.adopt
        self.schedule = DiagnosisSchedule(self.diagnose_every if self.adopt != "never" else 0)
        self._catching_up = False  # a restarted fitter pushing the recorded segments again
        #: the window's telemetry, (index, Telemetry) in index order
        self.window_tm = TelemetryWindow(self.window_duration)
        self._segments_seen = 0
        self._last_td: TDIData | None = None
        self._restarted = False
        self._caught_up = False
        self.recorded_fits: set[int] = set()
        self.summarised_fits: set[int] = set()
        self._fresh: tuple[int, float] | None = None  # the last fit that took in new data: index, t_stop
        self._singular: list[str] | None = None  # the model whose window refit was singular (reported)

    @property
    def effects(self) -> list[str]:
        """The effect specs of the model in force."""
        return self.model.effects

    @property
    def started_rolling(self) -> RollingFit:
        """The rolling fit, which the first segment pushed starts (a RuntimeError before)."""
        if self.rolling is None:
            raise RuntimeError("fitter: the rolling fit is used before a segment started it")
        return self.rolling

    def step_failed(self, kind: str, index: int, what: str, exc: Exception, consequence: str) -> None:
        """A step of segment ``index`` (the window refit, the live diagnosis) failed: logged with
        its traceback and recorded as a ``kind`` warning that says what was published instead."""
        self.log.exception("%s of segment %d failed", what, index)
        self.warn(kind, f"fit {index}: the {what} failed ({type(exc).__name__}: {exc}); {consequence}", index=index)

    def expect(self, topic, index):
        return tdi_expect(self.run_id, index)

    def setup(self) -> None:
        super().setup()
        # an earlier process of this stage left its recording (kept as fitter.<n>.mcap)
        self._restarted = any((self.config.recordings / self.run_id).glob(f"{self.stage_name}.*.mcap"))
        if self._restarted:
            self.restore_model()

    def controls_ready(self) -> bool:
        """A restarted fitter handles control commands once it knows its first segment (a
        model change applies from the segment after the one in hand)."""
        return not self._restarted or self.queue.next is not None

    def settings(self, meta: SegmentMeta) -> FitSettings:
        """The rolling fit's settings: the fitter's FFT segment (else the message's
        ``segment_duration``, else 1 h) and band (else the default), the message's DWS ASD."""
        segment = self.fit_segment or float(meta.segment_duration or 3600.0)
        dws_asd = float(meta.dws_asd) if meta.dws_asd is not None else None
        settings = FitSettings(segment_duration=segment, dws_asd=dws_asd)
        return replace(settings, band=self.band) if self.band else settings

    def handle(self, header, arrays):
        # before buffering: a segment that raises is not marked processed
        td, tm = tdi_of(header, arrays), telemetry_of(header, arrays)
        self.enqueue(header, (td, tm))
        return ()

    def progress_fields(self) -> dict:
        return {"fits": self.fits}

    def published(self, index: int) -> None:
        self.fits.add(index)

    def fill_gap(self, index: int) -> None:
        """A TDI segment that will not come: push NaN over its planned span, so that the
        window keeps what it has and the next segment follows in time (RollingFit masks NaN:
        an FFT segment less than half valid is left out, ttlcore.estimate.fit.spectra_of_segment;
        the telemetry window gets NaN readouts and the last light travel times held)."""
        last = self._last_td
        if self.rolling is None or last is None or self._next_t0 is None:
            return
        plan = self.validator.plan
        n = plan.segment(index)[1] if plan is not None else last.size
        nan = np.full((3, n), np.nan)
        names = self.rolling.names  # the 24 regressors, and the rolling model's columns when it has any
        td = TDIData(
            t0=self._next_t0,
            fs=last.fs,
            channels=last.channels,
            data=nan,
            regressors=np.full((3, len(names), n), np.nan),
            names=names,
            ltt_mean=last.ltt_mean,
        )
        self.rolling.push(td)
        self.window_tm.add_gap(index, td.t0, td.fs, n)
        self._next_t0 = td.t0 + n / td.fs
        self.event("gap", index=index, message=f"tdi segment {index} missing: {n} NaN samples pushed, window kept")

    def window_telemetry(self) -> Telemetry:
        """The window's telemetry, one series (:func:`streamer.bus.messages.concatenate_telemetry`:
        the same as ``ttl refit`` builds from the recorded segments)."""
        return self.window_tm.joined(source=str(self.config.recordings / self.run_id))

    def window_whitened(self, header, *, keep: bool) -> tuple[Telemetry, WhitenedData]:
        """The window's telemetry and its whitened data under the instrument noise model,
        shared by the window refit and the live diagnosis of a segment
        (:meth:`stages.fitter.window.TelemetryWindow.whitened`; ``keep`` False: not kept after)."""
        settings = replace(refit_settings(segment_meta(header).dws_asd, self.band), workers=self.diagnosis_workers)
        source = str(self.config.recordings / self.run_id)
        return self.window_tm.whitened(source, settings, self.effect_modules, keep=keep)

    def window_fit(self, header) -> dict | None:
        """Meta (and arrays) of the window refitted under the instrument noise model, when due:
        on a model change, on every segment of an extended model the rolling fit does not
        carry, every ``adequacy_every`` (:mod:`stages.fitter.window_refit`)."""
        change, extended = self.model.change_due, self.model.extended
        if change is not None and header.index < change["from_index"]:
            change = None  # a segment replayed after a restart, before the change
        due = (
            change is not None
            or (extended and self.rolling_model.column_effects(self.effects) is None)
            or (self.adequacy_every > 0 and self._segments_seen % self.adequacy_every == 0)
        )
        if not due:
            return None
        try:
            # kept for the live diagnosis when it runs on this segment too
            tm, data = self.window_whitened(header, keep=self.diagnosis_due(header.index))
            r = window_refit(
                tm,
                self.effects,
                change["before"] if change else ["linear-ttl"],
                dws_asd=segment_meta(header).dws_asd,
                band=self.band,
                effect_modules=self.effect_modules,
                transients=self.rolling.excluded if self.rolling else (),
                log=self.log,
                whitened=data,
            )
        except ConfigError as exc:  # the window too short for its spectra
            self.log.info("no window refit yet: %s", exc)
            return None
        except (TTLError, ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
            # the rolling fit of this segment stands; the refit is tried again when next due
            if isinstance(exc, np.linalg.LinAlgError):
                self.singular_model(header.index, exc)
            self.step_failed(
                "window-refit-failed",
                header.index,
                "window refit",
                exc,
                "the rolling fit is published without its adequacy",
            )
            return None
        if r is None:
            return None
        if change is not None:
            self.model.change_due = None
        ranked = self.candidates_every > 0 and self._segments_seen % self.candidates_every == 0
        # a change's candidates: ranked here only without the live diagnosis, which ranks
        # them on the new model's first segment (an adoption's, a control message's) or at
        # its next slot; a change that only lets transients go needs none.  Ranked on every
        # change, they cost a whole candidate phase per change (docs/operations.md, the
        # mission week's fifth run: a change's segment about 40 % shorter without it)
        ranked = ranked or (change is not None and self.schedule.every <= 0)
        window = (self.window_tm.first, self.window_tm.last, self.window_tm.telemetry[-1].size)
        return window_refit_meta(r, change=change, extended=extended, window=window, ranked=ranked)

    # ------------------------------------------------------------------ the live diagnosis
    def diagnosis_due(self, index: int) -> bool:
        """:meth:`stages.fitter.schedule.DiagnosisSchedule.due`."""
        return self.schedule.due(index, last=self.last_segment(index), new_model=self.model.diagnose_due)

    def live_diagnosis(self, header) -> dict | None:
        """The window diagnosed as ``ttl diagnose`` would (meta ``diagnosis``,
        :func:`stages.fitter.live_diagnosis.diagnosis_meta`); with ``adopt`` auto, its
        recommendation adopted when :func:`stages.fitter.live_diagnosis.adoptable`.  None when the
        window is too short for a diagnosis."""
        if self.stopping:  # the window's whitening alone takes a minute under load
            return None
        try:
            # the whitened window handed over, not held here: the diagnosis lets the ungated
            # data go once gated (a day's: 220 MB) and whitens them again if it needs them
            tm, data = self.window_whitened(header, keep=False)
            settings, handed = data.context.settings, [data]
            del data
            report = diagnose(
                tm,
                self.effects,
                settings=settings,
                effect_modules=self.effect_modules,
                checkpoint=stop_check(
                    lambda: self.stopping, lambda: self.controls.defer(f"diagnosing segment {header.index}")
                ),
                whitened=handed.pop(),
            )
        except ConfigError as exc:
            self.log.info("no diagnosis yet: %s", exc)
            return None
        except DiagnosisStopped as exc:
            self.log.info("fit %d: live diagnosis abandoned: %s", header.index, exc)
            return None
        self.model.diagnose_due = False
        self.diagnosis_done(header.index)
        out, ok = diagnosis_meta(
            report,
            index=header.index,
            window=(self.window_tm.first, self.window_tm.last),
            effects=self.effects,
            effect_modules=self.effect_modules,
            mode=self.adopt,
            command=self.control_command,
        )
        rec = out["recommendation"]
        if self.adopt == "auto" and ok:
            try:
                adopted = self.model.check(rec["effects"])
            except (ValueError, ConfigError) as exc:  # a limit: the model stays
                adoption_refused(out, exc)
                self.warn(
                    "adoption-refused", f"fit {header.index}: recommendation not adopted: {exc}", index=header.index
                )
            else:
                out["adoption"]["adopted"] = True
                self.change_model(
                    adopted,
                    by="adopt auto",
                    diagnosis_index=header.index,
                    reason=out["adoption"]["reason"],
                    recommendation=to_jsonable(rec),
                )
        self.event(
            "diagnosis",
            index=header.index,
            message=out["text"].splitlines()[0] if out["text"] else "",
            recommendation=to_jsonable(rec),
            adoption=out["adoption"],
        )
        return out

    def control_command(self, effects: list[str]) -> str:
        """The ``ttl control`` command that puts ``effects`` in this fitter's model."""
        return control_command(self.run_id, self.stage_name, self.config.zenoh, effects)

    # ------------------------------------------------------------------ a segment
    def process(self, header, item) -> Output | None:
        """Push one segment into the rolling fit and the telemetry window; the fit message if
        it refitted."""
        td, tm = item
        if self._restarted and not self._caught_up and not self._catching_up:
            self.catch_up(header.index)  # caught up only once the window is rebuilt whole
        # the changes queued for this segment: at its start only; a restored one reported
        # again when the segment is computed whole, as publish_fit does
        self.model.apply(header.index, recomputed=self.computed_whole(header.index))
        self.schedule.arrive(header.index)
        if self.rolling is not None and self._next_t0 is not None and abs(td.t0 - self._next_t0) > 0.5 / td.fs:
            self.event(
                "discontinuity",
                index=header.index,
                message=f"t0={td.t0} s does not follow the previous segment (expected {self._next_t0} s); "
                "the window restarts here",
            )
            self.rolling.reset()
            self.window_tm.clear()
        with threadpool_limits(limits=1, user_api="blas"):  # small products: threads would only spin
            res, owners, xyz = self.rolling_update(header, td, tm)
        self.window_tm.add(header.index, tm)
        if res is None and self.last_segment(header.index):
            res = self.rolling.flush() if self.rolling is not None else None
        if res is not None and not np.isfinite(res.sigma).any():  # a window without information
            res = None
        if res is None:
            self.no_fit(header.index, td)
            self.drop_expired(header.index)
            return None
        self.watch_excess(header.index, res)
        out = self.publish_fit(header, td, res, owners, xyz)
        self.drop_expired(header.index)
        return out

    def watch_excess(self, index: int, res) -> None:
        """A sustained excess brings the diagnosis forward (an ``excess`` event;
        :meth:`stages.fitter.schedule.DiagnosisSchedule.outlier`).  The hours left out stay in
        the window's telemetry: a model adopted for them rebuilds the rolling fit with them."""
        if self.schedule.outlier(res.extra.get("excluded")) and not self._catching_up and self.schedule.every > 0:
            self.model.diagnose_due = True
            self.event(
                "excess",
                index=index,
                message=f"fit {index}: {self.schedule.sustained} FFT segments in a row left out as outliers "
                "(a sustained excess, not a transient): the window is diagnosed now",
                segments=self.schedule.sustained,
            )

    def last_segment(self, index: int) -> bool:
        """Whether segment ``index`` is the run's last (the replayer's plan says how many)."""
        return self.segments_total is not None and index == self.segments_total - 1

    def no_fit(self, index: int, td: TDIData) -> None:
        """Segment ``index`` produced no fit: logged when a longer FFT segment is still filling
        (the next fit covers it), a ``no-fit`` warning naming the segment and why otherwise."""
        fft = self.rolling.settings.segment_duration if self.rolling is not None else None
        if fft is not None and fft > td.size / td.fs * 1.001 and not self.last_segment(index):
            return self.log.info("segment %d: FFT segment of %g s still filling, no refit", index, fft)
        why = "no FFT segment completed, or the window determines no parameter"
        if not (self.rolling and self.rolling.last):
            why = "the window holds no FFT segment with data yet (the first ones were gaps or left out)"
        self.warn("no-fit", f"segment {index}: no fit published: {why}", index=index)

    def rolling_update(self, header, td: TDIData, tm: Telemetry):
        """Push a segment into the rolling fit (with the rolling model's columns when there
        is one): ``(result or None, effect spec -> its columns' names or None, the columns)``."""
        owners, xyz, push = None, None, td
        column_effects = self.rolling_model.column_effects(self.effects)
        if column_effects:
            push, owners, xyz = self.rolling_model.with_columns(td, self.window_tm.telemetry, tm)
        if self.rolling is None:
            self.rolling = self.rolling_model.new_fit(
                self.settings(segment_meta(header)), self.window_duration, push.names
            )
            self.log.info(
                "rolling fit: FFT segment %g s, window %g s, band %s, %d regressors",
                self.rolling.settings.segment_duration,
                self.window_duration,
                self.rolling.settings.band,
                len(push.names),
            )
        elif self.rolling.names != push.names:
            gone = dropped_columns(self._owners, owners or {}, self.rolling.names, push.names)
            if gone:
                self.drop_columns(header, gone)
            else:
                self.rebuild_rolling(header, push.names)
        self._owners = dict(owners or {})
        self._next_t0 = td.t0 + td.size / td.fs
        self._last_td = td
        self._segments_seen = header.index + 1  # by index: the same after a restart
        # a model's gates leave their hours out of the rolling fit (whole FFT segments)
        self.rolling.set_gates(self.rolling_model.gates if column_effects is not None else ())
        return self.rolling.push(push), owners, xyz

    def computed_whole(self, index: int) -> bool:
        """Whether segment ``index``'s fit is computed whole (its window refit and diagnosis
        when due): not one an earlier process published, unless it did not record it."""
        return not self.handled_before(index) or self.unrecorded(index)

    def publish_fit(self, header, td: TDIData, res, owners: dict | None, xyz) -> Output:
        """The fit message of a segment: the rolling fit's (or the rolling model's), the
        window refit when due, the live diagnosis when due (:mod:`stages.fitter.message`)."""
        # a segment an earlier process published the fit of (replayed, or pushed again to
        # rebuild the window): its window fit and diagnosis would be thrown away
        replayed = self.handled_before(header.index)
        again = self.unrecorded(header.index)  # published, not recorded: recomputed whole, recorded
        window = None if replayed and not again else self.window_fit(header)
        if window is None and not replayed:
            self.warn_if_not_fitted(header.index)
        live = None if replayed else self.diagnosis_if_due(header)
        self.window_tm.release()  # kept for this segment only (a failed diagnosis did not take it)
        if window is not None or live is not None:
            release_free_memory()  # the refit's and the diagnosis' temporaries: not kept for the next peak
        meta = fit_meta(
            res,
            window_duration=self.window_duration,
            fft_segment=self.started_rolling.settings.segment_duration,
            segments_total=self.segments_total,
            model=self.effects,
        )
        if live is not None and live["adoption"]["adopted"]:
            # the model of this fit; the adopted one applies from the next segment
            meta = meta.with_fields({"model": live["model"]})
        arrays = {"coefficients": res.coefficients, "sigma": res.sigma, "covariance": res.covariance}
        if owners is not None:  # the rolling model: its 24 coefficients, the others and their parts
            arrays, more = rolling_outputs(res, td, owners, xyz)
            meta = meta.with_fields({"names": list(td.names), **more})
        if window is not None:
            if meta.model_update == "rolling" and "coefficients" in window.get("arrays", {}):
                # what the window refit replaces: for the trends
                meta = meta.with_fields({"rolling": rolling_estimate(arrays)})
            arrays.update(window.pop("arrays", {}))
            meta = meta.with_fields(window)
        if live is not None:
            meta = meta.with_fields({"diagnosis": live})
        stale = self.staleness(header.index, res)
        if stale is not None:
            meta = meta.with_fields({"stale": stale})
        summary = fit_summary(self.run_id, header.index, res, meta, arrays)
        self.log.info(
            "segment %d: fit over [%.0f, %.0f] s (%d FFT segments), chi2/dof %.3f",
            header.index,
            res.t_start,
            res.t_stop,
            res.n_segments,
            res.chi2_dof,
        )
        meta = self.record_notices(header.index, res, meta)
        out = Output(
            self.output_topic,
            arrays,
            fields={"units": UNITS, "meta": to_jsonable(meta.to_header())},
            summary=to_jsonable(summary),
            summary_schema="ttl.Fit",
            allow_nonfinite=True,
        )
        if again:
            self.record_again(header.index, out, header)
        return out

    def warn_if_not_fitted(self, index: int) -> None:
        """A ``model-not-fitted`` warning when an extended model had no window refit and
        the rolling model cannot fit it either (the window too short for its spectra)."""
        if self.model.extended and self.rolling_model.column_effects(self.effects) is None:
            self.warn(
                "model-not-fitted",
                f"fit {index}: the model {','.join(self.effects)} could not be fitted "
                "on the window (too short for its spectra): the linear rolling fit is "
                "published, and only the linear TTL is subtracted",
                index=index,
            )

    def diagnosis_if_due(self, header) -> dict | None:
        """The live diagnosis of the window when due (None otherwise, or when it failed: the
        window's fit stands without it, published, the failure recorded)."""
        if not self.diagnosis_due(header.index):
            return None
        try:
            return self.live_diagnosis(header)
        except (TTLError, ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
            self.model.diagnose_due = False
            self.step_failed("diagnosis-failed", header.index, "live diagnosis", exc, "the fit is published without it")
            return None

    def staleness(self, index: int, res) -> dict | None:
        """Meta ``stale`` of a fit that took in no new data (its window did not move: the
        newest FFT segment was a gap, gated or an outlier; the rolling fit's result is the last
        fit's): ``since``, the segment of the last fit that did, and ``no_data`` when the
        window holds no FFT segment at all - then a ``no-data`` warning names the segment, so
        that a copy is never taken for a fresh fit."""
        if self._fresh is None or res.t_stop > self._fresh[1] or self.rolling is None:
            self._fresh = (index, float(res.t_stop))
            return None
        no_data = self.rolling.n_segments == 0
        if no_data and not self._catching_up:
            self.warn(
                "no-data",
                f"fit {index}: the window holds no data (every FFT segment in it gated, a gap or left out): "
                f"the fit of segment {self._fresh[0]} is published again, flagged stale",
                index=index,
                since=self._fresh[0],
            )
        return {"since": self._fresh[0], "no_data": no_data}

    def singular_model(self, index: int, exc: Exception) -> None:
        """The window refit of the model in force was singular: the effects beyond
        ``linear-ttl`` are reported once per model (``model-singular``): one of them is not
        determined by the window (a glitch that explains nothing, a column of zeros)."""
        if self._singular == self.effects:
            return
        self._singular = list(self.effects)
        others = [e for e in self.effects if e != "linear-ttl"]
        self.warn(
            "model-singular",
            f"fit {index}: the window refit of the model is singular ({exc}): one of {', '.join(others) or '-'} "
            "is not determined by the window; the rolling estimate is published until the model changes",
            index=index,
            effects=others,
        )

    def record_notices(self, index: int, res, meta: FitMessage) -> FitMessage:
        """The events and warnings of the fit of segment ``index`` (:func:`stages.fitter.message.notices`);
        returns the meta with the FFT segment left out (``excluded``)."""
        said, meta = notices(index, res, meta)
        for level, kind, message, details in said:
            if level == "event":
                self.event(kind, index=index, message=message, **details)
            else:
                self.warn(kind, message, index=index, **details)
        return meta


def main(argv=None) -> int:
    return stage_main(Fitter, argv, add_options, options)
