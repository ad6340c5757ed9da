"""Unit tests of :mod:`streamer.tools.inspect_timeline`: the fitter's model over a run, read from
real recordings written by the recorder (no bus)."""

from streamer.recording.recorder import Recorder, read_recording
from streamer.tools.inspect_timeline import model_timeline

RUN = "r1"
HOUR = 3600.0


def fitter_file(path, summaries: dict[int, list], events=(), warnings=()):
    rec = Recorder(path, metadata={"run": RUN, "stage": "fitter", "class": "X", "config": "{}"})
    for i, model in summaries.items():
        rec.write_json("fit/summary", {"run": RUN, "index": i, "model": model})
    for e in events:
        rec.write_json("events", e)
    for w in warnings:
        rec.write_json("warnings", w)
    rec.close()
    return read_recording(path)


def model_event(from_index, effects, before, by, **more):
    details = {"from_index": from_index, "effects": effects, "before": before, "by": by, **more}
    return {"kind": "model", "index": from_index - 1, "details": details}


def test_model_spans_gaps_and_what_was_left_out(tmp_path):
    linear, drift = ["linear-ttl"], ["linear-ttl", "drift"]
    glitch = ["linear-ttl", "drift", "glitch:t0=30000"]
    first = fitter_file(
        tmp_path / "fitter.1.mcap",
        {i: linear for i in range(4)},
        events=[
            model_event(4, drift, linear, "adopt auto", diagnosis_index=3, reason="a drift"),
            {"kind": "gap", "index": 2},
        ],
        warnings=[
            {"kind": "segment-excluded", "index": 1, "details": {"t_start": 3600.0, "t_stop": 5400.0, "z": 8.0}},
            {"kind": "segment-excluded", "index": 2, "details": {"t_start": 5400.0, "t_stop": 7200.0, "z": 11.0}},
        ],
    )
    # the restarted fitter records the change again, then a transient that comes and goes
    second = fitter_file(
        tmp_path / "fitter.mcap",
        {4: drift, 5: drift, 6: glitch, 7: glitch, 8: drift},
        events=[
            model_event(4, drift, linear, "adopt auto", diagnosis_index=3, reason="a drift"),
            model_event(6, glitch, drift, "control"),
            model_event(8, drift, glitch, "window", removed=["glitch:t0=30000"]),
            {"kind": "gap", "index": 3},
            {"kind": "gap", "index": 7},
            {
                "kind": "segment-gated",
                "index": 6,
                "details": {"t_start": 9000.0, "t_stop": 10800.0, "gate": [9e3, 1e4]},
            },
        ],
        # the same FFT segment left out again by the restarted fitter: once
        warnings=[
            {"kind": "segment-excluded", "index": 2, "details": {"t_start": 5400.0, "t_stop": 7200.0, "z": 11.0}}
        ],
    )
    plan = {"t0": 0.0, "samples": 4 * 3600, "fs": 4.0}
    t = model_timeline([first, second], plan)
    spans = [(s["from_index"], s["to_index"], s["by"], s["fits"], s["new_epoch"]) for s in t["models"]]
    assert spans == [
        (0, 3, "configured", 4, False),
        (4, 5, "adopt auto", 2, True),  # a new coupling: a new series of the trends
        (6, 7, "control", 2, False),  # a transient alone: none
        (8, 8, "window", 1, False),
    ]
    assert t["models"][1]["added"] == ["drift"] and t["models"][1]["diagnosis_index"] == 3
    assert t["models"][3]["removed"] == ["glitch:t0=30000"] and t["models"][3]["effects"] == drift
    assert t["gaps"] == [
        {"from_index": 2, "to_index": 3, "segments": 2, "t_start": 2 * HOUR, "t_stop": 4 * HOUR},
        {"from_index": 7, "to_index": 7, "segments": 1, "t_start": 7 * HOUR, "t_stop": 8 * HOUR},
    ]
    outliers, gated = t["excluded"]
    assert (outliers["kind"], outliers["from_index"], outliers["to_index"], outliers["count"]) == ("outlier", 1, 2, 2)
    assert outliers["z_max"] == 11.0 and (outliers["t_start"], outliers["t_stop"]) == (3600.0, 7200.0)
    assert (gated["kind"], gated["gate"], gated["count"]) == ("gated", [9e3, 1e4], 1)


def test_a_run_started_with_a_change_before_its_first_fit(tmp_path):
    drift = ["linear-ttl", "drift"]
    rec = fitter_file(
        tmp_path / "fitter.mcap",
        {},
        events=[model_event(0, drift, ["linear-ttl"], "control")],
    )
    t = model_timeline([rec], None)
    assert [(s["from_index"], s["to_index"], s["by"]) for s in t["models"]] == [(0, None, "control")]
    assert t["gaps"] == [] and t["excluded"] == []
