"""The model timeline the monitor draws in Rerun, beside the coefficient trends.

``ttl inspect`` prints the fitter's model timeline from its recordings
(:mod:`streamer.tools.inspect_timeline`); the monitor draws the same from the fit messages as they
come, with the bookkeeping of :mod:`streamer.tools.model_timeline`:

* **which model was in force** (``timeline/model/<k>``, a time series view under the
  coefficient plots, on their time axis): one thick horizontal line (a *lane*) per effect
  of the model, drawn over the fits estimated with it - at the centres of their windows, as
  the trends are, and switching where the coefficient lines break (between the last fit
  under the old model and the first under the new one: :mod:`stages.monitor.epochs`);
* **each change** (``model/log``, a text log entry at the change's time): what was added and
  removed, by whom and why, and the chi^2/dof before and after;
* **gaps and left-out hours** as shaded spans on the same axis (``timeline/gaps``: TDI
  segments reported as gaps and FFT segments with less than half valid samples;
  ``timeline/excluded/outlier``: FFT segments the rolling fit left out as transients;
  ``timeline/excluded/gated``: over a gate of the model), each a thick line over its span
  [mission time of the data], broken between spans (an ``rr.Clear``);
* **chi^2/dof per band before and after each change** (``adequacy/change/before``, crosses,
  and ``adequacy/change/after``, dots, at the change's time in the per-band chi^2/dof view;
  the bar charts ``model/before`` and ``model/after``): the fit message's ``model_change``
  (both models refitted on the same window), else the latest per-band adequacy under the
  old model and the first under the new one;
* **the residual's ASD before and after each change** (``asd/plot/X2/residual_before``,
  ``residual_after`` in the noise view, labelled with their segments): the latest residual
  subtracted with a fit of the old model and the first with one of the new;
* a text document ``timeline`` with the model spans, the changes with their numbers, the
  gaps and the left-out spans.

Who changed the model is not in the fit messages (the fitter's ``model`` events, which say,
are in its MCAP recording, where ``ttl inspect`` reads them): the monitor infers it - ``adopt
auto`` when the latest diagnosis before the change says it adopted its recommendation
(meta ``diagnosis.adoption.adopted``), ``window`` when only transients (``glitch``, ``gate``)
left the model (they leave it once their span has left the one-day window), ``control``
otherwise (a ``ttl control`` message).
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import rerun as rr

from streamer.bus.fit_record import FitMessage, ModelChange
from streamer.tools.model_timeline import SpanMerger, change_text, excluded_kind, model_delta
from ttlcore.diagnose.trends import model_key

from . import views

#: Lanes of the spans (y of the timeline view; the model's effects are at 1, 2, ...).
SPAN_LANES = {
    "gap": (-1.0, views.TIMELINE_GAPS, (120, 120, 120), "gap: no data"),
    "outlier": (-2.0, f"{views.TIMELINE_EXCLUDED}/outlier", (214, 39, 40), "left out: transient / outlier"),
    "gated": (-3.0, f"{views.TIMELINE_EXCLUDED}/gated", (255, 127, 14), "left out: gated"),
}
#: Lanes of the model's effects (a lane is reused by a later effect once this many exist).
MAX_LANES = 12
LANE_COLORS = (
    (31, 119, 180),
    (148, 103, 189),
    (44, 160, 44),
    (140, 86, 75),
    (227, 119, 194),
    (188, 189, 34),
    (23, 190, 207),
)
LANE_WIDTH = 6.0
#: Changes and spans kept for the timeline document (the latest).
KEEP = 30
#: Mission time [s] by which a clear precedes or follows a span's point.
EPS = 1e-3


def _fmt(x) -> str:
    return f"{x:.3f}" if isinstance(x, (int, float)) and math.isfinite(x) else "?"


def _couplings(specs: list[str]) -> tuple[str, ...]:
    """The couplings of the effect specs ``specs`` (the first part of their model key)."""
    key = model_key(specs)
    return key[0] if key is not None else ()


class ModelTimeline:
    """The model timeline of the fits drawn so far (module docstring).

    Parameters
    ----------
    rec
        The recording stream (anything with ``log``).
    at : callable
        ``at(t, index)`` sets the recording's time: mission time ``t`` [s], segment ``index``.
    band : (float, float)
        The noise view's band [Hz].
    """

    def __init__(self, rec, at, band):
        self.rec, self._set_time, self.band = rec, at, tuple(band)
        self.latest: tuple[float, int] = (0.0, 0)  # the latest mission time drawn [s] and its segment
        self.lanes: dict[str, int] = {}  # effect spec -> its lane (0, 1, ...)
        self.lane_spec: dict[int, str] = {}  # lane -> the spec drawn in it last
        self.active: set[str] = set()
        self.drawn_lanes: set[int] = set()
        self.model: list | None = None
        self.centre: float | None = None  # the latest fit's centre drawn
        self.adoption: dict | None = None  # the latest adopted diagnosis not yet seen as a change
        self.spans = {kind: SpanMerger(keep=KEEP) for kind in SPAN_LANES}
        self.lane_end: dict[str, float] = {}  # kind -> latest time drawn in its lane
        self.segment_len: tuple[int, float, float] | None = None  # latest TDI segment: index, t0, duration
        self.residuals: dict[int, tuple] = {}  # recent residuals: index -> (fit_index, f, asd, ratio)
        self.bands: tuple | None = None  # latest per-band adequacy under the model in force: (fit, labels, values)
        self.changes: list[dict] = []  # the latest KEEP changes, for the document
        self.first: dict | None = None  # the run's first model: {"index", "effects"}
        self.pending: dict | None = None  # a change waiting for its residual or bands after

    def at(self, t: float, index: int) -> None:
        """Set the recording's time (mission time ``t`` [s], segment ``index``)."""
        self._set_time(t, index)
        if t >= self.latest[0]:
            self.latest = (float(t), int(index))

    # ------------------------------------------------------------------ fits
    def fit(self, index: int, meta: FitMessage, centre: float, t_break: float | None, t_stop: float) -> str | None:
        """Fit ``index`` (its meta, window centre and end [s]; ``t_break`` from
        :class:`stages.monitor.epochs.ModelEpochs` when its model changed): the lanes, a change
        of model, the FFT segment it left out, its adequacy and diagnosis.  Returns the
        change's who-and-why text (for the model log line) when the model changed."""
        model = meta.model
        said = None
        self.latest = max(self.latest, (float(t_stop), int(index)))
        late = self.centre is not None and centre <= self.centre
        if not late:
            if isinstance(model, (list, tuple)) and model_key(model) != model_key(self.model):
                said = self._change(index, [str(e) for e in model], meta, centre, t_break)
            self.centre = centre
            self.at(centre, index)
            self._lane_points(centre)
        self._excluded(index, dict(meta.excluded) if meta.excluded is not None else None)
        self._adequacy(index, meta, centre)
        adoption = meta.adopted
        if adoption is not None:
            self.adoption = {"index": index, "reason": adoption.reason}
        self.at(t_stop, index)
        return said

    def _change(self, index, model, meta, centre, t_break) -> str | None:
        before, self.model = self.model, model
        added, removed, new_epoch = model_delta(before, model)
        if before is None:
            self.first = {"index": index, "effects": model}
            self.active = set(model)
            for spec in model:
                self._lane_of(spec)
            self._document()
            return None
        by, diagnosis_index, reason = self._who(added, removed)
        self.adoption = None
        t = t_break if t_break is not None else centre
        self.at(t, index)
        self._lanes_changed(index, t, added, removed)
        text = change_text(added, removed, by, diagnosis_index=diagnosis_index, reason=reason, new_epoch=new_epoch)
        change = {
            "index": index,
            "t": t,
            "effects": model,
            "text": text,
            "by": by,
            "residual_before": self._residual_before(index),
            "residual_after": None,
            "bands": None,
        }
        mc = meta.model_change
        if mc is not None and mc.bands_before is not None and mc.bands_after is not None:
            before, after = list(mc.bands_before), list(mc.bands_after)
            change["bands"] = (self._labels(meta, mc, len(after)), before, after, "the window refitted")
            change["chi2"] = (mc.chi2_dof_before, mc.chi2_dof_after)
        elif self.bands is not None:
            change["bands_before"] = self.bands
        self.changes = (self.changes + [change])[-KEEP:]
        self.pending = change
        if change["bands"] is not None:
            self._band_markers(change)
        self._after_residual()
        self._document()
        return text

    def _who(self, added: list[str], removed: list[str]) -> tuple[str, int | None, str | None]:
        """Who changed the model, ``(by, diagnosis index, reason)``: the adoption of a live
        diagnosis (``adopt auto``), the window (transients that left it, removed alone) or a
        control message."""
        if self.adoption is not None:
            return "adopt auto", self.adoption["index"], self.adoption["reason"]
        if removed and not added and not _couplings(removed):
            return "window", None, None
        return "control", None, None

    def _lanes_changed(self, index: int, t: float, added: list[str], removed: list[str]) -> None:
        """The lanes of the ``removed`` effects end at ``t``, those of the ``added`` start
        there (a lane drawn before is not joined to its earlier span)."""
        for spec in removed:
            if spec in self.lanes:
                self._lane_point(self.lanes[spec], t, style=False)
            self.active.discard(spec)
        for spec in added:
            lane = self._lane_of(spec)
            if lane in self.drawn_lanes:
                self.at(t - EPS, index)
                self.rec.log(views.timeline_lane(lane), rr.Clear(recursive=False))
                self.at(t, index)
            self.active.add(spec)
            self._lane_point(lane, t, style=True)

    def _labels(self, meta: FitMessage, mc: ModelChange, n: int) -> list[str]:
        """The labels of the ``n`` bands of a model change: the fit's adequacy bands, else
        the change's band edges."""
        bands = [b.to_json() for b in meta.adequacy.bands] if meta.adequacy is not None else None
        if bands is not None and len(bands) == n:
            return [views.band_label(b) for b in bands]
        edges = mc.band_edges
        if edges is not None and len(edges) == n + 1:
            return [f"{a:.3g}-{b:.3g} Hz" for a, b in zip(edges[:-1], edges[1:])]
        return [f"band {g}" for g in range(n)]

    # ------------------------------------------------------------------ lanes
    def _lane_of(self, spec: str) -> int:
        lane = self.lanes.get(spec)
        if lane is None:
            used = set(self.lanes.values())
            if len(used) < MAX_LANES:
                lane = len(used)
            else:  # reuse the lowest lane no effect of the model holds
                held = {self.lanes[s] for s in self.active if s in self.lanes}
                lane = min((k for k in used if k not in held), default=MAX_LANES - 1)
                self.lanes = {s: k for s, k in self.lanes.items() if k != lane}
            self.lanes[spec] = lane
        return lane

    def _lane_point(self, lane: int, t: float, style: bool) -> None:
        spec = next((s for s, k in self.lanes.items() if k == lane), "?")
        values = rr.Scalars(float(lane + 1))
        if style or lane not in self.drawn_lanes or self.lane_spec.get(lane) != spec:
            color = LANE_COLORS[lane % len(LANE_COLORS)]
            self.rec.log(
                views.timeline_lane(lane),
                values,
                rr.SeriesLines(colors=[color], widths=[LANE_WIDTH], names=[f"model: {spec}"]),
            )
        else:
            self.rec.log(views.timeline_lane(lane), values)
        self.drawn_lanes.add(lane)
        self.lane_spec[lane] = spec

    def _lane_points(self, centre: float) -> None:
        for spec in sorted(self.active, key=lambda s: self.lanes.get(s, 0)):
            self._lane_point(self._lane_of(spec), centre, style=False)

    # ------------------------------------------------------------------ gaps and left-out hours
    def segment(self, index: int, t0: float, duration: float) -> None:
        """A TDI segment drawn (for the span of a gap segment without a plan)."""
        if self.segment_len is None or index >= self.segment_len[0]:
            self.segment_len = (index, float(t0), float(duration))
        self.latest = max(self.latest, (float(t0 + duration), int(index)))

    def gap(self, index: int, span: tuple[float, float] | None) -> None:
        """TDI segment ``index`` reported as a gap, over ``span`` [s] (from the run's plan),
        or extrapolated from the latest segment drawn; nothing without either."""
        if span is None and self.segment_len is not None:
            k, t0, duration = self.segment_len
            span = (t0 + (index - k) * duration, t0 + (index - k + 1) * duration)
        if span is not None:
            self._span("gap", index, span[0], span[1])

    def _excluded(self, index: int, excluded) -> None:
        if not isinstance(excluded, dict):
            return
        t_start, t_stop = excluded.get("t_start"), excluded.get("t_stop")
        if isinstance(t_start, (int, float)) and isinstance(t_stop, (int, float)) and t_stop > t_start:
            kind = excluded_kind(excluded)
            self._span(kind, index, float(t_start), float(t_stop), gate=excluded.get("gate"), z=excluded.get("z"))

    def _span(self, kind: str, index: int, t_start: float, t_stop: float, **extra) -> None:
        y, entity, color, name = SPAN_LANES[kind]
        span, new = self.spans[kind].add(kind, index, t_start, t_stop, **extra)
        end = self.lane_end.get(kind)
        style = rr.SeriesLines(colors=[color], widths=[LANE_WIDTH], names=[name])
        if new and end is not None:  # not joined to the span before
            self.at(t_start - EPS, index)
            self.rec.log(entity, rr.Clear(recursive=False))
        self.at(t_start, index)
        self.rec.log(entity, rr.Scalars(y), style)
        self.at(t_stop, index)
        self.rec.log(entity, rr.Scalars(y))
        if end is not None and t_stop < end:  # came late: not joined to the span after
            self.at(t_stop + EPS, index)
            self.rec.log(entity, rr.Clear(recursive=False))
        self.lane_end[kind] = max(end if end is not None else t_stop, t_stop)
        self._document()

    # ------------------------------------------------------------------ before and after
    def _adequacy(self, index: int, meta: FitMessage, centre: float) -> None:
        bands = [b.to_json() for b in meta.adequacy.bands] if meta.adequacy is not None else []
        if not bands:
            return
        values = [b["chi2_dof"] for b in bands]
        if not all(isinstance(v, (int, float)) for v in values):
            return
        labels = [views.band_label(b) for b in bands]
        change = self.pending
        if change is not None and change["bands"] is None and index >= change["index"]:
            before = change.get("bands_before")
            if before is not None and before[1] == labels:
                change["bands"] = (labels, before[2], values, f"adequacy of fits {before[0]} and {index}")
                self._band_markers(change)
                self.at(centre, index)
                self._document()
        if model_key(list(meta.model) if meta.model is not None else None) in (None, model_key(self.model)):
            self.bands = (index, labels, values)

    def _band_markers(self, change: dict) -> None:
        labels, before, after, _ = change["bands"]
        n = len(after)
        colors = [views.band_color(g, n) for g in range(n)]
        self.at(change["t"], change["index"])
        parts: tuple[tuple[str, list, Literal["cross", "circle"]], ...] = (
            ("before", before, "cross"),
            ("after", after, "circle"),
        )
        for part, values, marker in parts:
            vals = [float(v) if isinstance(v, (int, float)) else float("nan") for v in values]
            self.rec.log(
                f"{views.CHANGE_BANDS}/{part}",
                rr.Scalars(vals),
                rr.SeriesPoints(
                    colors=colors, markers=[marker] * n, marker_sizes=[5.0] * n, names=[f"{x} {part}" for x in labels]
                ),
            )
            if not isinstance(change.get("chi2"), tuple):  # else the fit's model_change drew them
                self.rec.log(f"model/{part}", rr.BarChart(np.array(vals, dtype=float)))

    def _residual_before(self, index: int):
        old = [i for i, r in self.residuals.items() if (r[0] if r[0] is not None else i) < index]
        return (max(old), *self.residuals[max(old)][1:]) if old else None

    def residual(self, index: int, fit_index, f, asd, ratio: float) -> None:
        """A residual drawn (segment ``index``, subtracted with fit ``fit_index``; its ASD and
        in-band residual / expected): the after of a change waiting for it."""
        fit_index = fit_index if isinstance(fit_index, int) else None
        self.residuals[index] = (fit_index, f, asd, ratio)
        while len(self.residuals) > 8:
            del self.residuals[min(self.residuals)]
        self._after_residual()

    def _after_residual(self) -> None:
        change = self.pending
        if change is None or change["residual_after"] is not None:
            return
        new = [i for i, r in self.residuals.items() if r[0] is not None and r[0] >= change["index"]]
        if not new:
            return
        i = min(new)
        change["residual_after"] = (i, *self.residuals[i][1:])
        for part in ("before", "after"):
            r = change[f"residual_{part}"]
            if r is not None:
                views.noise_curve(
                    self.rec,
                    f"residual_{part}",
                    r[1],
                    r[2],
                    self.band,
                    color=views.CHANGE_COLORS[part],
                    label=f"residual {part} the model change (segment {r[0]})",
                )
        self._document()

    # ------------------------------------------------------------------ the document
    def _document(self) -> None:
        """The timeline document, at the latest time drawn: a version logged earlier in mission
        time (at a change's time, the centre of a window, half a day behind the data) would
        hide every later one from the time cursor at the end."""
        lines = ["**Model timeline** (lanes under the coefficient plots; newest change last)", ""]
        if self.first is not None:
            lines.append(
                f"- from fit {self.first['index']}: {', '.join(self.first['effects'])} (the first model drawn)"
            )
        for c in self.changes:
            line = f"- from fit {c['index']} ({views.days(c['t'])}): {', '.join(c['effects'])}: {c['text']}"
            if c.get("chi2"):
                line += f"; χ²/dof {_fmt(c['chi2'][0])} → {_fmt(c['chi2'][1])}"
            if c["bands"] is not None:
                labels, before, after, how = c["bands"]
                per = ", ".join(f"{x} {_fmt(a)} → {_fmt(b)}" for x, a, b in zip(labels, before, after))
                line += f"; per band ({how}): {per}"
            rb, ra = c["residual_before"], c["residual_after"]
            if rb is not None and ra is not None:
                line += f"; residual / expected {_fmt(rb[3])} (segment {rb[0]}) → {_fmt(ra[3])} (segment {ra[0]})"
            lines.append(line)
        spans = sorted((s for m in self.spans.values() for s in m.spans), key=lambda s: s["t_start"])
        if spans:
            lines += ["", "**Gaps and hours left out of the fit** (shaded spans)", ""]
            for s in spans[-KEEP:]:
                what = {"gap": "gap (no data)", "outlier": "left out: transient / outlier", "gated": "left out: gated"}
                extra = f", up to {s['z_max']:.0f} σ" if isinstance(s.get("z_max"), (int, float)) else ""
                lines.append(
                    f"- {views.days(s['t_start'])} – {views.days(s['t_stop'])}: {what[s['kind']]} "
                    f"(segment/fit {s['from_index']}–{s['to_index']}, {s['count']} item(s){extra})"
                )
        self._set_time(*self.latest)
        self.rec.log(views.TIMELINE_DOC, rr.TextDocument("\n".join(lines), media_type="text/markdown"))
