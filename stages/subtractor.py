"""Subtractor stage: applies the fit covering each segment and publishes the residual.

Inputs ``ttl/<run>/tdi/<i>`` (tdi_builder) and ``ttl/<run>/fit/<j>`` (fitter).  Segment ``i``
gets the latest fit whose window includes or precedes it: the fit made when segment ``i``
arrived at the fitter (window ending with segment ``i``) if there is one, else the latest
earlier fit.  To know that no fit ``i`` will come, the subtractor follows the fitter's
progress messages (``fits_ranges``: the segments that produced a fit); a segment waits,
by its index, until the fitter's progress says it handled that segment (:func:`fit_for`):
a fit of a later segment is no proof that the fitter passed this one (a fit forged ahead,
issue 33, released every waiting segment with the fit before it).  A segment the fitter
handled without a fit (a gap, a ``no-fit`` warning, an FFT segment still filling) gets
the latest earlier fit; a fit received for such a segment is not the fitter's (forged) and
is reported, never applied.  A segment no fit covers yet (the fitter has not made one)
is published unchanged: residual = data, model = 0, ``fit_index`` null.  Segments need not
come in order (a late joiner's history does not); a segment waits only for its fit, and
the first is chosen after ``settle`` seconds of history so that the output starts in order.

Output ``ttl/<run>/residual/<i>``: arrays ``residual`` (3, n) and ``ttl_model`` (3, n),
channels X2, Y2, Z2 (NaN where the TDI input is NaN), header t0 and fs those of the TDI
segment; meta ``fit_index`` (the fit applied), ``coefficients_t_start``,
``coefficients_t_stop`` (its window), ``segments_total``.  Residual = data - model: the
linear TTL ``sum_k C_k R_k`` (:func:`ttlcore.estimate.subtraction.subtract`) and, when the
fitter's model holds more (the fit of this very segment carries ``model_parts``: each other
effect's contribution to X2, Y2, Z2 on this segment's samples), those too
(:func:`ttlcore.diagnose.prediction.model_residual`); they are published as
``effect_model`` (k, 3, n) with meta ``effects`` (their specs), so that the monitor can draw
each.  A segment whose own fit did not come gets the latest earlier fit's linear
coefficients only (meta ``model_parts_missing`` lists what could not be subtracted).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import numpy as np

from stages.tdi_builder import rebuilt_copy
from streamer.bus.codec import Expect
from streamer.bus.fit_record import FitMessage
from streamer.bus.message_schema import to_jsonable
from streamer.bus.messages import P, tdi_expect, tdi_of
from streamer.bus.residual_record import ResidualMessage
from streamer.runtime.pipeline_stage import PipelineStage
from streamer.runtime.rangeset import RangeSet
from streamer.runtime.stage import Output, stage_main
from streamer.runtime.stage_options import StageOptions, nonnegative_float, option, positive_float
from ttlcore.conventions import COEFFICIENT_NAMES
from ttlcore.diagnose.prediction import model_residual
from ttlcore.tdi.combinations import XYZ

UNITS = {
    "residual": "fractional frequency",
    "ttl_model": "fractional frequency",
    "effect_model": "fractional frequency",
}
#: Wait for a fit announced by the fitter's progress before falling back to an earlier one [s].
FIT_TIMEOUT = 30.0
#: After this long waiting for an announced fit [s], ask the fitter's cache for it (once):
#: a late joiner's history query can be lost on a loaded machine (5 fits never came, 2026-11-27)
FIT_FETCH_AFTER = 5.0


def fit_for(index: int, handled, announced: set[int], received: set[int]) -> tuple[str, int | None]:
    """Which fit segment ``index`` gets, by its index (module docstring).

    Parameters
    ----------
    index : int
        The TDI segment.
    handled : set of int
        Segments the fitter's progress says it handled (with a fit or without).
    announced : set of int
        Fits the fitter's progress says it published (less the refused ones).
    received : set of int
        Fits received and accepted here.  One of a segment the fitter handled without
        announcing a fit for it is not the fitter's (forged, or refused) and is never chosen.

    Returns
    -------
    ("wait", None)
        The fitter has not passed ``index``: whatever fits of later segments came.
    ("apply", j)
        Fit ``j``, the latest at or before ``index`` announced or received (None: none yet).
    ("await", j)
        That fit ``j`` is announced but has not come yet.
    """
    if index not in handled:
        return "wait", None
    known = [j for j in announced | received if j <= index and (j in announced or j not in handled)]
    if not known:
        return "apply", None
    best = max(known)
    return ("apply", best) if best in received else ("await", best)


@dataclass(frozen=True)
class SubtractorOptions(StageOptions):
    """The subtractor's options (their command-line help in :func:`add_options`)."""

    #: Seconds to wait for a fit the fitter announced before falling back to an earlier one.
    fit_timeout: float = option(FIT_TIMEOUT, positive_float)
    #: Seconds to collect cached history before the first segment (unless it is segment 0).
    settle: float = option(1.0, nonnegative_float)


class Subtractor(PipelineStage[SubtractorOptions]):
    """Subtracts the fitted TTL model from each TDI segment."""

    name = "subtractor"
    inputs = ("tdi", "fit")
    follow = ("fitter", "tdi_builder")
    reorders = ("tdi", "fit")  # no gap reports on arrival: which fit applies comes from the fitter's progress
    rebuilds = {"tdi": rebuilt_copy}  # a tdi segment read back from the recordings lacks its regressors
    options_type = SubtractorOptions

    def __init__(self, config):
        super().__init__(config)
        self.fit_timeout = self.options.fit_timeout
        self.tdi: dict[int, tuple] = {}
        self.fits: dict[int, dict] = {}  # the fits segments still to come may get (_prune_fits)
        self.applied = RangeSet()  # fits applied to a segment
        self._highest = -1  # highest segment handled (done or given up)
        self.refused_fits: set[int] = set()  # fits withdrawn (conflicting copies): never waited for
        self._waiting_since: dict[int, float] = {}
        self._fetched: set[int] = set()  # fits asked of the fitter's cache (choose)
        self._disowned: set[int] = set()  # fits received that the fitter says it never made (choose)
        self._started = time.monotonic()
        self._board_asked = 0.0  # when the fitter's progress was last asked again (_board_silent)
        # a late joiner gets its history from several publisher caches in any order: collect
        # for `settle` seconds before the first segment (unless it is segment 0)
        self.settle = self.options.settle
        self._first_arrival: float | None = None

    def expect(self, topic, index):
        if topic == "fit":
            # NaN allowed for the model parts (TDI delays at the window's start), never in
            # the coefficients: such a copy is malformed (rejected), not a conflicting one
            return Expect(
                run=self.run_id,
                index=index,
                allow_nonfinite=True,
                finite=("coefficients",),
                arrays={"coefficients": ("<f8", (P,)), "sigma": ("<f8", (P,)), "covariance": ("<f8", (P, P))},
            )
        return tdi_expect(self.run_id, index)

    def pending(self) -> int:
        return len(self.tdi)

    def withdraw(self, topic, index, held):
        """Conflicting copies: a fit is forgotten (the segments it would cover get an earlier
        one), a TDI segment not yet subtracted is given up (failed)."""
        if topic == "fit":
            self.fits.pop(index, None)
            self.refused_fits.add(index)
            return index not in self.applied
        if index in self.done or index in self.failed:
            return False
        self.tdi.pop(index, None)
        self.mark_failed(index)
        return True

    def handle(self, header, arrays):
        self.note_meta(header.meta)
        if header.topic == "fit":
            fit = FitMessage.from_header(header.meta, f"fit {header.index}")
            names = fit.names or COEFFICIENT_NAMES
            if len(names) != P:
                raise ValueError(f"meta.names has {len(names)} names for {P} coefficients")
            if not np.isfinite(arrays["coefficients"]).all():
                raise ValueError("arrays.coefficients: not all finite")
            parts = list(fit.model_parts or ())
            x = arrays.get("model_parts")
            if parts or x is not None:
                if x is None or x.ndim != 3 or x.shape[:2] != (len(parts), 3):
                    raise ValueError(
                        f"arrays.model_parts: expected (k, 3, n) with meta.model_parts naming k effects, "
                        f"got {None if x is None else x.shape} for {parts!r}"
                    )
            self.fits[header.index] = {
                "coefficients": dict(zip(names, map(float, arrays["coefficients"]))),
                "t_start": fit.t_start,
                "t_stop": fit.t_stop,
                "parts": dict(zip(parts, x)) if parts else {},
                "stale": fit.stale,  # a fit that took in no new data (stages/fitter/fitter.py)
            }
        else:
            if header.index in self.done:
                return ()
            self.tdi[header.index] = (header, tdi_of(header, arrays))
            if self._first_arrival is None:
                self._first_arrival = time.monotonic()
        self.drain()
        return ()

    def tick(self):
        self.drain()
        self.fetch_announced()
        self.give_up_gaps()
        self.check_complete()
        self._prune_fits()
        return ()

    def announced_inputs(self):
        """The tdi_builder's TDI segments and the fitter's fits (its ``fits`` progress): one
        announced that does not come is caught up (:mod:`streamer.runtime.catch_up`)."""
        out = super().announced_inputs()
        fitter = self.board.get("fitter")
        if fitter is not None:
            out["fit"] = ("fitter", fitter.extra.get("fits", RangeSet()))
        return out

    def still_needed(self, topic: str, index: int) -> bool:
        return topic != "fit" or (index not in self.refused_fits and index not in self.fits)

    def settle_lost(self, topic: str, index: int, why: str) -> None:
        """A lost TDI segment is given up (failed); a lost fit is waited for until
        ``fit_timeout`` as any announced fit, then reported (``missing-fit``) and an earlier one
        applied (:meth:`choose`)."""
        if topic == "tdi" and index not in self.done | self.failed:
            self.tdi.pop(index, None)
            self.mark_failed(index)

    def mark_done(self, index: int, **extra) -> None:
        self._highest = max(self._highest, index)
        super().mark_done(index, **extra)

    def mark_failed(self, index: int, **extra) -> None:
        self._highest = max(self._highest, index)
        super().mark_failed(index, **extra)

    def _prune_fits(self) -> None:
        """Forget the fits no segment still to come will get, so that memory stays flat in a
        long run.  A segment gets the latest fit at or before it: the fits older than the
        latest one at or before ``lo`` are never chosen again for a segment at or after
        ``lo``, the lowest segment waiting here or the one after the highest handled, minus
        the index window of the messages (``Validator.window``, 64 segments) for segments
        that arrive late (a late joiner's history comes in any order)."""
        lo = min([self._highest + 1, *self.tdi]) - self.validator.window
        older = [j for j in self.fits if j <= lo]
        if len(older) > 1:
            keep = max(older)
            for j in older:
                if j != keep:
                    del self.fits[j]

    def give_up_gaps(self) -> None:
        """Segments the tdi_builder gave up will not come: handled here as given up too
        (as gaps when they were gaps), so the run can end."""
        peer = self.board.get(self.upstream)
        if peer is None:
            return
        for i in sorted(peer.failed - self.done - self.failed - set(self.tdi)):
            (self.mark_gap if i in peer.gaps else self.mark_failed)(i)

    # ------------------------------------------------------------------ which fit
    def choose(self, index: int):
        """``("wait", None)``, or ``("apply", j)`` with ``j`` the fit index (None: no fit yet)."""
        fitter = self.board.get("fitter")
        announced = (set(fitter.extra.get("fits", ())) if fitter else set()) - self.refused_fits
        handled: RangeSet | set[int] = fitter.handled if fitter is not None else set()
        for j in sorted(set(self.fits) - announced - self._disowned):
            if j <= index and j in handled:  # a fit the fitter says it never made: not used
                self._disowned.add(j)
                self.report_error(
                    "forged",
                    f"fit {j} was received but the fitter's progress says segment {j} produced no fit: not applied",
                    index=j,
                )
        what, best = fit_for(index, handled, announced, set(self.fits))
        if what == "wait":
            self._board_silent(fitter)
        if what != "await":
            return what, best
        if best is None:  # fit_for awaits the fit it names
            raise RuntimeError(f"segment {index}: awaiting a fit with no index")
        since = self._waiting_since.setdefault(index, time.monotonic())
        waited = time.monotonic() - since
        if waited > min(FIT_FETCH_AFTER, self.fit_timeout / 2) and best not in self._fetched:
            self._fetched.add(best)
            self.fetch("fit", best)  # once: the fitter's cache holds it
        if waited < self.fit_timeout:
            return "wait", None  # announced by the fitter's progress, still on its way
        received = [j for j in self.fits if j <= index]
        fallback = max(received) if received else None
        self.report_error(
            "missing-fit",
            f"fit {best} announced by the fitter never arrived; segment {index} gets fit {fallback}",
            index=index,
        )
        return "apply", fallback

    def _board_silent(self, fitter) -> None:
        """A segment waits for the fitter's progress: when none came for FIT_FETCH_AFTER
        seconds, ask its cache again (at most that often; :meth:`refresh_progress`): a late
        joiner's history query lost on a loaded machine would otherwise leave every segment
        waiting for a fitter that has finished (a fit of a later segment is no proof)."""
        now = time.monotonic()
        heard = max(fitter.updated if fitter is not None else 0.0, self._board_asked)
        if now - max(heard, self._started) >= FIT_FETCH_AFTER:
            self._board_asked = now
            self.refresh_progress("fitter")

    def drain(self) -> None:
        if (
            not self.done
            and 0 not in self.tdi
            and self._first_arrival is not None
            and time.monotonic() - self._first_arrival < self.settle
        ):
            return
        for index in sorted(self.tdi):
            what, j = self.choose(index)
            if what == "wait":
                continue
            header, td = self.tdi.pop(index)
            self._waiting_since.pop(index, None)
            if self.handled_before(index):  # a restarted subtractor: that residual is out already
                self.event("replayed", index=index, message=f"segment {index} handled by an earlier process")
                self.mark_done(index)
                continue
            try:
                self.publish(self.subtract(header, td, j), source=header)
            except Exception as exc:
                self.log.exception("segment %d failed", index)
                self.report_error("failed", f"{type(exc).__name__}: {exc}", index=index, key=header.key)
                self.mark_failed(index)
                continue
            self.mark_done(index)

    def subtract(self, header, td, fit_index: int | None) -> Output:
        """The residual message of one TDI segment with fit ``fit_index`` (None: no fit)."""
        parts: dict = {}
        missing: list = []
        if fit_index is None:
            residual, model = np.array(td.data, dtype=float), np.zeros_like(td.data)
            fit: dict = {"t_start": None, "t_stop": None}
        else:
            fit = self.fits[fit_index]
            self.applied.add(fit_index)
            C = np.array([fit["coefficients"][n] for n in td.names])
            if (
                fit["parts"]
                and fit_index == header.index
                and all(p.shape[-1] == td.size for p in fit["parts"].values())
            ):
                parts = fit["parts"]
            elif fit["parts"]:
                missing = list(fit["parts"])
                self.warn(
                    "model-parts-missing",
                    f"segment {header.index} gets fit {fit_index}: its effects "
                    f"{', '.join(missing)} are not subtracted (linear TTL only)",
                    index=header.index,
                )
            residual = model_residual(td.data, td.regressors, C, parts.values())
            model = td.model(C)
        with np.errstate(invalid="ignore"):
            rms = {
                "data": np.sqrt(np.nanmean(td.data**2, axis=1)),
                "residual": np.sqrt(np.nanmean(residual**2, axis=1)),
            }
        meta = ResidualMessage.build(
            f"residual {header.index}",
            fit_index=fit_index,
            coefficients_t_start=fit["t_start"],
            coefficients_t_stop=fit["t_stop"],
            segments_total=self.segments_total,
            effects=list(parts),
            model_parts_missing=missing or None,
            fit_stale=fit.get("stale") or None,  # the fit applied is an earlier one's again, not fresh
        )
        arrays = {"residual": residual, "ttl_model": model}
        if parts:
            arrays["effect_model"] = np.stack(list(parts.values()))
        self.log.info(
            "segment %d: fit %s applied%s", header.index, fit_index, f" with {', '.join(parts)}" if parts else ""
        )
        return Output(
            self.output_topic,
            arrays,
            fields={
                "channels": list(XYZ),
                "channel_axis": {"residual": 0, "ttl_model": 0, "effect_model": 1},
                "units": UNITS,
                "meta": meta.to_header(),
            },
            summary=to_jsonable(
                {
                    "run": self.run_id,
                    "index": header.index,
                    "fit_index": fit_index,
                    "channels": list(XYZ),
                    "rms_data": rms["data"],
                    "rms_residual": rms["residual"],
                }
            ),
            allow_nonfinite=True,
        )


def add_options(p) -> None:
    p.add_argument(
        "--fit-timeout", type=float, help=f"seconds to wait for a fit the fitter announced (default {FIT_TIMEOUT:g})"
    )
    p.add_argument("--settle", type=float, help="seconds to collect cached history before the first segment")


def options(args) -> dict:
    return {"fit_timeout": args.fit_timeout, "settle": args.settle}


def main(argv=None) -> int:
    return stage_main(Subtractor, argv, add_options, options)


if __name__ == "__main__":
    sys.exit(main())
