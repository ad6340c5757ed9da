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
The model is a list of effects (option ``effects``, default ``linear-ttl``): any effect
``ttl diagnose`` can fit - named effects, witness effects, fd-couplings, ``vary=``, and
plugins from the stage's configuration (``effect_modules``, never from a message).  The TDI
builder forwards each segment's telemetry (``eta``, ``dws_phi``, ``dws_eta``, ``ltt``) with
its TDI, and the fitter keeps the window's telemetry.  An extended model is fitted two ways:

- **the window refit**, every ``adequacy_every`` segments (default 24: the last segment of
  each day of 1-h segments) and on the first segment of every new model: the window's
  telemetry refitted with the model by :func:`ttlcore.diagnose.diagnoser.refit` under the
  instrument noise model - exactly what ``ttl refit --segments A:B`` does offline on the same
  segments (searched parameters searched again on the window); the meta holds ``adequacy``
  (chi^2/dof per band) and ``model_update: "window refit"``;
- **the rolling update** in between (``model_update`` ``rolling``, the default): the model's
  columns of the new segment are computed from its telemetry with :data:`COLUMN_HISTORY`
  before it (:func:`ttlcore.diagnose.prediction.column_regressors`) and appended to its 24
  TDI regressors, and the rolling fit (:class:`ttlcore.estimate.rolling.RollingFit`, the
  estimator of ``ttl analyze``) fits all of them: the work of one segment, not of a window
  (meta ``model_update: "rolling"``).  It needs every parameter of the model given (a
  searched parameter, or the shifted regressors of ``timing-offset`` and ``ltt-error``, make
  every segment a window refit, as ``model_update`` ``refit`` does for any model).

Either way the fit message carries the model's 24 coefficients, ``extra_parameters`` and,
for the newest segment, each other effect's contribution to X2, Y2, Z2 (array
``model_parts`` (k, 3, n), meta ``model_parts``: the effect specs), which the subtractor
subtracts.  The rolling update and the window refit are two GLS estimates of the same model
(the rolling one weighted by the residual CSD of its last full refit, the window refit by the
instrument noise model): they agree within a fraction of sigma, and a window-refit segment's
residual equals ``ttl refit --residual``'s to 1e-9.  A new model rebuilds the rolling fit
from the window's telemetry; a restarted fitter replays the recorded model changes while it
rebuilds its window, so that its state is the uninterrupted run's.

Every ``diagnose_every`` segments (default 24, counted by index) and on the first segment of
a new model, the window is diagnosed as ``ttl diagnose`` would (:func:`ttlcore.diagnose.diagnoser.diagnose`,
the witness search included): meta ``diagnosis`` holds the failing bands and hours, the top
witnesses and candidates, the recommendation with the ``ttl control`` command that applies
it, and the text report.  With ``adopt`` ``auto`` a recommendation that explains the excess
(:func:`adoptable`) becomes the model from the next segment on (a ``model`` event records
why); ``ask`` (default) only recommends, ``never`` does not diagnose.

A control message ``ttl/<run>/control/fitter/model`` with JSON ``{"effects": [...]}`` (or
``"linear-ttl,drift"``) changes the model from the next segment on (a ``model`` event in the
recording says from which); that segment's fit message carries ``model_change``: both models
refitted on the same window, with chi^2/dof and per-band chi^2/dof before and after, delta
chi^2 and log Bayes factor, and ``candidates``.  A restarted fitter takes the model in force
from the ``model`` events of its earlier processes' recordings (:meth:`Fitter.restore_model`),
not the configured one, and rebuilds its window from the replayer's recorded telemetry
(:meth:`Fitter.catch_up`).
"""

# size: not yet split (issue 22): the live loop (rolling model update, window refits, live
# diagnosis and adoption, restarts) grew here; the rolling-model update and the live diagnosis are
# the next parts to move to streamer/ or ttlcore/.

from __future__ import annotations

import json
import shlex
import sys
from collections import deque

import numpy as np
from threadpoolctl import threadpool_limits

from streamer.keys import to_ranges
from streamer.memtrace import release_free_memory
from streamer.messages import concatenate_telemetry, tdi_expect, tdi_of, telemetry_of
from streamer.pipeline_stage import OrderedStage
from streamer.rangeset import RangeSet
from streamer.recorder import read_recording, to_jsonable
from streamer.refit import refit_settings
from streamer.stage import Output, stage_main
from ttlcore.conventions import COEFFICIENT_NAMES, DAY, parse_duration
from ttlcore.diagnose.candidates import candidates
from ttlcore.diagnose.diagnoser import diagnose, refit, text_report
from ttlcore.diagnose.prediction import column_regressors, effect_predictions
from ttlcore.effects import make_effects
from ttlcore.effects.glitch import merge_gates, split_gates
from ttlcore.errors import ConfigError, TTLError
from ttlcore.estimate.fit import FitSettings, with_extra_regressors
from ttlcore.estimate.rolling import RollingFit
from ttlcore.io.telemetry import Telemetry
from ttlcore.tdi.data import TDIData, TDIStream

UNITS = {"coefficients": "m/rad", "sigma": "m/rad", "covariance": "m^2/rad^2", "model_parts": "fractional frequency"}
#: Candidates reported in a fit message.
TOP_CANDIDATES = 3
#: Adoption modes of ``--adopt``.
ADOPT_MODES = ("ask", "auto", "never")
#: How an extended model is fitted between the window refits of ``--model-update``.
MODEL_UPDATES = ("rolling", "refit")
#: Telemetry [s] before a segment from which the rolling model's columns of that segment are
#: computed: the TDI delays (~70 s), a witness' delay of a few light travel times and the
#: ring-in of a column's filter (an fd-coupling pole at 1 mHz decays in 160 s: 1e-5 of it
#: is left after 1800 s).
COLUMN_HISTORY = 1800.0


def transients_meta(transients: dict | None) -> dict | None:
    """The live diagnosis' reading of the window's transients (meta ``diagnosis.transients``):
    the class of the excess (gravitational-wave, glitch, gap, noise-change, missing-coupling...),
    whether it is a signal or a defect of the data, and each event's class and span [s]."""
    if not transients:
        return None
    verdict = transients.get("classification") or {}
    return {
        "class": verdict.get("class"),
        "signal": bool(verdict.get("signal")),
        "events": [
            {k: e.get(k) for k in ("class", "t_start", "t_stop", "f_lo", "f_hi", "snr")}
            for e in transients.get("events") or []
        ],
        "gaps": transients.get("gaps") or [],
    }


def adoptable(recommendation: dict | None, log_bf_threshold: float = 2.3) -> tuple[bool, str]:
    """Whether a diagnosis' recommendation may be adopted without a person, and why.

    Adopted only when every one of these holds: a candidate is recommended (``option`` set),
    the diagnosis says it explains the excess (``explains``: at least half of the chi^2
    beyond the tolerance, :func:`ttlcore.diagnose.report.recommendation`), and its evidence
    is decisive (log Bayes factor above ``log_bf_threshold`` - the diagnosis' own
    significance threshold, odds 10:1 - as the candidate's ``significant`` flag already
    requires together with p < alpha)."""
    if not recommendation or not recommendation.get("option") or not recommendation.get("spec"):
        return False, "nothing recommended"
    if not recommendation.get("explains"):
        return False, (
            f"the best candidate explains {100 * float(recommendation.get('explained_fraction') or 0):.0f} % "
            "of the excess: not adopted"
        )
    lbf = recommendation.get("log_bayes_factor")
    if lbf is not None and float(lbf) < log_bf_threshold:
        return False, f"log Bayes factor {float(lbf):.1f} below {log_bf_threshold:g}: not adopted"
    return True, (
        f"explains {100 * float(recommendation.get('explained_fraction') or 0):.0f} % of the excess"
        + (f", log Bayes factor {float(lbf):.1f}" if lbf is not None else "")
    )


class Fitter(OrderedStage):
    """Rolling-window fit of the TTL coefficients (ttlcore.estimate.rolling.RollingFit), and
    of any extended model on the window's telemetry (ttlcore.diagnose.diagnoser.refit)."""

    name = "fitter"
    inputs = ("tdi",)
    follow = ("tdi_builder",)
    reorders = ("tdi",)

    def __init__(self, config):
        super().__init__(config)
        o = self.options
        try:
            self.fit_segment = parse_duration(o["fit_segment"]) if o.get("fit_segment") else None
            self.window_duration = parse_duration(o.get("window_duration") or DAY)
        except ValueError as exc:
            raise ConfigError(f"fitter: {exc}") from None
        band = o.get("band")
        if band is not None and (len(band) != 2 or not 0 < float(band[0]) < float(band[1])):
            raise ConfigError(f"--band: expected FMIN FMAX with 0 < FMIN < FMAX, got {band}")
        self.band = tuple(float(b) for b in band) if band else None
        self.rolling: RollingFit | None = None
        self.fits = RangeSet()
        self._next_t0: float | None = None
        self.effect_modules = tuple(o.get("effect_modules") or ())
        try:
            self.effects = self.check_model(o.get("effects") or ["linear-ttl"])
        except (ValueError, ConfigError) as exc:
            raise ConfigError(f"fitter --effects: {exc}") from None
        self.adequacy_every = int(o.get("adequacy_every", 24) or 0)
        self.candidates_every = int(o.get("candidates_every", 0) or 0)
        self.diagnose_every = int(o.get("diagnose_every", 24) if o.get("diagnose_every") is not None else 24)
        self.adopt = o.get("adopt") or "ask"
        self.model_update = o.get("model_update") or "rolling"
        if self.model_update not in MODEL_UPDATES:
            raise ConfigError(
                f"fitter --model-update: expected one of {', '.join(MODEL_UPDATES)}, got {self.model_update!r}"
            )
        #: the configured model and the recorded changes (from_index, effects) of earlier
        #: processes: a restarted fitter replays the window under the model of each segment
        self._initial_effects = list(self.effects)
        self._model_history: list[tuple[int, list[str]]] = []
        self._catching_up = False  # a restarted fitter pushing the recorded segments again
        #: the rolling model (:meth:`rolling_model`): the effects list it was derived from, its
        #: column effects (None: not rollable), its gates' spans, its columns' readout parts
        self._rolling_key: tuple | None = None
        self._rolling_effects: list | None = None
        self._rolling_gates: list = []
        self._rolling_eiv: dict = {}
        if self.adopt not in ADOPT_MODES:
            raise ConfigError(f"fitter --adopt: expected one of {', '.join(ADOPT_MODES)}, got {self.adopt!r}")
        #: the window's telemetry, (index, Telemetry) in index order
        self.window_tm: deque[tuple[int, Telemetry]] = deque()
        self._model_change: dict | None = None
        self._diagnose_model = False  # the first segment of a new model is diagnosed
        self._segments_seen = 0
        self._last_td: TDIData | None = None
        self._restarted = False
        self._caught_up = False

    def expect(self, topic, index):
        return tdi_expect(self.run_id, index)

    def setup(self) -> None:
        super().setup()
        # an earlier process of this stage left its recording (kept as fitter.<n>.mcap)
        self._restarted = any((self.config.recordings / self.run_id).glob(f"{self.stage_name}.*.mcap"))
        if self._restarted:
            self.restore_model()

    def restore_model(self) -> None:
        """A restarted fitter: the model in force is the last one an earlier process of this
        stage accepted (``model`` events of ``<stage>.<n>.mcap``, oldest file first), and its
        ``model_change`` is still due when no fit was recorded from the segment it applies
        from on.  A damaged or unreadable file is skipped (warned)."""
        run_dir = self.config.recordings / self.run_id
        files = sorted(run_dir.glob(f"{self.stage_name}.*.mcap"), key=lambda p: _file_number(p, self.stage_name))
        last, fits, history = None, set(), []
        for path in files:
            try:
                rec = read_recording(path)
            except Exception as exc:  # noqa: BLE001 - a damaged file: use what the others have
                self.log.warning("cannot read %s: %s", path, exc)
                continue
            models = [e for e in rec.json("events") if e.get("kind") == "model"]
            last = models[-1] if models else last
            history += models
            # the fit's segment is written before its summary: a kill between leaves only the former
            fits.update(m.header.index for m in rec.segments("fit"))
            fits.update(s["index"] for s in rec.json("fit/summary") if isinstance(s.get("index"), int))
        if last is None:
            return
        d = last.get("details") or {}
        try:
            effects, before = self.check_model(d["effects"]), list(d["before"])
            start = int(d["from_index"])
        except (KeyError, TypeError, ValueError, ConfigError) as exc:
            self.report_error(
                "failed",
                f"restart: the recorded model change cannot be restored ({exc}); "
                f"the configured model {','.join(self.effects)} stays",
                field="model",
            )
            return
        self.effects = effects
        for e in history:
            try:
                d_e = e.get("details") or {}
                self._model_history.append((int(d_e["from_index"]), self.check_model(d_e["effects"])))
            except (KeyError, TypeError, ValueError, ConfigError):
                continue  # a change that cannot be restored: the segments before it use the model before
        due = not any(i >= start for i in fits)
        if due:
            self._model_change = {"before": before, "after": effects, "from_index": start}
            self._diagnose_model = True
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

    def settings(self, meta: dict) -> FitSettings:
        kwargs = {"segment_duration": self.fit_segment or float(meta.get("segment_duration") or 3600.0)}
        if self.band:
            kwargs["band"] = self.band
        if meta.get("dws_asd") is not None:
            kwargs["dws_asd"] = float(meta["dws_asd"])
        return FitSettings(**kwargs)

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
        if self.window_tm:
            prev = self.window_tm[-1][1]
            blank = np.full((6, n), np.nan)
            self.window_tm.append(
                (
                    index,
                    Telemetry(
                        t0=td.t0,
                        fs=td.fs,
                        eta=blank,
                        dws_phi=blank,
                        dws_eta=blank,
                        ltt=np.repeat(prev.ltt[:, -1:], n, axis=1),
                        source=prev.source,
                    ),
                )
            )
        self._next_t0 = td.t0 + n / td.fs
        self.event("gap", index=index, message=f"tdi segment {index} missing: {n} NaN samples pushed, window kept")

    # ------------------------------------------------------------------ the model
    def check_model(self, specs) -> list[str]:
        """Validated effect specs of a model (a list, or one comma-separated string)."""
        if isinstance(specs, str):  # the command line's form: ';' between one effect's options
            specs = [s for s in specs.split(",") if s.strip()]
        if not isinstance(specs, (list, tuple)) or not specs or not all(isinstance(s, str) for s in specs):
            raise ValueError(f"effects: expected a list of effect specs, got {specs!r}")
        effects = make_effects([s.strip().replace(";", ",") for s in specs], self.effect_modules)
        if "linear-ttl" not in [e.name for e in effects]:
            raise ValueError("effects: the model must include linear-ttl")
        return [e.spec() for e in effects]

    def change_model(self, new: list[str], **why) -> None:
        """The model ``new`` from the next segment on (a ``model`` event records it and why)."""
        start = self.queue.next if self.queue.next is not None else 0
        self._model_change = {"before": list(self.effects), "after": new, "from_index": start}
        self._diagnose_model = True
        self.log.info("model change: %s -> %s from segment %d", ",".join(self.effects), ",".join(new), start)
        self.event(
            "model",
            index=start,
            message=f"model {','.join(new)} from segment {start} on",
            effects=new,
            before=list(self.effects),
            from_index=start,
            **why,
        )
        self.effects = new

    def control(self, command: str, payload: bytes):
        """``model``: ``{"effects": [...]}`` changes the model from the next segment on."""
        if command != "model":
            return super().control(command, payload)
        try:
            msg = json.loads(payload)
        except ValueError as exc:
            raise ValueError(f"not JSON: {exc}") from None
        if not isinstance(msg, dict) or "effects" not in msg:
            raise ValueError('expected {"effects": [...]}')
        if set(msg) - {"effects"}:
            raise ValueError(
                f"unknown field(s) {sorted(set(msg) - {'effects'})}; plugin modules come from the "
                "stage's configuration only"
            )
        try:
            new = self.check_model(msg["effects"])
        except ConfigError as exc:
            raise ValueError(str(exc)) from None
        self.change_model(new, by="control")
        return ()

    def window_telemetry(self) -> Telemetry:
        """The window's telemetry, one series (:func:`streamer.messages.concatenate_telemetry`:
        the same as ``ttl refit`` builds from the recorded segments)."""
        return concatenate_telemetry([tm for _, tm in self.window_tm], source=str(self.config.recordings / self.run_id))

    def window_fit(self, header) -> dict | None:
        """Meta (and arrays) of the window refitted under the instrument noise model, when due:
        on a model change, on every segment of an extended model, every ``adequacy_every``."""
        change, extended = self._model_change, self.effects != ["linear-ttl"]
        if change is not None and header.index < change["from_index"]:
            change = None  # a segment replayed after a restart, before the change
        due = (
            change is not None
            or (extended and self.rolling_model() is None)
            or (self.adequacy_every > 0 and self._segments_seen % self.adequacy_every == 0)
        )
        if not due:
            return None
        try:
            r = self._window_refit(header.meta, change["before"] if change else ["linear-ttl"])
        except (TTLError, ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
            # the rolling fit of this segment stands; the refit is tried again when next due
            self.log.exception("window refit of segment %d failed", header.index)
            self.warn(
                "window-refit-failed",
                f"fit {header.index}: the window refit failed ({type(exc).__name__}: {exc}); "
                "the rolling fit is published without its adequacy",
                index=header.index,
            )
            return None
        if r is None:
            return None
        if change is not None:
            self._model_change = None
        model = r["_internals"]["fit"]
        adequacy = r["model"]["adequacy"]
        out: dict = {
            "adequacy": {
                "noise_model": "instrument (analytic secondary noises + DWS readout noise), not re-estimated",
                "chi2_dof": adequacy["chi2_dof"],
                "fails": adequacy["fails"],
                "summary": adequacy["summary"],
                "bands": [
                    {k: b[k] for k in ("f_lo", "f_hi", "chi2_dof", "p_value", "fails")} for b in adequacy["bands"]
                ],
            }
        }
        if extended:
            k = [model.parameter_names.index(n) for n in COEFFICIENT_NAMES]
            out["arrays"] = {
                "coefficients": model.ttl_coefficients(),
                "sigma": model.ttl_sigma(),
                "covariance": model.covariance[np.ix_(k, k)],
            }
            out["extra_parameters"] = {
                n: [float(v), float(s)]
                for n, v, s in zip(model.names, model.theta, model.sigma)
                if n not in COEFFICIENT_NAMES
            }
            predictions = effect_predictions(model)
            n = self.window_tm[-1][1].size
            if predictions:
                out["arrays"]["model_parts"] = np.stack([p[:, -n:] for p in predictions.values()])
                out["model_parts"] = list(predictions)
            out["window"] = {"first": self.window_tm[0][0], "last": self.window_tm[-1][0]}
            out["model_update"] = "window refit"
        if change is not None:
            c = r["change"]
            out["model_change"] = {
                "before": change["before"],
                "after": change["after"],
                "chi2_dof_before": c["chi2_dof_before"],
                "chi2_dof_after": c["chi2_dof_after"],
                "bands_before": c["bands_before"],
                "bands_after": c["bands_after"],
                "delta_chi2": c["delta_chi2"],
                "log_bayes_factor": c["log_bayes_factor"],
                "band_edges": [b["f_lo"] for b in adequacy["bands"]] + [adequacy["bands"][-1]["f_hi"]],
            }
        if change is not None or (self.candidates_every > 0 and self._segments_seen % self.candidates_every == 0):
            ranked = candidates(model)
            out["candidates"] = [
                {
                    k: c.get(k)
                    for k in ("effect", "spec", "delta_chi2", "log_bayes_factor", "explained_fraction", "significant")
                }
                for c in ranked[:TOP_CANDIDATES]
            ]
        return out

    def _window_refit(self, meta: dict, baseline: list[str]) -> dict | None:
        """Refit the window's telemetry with the model (and ``baseline``) under the instrument
        noise model, as ``ttl refit`` does; None when the window is still too short for it."""
        try:
            # no time table: the live diagnosis gives the failing hours; without it the refit
            # keeps no column series (~110 MB less at its peak for a day, the same numbers)
            return refit(
                self.window_telemetry(),
                self.effects,
                settings=refit_settings(meta.get("dws_asd"), self.band),
                effect_modules=self.effect_modules,
                baseline=baseline,
                time_table=False,
            )
        except ConfigError as exc:
            self.log.info("no window refit yet: %s", exc)
            return None

    # ------------------------------------------------------------------ the rolling model
    def rolling_model(self) -> list | None:
        """The effects beyond ``linear-ttl`` whose columns the rolling fit carries, or None
        when it carries the 24 regressors alone: under ``--model-update rolling``, an extended
        model whose parameters are all given and whose columns come from the telemetry (not
        the linearised shifts of ``timing-offset`` and ``ltt-error``).  Other extended models
        are refitted on the window every segment."""
        if self.model_update != "rolling" or self.effects == ["linear-ttl"]:
            return None
        key = tuple(self.effects)
        if self._rolling_key != key:
            gates, effects = split_gates(make_effects(list(self.effects), self.effect_modules))
            ok = all(not e.needs_coefficients and not e.unresolved() for e in effects)
            self._rolling_effects = [e for e in effects if e.name != "linear-ttl"] if ok else None
            self._rolling_gates = [g.span for g in gates]
            self._rolling_key = key
        return self._rolling_effects

    def with_model_columns(
        self, td: TDIData, history: list[Telemetry], tm: Telemetry
    ) -> tuple[TDIData, dict, np.ndarray]:
        """``td`` with the rolling model's columns appended to its 24 regressors.

        The columns' X2, Y2, Z2 (:func:`ttlcore.diagnose.prediction.column_regressors`) are
        computed on ``tm`` with up to :data:`COLUMN_HISTORY` of the contiguous telemetry
        before it (``history``, oldest first), and kept on ``tm``'s samples.  Returns the
        extended TDI, effect spec -> its column names, and the columns (3, k, n)."""
        parts, have = [tm], 0.0
        for prev in reversed(history):
            if have >= COLUMN_HISTORY:
                break
            parts.insert(0, prev)
            have += prev.duration
        tail = concatenate_telemetry(parts) if len(parts) > 1 else tm
        s = refit_settings(None, self.band)
        owners: dict[str, tuple] = {}
        columns = []
        self._rolling_eiv = {}  # the DWS readouts each column carries the noise of
        for effect in self._rolling_effects:
            names, xyz, eiv = column_regressors(tail, effect, order=s.order, delay_order=s.delay_order)
            owners[effect.spec()] = names
            columns.append(xyz[:, :, -tm.size :])
            self._rolling_eiv.update(eiv)
        xyz = np.concatenate(columns, axis=1)
        names = tuple(n for ns in owners.values() for n in ns)
        extra = TDIData(
            t0=td.t0, fs=td.fs, channels=td.channels, data=td.data, regressors=xyz, names=names, ltt_mean=td.ltt_mean
        )
        return with_extra_regressors(td, extra), owners, xyz

    def rebuild_rolling(self, header, names: tuple) -> None:
        """A new rolling fit for the regressors ``names``, the window pushed into it again from
        the window's telemetry (TDI from a new stream, the model's columns with their history):
        when the rolling model's columns change (a model change)."""
        self.rolling = RollingFit(
            self.settings(header.meta),
            window_duration=self.window_duration,
            names=names,
            eiv_extra=self._rolling_eiv if self._rolling_effects else None,
        )
        stream = TDIStream()
        window = [tm for _, tm in self.window_tm]
        for j, tm in enumerate(window):
            td = stream.push(tm)
            if self._rolling_effects:
                td = self.with_model_columns(td, window[:j], tm)[0]
            self.rolling.push(td)
        self.event(
            "rolling-rebuilt",
            index=header.index,
            message=f"rolling fit rebuilt for {len(names)} regressors from the window's {len(window)} "
            f"telemetry segments",
            names=list(names),
            segments=len(window),
        )

    def replay_model(self, index: int) -> None:
        """While a restarted fitter catches up: the model in force at segment ``index`` (the
        configured one, then each recorded change from its segment on), so that the rolling
        fit is rebuilt where the uninterrupted run rebuilt it."""
        effects = self._initial_effects
        for start, changed in sorted(self._model_history, key=lambda c: c[0]):
            if start <= index:
                effects = changed
        self.effects = list(effects)

    def rolling_outputs(self, res, td: TDIData, owners: dict, xyz: np.ndarray) -> tuple[dict, dict]:
        """Arrays and meta of a fit of the rolling model: the 24 coefficients (and their
        covariance), ``extra_parameters`` and, for this segment, each effect's contribution
        ``sum_k theta_k TDI(col_k)`` (``model_parts``; zero where a column is not computable)."""
        k = [res.names.index(n) for n in td.names]
        arrays = {
            "coefficients": res.coefficients[k],
            "sigma": res.sigma[k],
            "covariance": res.covariance[np.ix_(k, k)],
        }
        theta = dict(zip(res.names, map(float, res.coefficients)))
        extra = {
            n: [float(v), float(s)] for n, v, s in zip(res.names, res.coefficients, res.sigma) if n not in td.names
        }
        col = {n: j for j, n in enumerate(n for ns in owners.values() for n in ns)}
        parts = [
            np.nan_to_num(sum(theta[n] * xyz[:, col[n]] for n in names), nan=0.0, posinf=0.0, neginf=0.0)
            for names in owners.values()
        ]
        arrays["model_parts"] = np.stack(parts)
        return arrays, {"extra_parameters": extra, "model_parts": list(owners), "model_update": "rolling"}

    # ------------------------------------------------------------------ the live diagnosis
    def diagnosis_due(self, index: int) -> bool:
        if self.adopt == "never" or self.diagnose_every <= 0:
            return False
        return self._diagnose_model or (index + 1) % self.diagnose_every == 0

    def live_diagnosis(self, header) -> dict | None:
        """The window diagnosed as ``ttl diagnose`` would (meta ``diagnosis``); with ``adopt``
        auto, its recommendation adopted when :func:`adoptable`.  None when the window is too
        short for a diagnosis."""
        try:
            report = diagnose(
                self.window_telemetry(),
                self.effects,
                settings=refit_settings(header.meta.get("dws_asd"), self.band),
                effect_modules=self.effect_modules,
            )
        except ConfigError as exc:
            self.log.info("no diagnosis yet: %s", exc)
            return None
        self._diagnose_model = False
        rec = report.get("recommendation")
        first, last = self.window_tm[0][0], self.window_tm[-1][0]
        out = {
            "index": header.index,
            "segments": [first, last],
            "model": list(self.effects),
            "chi2_dof": report["adequacy"]["chi2_dof"],
            "fails": bool(report["adequacy"]["fails"]),
            "bands": [{k: b[k] for k in ("f_lo", "f_hi", "chi2_dof", "fails")} for b in report["adequacy"]["bands"]],
            "failing_hours": [
                [s["t_start"], s["t_stop"]]
                for s in (report["adequacy"].get("time") or {}).get("segments", [])
                if s.get("fails")
            ],
            "summary": report["adequacy"]["summary"],
            "witnesses": [
                {k: w.get(k) for k in ("name", "spec", "delta_chi2", "best_band")}
                for w in ((report.get("witnesses") or {}).get("overall") or [])[:3]
            ],
            "candidates": [
                {
                    k: c.get(k)
                    for k in ("spec", "cli_spec", "delta_chi2", "log_bayes_factor", "explained_fraction", "significant")
                }
                for c in report["candidates"][:5]
            ],
            "transients": transients_meta(report.get("transients")),
            "text": text_report(report, source=f"window {first}..{last}"),
        }
        if rec:
            rec = dict(rec)
            best = next((c for c in report["candidates"] if c.get("spec") == rec.get("spec")), None)
            if best is not None:
                rec["log_bayes_factor"] = best.get("log_bayes_factor")
            if rec.get("spec"):
                # a transient's advice adds several glitches and gates at once (``actions``)
                added = [a["spec"] for a in rec.get("actions") or []] or [rec["spec"]]
                # a gate overlapping one of the model's (an ongoing signal, seen again) is merged
                effects = make_effects([e.replace(";", ",") for e in [*self.effects, *added]], self.effect_modules)
                rec["effects"] = [e.spec() for e in merge_gates(effects)]
                rec["command"] = self.control_command(rec["effects"])
        out["recommendation"] = rec
        ok, why = adoptable(rec)
        if ok and rec["effects"] == list(self.effects):
            ok, why = False, "the model already holds it"
        out["adoption"] = {"mode": self.adopt, "adopted": False, "reason": why}
        if self.adopt == "auto" and ok:
            out["adoption"]["adopted"] = True
            self.change_model(
                self.check_model(rec["effects"]),
                by="adopt auto",
                diagnosis_index=header.index,
                reason=why,
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
        z = self.config.zenoh
        parts = ["ttl", "control", "--run", self.run_id]
        if getattr(z, "connect", None):
            parts += ["--connect", str(list(z.connect)[0])]
        if getattr(z, "credentials", None):
            parts += ["--credentials", str(z.credentials)]
        return shlex.join(parts + [self.stage_name, "model", json.dumps({"effects": list(effects)})])

    # ------------------------------------------------------------------ restarts
    def catch_up(self, first: int) -> None:
        """A restarted fitter whose first segment is ``first`` > 0: rebuild the rolling window
        and the telemetry window by pushing again the segments before it, their TDI computed
        again from the replayer's recorded telemetry (``<recordings>/<run>/replayer*.mcap``;
        the same TDI stream as the TDI builder's, from the run's first segment), never from
        the publishers' caches alone.  From the start of the run when the recordings have it,
        so that the state (window, weights of the full refits) is the uninterrupted run's."""

        run_dir = self.config.recordings / self.run_id
        segments = {}
        for path in sorted(run_dir.glob("replayer*.mcap")):
            try:
                for m in read_recording(path).segments("telemetry"):
                    if m.header.index < first and "eta" in m.arrays:
                        segments.setdefault(m.header.index, m)
            except Exception as exc:  # noqa: BLE001 - a damaged file: use what the others have
                self.log.warning("cannot read %s: %s", path, exc)
        have = sorted(segments)
        start = first
        while start - 1 in segments:
            start -= 1
        if start > 0:
            self.report_error(
                "window-shortened",
                f"restart: telemetry segments before {start} are not in the "
                f"recordings; the window restarts at {start} instead of the run's start",
                index=first,
                details={"recorded": to_ranges(have)},
            )
        stream = TDIStream()
        restored = list(self.effects)
        self._catching_up = True
        try:
            for i in range(start, first):
                m = segments[i]
                tm = telemetry_of(m.header, m.arrays)
                if stream.next_t0 is not None and abs(tm.t0 - stream.next_t0) > 0.5 / tm.fs:
                    stream.reset()
                self.process(m.header, (stream.push(tm), tm))
        finally:
            self._catching_up = False
            self.effects = restored
        self.event(
            "restored",
            index=first,
            message=f"window rebuilt from the replayer's recorded telemetry: segments "
            f"{start}..{first - 1} pushed again",
            first=start,
            last=first - 1,
        )
        self.log.info("restart: window rebuilt from segments %d..%d of the recordings", start, first - 1)

    def process(self, header, item) -> Output | None:
        """Push one segment into the rolling fit and the telemetry window; the fit message if
        it refitted."""
        td, tm = item
        if self.rolling is None and header.index > 0 and self._restarted and not self._caught_up:
            self._caught_up = True
            self.catch_up(header.index)
        if self._catching_up:
            self.replay_model(header.index)
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
        self.window_tm.append((header.index, tm))
        end = tm.t0 + tm.size / tm.fs
        while self.window_tm and self.window_tm[0][1].t0 < end - self.window_duration - 1.0:
            self.window_tm.popleft()
        if res is None:
            self.log.info("segment %d: no FFT segment completed, no refit", header.index)
            return None
        return self.publish_fit(header, td, res, owners, xyz)

    def rolling_update(self, header, td: TDIData, tm: Telemetry):
        """Push a segment into the rolling fit (with the rolling model's columns when there
        is one): ``(result or None, effect spec -> its columns' names or None, the columns)``."""
        owners, xyz, push = None, None, td
        rolling_model = self.rolling_model()
        if rolling_model:
            push, owners, xyz = self.with_model_columns(td, [t for _, t in self.window_tm], tm)
        if self.rolling is None:
            self.rolling = RollingFit(
                self.settings(header.meta),
                window_duration=self.window_duration,
                names=push.names,
                eiv_extra=self._rolling_eiv if owners is not None else None,
            )
            self.log.info(
                "rolling fit: FFT segment %g s, window %g s, band %s, %d regressors",
                self.rolling.settings.segment_duration,
                self.window_duration,
                self.rolling.settings.band,
                len(push.names),
            )
        elif self.rolling.names != push.names:
            self.rebuild_rolling(header, push.names)
        self._next_t0 = td.t0 + td.size / td.fs
        self._last_td = td
        self._segments_seen = header.index + 1  # by index: the same after a restart
        # a model's gates leave their hours out of the rolling fit (whole FFT segments)
        self.rolling.set_gates(self._rolling_gates if rolling_model is not None else ())
        return self.rolling.push(push), owners, xyz

    def publish_fit(self, header, td: TDIData, res, owners: dict | None, xyz) -> Output:
        """The fit message of a segment: the rolling fit's (or the rolling model's), the
        window refit when due, the live diagnosis when due."""
        # a segment an earlier process published the fit of (replayed, or pushed again to
        # rebuild the window): its window fit and diagnosis would be thrown away
        replayed = self.handled_before(header.index)
        window = None if replayed else self.window_fit(header)
        if window is None and not replayed and self.effects != ["linear-ttl"] and self.rolling_model() is None:
            self.warn(
                "model-not-fitted",
                f"fit {header.index}: the model {','.join(self.effects)} could not be fitted "
                "on the window (too short for its spectra): the linear rolling fit is "
                "published, and only the linear TTL is subtracted",
                index=header.index,
            )
        live = None
        if not replayed and self.diagnosis_due(header.index):
            try:
                live = self.live_diagnosis(header)
            except (TTLError, ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
                # the window's fit stands without its diagnosis: published, the failure recorded
                self._diagnose_model = False
                self.log.exception("live diagnosis of segment %d failed", header.index)
                self.warn(
                    "diagnosis-failed",
                    f"fit {header.index}: the live diagnosis failed ({type(exc).__name__}: {exc}); "
                    "the fit is published without it",
                    index=header.index,
                )
        if window is not None or live is not None:
            release_free_memory()  # the refit's and the diagnosis' temporaries: not kept for the next peak
        meta = {
            "names": list(res.names),
            "chi2_dof": res.chi2_dof,
            "t_start": res.t_start,
            "t_stop": res.t_stop,
            "segments": int(res.n_segments),
            "band": list(res.band),
            "converged": bool(res.converged),
            "chi2": res.chi2,
            "dof": res.dof,
            "iterations": int(res.iterations),
            "method": res.method,
            "window_duration": self.window_duration,
            "fft_segment": self.rolling.settings.segment_duration,
            "segments_total": self.segments_total,
            "model": list(self.effects),
        }
        if live is not None and live["adoption"]["adopted"]:
            meta["model"] = live["model"]  # the model of this fit; the adopted one applies from the next segment
        arrays = {"coefficients": res.coefficients, "sigma": res.sigma, "covariance": res.covariance}
        if owners is not None:  # the rolling model: its 24 coefficients, the others and their parts
            meta["names"] = list(td.names)
            arrays, more = self.rolling_outputs(res, td, owners, xyz)
            meta.update(more)
        if window is not None:
            arrays.update(window.pop("arrays", {}))
            meta.update(window)
        if live is not None:
            meta["diagnosis"] = live
        summary = {
            "run": self.run_id,
            "index": header.index,
            "names": meta["names"],
            "coefficients": arrays["coefficients"],
            "sigma": arrays["sigma"],
            "covariance": arrays["covariance"],
            "chi2": res.chi2,
            "dof": res.dof,
            "chi2_dof": res.chi2_dof,
            "t_start": res.t_start,
            "t_end": res.t_stop,
            "segments": int(res.n_segments),
            "fit": res.to_json(),
            **{
                k: meta[k]
                for k in (
                    "model",
                    "adequacy",
                    "model_change",
                    "candidates",
                    "extra_parameters",
                    "model_parts",
                    "diagnosis",
                    "model_update",
                )
                if k in meta
            },
        }
        self.log.info(
            "segment %d: fit over [%.0f, %.0f] s (%d FFT segments), chi2/dof %.3f",
            header.index,
            res.t_start,
            res.t_stop,
            res.n_segments,
            res.chi2_dof,
        )
        excluded = res.extra.get("excluded")
        if excluded and "gate" in excluded:
            meta["excluded"] = excluded
            self.event(
                "segment-gated",
                index=header.index,
                message=f"fit {header.index}: the FFT segment [{excluded['t_start']:.0f}, {excluded['t_stop']:.0f}] s "
                f"overlaps the model's gate {excluded['gate']} s: left out of the rolling fit",
                **excluded,
            )
        elif excluded:
            meta["excluded"] = excluded
            self.warn(
                "segment-excluded",
                f"fit {header.index}: the FFT segment [{excluded['t_start']:.0f}, "
                f"{excluded['t_stop']:.0f}] s is left out of the rolling fit: chi2/dof "
                f"{excluded['chi2_dof']:.3f} at its own best fit, {excluded['z']:.0f} sigma "
                f"above the window's {excluded['reference']:.3f} (a transient: a glitch, a "
                "merger, a noise burst)",
                index=header.index,
                **excluded,
            )
        if not res.converged:
            self.warn(
                "not-converged",
                f"fit {header.index} did not converge in {res.iterations} iterations",
                index=header.index,
                iterations=int(res.iterations),
            )
        if "adequacy" in meta:
            self.log.info(
                "segment %d: model %s, chi2/dof against the instrument noise model %.3f%s",
                header.index,
                ",".join(meta["model"]),
                meta["adequacy"]["chi2_dof"],
                " (fails)" if meta["adequacy"]["fails"] else "",
            )
            if meta["adequacy"]["fails"]:
                self.warn(
                    "model-inadequate",
                    f"fit {header.index}: the model {','.join(meta['model'])} fails against "
                    f"the instrument noise model (chi2/dof {meta['adequacy']['chi2_dof']:.3f}; "
                    + "; ".join(meta["adequacy"]["summary"])
                    + ")",
                    index=header.index,
                    chi2_dof=meta["adequacy"]["chi2_dof"],
                )
        return Output(
            self.output_topic,
            arrays,
            fields={"units": UNITS, "meta": to_jsonable(meta)},
            summary=to_jsonable(summary),
            summary_schema="ttl.Fit",
            allow_nonfinite=True,
        )


def _file_number(path, stage: str) -> int:
    """``n`` of ``<stage>.<n>.mcap`` (the order the processes ran in)."""
    try:
        return int(path.name[len(stage) + 1 : -len(".mcap")])
    except ValueError:
        return 0


def add_options(p) -> None:
    p.add_argument("--fit-segment", help="FFT segment length (default: the telemetry segment length)")
    p.add_argument("--window-duration", help="rolling window length (default 1d)")
    p.add_argument("--band", nargs=2, type=float, metavar=("FMIN", "FMAX"), help="fit band [Hz]")
    p.add_argument("--settle", type=float, help="seconds to collect cached history before choosing the first segment")
    p.add_argument("--gap-timeout", type=float, help="seconds to wait for a missing segment before skipping it")
    p.add_argument(
        "--effects",
        help="the model: effect specs, comma-separated (default linear-ttl; any effect "
        "ttl diagnose can fit, e.g. 'linear-ttl,witness:source=12.eta;link=23;delay=2')",
    )
    p.add_argument("--effect-module", action="append", help="plugin module or .py file defining effects (repeatable)")
    p.add_argument(
        "--adequacy-every",
        type=int,
        help="refit the window under the instrument noise model every N segments (default 24; 0: never)",
    )
    p.add_argument(
        "--candidates-every",
        type=int,
        help="rank the effects not in the model every N segments (default 0: on model changes only)",
    )
    p.add_argument(
        "--diagnose-every",
        type=int,
        help="diagnose the window as ttl diagnose would every N segments (default 24; 0: never)",
    )
    p.add_argument(
        "--adopt",
        choices=ADOPT_MODES,
        help="ask (default): recommend what to add; auto: adopt a recommendation that explains the excess; "
        "never: no live diagnosis",
    )
    p.add_argument(
        "--model-update",
        choices=MODEL_UPDATES,
        help="an extended model between the window refits (every --adequacy-every segments and on a "
        "model change): rolling (default: the rolling fit with the model's columns, the work of one "
        "segment) or refit (the window refitted every segment, as ttl refit)",
    )


def options(args) -> dict:
    return {
        "fit_segment": args.fit_segment,
        "window_duration": args.window_duration,
        "band": args.band,
        "settle": args.settle,
        "gap_timeout": args.gap_timeout,
        "effects": args.effects,
        "effect_modules": args.effect_module,
        "adequacy_every": args.adequacy_every,
        "candidates_every": args.candidates_every,
        "diagnose_every": args.diagnose_every,
        "adopt": args.adopt,
        "model_update": args.model_update,
    }


def main(argv=None) -> int:
    return stage_main(Fitter, argv, add_options, options)


if __name__ == "__main__":
    sys.exit(main())
