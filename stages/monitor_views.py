"""What the monitor draws in Rerun, and how the views are laid out (the blueprint).

The monitor's state (what arrived, the trends) lives in :mod:`stages.monitor`; the drawing
lives here, in functions of a recording stream ``rec`` (an ``rr.RecordingStream`` or
anything with its ``log``), so that a view can be changed without touching the stage.

Views (entity paths in brackets):

* **Noise in the fit band** (``asd``, a 2-D view): ASDs of X2 in displacement
  [m/sqrt(Hz)] of the latest segment, drawn as log10 values (Rerun has no log axes)
  against log10 f, only inside the fit band and with the y range held on the science range
  (1e-13 to 1e-9 m/sqrt(Hz)): the data (with TTL), the residual after subtraction, the
  fitted TTL, the noise without TTL the instrument model expects for the segment's arms, and
  the LISA requirement. A decade grid, tick labels on the edges and a legend in the corner
  (no labels on the curves).
* **chi2/dof** (``adequacy/chi2_dof``, ``adequacy/instrument/chi2_dof``): alone on its
  axis, 1 is a model that explains the data.
* **Residual over expected** (``adequacy/log10_residual_over_expected``): log10 of the
  in-band median ratio of the residual's ASD to the expected noise (0 = as expected).
* **chi2/dof per band** (``adequacy/bands/<g>``) against the instrument noise model.
* **Coefficients** (``coefficients/<mosa>/<angle>_<side>/{fit,plus_sigma,minus_sigma,truth}``):
  one small plot per coefficient [mm/rad], the fit at the centre of its window with
  +-1 sigma and the truth averaged over the same window; same colours everywhere, so no
  legend covers the plots.
* **Alerts** (``alerts``), **Model and candidates** (``model/log``, bar charts
  ``model/before``, ``model/after``, ``model/candidates``) and the monitor's **log** (``log``):
  text logs.
"""

from __future__ import annotations

import math

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ttlcore.conventions import COEFFICIENT_NAMES, PAPER_ORDER

#: Curves of the noise view: name -> (legend label, RGB).
CURVES = {
    "data": ("X2 data (with TTL)", (31, 119, 180)),
    "residual": ("X2 residual (TTL subtracted)", (44, 160, 44)),
    "ttl_model": ("fitted TTL", (255, 127, 14)),
    "expected": ("noise without TTL (instrument model)", (90, 90, 90)),
    "requirement": ("LISA requirement", (214, 39, 40)),
}
#: Science range of the noise view: log10 ASD [m/sqrt(Hz)] shown (the requirement in the
#: fit band lies between 1e-12 and 1e-10).
SCIENCE_LOG10 = (-13.0, -9.0)
#: Colours of a coefficient plot's series.
FIT_COLOR = (31, 119, 180)
SIGMA_COLOR = (158, 190, 224)
TRUTH_COLOR = (30, 30, 30)
#: Greek letters of the angles, for view titles.
_ANGLE = {"phi": "φ", "eta": "η"}


def coefficient_entity(name: str) -> str:
    """Entity path of coefficient ``<mosa>.<angle>.<side>``."""
    mosa, angle, side = name.split(".")
    return f"coefficients/{mosa}/{angle}_{side}"


def coefficient_title(name: str) -> str:
    mosa, angle, side = name.split(".")
    return f"{mosa} {_ANGLE[angle]} {side} [mm/rad]"


def _log_band(band) -> tuple[float, float]:
    return math.log10(band[0]), math.log10(band[1])


# ---------------------------------------------------------------------------- blueprint

def blueprint(band) -> rrb.Blueprint:
    """The layout: noise and adequacy on the left, the 24 coefficient plots on the right,
    the text logs below; time series show the whole mission time range."""
    everything = rrb.TimeRangeBoundary.infinite()
    whole = [rrb.VisibleTimeRange(t, start=everything, end=everything) for t in ("mission_time", "segment")]
    no_legend = rrb.PlotLegend(visible=False)

    def series(name: str, contents, **kw):
        return rrb.TimeSeriesView(name=name, contents=contents, time_ranges=whole,
                                  axis_x=rrb.TimeAxis(view_range=rr.TimeRange(start=everything, end=everything)),
                                  **kw)

    order = [n for m in PAPER_ORDER for n in COEFFICIENT_NAMES if n.startswith(m + ".")]
    coefficients = [series(coefficient_title(n), [f"+ /{coefficient_entity(n)}/**"], plot_legend=no_legend)
                    for n in order]
    x0, x1 = _log_band(band)
    y0, y1 = SCIENCE_LOG10
    noise = rrb.Spatial2DView(
        origin="asd", name="Noise in the fit band: log10 ASD of X2 [m/√Hz] vs log10 f [Hz]",
        # the plot is flipped (larger ASD up): its y is -log10 ASD
        visual_bounds=rrb.VisualBounds2D(x_range=[x0 - 0.45, x1 + 0.05], y_range=[-y1 - 0.45, -y0 + 0.35]))
    adequacy = rrb.Horizontal(
        series("χ²/dof (1 = model explains the data)",
               ["+ /adequacy/chi2_dof", "+ /adequacy/instrument/chi2_dof"],
               plot_legend=rrb.PlotLegend(corner=rrb.Corner2D.LeftTop)),
        series("log10 residual / expected noise (in band)", ["+ /adequacy/log10_residual_over_expected"],
               plot_legend=no_legend),
        series("χ²/dof per band (instrument noise model)", ["+ /adequacy/bands/**"],
               plot_legend=rrb.PlotLegend(corner=rrb.Corner2D.LeftTop)),
    )
    logs = rrb.Tabs(
        rrb.TextLogView(origin="/alerts", name="Alerts"),
        rrb.TextLogView(origin="/model", contents=["+ /model/log"], name="Model and candidates"),
        rrb.BarChartView(origin="model/candidates", name="Top candidates: Δχ²"),
        rrb.BarChartView(origin="model/before", name="χ²/dof per band before the model change"),
        rrb.BarChartView(origin="model/after", name="χ²/dof per band after"),
        rrb.TextLogView(origin="/log", name="Monitor log"),
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(noise, adequacy, logs, row_shares=[5, 3, 2]),
            rrb.Grid(*coefficients, grid_columns=4, name="Coefficients: fit ±1σ (blue), truth (black)"),
            column_shares=[2, 3],
        ),
        rrb.TimePanel(timeline="mission_time", play_state="following", state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


# ---------------------------------------------------------------------------- static parts

def static_styles(rec, band) -> None:
    """Axes of the noise view, its legend, and the series styles (once, static)."""
    rec.log("asd/plot", rr.Transform3D(scale=[1.0, -1.0, 1.0]), static=True)  # larger ASD up
    noise_axes(rec, band)
    for name in COEFFICIENT_NAMES:
        ent = coefficient_entity(name)
        rec.log(f"{ent}/fit", rr.SeriesLines(colors=[FIT_COLOR], widths=[2.0], names=["fit"]), static=True)
        for part, label in (("plus_sigma", "+1σ"), ("minus_sigma", "−1σ")):
            rec.log(f"{ent}/{part}", rr.SeriesLines(colors=[SIGMA_COLOR], widths=[1.0], names=[label]), static=True)
        rec.log(f"{ent}/truth", rr.SeriesLines(colors=[TRUTH_COLOR], widths=[1.0], names=["truth"]), static=True)
    rec.log("adequacy/chi2_dof", rr.SeriesLines(colors=[(30, 30, 30)], widths=[2.0],
                                                names=["fit (re-estimated noise)"]), static=True)
    rec.log("adequacy/instrument/chi2_dof", rr.SeriesLines(colors=[(214, 39, 40)], widths=[2.0],
                                                           names=["instrument noise model"]), static=True)
    rec.log("adequacy/log10_residual_over_expected",
            rr.SeriesLines(colors=[CURVES["residual"][1]], widths=[1.5], names=["log10 residual/expected"]),
            static=True)


def noise_axes(rec, band) -> None:
    """Decade grid of the noise view over the fit band and the science range, tick labels
    on the left and bottom edges, and the legend in the top-left corner."""
    x0, x1 = _log_band(band)
    y0, y1 = SCIENCE_LOG10
    xt = list(range(math.ceil(x0), math.floor(x1) + 1))
    yt = list(range(int(y0), int(y1) + 1))
    lines = [[(x, y0), (x, y1)] for x in xt] + [[(x0, y), (x1, y)] for y in yt]
    lines += [[(x0, y0), (x0, y1)], [(x1, y0), (x1, y1)]]  # the band's edges
    rec.log("asd/plot/grid", rr.LineStrips2D(lines, colors=[(210, 210, 210)], radii=rr.Radius.ui_points(0.5)),
            static=True)
    ticks = [(x, y0 - 0.18) for x in xt] + [(x0 - 0.22, y) for y in yt]
    labels = [f"{10.0 ** x:g} Hz" for x in xt] + [f"1e{y}" for y in yt]
    rec.log("asd/plot/ticks", rr.Points2D(ticks, labels=labels, radii=rr.Radius.ui_points(0.1),
                                          colors=[(110, 110, 110)], show_labels=True), static=True)
    names = list(CURVES)
    step = 0.22
    pts = [(x0 + 0.08, y0 + 0.95 - step * k) for k in range(len(names))]  # bottom left: below the noise
    rec.log("asd/plot/legend", rr.Points2D(pts, labels=[CURVES[n][0] for n in names],
                                           colors=[CURVES[n][1] for n in names],
                                           radii=rr.Radius.ui_points(5.0), show_labels=True), static=True)


# ---------------------------------------------------------------------------- per message

def noise_curve(rec, name: str, f, asd, band) -> None:
    """One ASD [m/sqrt(Hz)] of the noise view, inside the fit band, in log10 (points
    outside the science range are left out, so no curve leaves the view)."""
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
    rec.log(f"asd/plot/X2/{name}", rr.LineStrips2D(strips, colors=[CURVES[name][1]],
                                                   radii=rr.Radius.ui_points(1.5)))


def fit_point(rec, C, S) -> None:
    """The 24 coefficients [m/rad] with their sigma, in mm/rad."""
    for p, name in enumerate(COEFFICIENT_NAMES):
        ent = coefficient_entity(name)
        rec.log(f"{ent}/fit", rr.Scalars(C[p] * 1e3))
        rec.log(f"{ent}/plus_sigma", rr.Scalars((C[p] + S[p]) * 1e3))
        rec.log(f"{ent}/minus_sigma", rr.Scalars((C[p] - S[p]) * 1e3))


def truth_point(rec, truth) -> None:
    """The 24 true coefficients [m/rad] averaged over a fit's window, in mm/rad."""
    for p, name in enumerate(COEFFICIENT_NAMES):
        rec.log(f"{coefficient_entity(name)}/truth", rr.Scalars(truth[p] * 1e3))


def band_series(rec, g: int, band: dict, styled: set) -> None:
    """chi2/dof of band ``g`` against the instrument noise model."""
    ent = f"adequacy/bands/{g}"
    if ent not in styled:
        styled.add(ent)
        rec.log(ent, rr.SeriesLines(names=[f"{band.get('f_lo', 0):.3g}-{band.get('f_hi', 0):.3g} Hz"],
                                    widths=[1.0]), static=True)
    rec.log(ent, rr.Scalars(float(band["chi2_dof"])))


def text(rec, entity: str, message: str, level: str = "INFO") -> None:
    rec.log(entity, rr.TextLog(message, level=level))
