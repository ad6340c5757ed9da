"""The model timeline in the monitor's Rerun recording (issue 31, item 5), read back.

The monitor's handlers are driven in this process (no bus: the view-building of
:class:`stages.monitor.monitor.Monitor`, its recording opened as the stage opens it) with a synthetic
run of half-hour segments: a TDI segment reported as a gap, FFT segments left out as
outliers, and three changes of the model - an auto-adoption after a diagnosis (with the
fitter's ``model_change``: both models refitted on the window), a glitch added by a control
message and that glitch leaving with the window.  The ``.rrd`` file is read back with Rerun's
RRD reader: the lanes of the effects, the shaded spans, the log entries at the change times
saying who changed what, the per-band chi^2/dof before and after every change, the residual
ASDs before and after, the timeline document and the blueprint.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from rrd_testutil import blueprint_views, rrd_entities

from stages.monitor.monitor import Monitor, views
from streamer.bus.codec import decode, encode
from streamer.bus.message_schema import MessageError
from streamer.bus.residual_record import SCHEMA as RESIDUAL_SCHEMA
from streamer.runtime.stage import StageConfig
from ttlcore.conventions import COEFFICIENT_NAMES, C

RUN = "timeline-test"
FS = 4.0
SEG = 1800.0  # [s] half-hour segments
N = int(SEG * FS)
SEGMENTS = 12
GAP = 6  # the TDI segment reported as a gap (no fit, no residual)
OUTLIERS = (3, 4)  # fits that leave their newest FFT segment out as an outlier
DRIFT = ["linear-ttl", "drift"]
GLITCH = "glitch:t=4.6h,tm=12,beta=100s"
#: the model of each fit: adopted at 8 (diagnosis of fit 7), a glitch added by hand at 10,
#: gone with the window at 11
MODELS = {k: ["linear-ttl"] for k in range(8)} | {8: DRIFT, 9: DRIFT, 10: DRIFT + [GLITCH], 11: DRIFT}
LABELS = ["0.003-0.01 Hz", "0.01-0.9 Hz"]


def header(topic, index, arrays, meta, t0, fs=FS):
    fields = {"run": RUN, "index": index, "t0": t0, "fs": fs, "producer": "test", "meta": meta}
    if topic in ("tdi", "residual"):
        fields.update(channels=["X2", "Y2", "Z2"], channel_axis=0)
    return decode(*encode(arrays, fields, allow_nonfinite=True))[0]


def bands(before: bool) -> list[dict]:
    values = (2.5, 1.6) if before else (1.02, 0.99)
    return [
        {"f_lo": 3e-3, "f_hi": 1e-2, "chi2_dof": values[0], "p_value": 0.0, "fails": before},
        {"f_lo": 1e-2, "f_hi": 0.9, "chi2_dof": values[1], "p_value": 0.0, "fails": before},
    ]


def fit_meta(k: int) -> dict:
    meta = {
        "names": list(COEFFICIENT_NAMES),
        "chi2_dof": 1.0,
        "t_start": 0.0,
        "t_stop": (k + 1) * SEG,
        "converged": True,
        "model": MODELS[k],
        "adequacy": {"chi2_dof": 1.0, "fails": k < 8, "summary": [], "bands": bands(k < 8)},
    }
    if k in OUTLIERS:
        meta["excluded"] = {
            "t_start": k * SEG,
            "t_stop": (k + 1) * SEG,
            "chi2_dof": 3.0,
            "z": 9.0 + k,
            "reference": 1.0,
        }
    if k == 7:  # the live diagnosis adopted its recommendation: the model changes from fit 8 on
        meta["diagnosis"] = {
            "text": "a drift",
            "recommendation": {"spec": "drift"},
            "adoption": {"mode": "auto", "adopted": True, "reason": "drift explains the excess"},
        }
    if k == 8:
        meta["model_change"] = {
            "before": ["linear-ttl"],
            "after": DRIFT,
            "chi2_dof_before": 1.8,
            "chi2_dof_after": 1.01,
            "bands_before": [2.4, 1.5],
            "bands_after": [1.01, 0.98],
            "delta_chi2": 500.0,
            "log_bayes_factor": 240.0,
            "band_edges": [3e-3, 1e-2, 0.9],
        }
        meta["candidates"] = [
            {
                "effect": "step",
                "spec": "step",
                "delta_chi2": 12.5,
                "log_bayes_factor": 3.25,
                "explained_fraction": 0.1,
                "significant": False,
            }
        ]
    return meta


def test_monitor_draws_the_model_timeline_gaps_and_before_after(tmp_path):
    rrd = _draw_timeline_run(tmp_path)
    ent = rrd_entities(rrd)
    centre = {k: 0.5 * (k + 1) * SEG for k in range(SEGMENTS) if k != GAP}
    t_break = {
        8: 0.5 * (centre[7] + centre[8]),
        10: 0.5 * (centre[9] + centre[10]),
        11: 0.5 * (centre[10] + centre[11]),
    }
    _check_model_lanes(ent, centre, t_break)
    _check_gaps_and_left_out(ent)
    _check_change_log(ent, t_break)
    _check_before_after(ent, t_break)
    _check_residual_before_after(ent)
    _check_timeline_document(ent, rrd)


def _draw_timeline_run(tmp_path):
    """A monitor fed a run's segments (one a gap), fits whose model changes at 8, 10 and 11,
    and residuals halved from fit 8 on; returns its Rerun recording's path."""
    # the run's plan: the gap segment holds half the samples of the others (its span from the plan)
    table = [[k * SEG, N // 2 if k == GAP else N] for k in range(SEGMENTS)]
    plan = {"segments_total": SEGMENTS, "fs": FS, "t0": 0.0, "samples": N, "samples_total": N * SEGMENTS}
    m = Monitor(StageConfig(run=RUN, recordings=tmp_path, plan={**plan, "table": table}))
    m.rrd = tmp_path / "monitor.rrd"
    m.open_recording()
    rng = np.random.default_rng(3)
    ltt = np.full((6, N), 2.5e9 / C)
    m.on_telemetry(header("telemetry", 0, {"ltt": ltt}, {"segment_duration": SEG}, 0.0), {"ltt": ltt})
    sigma = np.full(24, 1e-5)
    for k in range(SEGMENTS):
        if k == GAP:
            m.draw_gap(k)  # reported as a gap upstream
            continue
        data = rng.normal(0.0, 1e-21, (3, N))
        h = header("tdi", k, {"data": data}, {"ltt_mean": [2.5e9 / C] * 6}, k * SEG)
        m.on_tdi(h, {"data": data})
        meta = fit_meta(k)
        coefficients = np.linspace(-2e-3, 2e-3, 24)
        arrays = {"coefficients": coefficients, "sigma": sigma}
        m.on_fit(header("fit", k, arrays, meta, meta["t_stop"] - SEG, fs=1 / SEG), arrays)
        # the residual shrinks once the drift is in the model (fit 8 on)
        scale = 1.0 if k < 8 else 0.5
        res = {"residual": data * scale, "ttl_model": np.zeros((3, N))}
        m.on_residual(header("residual", k, res, {"fit_index": k}, k * SEG), res)
    m.rec.disconnect()
    return m.rrd


def _scalars(ent, entity):
    """The scalar rows of ``entity``: (mission time [s], values), in time order."""
    rows = [(r[0]["mission_time"].total_seconds(), r[1].get("Scalars:scalars")) for r in ent.get(entity, [])]
    return sorted((t, v) for t, v in rows if v is not None)


def _clears(ent, entity):
    """The mission times [s] of the recursive clears of ``entity``."""
    return [r[0]["mission_time"].total_seconds() for r in ent.get(entity, []) if "Clear:is_recursive" in r[1]]


def _check_model_lanes(ent, centre, t_break):
    """The lanes: linear-ttl throughout, the drift from the change at fit 8, the glitch between 10 and 11."""
    lanes = {}
    for k in range(3):
        rows = ent[f"/timeline/model/{k}"]
        names = {n for r in rows for n in r[1].get("SeriesLines:names") or ()}
        (name,) = names
        lanes[name] = sorted(t for t, _ in _scalars(ent, f"/timeline/model/{k}"))
        assert {v[0] for _, v in _scalars(ent, f"/timeline/model/{k}")} == {k + 1.0}, name
    assert lanes["model: linear-ttl"][0] == centre[0] and lanes["model: linear-ttl"][-1] == centre[11]
    assert lanes["model: drift"] == sorted([t_break[8]] + [centre[k] for k in (8, 9, 10, 11)])
    assert lanes[f"model: {GLITCH}"] == [t_break[10], centre[10], t_break[11]]
    assert "/timeline/model/3" not in ent


def _check_gaps_and_left_out(ent):
    """Gaps and hours left out: shaded spans over their mission time."""
    gap = _scalars(ent, "/timeline/gaps")
    assert [t for t, _ in gap] == [GAP * SEG, (GAP + 0.5) * SEG] and {v[0] for _, v in gap} == {-1.0}
    outliers = _scalars(ent, "/timeline/excluded/outlier")
    # two adjacent FFT segments: one span, no clear between them
    assert sorted({t for t, _ in outliers}) == [3 * SEG, 4 * SEG, 5 * SEG], outliers
    assert _clears(ent, "/timeline/excluded/outlier") == []


def _check_change_log(ent, t_break):
    """The log: at each change's time, who changed what."""
    log = {
        round(r[0]["mission_time"].total_seconds(), 3): r[1]["TextLog:text"][0]
        for r in ent["/model/log"]
        if "TextLog:text" in r[1] and "model " in r[1]["TextLog:text"][0] and " by " in r[1]["TextLog:text"][0]
    }
    assert sorted(log) == [pytest.approx(t_break[k]) for k in (8, 10, 11)], log
    texts = [log[t] for t in sorted(log)]
    lines = [r[1]["TextLog:text"][0] for r in ent["/model/log"] if "TextLog:text" in r[1]]
    # the fit's model_change and candidates (typed values of the fit message) in the log
    assert "fit 8: model linear-ttl -> " + ",".join(DRIFT) + ": χ²/dof 1.800 -> 1.010, Δχ² 500.000, " in " ".join(lines)
    assert "fit 8: top candidates: step: Δχ² 12.5, log BF 3.2" in " ".join(lines)
    assert "+ drift by adopt auto after the diagnosis of segment 7: drift explains the excess" in texts[0]
    assert "[new model epoch]" in texts[0]
    assert f"+ {GLITCH} by control" in texts[1] and "[new model epoch]" not in texts[1]
    assert f"- {GLITCH} by window (it left the one-day window)" in texts[2]


def _check_before_after(ent, t_break):
    """chi2/dof per band before (crosses) and after (dots) each change, at its time."""
    before, after = _scalars(ent, "/adequacy/change/before"), _scalars(ent, "/adequacy/change/after")
    assert [t for t, _ in before] == [pytest.approx(t_break[k]) for k in (8, 10, 11)]
    assert [t for t, _ in after] == [t for t, _ in before]
    assert before[0][1] == [2.4, 1.5] and after[0][1] == pytest.approx([1.01, 0.98])  # the window refitted
    assert before[1][1] == pytest.approx([1.02, 0.99]) and after[2][1] == pytest.approx([1.02, 0.99])  # adequacy
    styles = [r[1] for r in ent["/adequacy/change/before"] if "SeriesPoints:names" in r[1]]
    assert styles[0]["SeriesPoints:names"] == [f"{x} before" for x in LABELS], styles[0]


def _check_residual_before_after(ent):
    """The residual's ASD before and after each change (noise view), labelled with their segments."""
    for part, segment in (("before", 7), ("after", 8)):
        rows = [r for r in ent[f"/asd/plot/X2/residual_{part}"] if "LineStrips2D:strips" in r[1]]
        assert rows, part
        assert f"residual {part} the model change (segment {segment})" in rows[0][1]["LineStrips2D:labels"][0]
    first_after = [r for r in ent["/asd/plot/X2/residual_after"] if "LineStrips2D:strips" in r[1]][0]
    first_before = [r for r in ent["/asd/plot/X2/residual_before"] if "LineStrips2D:strips" in r[1]][0]
    lb = {round(x, 5): y for x, y in np.concatenate([np.array(s) for s in first_before[1]["LineStrips2D:strips"]])}
    la = {round(x, 5): y for x, y in np.concatenate([np.array(s) for s in first_after[1]["LineStrips2D:strips"]])}
    common = sorted(set(lb) & set(la))  # log10 f inside the view's range in both
    assert len(common) > 10
    shift = np.median([lb[x] - la[x] for x in common])
    assert shift == pytest.approx(math.log10(2.0), abs=0.1)  # half the residual after the change


def _check_timeline_document(ent, rrd):
    """The timeline document (its latest version holds every change) and the blueprint."""
    doc = [r for r in ent["/model/timeline"] if "TextDocument:text" in r[1]]
    # the viewer shows the latest row at the time cursor (of rows at one time, the last logged)
    last = max(enumerate(doc), key=lambda kr: (kr[1][0]["mission_time"], kr[1][0]["segment"], kr[0]))[1]
    last = last[1]["TextDocument:text"][0]
    assert "from fit 0: linear-ttl (the first model drawn)" in last
    assert "from fit 8" in last and "by adopt auto" in last and "χ²/dof 1.800 → 1.010" in last
    assert "0.003-0.01 Hz 2.400 → 1.010" in last and "residual / expected" in last
    assert f"- {GLITCH} by window" in last  # the latest version of the document holds every change
    assert "gap (no data)" in last and "left out: transient / outlier" in last and "up to 13 σ" in last
    kinds = blueprint_views(rrd)
    assert ("TextDocument", f"/{views.TIMELINE_DOC}") in kinds, kinds
    assert sum(1 for k, _ in kinds if k == "TimeSeries") == 24 + 4


def test_timeline_lanes_and_spans_are_broken_between_spans():
    """A lane or span drawn again after a pause is not joined to its earlier part (an
    ``rr.Clear`` just before it), a span that comes late is closed after it too, and a gap
    segment without a plan takes its span from the latest segment drawn."""
    from stages.monitor.timeline import EPS, ModelTimeline
    from streamer.bus.fit_record import FitMessage

    class Rec:
        def __init__(self):
            self.t, self.rows = 0.0, []

        def log(self, entity, *parts):
            self.rows.append((self.t, entity, parts[0].__class__.__name__))

    rec = Rec()
    tl = ModelTimeline(rec, lambda t, i: setattr(rec, "t", t), (3e-3, 0.9))

    def fit(k, model, **meta):
        fm = FitMessage.from_header({"model": model, **meta})
        tl.fit(k, fm, k * 100.0, None if k == 0 else k * 100.0 - 50.0, k * 100.0 + 50.0)

    fit(0, ["linear-ttl", "drift"])
    fit(1, ["linear-ttl"])
    fit(2, ["linear-ttl", "drift"])  # drift back: its lane broken before it comes back
    drift = views.timeline_lane(1)
    assert [(t, kind) for t, e, kind in rec.rows if e == drift] == [
        (0.0, "Scalars"),
        (50.0, "Scalars"),
        (150.0 - EPS, "Clear"),
        (150.0, "Scalars"),
        (200.0, "Scalars"),
    ]
    out = f"{views.TIMELINE_EXCLUDED}/outlier"
    fit(3, ["linear-ttl", "drift"], excluded={"t_start": 1000.0, "t_stop": 1100.0, "z": 9.0})
    fit(4, ["linear-ttl", "drift"], excluded={"t_start": 500.0, "t_stop": 600.0, "z": 9.0})  # late, apart
    assert [(t, kind) for t, e, kind in rec.rows if e == out] == [
        (1000.0, "Scalars"),
        (1100.0, "Scalars"),
        (500.0 - EPS, "Clear"),
        (500.0, "Scalars"),
        (600.0, "Scalars"),
        (600.0 + EPS, "Clear"),
    ]
    tl.segment(7, 700.0, 100.0)
    tl.gap(9, None)  # no plan: after segment 7 of 100 s
    assert [(t, kind) for t, e, kind in rec.rows if e == views.TIMELINE_GAPS] == [
        (900.0, "Scalars"),
        (1000.0, "Scalars"),
    ]


def test_a_residual_meta_not_of_its_schema_is_an_error_naming_the_message_and_field(tmp_path):
    """The monitor reads a residual's meta as a :class:`ResidualMessage`: a field missing at
    the current schema, or one of the wrong type, stops at the boundary with the field named."""
    m = Monitor(StageConfig(run=RUN, recordings=tmp_path))
    m.rrd = tmp_path / "monitor.rrd"
    m.open_recording()
    data = np.random.default_rng(4).normal(0.0, 1e-21, (3, N))
    res = {"residual": data, "ttl_model": np.zeros((3, N))}
    current = {"fit_index": 3, "segments_total": 5, "schema": RESIDUAL_SCHEMA}
    with pytest.raises(MessageError, match=r"residual 3: meta field 'coefficients_t_start': missing"):
        m.on_residual(header("residual", 3, res, current, 0.0), res)
    with pytest.raises(MessageError, match=r"residual 3: meta field 'fit_index': expected int"):
        m.on_residual(header("residual", 3, res, {"fit_index": "3"}, 0.0), res)
    m.rec.disconnect()
