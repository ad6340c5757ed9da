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

Model and adequacy (``docs/diagnostics.md``)
--------------------------------------------
The model is a list of effects (option ``effects``, default ``linear-ttl``).  The fitter
keeps the window's TDI segments; every ``adequacy_every`` segments (default 24), and on
every segment while the model holds more than the linear TTL, it refits the window with
:func:`ttlcore.diagnose.diagnoser.refit` under the *instrument* noise model and adds to the fit
message's meta ``model`` (the effect specs) and ``adequacy`` (chi^2/dof, per-band chi^2/dof,
p-value and failure flag; ``fails``).  With an extended model the published 24
coefficients, sigmas and covariance are that model's; ``extra_parameters`` holds the
others (value, sigma).  Every ``candidates_every`` segments (default 0: never) and on a
model change the effects not in the model are ranked (``candidates``: the top 3 with delta chi^2, log Bayes factor,
significance).

A control message ``ttl/<run>/control/fitter/model`` with JSON ``{"effects": [...]}`` (or
``"linear-ttl,drift"``) changes the model from the next segment on (a ``model`` event in the
recording says from which); that segment's fit message carries ``model_change``: both models refitted on the same window, with chi^2/dof
and per-band chi^2/dof before and after, delta chi^2 and log Bayes factor, and
``candidates``.  In the pipeline the fitter sees TDI outputs, not the DWS series, so the
model may use the effects derived from the TDI regressors (``linear-ttl``, ``drift``,
``step``); ``ttl diagnose`` and ``ttl refit`` offer the others.  Plugin modules
(``effect_modules``) are loaded from the stage's configuration only, never from a message.
A restarted fitter takes the model in force from the ``model`` events of its earlier
processes' recordings (:meth:`Fitter.restore_model`), not the configured one.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from collections import deque

import numpy as np

from streamer.codec import Expect
from streamer.keys import to_ranges
from streamer.messages import tdi_of
from streamer.pipeline_stage import OrderedStage
from streamer.plan import RangeSet
from streamer.recorder import read_recording, to_jsonable
from streamer.stage import Output, stage_main
from ttlcore.conventions import COEFFICIENT_NAMES, DAY, parse_duration
from ttlcore.diagnose.candidates import candidates
from ttlcore.diagnose.diagnoser import DiagnoseSettings, refit
from ttlcore.diagnose.effects import make_effects
from ttlcore.errors import ConfigError
from ttlcore.estimate.fit import FitSettings
from ttlcore.estimate.rolling import RollingFit
from ttlcore.tdi.combinations import XYZ
from ttlcore.tdi.data import TDIData

UNITS = {"coefficients": "m/rad", "sigma": "m/rad", "covariance": "m^2/rad^2"}
P = len(COEFFICIENT_NAMES)
#: Effects the fitter can add from TDI outputs alone (no DWS series on its input).
TDI_EFFECTS = ("linear-ttl", "drift", "step")
#: Candidates reported in a fit message.
TOP_CANDIDATES = 3


def tdi_expect(run: str, index: int) -> Expect:
    """What a ``tdi`` message must fit (NaN allowed: first samples of a stream)."""
    return Expect(run=run, index=index, channels=XYZ, allow_nonfinite=True,
                  arrays={"data": ("<f8", (3, None)), "regressors": ("<f8", (3, P, None))})


class Fitter(OrderedStage):
    """Rolling-window fit of the TTL coefficients (ttlcore.estimate.rolling.RollingFit)."""

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
        self.effects = self.check_model(o.get("effects") or ["linear-ttl"])
        self.adequacy_every = int(o.get("adequacy_every", 24))
        self.candidates_every = int(o.get("candidates_every", 0))
        self.window_tdi: deque[TDIData] = deque()
        self._model_change: dict | None = None
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
        last, fits = None, set()
        for path in files:
            try:
                rec = read_recording(path)
            except Exception as exc:  # noqa: BLE001 - a damaged file: use what the others have
                self.log.warning("cannot read %s: %s", path, exc)
                continue
            models = [e for e in rec.json("events") if e.get("kind") == "model"]
            last = models[-1] if models else last
            # the fit's segment is written before its summary: a kill between leaves only the former
            fits.update(m.header.index for m in rec.segments("fit"))
            fits.update(s["index"] for s in rec.json("fit/summary") if isinstance(s.get("index"), int))
        if last is None:
            return
        d = last.get("details") or {}
        try:
            effects, before = self.check_model(d["effects"]), list(d["before"])
            start = int(d["from_index"])
        except (KeyError, TypeError, ValueError) as exc:
            self.report_error("failed", f"restart: the recorded model change cannot be restored ({exc}); "
                                        f"the configured model {','.join(self.effects)} stays", field="model")
            return
        self.effects = effects
        due = not any(i >= start for i in fits)
        if due:
            self._model_change = {"before": before, "after": effects, "from_index": start}
        self.event("model-restored", index=start, message=f"model {','.join(effects)} restored from the earlier "
                                                          f"process (in force from segment {start}"
                                                          f"{'; its model change is still to be reported' if due else ''})",
                   effects=effects, from_index=start, change_due=due)
        self.log.info("restart: model %s restored (from segment %d)", ",".join(effects), start)

    def settings(self, meta: dict) -> FitSettings:
        kwargs = {"segment_duration": self.fit_segment or float(meta.get("segment_duration") or 3600.0)}
        if self.band:
            kwargs["band"] = self.band
        if meta.get("dws_asd") is not None:
            kwargs["dws_asd"] = float(meta["dws_asd"])
        return FitSettings(**kwargs)

    def handle(self, header, arrays):
        td = tdi_of(header, arrays)  # before buffering: a segment that raises is not marked processed
        self.enqueue(header, td)
        return ()

    def progress_fields(self) -> dict:
        return {"fits": self.fits}

    def published(self, index: int) -> None:
        self.fits.add(index)

    def fill_gap(self, index: int) -> None:
        """A TDI segment that will not come: push NaN over its planned span, so that the
        window keeps what it has and the next segment follows in time (RollingFit masks NaN:
        an FFT segment less than half valid is left out, ttlcore.estimate.fit.spectra_of_segment)."""
        last = self._last_td
        if self.rolling is None or last is None or self._next_t0 is None:
            return
        plan = self.validator.plan
        n = plan.segment(index)[1] if plan is not None else last.size
        nan = np.full((3, n), np.nan)
        td = TDIData(t0=self._next_t0, fs=last.fs, channels=last.channels, data=nan,
                     regressors=np.full((3, len(last.names), n), np.nan), names=last.names, ltt_mean=last.ltt_mean)
        self.rolling.push(td)
        self._next_t0 = td.t0 + n / td.fs
        self.event("gap", index=index, message=f"tdi segment {index} missing: {n} NaN samples pushed, window kept")

    # ------------------------------------------------------------------ the model
    def check_model(self, specs) -> list[str]:
        """Validated effect specs of a model (a list, or one comma-separated string)."""
        if isinstance(specs, str):
            specs = [s for s in specs.split(",") if s.strip()]
        if not isinstance(specs, (list, tuple)) or not specs or not all(isinstance(s, str) for s in specs):
            raise ValueError(f"effects: expected a list of effect specs, got {specs!r}")
        effects = make_effects(list(specs), self.effect_modules)
        names = [e.name for e in effects]
        if "linear-ttl" not in names:
            raise ValueError("effects: the model must include linear-ttl")
        beyond = [e.spec() for e in effects if e.name not in TDI_EFFECTS]
        if beyond:
            raise ValueError(f"effects {', '.join(beyond)} need the DWS series, which the fitter does not receive; "
                             f"in the pipeline the model may use {', '.join(TDI_EFFECTS)} "
                             "(ttl diagnose and ttl refit offer the others)")
        return [e.spec() for e in effects]

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
            raise ValueError(f"unknown field(s) {sorted(set(msg) - {'effects'})}; plugin modules come from the "
                             "stage's configuration only")
        new = self.check_model(msg["effects"])
        start = self.queue.next if self.queue.next is not None else 0
        self._model_change = {"before": list(self.effects), "after": new, "from_index": start}
        self.log.info("model change requested: %s -> %s", ",".join(self.effects), ",".join(new))
        self.event("model", index=start, message=f"model {','.join(new)} from segment {start} on",
                   effects=new, before=list(self.effects), from_index=start)
        self.effects = new
        return ()

    def diagnosis(self, header) -> dict | None:
        """Meta (and arrays) of the window refitted under the instrument noise model, when due:
        on a model change, on every segment of an extended model, every ``adequacy_every``."""
        change, extended = self._model_change, self.effects != ["linear-ttl"]
        if change is not None and header.index < change["from_index"]:
            change = None  # a segment replayed after a restart, before the change
        due = (change is not None or extended
               or (self.adequacy_every > 0 and self._segments_seen % self.adequacy_every == 0))
        if not due:
            return None
        r = self._window_refit(header.meta, change["before"] if change else ["linear-ttl"])
        if r is None:
            return None
        if change is not None:
            self._model_change = None
        model = r["_internals"]["fit"]
        adequacy = r["model"]["adequacy"]
        out: dict = {"adequacy": {
            "noise_model": "instrument (analytic secondary noises + DWS readout noise), not re-estimated",
            "chi2_dof": adequacy["chi2_dof"], "fails": adequacy["fails"], "summary": adequacy["summary"],
            "bands": [{k: b[k] for k in ("f_lo", "f_hi", "chi2_dof", "p_value", "fails")} for b in adequacy["bands"]],
        }}
        if extended:
            k = [model.names.index(n) for n in COEFFICIENT_NAMES]
            out["arrays"] = {"coefficients": model.ttl_coefficients(), "sigma": model.ttl_sigma(),
                             "covariance": model.covariance[np.ix_(k, k)]}
            out["extra_parameters"] = {n: [float(v), float(s)] for n, v, s in zip(model.names, model.theta, model.sigma)
                                       if n not in COEFFICIENT_NAMES}
        if change is not None:
            c = r["change"]
            out["model_change"] = {
                "before": change["before"], "after": change["after"],
                "chi2_dof_before": c["chi2_dof_before"], "chi2_dof_after": c["chi2_dof_after"],
                "bands_before": c["bands_before"], "bands_after": c["bands_after"],
                "delta_chi2": c["delta_chi2"], "log_bayes_factor": c["log_bayes_factor"],
                "band_edges": [b["f_lo"] for b in adequacy["bands"]] + [adequacy["bands"][-1]["f_hi"]],
            }
        if change is not None or (self.candidates_every > 0 and self._segments_seen % self.candidates_every == 0):
            ranked = candidates(model)
            out["candidates"] = [{k: c.get(k) for k in ("effect", "spec", "delta_chi2", "log_bayes_factor",
                                                       "explained_fraction", "significant")}
                                 for c in ranked[:TOP_CANDIDATES]]
        return out

    def _window_refit(self, meta: dict, baseline: list[str]) -> dict | None:
        """Refit the window's TDI with the model (and ``baseline``) under the instrument noise
        model; None when the window is still too short for it."""
        kwargs = {"band": self.band} if self.band else {}
        try:
            return refit(list(self.window_tdi), self.effects, settings=DiagnoseSettings(**kwargs),
                         effect_modules=self.effect_modules, baseline=baseline,
                         dws_asd=None if meta.get("dws_asd") is None else float(meta["dws_asd"]))
        except ConfigError as exc:
            self.log.info("no adequacy yet: %s", exc)
            return None

    def catch_up(self, first: int) -> None:
        """A restarted fitter whose first segment is ``first`` > 0: rebuild the rolling window
        by pushing again the TDI segments before it, read from the tdi_builder's recordings
        (``<recordings>/<run>/tdi_builder*.mcap``; the publishers' caches hold only a few
        segments, the window a day).  From the start of the run when the recordings have it,
        so that the state (window, weights of the full refits) is the uninterrupted run's."""

        run_dir = self.config.recordings / self.run_id
        segments = {}
        for path in sorted(run_dir.glob("tdi_builder*.mcap")):
            try:
                for m in read_recording(path).segments("tdi"):
                    if m.header.index < first:
                        segments.setdefault(m.header.index, m)
            except Exception as exc:  # noqa: BLE001 - a damaged file: use what the others have
                self.log.warning("cannot read %s: %s", path, exc)
        have = sorted(segments)
        start = first
        while start - 1 in segments:
            start -= 1
        if start > 0:
            self.report_error("window-shortened", f"restart: TDI segments before {start} are not in the recordings; "
                                                  f"the window restarts at {start} instead of the run's start",
                              index=first, details={"recorded": to_ranges(have)})
        for i in range(start, first):
            m = segments[i]
            self.process(m.header, tdi_of(m.header, m.arrays))
        self.event("restored", index=first, message=f"window rebuilt from the tdi_builder's recordings: segments "
                                                     f"{start}..{first - 1} pushed again", first=start, last=first - 1)
        self.log.info("restart: window rebuilt from segments %d..%d of the recordings", start, first - 1)

    def process(self, header, td: TDIData) -> Output | None:
        """Push one TDI segment into the rolling fit; the fit message if it refitted."""
        if self.rolling is None and header.index > 0 and self._restarted and not self._caught_up:
            self._caught_up = True
            self.catch_up(header.index)
        if self.rolling is None:
            self.rolling = RollingFit(self.settings(header.meta), window_duration=self.window_duration, names=td.names)
            self.log.info("rolling fit: FFT segment %g s, window %g s, band %s",
                          self.rolling.settings.segment_duration, self.window_duration, self.rolling.settings.band)
        elif self._next_t0 is not None and abs(td.t0 - self._next_t0) > 0.5 / td.fs:
            self.event("discontinuity", index=header.index,
                       message=f"t0={td.t0} s does not follow the previous segment (expected {self._next_t0} s); "
                               "the window restarts here")
            self.rolling.reset()
            self.window_tdi.clear()
        self._next_t0 = td.t0 + td.size / td.fs
        self._last_td = td
        self._segments_seen = header.index + 1  # by index: the same after a restart
        res = self.rolling.push(td)
        # the window's TDI for the adequacy refits, as the rolling fit low-passed and decimated
        # it (A, E, T at 2 Hz: half the memory, and the refit need not decimate again); copied,
        # because the decimator's outputs are strided views of its full-rate convolution, which
        # they would keep alive for the whole window (twice the memory: ~100 MB for a day of
        # 4-Hz data, measured with TTL_MEMTRACE)
        dec = self.rolling.last_decimated
        dec = dataclasses.replace(dec, data=np.ascontiguousarray(dec.data),
                                  regressors=np.ascontiguousarray(dec.regressors))
        self.window_tdi.append(dec)
        while self.window_tdi and self.window_tdi[0].t0 < dec.t0 + dec.size / dec.fs - self.window_duration - 1.0:
            self.window_tdi.popleft()
        if res is None:
            self.log.info("segment %d: no FFT segment completed, no refit", header.index)
            return None
        # a segment an earlier process published the fit of (replayed, or pushed again to
        # rebuild the window): its diagnosis would be thrown away
        diagnosis = None if self.handled_before(header.index) else self.diagnosis(header)
        meta = {"names": list(res.names), "chi2_dof": res.chi2_dof, "t_start": res.t_start, "t_stop": res.t_stop,
                "segments": int(res.n_segments), "band": list(res.band), "converged": bool(res.converged),
                "chi2": res.chi2, "dof": res.dof, "iterations": int(res.iterations), "method": res.method,
                "window_duration": self.window_duration,
                "fft_segment": self.rolling.settings.segment_duration,
                "segments_total": self.segments_total, "model": list(self.effects)}
        arrays = {"coefficients": res.coefficients, "sigma": res.sigma, "covariance": res.covariance}
        if diagnosis is not None:
            arrays.update(diagnosis.pop("arrays", {}))
            meta.update(diagnosis)
        summary = {"run": self.run_id, "index": header.index, "names": list(res.names),
                   "coefficients": res.coefficients, "sigma": res.sigma, "covariance": res.covariance,
                   "chi2": res.chi2, "dof": res.dof, "chi2_dof": res.chi2_dof,
                   "t_start": res.t_start, "t_end": res.t_stop, "segments": int(res.n_segments),
                   "fit": res.to_json(), **{k: meta[k] for k in ("model", "adequacy", "model_change",
                                                                 "candidates", "extra_parameters") if k in meta}}
        self.log.info("segment %d: fit over [%.0f, %.0f] s (%d FFT segments), chi2/dof %.3f", header.index,
                      res.t_start, res.t_stop, res.n_segments, res.chi2_dof)
        if not res.converged:
            self.warn("not-converged", f"fit {header.index} did not converge in {res.iterations} iterations",
                      index=header.index, iterations=int(res.iterations))
        if "adequacy" in meta:
            self.log.info("segment %d: model %s, chi2/dof against the instrument noise model %.3f%s", header.index,
                          ",".join(self.effects), meta["adequacy"]["chi2_dof"],
                          " (fails)" if meta["adequacy"]["fails"] else "")
        return Output(self.output_topic, arrays,
                      fields={"units": UNITS, "meta": to_jsonable(meta)},
                      summary=to_jsonable(summary), summary_schema="ttl.Fit")


def _file_number(path, stage: str) -> int:
    """``n`` of ``<stage>.<n>.mcap`` (the order the processes ran in)."""
    try:
        return int(path.name[len(stage) + 1:-len(".mcap")])
    except ValueError:
        return 0


def add_options(p) -> None:
    p.add_argument("--fit-segment", help="FFT segment length (default: the telemetry segment length)")
    p.add_argument("--window-duration", help="rolling window length (default 1d)")
    p.add_argument("--band", nargs=2, type=float, metavar=("FMIN", "FMAX"), help="fit band [Hz]")
    p.add_argument("--settle", type=float, help="seconds to collect cached history before choosing the first segment")
    p.add_argument("--gap-timeout", type=float, help="seconds to wait for a missing segment before skipping it")
    p.add_argument("--effects", help=f"the model: effect specs, comma-separated (default linear-ttl; "
                                     f"from TDI alone: {', '.join(TDI_EFFECTS)})")
    p.add_argument("--effect-module", action="append", help="plugin module or .py file defining effects (repeatable)")
    p.add_argument("--adequacy-every", type=int,
                   help="refit the window under the instrument noise model every N segments (default 24; 0: never)")
    p.add_argument("--candidates-every", type=int,
                   help="rank the effects not in the model every N segments (default 0: on model changes only)")


def options(args) -> dict:
    return {"fit_segment": args.fit_segment, "window_duration": args.window_duration, "band": args.band,
            "settle": args.settle, "gap_timeout": args.gap_timeout, "effects": args.effects,
            "effect_modules": args.effect_module, "adequacy_every": args.adequacy_every,
            "candidates_every": args.candidates_every}


def main(argv=None) -> int:
    return stage_main(Fitter, argv, add_options, options)


if __name__ == "__main__":
    sys.exit(main())
