"""Fitter stage: rolling one-day fit of the 24 TTL coefficients, refit on every new segment.

Input ``ttl/<run>/tdi/<i>`` (tdi_builder).  The TDI segments go, in index order, into
:class:`ttlcore.rolling.RollingFit` -- the batch estimator of :func:`ttlcore.fit.fit_tdi`
over a rolling window (default one day) of FFT segments.  The FFT segment defaults to the
telemetry segment length (``segment_duration`` of the input meta), so every new segment
completes one FFT segment and triggers a refit; a longer FFT segment refits less often.

Output ``ttl/<run>/fit/<i>`` when segment ``i`` produced a fit: arrays ``coefficients``
(24,) [m/rad], ``sigma`` (24,), ``covariance`` (24, 24); meta ``names``, ``chi2_dof``,
``t_start``, ``t_stop`` (the window fitted), ``segments`` (FFT segments in it), ``band``,
``converged``, plus ``chi2``, ``dof``, ``iterations``, ``method``, ``segments_total``.  The
full :meth:`ttlcore.fit.FitResult.to_json` goes into the recording on ``fit/summary``
(schema ``ttl.Fit``: the schema's fields, and the whole result under ``fit``).

The progress messages carry ``fits_ranges``: the segments that produced a fit, so that the
subtractor knows, for each segment, which fit is the latest one covering it.
"""

from __future__ import annotations

import sys

import numpy as np

from streamer.codec import Expect
from streamer.stage import Output

from ttlcore.conventions import COEFFICIENT_NAMES, DAY, parse_duration
from ttlcore.errors import ConfigError
from ttlcore.fit import FitSettings
from ttlcore.rolling import RollingFit
from ttlcore.tdi_data import TDIData

from . import OUTPUT_TOPIC, XYZ, OrderedStage, jsonable, stage_main

UNITS = {"coefficients": "m/rad", "sigma": "m/rad", "covariance": "m^2/rad^2"}
P = len(COEFFICIENT_NAMES)


def tdi_expect(run: str, index: int) -> Expect:
    """What a ``tdi`` message must fit (NaN allowed: first samples of a stream)."""
    return Expect(run=run, index=index, channels=XYZ, allow_nonfinite=True,
                  arrays={"data": ("<f8", (3, None)), "regressors": ("<f8", (3, P, None))})


def tdi_data(header, arrays) -> TDIData:
    """The :class:`ttlcore.tdi_data.TDIData` of a ``tdi`` message."""
    meta = header.meta
    names = tuple(meta.get("names") or COEFFICIENT_NAMES)
    if len(names) != arrays["regressors"].shape[1]:
        raise ValueError(f"meta.names has {len(names)} names for {arrays['regressors'].shape[1]} regressors")
    ltt = np.asarray(meta.get("ltt_mean", [np.nan] * 6), dtype=float)
    if ltt.shape != (6,):
        raise ValueError(f"meta.ltt_mean: expected 6 values, got shape {ltt.shape}")
    return TDIData(t0=header.t0, fs=header.fs, channels=tuple(header.channels), data=arrays["data"],
                   regressors=arrays["regressors"], names=names, ltt_mean=ltt)


class Fitter(OrderedStage):
    """Rolling-window fit of the TTL coefficients (ttlcore.rolling.RollingFit)."""

    name = "fitter"
    inputs = ("tdi",)
    follow = ("tdi_builder",)
    upstream = "tdi_builder"
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
        self.fits: set[int] = set()
        self._next_t0: float | None = None

    def expect(self, topic, index):
        return tdi_expect(self.run_id, index)

    def settings(self, meta: dict) -> FitSettings:
        kwargs = {"segment_duration": self.fit_segment or float(meta.get("segment_duration") or 3600.0)}
        if self.band:
            kwargs["band"] = self.band
        if meta.get("dws_asd") is not None:
            kwargs["dws_asd"] = float(meta["dws_asd"])
        return FitSettings(**kwargs)

    def handle(self, header, arrays):
        if not self.config.record_inputs:
            self.recorder.write_json("tdi/input", header.to_dict(), schema="ttl.SegmentHeader")
        td = tdi_data(header, arrays)  # before buffering: a segment that raises is not marked processed
        self.enqueue(header, td)
        return ()

    def progress_fields(self) -> dict:
        return {"fits": self.fits}

    def published(self, index: int) -> None:
        self.fits.add(index)

    def process(self, header, td: TDIData) -> Output | None:
        """Push one TDI segment into the rolling fit; the fit message if it refitted."""
        if self.rolling is None:
            self.rolling = RollingFit(self.settings(header.meta), window_duration=self.window_duration, names=td.names)
            self.log.info("rolling fit: FFT segment %g s, window %g s, band %s",
                          self.rolling.settings.segment_duration, self.window_duration, self.rolling.settings.band)
        elif self._next_t0 is not None and abs(td.t0 - self._next_t0) > 0.5 / td.fs:
            self.event("discontinuity", index=header.index,
                       message=f"t0={td.t0} s does not follow the previous segment (expected {self._next_t0} s); "
                               "the window restarts here")
            self.rolling.reset()
        self._next_t0 = td.t0 + td.size / td.fs
        res = self.rolling.push(td)
        if res is None:
            self.log.info("segment %d: no FFT segment completed, no refit", header.index)
            return None
        meta = {"names": list(res.names), "chi2_dof": res.chi2_dof, "t_start": res.t_start, "t_stop": res.t_stop,
                "segments": int(res.n_segments), "band": list(res.band), "converged": bool(res.converged),
                "chi2": res.chi2, "dof": res.dof, "iterations": int(res.iterations), "method": res.method,
                "window_duration": self.window_duration,
                "fft_segment": self.rolling.settings.segment_duration,
                "segments_total": self.segments_total}
        summary = {"run": self.run_id, "index": header.index, "names": list(res.names),
                   "coefficients": res.coefficients, "sigma": res.sigma, "covariance": res.covariance,
                   "chi2": res.chi2, "dof": res.dof, "chi2_dof": res.chi2_dof,
                   "t_start": res.t_start, "t_end": res.t_stop, "segments": int(res.n_segments),
                   "fit": res.to_json()}
        self.log.info("segment %d: fit over [%.0f, %.0f] s (%d FFT segments), chi2/dof %.3f", header.index,
                      res.t_start, res.t_stop, res.n_segments, res.chi2_dof)
        return Output(OUTPUT_TOPIC[self.name],
                      {"coefficients": res.coefficients, "sigma": res.sigma, "covariance": res.covariance},
                      fields={"units": UNITS, "meta": jsonable(meta)},
                      summary=jsonable(summary), summary_schema="ttl.Fit")


def add_options(p) -> None:
    p.add_argument("--fit-segment", help="FFT segment length (default: the telemetry segment length)")
    p.add_argument("--window-duration", help="rolling window length (default 1d)")
    p.add_argument("--band", nargs=2, type=float, metavar=("FMIN", "FMAX"), help="fit band [Hz]")
    p.add_argument("--settle", type=float, help="seconds to collect cached history before choosing the first segment")
    p.add_argument("--gap-timeout", type=float, help="seconds to wait for a missing segment before skipping it")


def options(args) -> dict:
    return {"fit_segment": args.fit_segment, "window_duration": args.window_duration, "band": args.band,
            "settle": args.settle, "gap_timeout": args.gap_timeout}


def main(argv=None) -> int:
    return stage_main(Fitter, argv, add_options, options)


if __name__ == "__main__":
    sys.exit(main())
