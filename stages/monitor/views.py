"""What the monitor draws in Rerun, and how the views are laid out (the blueprint).

The monitor's state (what arrived, the trends) lives in :mod:`stages.monitor.monitor` (when a segment
is done: :mod:`stages.monitor.settling`; the truth: :mod:`stages.monitor.truth`); the drawing
lives here, in functions of a recording stream ``rec`` (an ``rr.RecordingStream`` or
anything with its ``log``), so that a view can be changed without touching the stage.

Views (entity paths in brackets), laid out for a 1920x1080 screen:

* **Noise** (``asd``, a 2-D view, the largest panel): ASDs of X2 in displacement
  [m/sqrt(Hz)] of the latest segment, drawn as log10 values (Rerun has no log axes)
  against log10 f, only inside the fit band and with the y range held on the science range
  (1e-13 to 1e-9 m/sqrt(Hz)): the data (with TTL), the residual after subtraction, the
  fitted TTL, the noise without TTL the instrument model expects for the segment's arms, and
  the LISA requirement.  A decade grid with tick labels in real units (``0.01 Hz``,
  ``1e-12``) on the left and bottom edges, axis titles saying the axes are log10, and the
  legend above the plot, outside the data.  The x axis is stretched (``ASD_X_STRETCH``) so
  that the plot fills a landscape panel (a 2-D view keeps one unit the same length on both
  axes: unstretched, 2.5 decades of frequency against 4 of ASD filled a quarter of it).
* **χ²/dof** (``adequacy/chi2_dof``, ``adequacy/instrument/chi2_dof``): 1 is a model that
  explains the data.  **Residual / expected** (``adequacy/log10_residual_over_expected``):
  log10 of the in-band median ratio of the residual's ASD to the expected noise.
  **χ²/dof per band** (``adequacy/bands``, one series per band) against the instrument noise
  model, coloured from blue (lowest band) to red (highest).  No legend over the data: the
  series are named in the view titles and in the run summary.
* **Coefficients** (``coefficients/<mosa>/<angle>_<side>``): one small plot per coefficient
  [mm/rad] of one entity with four series: the fit at the centre of its window, fit +-1
  sigma and the truth averaged over the same window (when a truth is known); same colours
  everywhere.  Where the fitter's model changed, the lines are broken (:func:`break_series`)
  and a new model epoch (new couplings: a new series of the trend tests) is drawn in a colour
  of its own (:func:`epoch_style`: blue, orange, green, purple, then blue again);
  :mod:`stages.monitor.epochs`.
* **Model timeline** (``timeline/**``, under the coefficients, on their time axis, with a
  legend): a lane per effect of the model, the gaps and the hours left out of the fit as
  shaded spans; the per-band chi^2/dof before and after each change (``adequacy/change``) in
  the per-band view; the residual before and after in the noise view; a document
  (``model/timeline``).  :mod:`stages.monitor.timeline`.
* **Run and alerts** (``summary``, a text document): how far the run has been drawn, every
  alert so far and the model epochs, word-wrapped.  **Diagnosis** (``diagnosis``, a text document): the
  text and recommendation of the latest fit message whose meta carries a ``diagnosis``.
  Tabs beside the diagnosis: **Logs**, one text log of the alerts (``alerts``), the model
  changes and candidates (``model/log``) and the monitor's own log (``log``); bar charts
  ``model/candidates``, ``model/before``, ``model/after``.

What makes the recording cheap to open is described in :mod:`stages.monitor.monitor`: the web viewer
ingests a bounded number of messages per frame, so every chunk (blueprint ones included)
counts; hence one chunk per entity (:class:`SeriesLog`) and no view property that the
default already gives.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from streamer.bus.diagnosis_record import LiveDiagnosis
from streamer.bus.fit_record import ModelChange, RankedCandidate
from ttlcore.conventions import COEFFICIENT_NAMES, PAPER_ORDER

#: Curves of the noise view: name -> (legend label, RGB).
CURVES = {
    "data": ("X2 data (with TTL)", (31, 119, 180)),
    "residual": ("X2 residual (TTL subtracted)", (44, 160, 44)),
    "ttl_model": ("fitted TTL", (255, 127, 14)),
    "effect_model": ("other fitted effects (one each)", (148, 103, 189)),
    "expected": ("expected noise without TTL", (90, 90, 90)),
    "requirement": ("LISA requirement", (214, 39, 40)),
}
#: Science range of the noise view: log10 ASD [m/sqrt(Hz)] shown (the requirement in the
#: fit band lies between 1e-12 and 1e-10).
SCIENCE_LOG10 = (-13.0, -9.0)
#: How much longer a decade of frequency is drawn than a decade of ASD (see the module doc).
ASD_X_STRETCH = 2.4
#: Colours of a coefficient plot's series.
FIT_COLOR = (31, 119, 180)
SIGMA_COLOR = (158, 190, 224)
TRUTH_COLOR = (30, 30, 30)
#: Fit and +-1 sigma colours of the model epochs (epoch k: ``EPOCH_COLORS[k % 4]``).
EPOCH_COLORS = (
    (FIT_COLOR, SIGMA_COLOR),
    ((255, 127, 14), (255, 197, 140)),
    ((44, 160, 44), (160, 216, 160)),
    ((148, 103, 189), (205, 185, 225)),
)
#: chi^2/dof lines: the fit's own (re-estimated noise) and against the instrument noise model.
CHI2_COLOR = (30, 30, 30)
INSTRUMENT_COLOR = (214, 39, 40)
#: Greek letters of the angles, for view titles.
_ANGLE = {"phi": "φ", "eta": "η"}
#: Entity of the per-band chi^2/dof series (one series per band).
BANDS = "adequacy/bands"
#: Entities of the text documents.
SUMMARY = "summary"
DIAGNOSIS = "diagnosis"
#: The model timeline (:mod:`stages.monitor.timeline`): its document, the lanes of the
#: model's effects (``timeline/model/<k>``), of the gaps and of the hours left out of the fit,
#: and the per-band chi^2/dof before and after each change (``before``, ``after``).
TIMELINE_DOC = "model/timeline"
TIMELINE = "timeline"
TIMELINE_GAPS = "timeline/gaps"
TIMELINE_EXCLUDED = "timeline/excluded"
CHANGE_BANDS = "adequacy/change"
#: The residual's ASD before and after the latest model change (noise view).
CHANGE_COLORS = {"before": (188, 189, 34), "after": (0, 90, 50)}


def timeline_lane(k: int) -> str:
    """Entity of lane ``k`` of the model timeline (an effect of the model)."""
    return f"{TIMELINE}/model/{k}"


def coefficient_entity(name: str) -> str:
    """Entity path of coefficient ``<mosa>.<angle>.<side>``."""
    mosa, angle, side = name.split(".")
    return f"coefficients/{mosa}/{angle}_{side}"


def coefficient_title(name: str) -> str:
    mosa, angle, side = name.split(".")
    return f"{mosa} {_ANGLE[angle]} {side} [mm/rad]"


def _log_band(band) -> tuple[float, float]:
    return math.log10(band[0]), math.log10(band[1])


def band_color(g: int, n: int = 8) -> tuple[int, int, int]:
    """Colour of adequacy band ``g`` (0 = lowest frequency): blue through purple to red."""
    s = min(max(g / max(n - 1, 1), 0.0), 1.0)
    return int(31 + s * (214 - 31)), int(119 - s * (119 - 39)), int(180 - s * (180 - 40))


# ---------------------------------------------------------------------------- blueprint


def _series(name: str, contents, legend: bool = False, **kw) -> rrb.TimeSeriesView:
    """A time series over the whole mission time range, without a legend over its data
    (``legend``: one in the left top corner, for the model timeline's lanes).

    The x axis is set to the whole range (by default it follows the time cursor over a few
    minutes); the data range is left at its default, which is already everything: an
    explicit ``VisibleTimeRanges`` per view was one more blueprint chunk per view to load
    (27 of them) for the same picture.
    """
    everything = rrb.TimeRangeBoundary.infinite()
    return rrb.TimeSeriesView(
        name=name,
        contents=contents,
        axis_x=rrb.TimeAxis(view_range=rr.TimeRange(start=everything, end=everything)),
        # a legend in the left top corner: over the earliest fits, where later effects have no lane yet
        plot_legend=rrb.PlotLegend(corner="lefttop", visible=True) if legend else rrb.PlotLegend(visible=False),
        **kw,
    )


def noise_view(band) -> rrb.Spatial2DView:
    """The residual ASD against the requirement, with room for ticks, axis titles and legend."""
    x0, x1 = _log_band(band)
    y0, y1 = SCIENCE_LOG10
    s = ASD_X_STRETCH
    # the plot is flipped (larger ASD up): its y is -log10 ASD; margins: tick labels and the
    # y-axis title on the left, frequency labels and x-axis title below, the legend above
    return rrb.Spatial2DView(
        origin="asd",
        name="Noise of X2: ASD [m/√Hz] vs frequency [Hz], both log10 scales",
        visual_bounds=rrb.VisualBounds2D(x_range=[s * x0 - 0.75, s * x1 + 0.15], y_range=[-y1 - 1.05, -y0 + 0.6]),
    )


def blueprint(band) -> rrb.Blueprint:
    """The layout: the noise and adequacy on the left, the 24 coefficient plots on the right,
    the run summary with the alerts and the diagnosis below them; time series show the whole
    mission time range."""
    order = [n for m in PAPER_ORDER for n in COEFFICIENT_NAMES if n.startswith(m + ".")]
    coefficients = [_series(coefficient_title(n), [f"+ /{coefficient_entity(n)}/**"]) for n in order]
    adequacy = rrb.Horizontal(
        _series("χ²/dof: fit black, model red", ["+ /adequacy/chi2_dof", "+ /adequacy/instrument/chi2_dof"]),
        _series("log10 residual/expected", ["+ /adequacy/log10_residual_over_expected"]),
        _series(
            "χ²/dof per band, f: blue→red; at a model change before × after ●",
            [f"+ /{BANDS}", f"+ /{CHANGE_BANDS}/**"],
        ),
    )
    texts = rrb.Horizontal(
        rrb.TextDocumentView(origin=f"/{SUMMARY}", name="Run and alerts"),
        rrb.Tabs(
            rrb.TextDocumentView(origin=f"/{DIAGNOSIS}", name="Diagnosis"),
            rrb.TextDocumentView(origin=f"/{TIMELINE_DOC}", name="Model timeline"),
            # one log view for the alerts, the model changes and the monitor's log (their
            # entities are its columns): a view is a few blueprint chunks to load
            rrb.TextLogView(
                origin="/", contents=["+ /alerts", "+ /model/log", "+ /log"], name="Logs: alerts, model, monitor"
            ),
            rrb.BarChartView(origin="model/candidates", name="Candidates Δχ²"),
            rrb.BarChartView(origin="model/before", name="χ²/dof per band before"),
            rrb.BarChartView(origin="model/after", name="after"),
        ),
        column_shares=[1, 1],
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(noise_view(band), adequacy, row_shares=[7, 3]),
            rrb.Vertical(
                rrb.Grid(
                    *coefficients,
                    grid_columns=4,
                    name="Coefficients: fit ±1σ (blue; a colour per model epoch), truth (black)",
                ),
                _series(
                    "Model timeline: effects in the model (a lane each), gaps (grey), hours left out (red, orange)",
                    [f"+ /{TIMELINE}/**"],
                    legend=True,
                ),
                texts,
                row_shares=[13, 3, 5],
            ),
            column_shares=[1, 1],
        ),
        rrb.TimePanel(timeline="mission_time", play_state="following", state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


# ---------------------------------------------------------------------------- static parts


def static_styles(rec, band) -> None:
    """The noise view's transform, axes and legend (once, static).  The time series' styles
    are not static: they go with each series' earliest row (:class:`SeriesLog`)."""
    rec.log("asd/plot", rr.Transform3D(scale=[ASD_X_STRETCH, -1.0, 1.0]), static=True)  # larger ASD up
    noise_axes(rec, band)


def epoch_style(number: int) -> rr.SeriesLines:
    """The style of a coefficient's series (fit, +-1 sigma, truth) in model epoch ``number``."""
    fit, sigma = EPOCH_COLORS[number % len(EPOCH_COLORS)]
    return rr.SeriesLines(
        colors=[fit, sigma, sigma, TRUTH_COLOR],
        widths=[2.0, 1.0, 1.0, 1.0],
        names=["fit" if number == 0 else f"fit (model epoch {number})", "+1σ", "−1σ", "truth"],
    )


def break_series(rec) -> None:
    """Break the 24 coefficient lines at the recording's current time (a model change between
    two fits): a time series plot draws an ``rr.Clear`` as a hole in its lines.  The clear
    also hides the style logged before it from the rows after it, so the next row of each
    entity carries its style again (:func:`fit_point`'s ``style``)."""
    for name in COEFFICIENT_NAMES:
        rec.log(coefficient_entity(name), rr.Clear(recursive=False))


def series_styles() -> dict[str, rr.SeriesLines]:
    """Colours, widths and names of the time series whose entities are known in advance
    (the per-band chi^2/dof series are styled when their bands are known: :func:`band_series`)."""
    styles = {}
    for name in COEFFICIENT_NAMES:
        styles[coefficient_entity(name)] = epoch_style(0)
    styles["adequacy/chi2_dof"] = rr.SeriesLines(colors=[CHI2_COLOR], widths=[2.0], names=["fit (re-estimated noise)"])
    styles["adequacy/instrument/chi2_dof"] = rr.SeriesLines(
        colors=[INSTRUMENT_COLOR], widths=[2.0], names=["instrument noise model"]
    )
    styles["adequacy/log10_residual_over_expected"] = rr.SeriesLines(
        colors=[CURVES["residual"][1]], widths=[1.5], names=["log10 residual/expected"]
    )
    return styles


class SeriesLog:
    """Logs the scalars of the time series, each entity's style (``rr.SeriesLines``) in the
    same row as its earliest point.

    A static style is a chunk of its own that no merging can join to the entity's data (a
    static chunk has no timeline): 57 of the 296 chunks of a week's recording, each one more
    message for the viewer to ingest.  Logged with the earliest row instead, the style and the
    data of an entity end up in one chunk; the series visualizer carries a style forward to
    the later points.  A row earlier than every row so far (a fit that arrived out of order)
    carries the style again.

    Parameters
    ----------
    rec
        The recording stream (anything with ``log``).
    """

    def __init__(self, rec):
        self.rec = rec
        self.styles = series_styles()
        self._earliest: dict[str, float] = {}
        self._keys: dict[str, object] = {}  # what each style set with a key was made of
        self._restyle: set[str] = set()  # entities whose next row carries a changed style

    def style(self, entity: str, lines: rr.SeriesLines, key=None) -> None:
        """Set the style of ``entity`` if it has none yet, or if ``key`` (what the style is made
        of, e.g. the series' names) differs from the one it was set with; a style changed after
        rows were logged goes with the next row."""
        if entity in self.styles and (key is None or self._keys.get(entity) == key):
            return
        if entity in self._earliest:
            self._restyle.add(entity)
        self.styles[entity] = lines
        self._keys[entity] = key

    def log(self, entity: str, values, t: float, style: rr.SeriesLines | None = None) -> None:
        """Scalars ``values`` of ``entity`` at the recording's current time, whose mission time
        is ``t`` [s]; ``style``: this row's style (after a break of the series), whatever the
        entity's."""
        earliest = self._earliest.get(entity)
        if style is not None:
            self._earliest[entity] = float(t) if earliest is None else min(earliest, float(t))
            self.rec.log(entity, rr.Scalars(values), style)
        elif entity in self._restyle:
            self._restyle.discard(entity)
            self._earliest[entity] = float(t) if earliest is None else min(earliest, float(t))
            self.rec.log(entity, rr.Scalars(values), self.styles[entity])
        elif entity in self.styles and (earliest is None or t < earliest):
            self._earliest[entity] = float(t)
            self.rec.log(entity, rr.Scalars(values), self.styles[entity])
        else:
            self.rec.log(entity, rr.Scalars(values))


def first_texts(rec) -> None:
    """The text panels before anything is drawn, at the current time (mission time 0: not
    static, which would hide every later document of the entity)."""
    summary_document(rec, "No segment drawn yet", [], [])
    rec.log(
        DIAGNOSIS,
        rr.TextDocument(
            "No diagnosis yet: it appears here when a fit message carries one.", media_type="text/markdown"
        ),
    )


def noise_axes(rec, band) -> None:
    """Decade grid of the noise view over the fit band and the science range, tick labels
    on the left and bottom edges, axis titles, and the legend above the plot."""
    x0, x1 = _log_band(band)
    y0, y1 = SCIENCE_LOG10
    s = ASD_X_STRETCH
    xt = list(range(math.ceil(x0), math.floor(x1) + 1))
    yt = list(range(int(y0), int(y1) + 1))
    lines: list[list[tuple[float, float]]] = [[(x, y0), (x, y1)] for x in xt]
    lines += [[(x0, y), (x1, y)] for y in yt]
    lines += [[(x0, y0), (x0, y1)], [(x1, y0), (x1, y1)]]  # the band's edges
    rec.log(
        "asd/plot/grid", rr.LineStrips2D(lines, colors=[(210, 210, 210)], radii=rr.Radius.ui_points(0.5)), static=True
    )
    # label positions in data units; the x stretch makes a data unit of x longer on screen
    ticks = [(x, y0 - 0.12) for x in xt] + [(x0 - 0.16 / s, y) for y in yt]
    labels = [f"{10.0**x:g} Hz" for x in xt] + [f"1e{y}" for y in yt]
    titles = [(0.5 * (x0 + x1), y0 - 0.32), (x0 + 0.1, y1 + 0.2)]
    rec.log(
        "asd/plot/ticks",
        rr.Points2D(
            ticks + titles,
            labels=labels + ["frequency [Hz], log10 scale", "ASD [m/√Hz], log10 scale"],
            radii=rr.Radius.ui_points(0.1),
            colors=[(90, 90, 90)],
            show_labels=True,
        ),
        static=True,
    )
    names = list(CURVES)
    # the legend in two rows of three above the plot (y above the science range): outside the data
    pts = [(x0 + (0.12 + 0.36 * (k % 3)) * (x1 - x0), y1 + 0.85 - 0.3 * (k // 3)) for k in range(len(names))]
    rec.log(
        "asd/plot/legend",
        rr.Points2D(
            pts,
            labels=[CURVES[n][0] for n in names],
            colors=[CURVES[n][1] for n in names],
            radii=rr.Radius.ui_points(5.0),
            show_labels=True,
        ),
        static=True,
    )


# ---------------------------------------------------------------------------- per message

#: Colours of the model's other effects (``effect_model``, one curve each, in the order of the
#: subtractor's meta ``effects``): shades of the legend's purple.
EFFECT_COLORS = ((148, 103, 189), (197, 176, 213), (106, 61, 154), (202, 178, 214))


def noise_curve(rec, name: str, f, asd, band, color=None, label: str | None = None) -> None:
    """One ASD [m/sqrt(Hz)] of the noise view, inside the fit band, in log10 (points
    outside the science range are left out, so no curve leaves the view); ``color`` and
    ``label`` for a curve not in :data:`CURVES` (an effect of the model)."""
    f = np.asarray(f, dtype=float)
    asd = np.asarray(asd, dtype=float)
    sel = (f >= band[0]) & (f <= band[1]) & (asd > 0) & np.isfinite(asd)
    x, y = np.log10(f[sel]), np.log10(asd[sel])
    y0, y1 = SCIENCE_LOG10
    inside = (y >= y0) & (y <= y1)
    # break the line where it leaves the range: one strip per stretch inside
    strips, start = [], None
    for k, ok in enumerate(np.append(inside, False)):
        if ok and start is None:
            start = k
        elif not ok and start is not None:
            if k - start >= 2:
                strips.append(np.column_stack([x[start:k], y[start:k]]).astype(np.float32))
            start = None
    rec.log(
        f"asd/plot/X2/{name}",
        rr.LineStrips2D(
            strips,
            colors=[color or CURVES[name][1]],
            radii=rr.Radius.ui_points(1.5),
            labels=[label] * len(strips) if label and strips else None,  # (None: Rerun's defaults)
            show_labels=True if label and strips else None,
        ),
    )


def fit_point(series: SeriesLog, C, S, t: float, truth=None, style: rr.SeriesLines | None = None) -> None:
    """The 24 coefficients [m/rad] with their sigma and, when known, the truth averaged over
    the fit's window, in mm/rad, at mission time ``t`` [s]: one row per coefficient of the
    series fit, fit + sigma, fit - sigma and truth.  One entity per coefficient, not a fit and
    a truth entity: half the rows and chunks for the web viewer to ingest.  ``style``: the
    rows' style (the first fit after a model change: :func:`epoch_style`)."""
    for p, name in enumerate(COEFFICIENT_NAMES):
        c, s = C[p] * 1e3, S[p] * 1e3
        values = [c, c + s, c - s] if truth is None else [c, c + s, c - s, truth[p] * 1e3]
        series.log(coefficient_entity(name), values, t, style)


def band_label(band: dict) -> str:
    return f"{band.get('f_lo', 0):.3g}-{band.get('f_hi', 0):.3g} Hz"


def band_series(series: SeriesLog, bands: list[dict], t: float) -> bool:
    """chi2/dof of every adequacy band against the instrument noise model at mission time ``t``
    [s]: one row of the entity ``adequacy/bands``, one series per band (coloured from blue,
    the lowest band, to red).  One entity rather than one per band: a row and a chunk less
    per band for the viewer to ingest.  Nothing is drawn (False) unless every band has a
    finite ``chi2_dof`` (a series per band: a missing one would shift the others)."""
    values = [float(v) for b in bands if isinstance(v := b.get("chi2_dof"), (int, float)) and math.isfinite(v)]
    if not values or len(values) != len(bands):
        return False
    labels = [band_label(b) for b in bands]
    n = len(bands)
    lines = rr.SeriesLines(names=labels, colors=[band_color(g, n) for g in range(n)], widths=[1.5] * n)
    series.style(BANDS, lines, key=tuple(labels))
    series.log(BANDS, values, t)
    return True


def text(rec, entity: str, message: str, level: str = "INFO") -> None:
    rec.log(entity, rr.TextLog(message, level=level))


def days(t: float) -> str:
    """Mission time [s] for people: ``3.50 d``."""
    return f"{t / 86400.0:.2f} d"


def summary_document(rec, progress: str, alerts: list[str], bands: list[str], epochs: Sequence[str] = ()) -> None:
    """The run summary: how far the run is drawn, every alert so far (newest last), the model
    epochs and changes of transients (when the model changed) and the key of the per-band
    chi^2/dof plot, as a word-wrapped markdown document."""
    lines = [f"**{progress}**", ""]
    lines += [f"**Alerts ({len(alerts)})**", ""] + ([f"- {a}" for a in alerts] or ["- none"])
    if len(epochs) > 1:  # the trends compare fits within an epoch (stages.monitor.epochs)
        lines += ["", "**Model epochs** (the trends compare fits within one)", ""] + [f"- {e}" for e in epochs]
    if bands:
        lines += ["", "**χ²/dof bands** (blue → red): " + ", ".join(bands)]
    rec.log(SUMMARY, rr.TextDocument("\n".join(lines), media_type="text/markdown"))


def diagnosis_document(rec, index: int, diagnosis: LiveDiagnosis | None) -> bool:
    """The live diagnosis of fit ``index`` (its meta ``diagnosis``: ``text`` and, when
    present, ``recommendation``) as a markdown document; False (nothing drawn) when the
    meta has no usable text."""
    if diagnosis is None or diagnosis.text is None or not diagnosis.text.strip():
        return False
    lines = [f"**Fit {index}**", "", diagnosis.text.strip()]
    if diagnosis.recommendation is not None:
        lines += ["", f"**Recommendation:** {json.dumps(diagnosis.recommendation.to_json(), default=str).strip()}"]
    rec.log(DIAGNOSIS, rr.TextDocument("\n".join(lines), media_type="text/markdown"))
    return True


def model_change(rec, index: int, change: ModelChange | None) -> None:
    """A fit's ``model_change`` (meta): a line of the model log (the models, chi^2/dof before
    and after, delta chi^2, log Bayes factor) and the per-band chi^2/dof before and after as
    bar charts (``model/before``, ``model/after``).  Nothing when there is none."""
    if change is None:
        return

    def fmt(x):
        return f"{x:.3f}" if isinstance(x, (int, float)) else "?"

    text(
        rec,
        "model/log",
        f"fit {index}: model {','.join(change.before)} -> "
        f"{','.join(change.after)}: χ²/dof {fmt(change.chi2_dof_before)}"
        f" -> {fmt(change.chi2_dof_after)}, Δχ² {fmt(change.delta_chi2)}, "
        f"log Bayes factor {fmt(change.log_bayes_factor)}",
    )
    for part, values in (("before", change.bands_before), ("after", change.bands_after)):
        if values:
            rec.log(f"model/{part}", rr.BarChart(np.array([np.nan if v is None else v for v in values], dtype=float)))


def candidate_ranking(rec, index: int, candidates: tuple[RankedCandidate, ...] | None) -> None:
    """A fit's ``candidates`` (meta): a line of the model log and their delta chi^2 as a bar
    chart (``model/candidates``).  Nothing when there are none."""
    if not candidates:
        return
    lines = [
        f"{c.effect}: Δχ² {c.delta_chi2 or 0:.1f}, log BF {c.log_bayes_factor or 0:.1f}"
        f"{' (significant)' if c.significant else ''}"
        for c in candidates
    ]
    text(rec, "model/log", f"fit {index}: top candidates: " + "; ".join(lines))
    rec.log("model/candidates", rr.BarChart(np.array([float(c.delta_chi2 or 0.0) for c in candidates])))
