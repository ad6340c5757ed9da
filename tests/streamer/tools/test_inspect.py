"""``ttl inspect`` and ``ttl view`` (streamer.tools.inspect) on recordings of a run.

Most recordings are written with :class:`streamer.recording.recorder.Recorder` exactly as the stage
base writes them (metadata record, ``events``, input and output segments, ``<topic>/summary``,
``errors``, the monitor's ``alerts``), including a stage killed mid-write and restarted;
one test kills and restarts a real stage process (the monitor).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from streamer_testutil import ROOT, wait_for

from streamer.bus.codec import encode
from streamer.recording.recorder import Recorder, read_recording
from streamer.tools.cli import main as ttl_main
from streamer.tools.inspect import InspectError, format_report, inspect_run, view_command
from ttlcore.conventions import COEFFICIENT_NAMES

RUN = "r1"
TOTAL = 6
HOUR = 3600.0


class StageFile:
    """A recording in the stage base's layout."""

    def __init__(self, run_dir: Path, stage: str, filename: str | None = None):
        self.stage = stage
        self.rec = Recorder(
            run_dir / (filename or f"{stage}.mcap"),
            metadata={"run": RUN, "stage": stage, "class": stage.title(), "config": "{}"},
        )
        self.event("start", message="inputs [...]")

    def event(self, kind, index=None, message="", **details):
        self.rec.write_json(
            "events",
            {
                "run": RUN,
                "stage": self.stage,
                "kind": kind,
                "index": index,
                "message": message,
                "time": time.time(),
                "details": details,
            },
        )

    def error(self, kind, index, message, field=None):
        self.rec.write_json(
            "errors",
            {
                "run": RUN,
                "stage": self.stage,
                "kind": kind,
                "index": index,
                "key": f"ttl/{RUN}/x/{index}",
                "field": field,
                "message": message,
                "time": time.time(),
                "details": {},
            },
        )

    def segment(self, topic, index, arrays, producer=None, **meta):
        payload, attachment = encode(
            arrays,
            {
                "run": RUN,
                "index": index,
                "t0": index * HOUR,
                "fs": 4.0,
                "producer": producer or self.stage,
                "meta": {"segments_total": TOTAL, **meta},
            },
        )
        self.rec.write_segment(topic, json.loads(attachment), payload)
        return payload

    def close(self, stop=True):
        if stop:
            self.event("stop")
        self.rec.close()


def fit_values(i):
    c = np.linspace(-1e-3, 1e-3, 24) + 2e-5 * i  # every coefficient drifts by 0.02 mm/rad per fit
    return c, np.full(24, 1e-5)


def write_fit(f: StageFile, i):
    c, s = fit_values(i)
    f.segment("tdi", i, {"data": np.zeros((3, 8))}, producer="tdi_builder")
    f.segment(
        "fit",
        i,
        {"coefficients": c, "sigma": s, "covariance": np.diag(s**2)},
        t_start=(i - 23) * HOUR,
        t_stop=(i + 1) * HOUR,
        names=list(COEFFICIENT_NAMES),
    )
    f.rec.write_json(
        "fit/summary",
        {
            "run": RUN,
            "index": i,
            "names": list(COEFFICIENT_NAMES),
            "coefficients": c,
            "sigma": s,
            "chi2": 10.0,
            "dof": 10.0,
            "chi2_dof": 1.0,
            "t_start": (i - 23) * HOUR,
            "t_end": (i + 1) * HOUR,
            "fit": {"converged": True},
        },
        schema="ttl.Fit",
    )


@pytest.fixture
def run_dir(tmp_path):
    d = tmp_path / "recordings" / RUN
    d.mkdir(parents=True)
    tel = {"eta": np.zeros((6, 8)), "ltt": np.full((6, 8), 8.3)}

    f = StageFile(d, "replayer")
    for i in range(TOTAL):
        f.segment("telemetry", i, tel)
    f.event("complete", index=TOTAL - 1)
    f.close()

    f = StageFile(d, "tdi_builder")
    for i in range(TOTAL):
        f.segment("telemetry", i, tel, producer="replayer")
        if i == 3:
            f.error("rejected", 3, "shape (5, 8) does not match (6, None)", field="arrays[eta].shape")
        f.segment("tdi", i, {"data": np.zeros((3, 8))})
    f.event("duplicate", index=2, message="already processed")
    f.close()

    # the fitter, killed while writing fit 3 (its chunk cut off in the middle), then restarted
    f = StageFile(d, "fitter", "fitter.1.mcap")
    for i in range(3):
        write_fit(f, i)
    before = f.rec.path.stat().st_size
    f.segment("fit", 3, {"coefficients": np.zeros(24), "sigma": np.ones(24)})
    size = f.rec.path.stat().st_size
    os.truncate(f.rec.path, before + (size - before) // 2)
    f.rec._file.close()  # the process dies: no summary, no footer
    f = StageFile(d, "fitter")
    for i in range(TOTAL):
        write_fit(f, i)
    f.rec.write_json(
        "warnings",
        {
            "run": RUN,
            "stage": "fitter",
            "kind": "not-converged",
            "index": 5,
            "message": "fit 5 did not converge in 8 iterations",
            "time": 1.0,
        },
    )
    f.event("complete", index=TOTAL - 1)
    f.close()

    f = StageFile(d, "subtractor")
    for i in range(TOTAL):
        f.segment("tdi", i, {"data": np.zeros((3, 8))}, producer="tdi_builder")
        if i == 4:
            f.error("failed", 4, "RuntimeError: no fit covers segment 4")
            continue
        f.segment("residual", i, {"residual": np.zeros((3, 8)), "ttl_model": np.zeros((3, 8))})
    f.close()

    f = StageFile(d, "monitor")
    for i in range(TOTAL):
        f.segment("monitor", i, {"drift_rate": np.zeros(24), "drift_significance": np.zeros(24)})
    f.rec.write_json(
        "alerts",
        {
            "run": RUN,
            "kind": "step",
            "coefficient": "23.phi.tx",
            "t": 7200.0,
            "value": 0.3,
            "significance": 7.1,
            "message": "step of +0.300 mm/rad in 23.phi.tx at 0.083 d",
            "t_detected": 10800.0,
            "index": 2,
            "units": "mm/rad",
            "details": {},
        },
    )
    f.close()
    (d / "monitor.rrd").write_bytes(b"")
    # the router's refusals (streamer.bus.security.refusals): 7 forbidden publications, 2 peers
    # without a valid certificate, and a line cut off
    refusals = [
        {
            "kind": "forbidden",
            "subject": "subtractor",
            "action": "Put",
            "key": f"ttl/{RUN}/fit/{i}",
            "time": f"2025-01-01T00:00:0{i}Z",
        }
        for i in range(7)
    ]
    refusals[2:2] = [
        {
            "kind": "unauthenticated",
            "message": "invalid peer certificate: UnknownIssuer",
            "time": "2025-01-01T00:00:10Z",
        }
    ] * 2
    (d / "security.jsonl").write_text("".join(json.dumps(r) + "\n" for r in refusals) + '{"kind": "forb')
    return d


def run_ttl(capsys, *args) -> tuple[int, str, str]:
    code = ttl_main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_inspect_json_report(run_dir, capsys):
    code, out, err = run_ttl(capsys, "inspect", run_dir, "--json", "-")
    assert code == 0, err
    r = json.loads(out)
    assert r["run"] == RUN and r["segments_total"] == TOTAL and r["stages_missing"] == []
    st = r["stages"]
    assert list(st) == ["replayer", "tdi_builder", "fitter", "subtractor", "monitor"]
    assert st["replayer"]["outputs"]["telemetry"]["distinct"] == TOTAL
    assert st["tdi_builder"]["inputs"]["telemetry"]["distinct"] == TOTAL
    assert st["tdi_builder"]["outputs"]["tdi"] == {
        "count": TOTAL,
        "distinct": TOTAL,
        "indices": [[0, TOTAL - 1]],
        "duplicates": [],
        "missing": [],
    }
    fit = st["fitter"]["outputs"]["fit"]
    assert fit["distinct"] == TOTAL and fit["duplicates"] == [0, 1, 2] and fit["missing"] == []
    assert st["fitter"]["restarts"] == 1
    assert [f["file"] for f in st["fitter"]["files"]] == ["fitter.1.mcap", "fitter.mcap"]
    assert [f["complete"] for f in st["fitter"]["files"]] == [False, True]
    assert st["fitter"]["inputs"]["tdi"]["distinct"] == TOTAL
    assert st["subtractor"]["outputs"]["residual"]["missing"] == [[4, 4]]
    assert st["monitor"]["outputs"]["monitor"]["distinct"] == TOTAL
    # errors of all stages
    assert sorted((e["stage"], e["kind"], e["index"]) for e in r["errors"]) == [
        ("subtractor", "failed", 4),
        ("tdi_builder", "rejected", 3),
    ]
    assert st["tdi_builder"]["errors"] == 1
    # alerts of the monitor
    assert [(a["kind"], a["coefficient"]) for a in r["alerts"]] == [("step", "23.phi.tx")]
    # warnings of every stage (a fit that did not converge)
    assert [(w["stage"], w["kind"], w["index"]) for w in r["warnings"]] == [("fitter", "not-converged", 5)]
    # interruptions: the killed fitter, its restart, the fit cut off while written
    kinds = sorted((i["stage"], i["kind"]) for i in r["interruptions"])
    # (a chunk is whole or lost: the cut-off fit 3 leaves no half-written segment behind)
    assert kinds == [("fitter", "restart"), ("fitter", "unfinished")]
    # coefficient trends from the fit JSON: the restarted fitter's fits win, in mm/rad
    f = r["fits"]
    assert f["count"] == TOTAL and f["indices"] == [[0, TOTAL - 1]] and f["names"] == list(COEFFICIENT_NAMES)
    c_last, s_last = fit_values(TOTAL - 1)
    t = f["trends"]["12.phi.rx"]
    assert t["latest"] == pytest.approx(c_last[0] * 1e3) and t["sigma"] == pytest.approx(0.01)
    assert t["first"] == pytest.approx(fit_values(0)[0][0] * 1e3)
    assert t["rate"] == pytest.approx(0.02 * 24, rel=1e-6)  # 0.02 mm/rad per hourly fit
    assert t["rate_se"] > 0 and t["significance"] > 5
    # the router's refusals: counted per kind, the first few kept
    sec = r["security"]
    assert sec["present"] and sec["count"] == 9 and sec["unreadable"] == [10]
    assert {k: v["count"] for k, v in sec["kinds"].items()} == {"forbidden": 7, "unauthenticated": 2}
    assert [x["key"] for x in sec["kinds"]["forbidden"]["first"]] == [f"ttl/{RUN}/fit/{i}" for i in range(5)]
    assert len(sec["kinds"]["unauthenticated"]["first"]) == 2
    (run_dir / "security.jsonl").unlink()  # a run with --insecure has none
    code, out, err = run_ttl(capsys, "inspect", run_dir, "--json", "-")
    assert json.loads(out)["security"] == {
        "file": str(run_dir / "security.jsonl"),
        "present": False,
        "count": 0,
        "kinds": {},
        "unreadable": [],
    }


def test_inspect_text_report(run_dir, capsys):
    code, out, err = run_ttl(capsys, "inspect", run_dir)
    assert code == 0, err
    assert f"run {RUN}" in out and f"{TOTAL} segments expected" in out
    assert "fitter       2 file(s)" in out and "restarted 1x" in out
    assert "fit 6 [0-5] dup 0-2" in out
    assert "residual 5 [0-3,5] missing 4" in out
    assert "Errors: 2" in out and "tdi_builder rejected segment 3 field 'arrays[eta].shape'" in out
    assert "subtractor failed segment 4: RuntimeError: no fit covers segment 4" in out
    assert "Alerts (monitor): 1" in out and "step of +0.300 mm/rad in 23.phi.tx" in out
    assert "Warnings: 1" in out and "fitter [not-converged] fit 5 did not converge" in out
    assert "fitter: unfinished: fitter.1.mcap was not closed" in out
    assert "fitter: restart: fitter ran 2 times" in out
    assert "Coefficient trends (fitter fit JSON: 6 fits [0-5]" in out
    assert "Security (security.jsonl): 9 refusal(s) by the router, forbidden x7, unauthenticated x2" in out
    assert f"  forbidden: subtractor may not Put on ttl/{RUN}/fit/4 at 2025-01-01T00:00:04Z" in out
    assert f"ttl/{RUN}/fit/5" not in out and "  forbidden: ... 2 more" in out
    assert "  unauthenticated: invalid peer certificate: UnknownIssuer at 2025-01-01T00:00:10Z" in out
    assert "  unreadable line(s) 10" in out
    row = next(line for line in out.splitlines() if line.strip().startswith("21.eta.tx"))
    assert "± 0.0100" in row and "+0.4800 ±" in row and row.rstrip().endswith("*")


def test_inspect_errors_name_the_directory(tmp_path, capsys):
    code, out, err = run_ttl(capsys, "inspect", tmp_path / "nope")
    assert code == 2 and err.strip() == f"ttl inspect: error: {tmp_path / 'nope'}: no such run directory"
    code, out, err = run_ttl(capsys, "inspect", tmp_path)
    assert code == 2 and f"{tmp_path}: no MCAP recordings" in err and len(err.strip().splitlines()) == 1
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "fitter.mcap").write_bytes(b"not an mcap file")
    r = inspect_run(bad)  # an unreadable file is reported, not fatal
    assert r["stages"]["fitter"]["files"][0]["readable"] is False
    assert [i["kind"] for i in r["interruptions"]] == ["unreadable"]
    assert "fitter.mcap: not an MCAP file" in format_report(r)
    code, out, err = run_ttl(capsys, "inspect", bad)  # the report, and a status that says it
    assert code == 1 and "fitter.mcap: not an MCAP file" in out
    assert err.strip() == "ttl inspect: not readable as MCAP: fitter.mcap (exit status 1)"


def test_inspect_salvages_a_damaged_closed_file(run_dir, tmp_path, capsys):
    """A closed stage recording with flipped bytes in one chunk: ``ttl inspect`` reads past
    the damage (no ZstdError traceback), exits 0 and says what it salvaged and skipped."""
    import shutil

    from mcap.reader import make_reader

    damaged = tmp_path / "damaged"
    shutil.copytree(run_dir, damaged)
    path = damaged / "tdi_builder.mcap"
    with open(path, "rb") as f:
        chunks = [c for c in make_reader(f).get_summary().chunk_indexes if c.compressed_size > 500]
    data = bytearray(path.read_bytes())
    target = chunks[len(chunks) // 2]
    for k in range(50):  # inside the compressed records (the chunk's fixed fields take ~60 bytes)
        data[target.chunk_start_offset + 100 + 5 * k] ^= 0x55
    path.write_bytes(bytes(data))
    code, out, err = run_ttl(capsys, "inspect", damaged)
    assert code == 0 and "Traceback" not in out + err, (out, err)
    assert "tdi_builder: damaged: tdi_builder.mcap is damaged: salvaged" in out
    assert "1 corrupt stretch(es) skipped" in out, out


def test_view_prints_a_loopback_only_command(run_dir, tmp_path, capsys):
    code, out, err = run_ttl(capsys, "view", run_dir, "--print")
    assert code == 0, err
    assert "--bind 127.0.0.1" in out and out.strip().endswith(str(run_dir / "monitor.rrd"))
    assert "--serve-web" not in out and "--web-viewer" not in out
    cmd = view_command(run_dir / "monitor.rrd", binary="rerun")
    assert cmd == ["rerun", "--bind", "127.0.0.1", "--new", str(run_dir / "monitor.rrd")]
    code, out, err = run_ttl(capsys, "view", tmp_path)
    assert code == 2 and f"{tmp_path}: no monitor.rrd" in err
    with pytest.raises(InspectError, match="no such run directory"):
        view_command(tmp_path / "nope")


def test_inspect_a_killed_and_restarted_stage_process(tmp_path):
    """A real stage (the monitor, alone on its loopback session): SIGKILL, restart, SIGTERM."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    rec_dir = tmp_path / "rec"
    cmd = [sys.executable, "-m", "stages.monitor", "--run", "r2", "--recordings", str(rec_dir)]
    procs = []
    try:
        for sig in (signal.SIGKILL, signal.SIGTERM):
            log = open(tmp_path / f"monitor-{len(procs)}.log", "wb")
            procs.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=tmp_path))
            log.close()
            path = rec_dir / "r2" / "monitor.mcap"

            def started(path=path):
                if len(procs) == 2 and not path.with_name("monitor.1.mcap").exists():
                    return False  # the killed process's file is still the current one
                try:
                    return any(e["kind"] == "start" for e in read_recording(path).json("events"))
                except Exception:
                    return False

            wait_for(started, 60, "the monitor's start event")
            procs[-1].send_signal(sig)
            procs[-1].wait(30)
        assert procs[-1].returncode == 0, (tmp_path / "monitor-1.log").read_text()
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(10)
    out = subprocess.run(
        [sys.executable, "-m", "streamer.tools.cli", "inspect", str(rec_dir / "r2"), "--json", "-"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout)
    files = r["stages"]["monitor"]["files"]
    assert [(f["file"], f["complete"], f["stopped"]) for f in files] == [
        ("monitor.1.mcap", False, False),
        ("monitor.mcap", True, True),
    ]
    assert sorted(i["kind"] for i in r["interruptions"]) == ["restart", "unfinished"]
    assert set(r["stages_missing"]) == {"replayer", "tdi_builder", "fitter", "subtractor"}
    assert (rec_dir / "r2" / "monitor.rrd").exists() and (rec_dir / "r2" / "monitor.1.rrd").exists()


WITNESS = "witness:source=12.eta,link=23,delay=2"
GLITCH = "glitch:t=7h,tm=12,beta=100s"
#: (first segment, model, by, event details beyond them) of the run below
MODELS = [
    (0, ["linear-ttl"], None, {}),
    (
        4,
        ["linear-ttl", WITNESS],
        "adopt auto",
        {
            "diagnosis_index": 3,
            "reason": "explains 100 % of the excess, log Bayes factor 3.3e+05",
            "recommendation": {"spec": WITNESS, "explains": True, "explained_fraction": 1.0, "log_bayes_factor": 3.3e5},
        },
    ),
    (7, ["linear-ttl", WITNESS, GLITCH], "adopt auto", {"diagnosis_index": 6, "reason": "explains 80 %"}),
    (10, ["linear-ttl", WITNESS], "window", {"removed": [GLITCH]}),
    (11, ["linear-ttl", WITNESS, "drift"], "control", {}),
]
N_TIMELINE = 13


def model_of(i):
    return next(m for start, m, _, _ in reversed(MODELS) if i >= start)


def _record_model_timeline(d) -> None:
    """The fitter's and the monitor's recordings of a run in ``d`` whose model changes four
    times (:data:`MODELS`), with a gap at segment 8, fits 2-3 left out as outliers, fit 9
    gated, and a step alert in model epoch 2."""
    (d / "plan.json").write_text(json.dumps({"segments_total": N_TIMELINE, "fs": 4.0, "t0": 0.0, "samples": 14400}))
    f = StageFile(d, "fitter")
    changes = {start: (m, by, extra) for start, m, by, extra in MODELS[1:]}
    for i in range(N_TIMELINE):
        if i in changes:  # recorded when the change is made: before the segment it applies from
            m, by, extra = changes[i]
            f.event(
                "model",
                index=i,
                message=f"model {','.join(m)} from segment {i} on",
                effects=m,
                before=model_of(i - 1),
                from_index=i,
                by=by,
                **extra,
            )
        if i == 8:
            f.event("gap", index=8, message="tdi segment 8 missing: 14400 NaN samples pushed, window kept")
            continue
        write_fit(f, i)
        f.rec.write_json(
            "fit/summary",
            {
                "run": RUN,
                "index": i,
                "names": list(COEFFICIENT_NAMES),
                "coefficients": fit_values(i)[0],
                "sigma": fit_values(i)[1],
                "t_start": (i - 23) * HOUR,
                "t_end": (i + 1) * HOUR,
                "model": model_of(i),
                "fit": {"converged": True},
            },
            schema="ttl.Fit",
        )
    for i, z in ((2, 300.0), (3, 120.0)):
        f.rec.write_json(
            "warnings",
            {
                "run": RUN,
                "stage": "fitter",
                "kind": "segment-excluded",
                "index": i,
                "message": f"fit {i}: left out",
                "time": 1.0,
                "details": {"t_start": i * HOUR, "t_stop": (i + 1) * HOUR, "chi2_dof": 9.0, "z": z, "reference": 1.0},
            },
        )
    f.event(
        "segment-gated",
        index=9,
        message="fit 9: gated",
        t_start=9 * HOUR,
        t_stop=10 * HOUR,
        gate=[9 * HOUR, 9.5 * HOUR],
    )
    f.close()
    f = StageFile(d, "monitor")
    f.rec.write_json(
        "alerts",
        {
            "run": RUN,
            "kind": "step",
            "coefficient": "23.phi.tx",
            "t": 12 * HOUR,
            "value": 0.3,
            "significance": 7.0,
            "message": "step of +0.300 mm/rad in 23.phi.tx at 0.500 d",
            "details": {"model_epoch": 2},
        },
    )
    f.close()


def test_inspect_prints_the_model_timeline(tmp_path, capsys):
    """The fitter's model from which segment to which and why (``model`` events: adopt auto
    with its reason and recommendation, a transient taken out by ``window``, a control
    message), its gaps and the FFT segments it left out (outliers, gated), in the text and
    the JSON; a new coupling is a new model epoch of the monitor's trends, a transient is not."""
    d = tmp_path / "recordings" / RUN
    d.mkdir(parents=True)
    _record_model_timeline(d)

    code, out, err = run_ttl(capsys, "inspect", d, "--json", "-")
    assert code == 0, err
    t = json.loads(out)["timeline"]
    spans = [(s["from_index"], s["to_index"], s["effects"], s["by"], s["new_epoch"], s["fits"]) for s in t["models"]]
    assert spans == [
        (0, 3, ["linear-ttl"], "configured", False, 4),
        (4, 6, ["linear-ttl", WITNESS], "adopt auto", True, 3),
        (7, 9, ["linear-ttl", WITNESS, GLITCH], "adopt auto", False, 2),
        (10, 10, ["linear-ttl", WITNESS], "window", False, 1),
        (11, 12, ["linear-ttl", WITNESS, "drift"], "control", True, 2),
    ], spans
    adopted = t["models"][1]
    assert adopted["added"] == [WITNESS] and adopted["removed"] == [] and adopted["diagnosis_index"] == 3
    assert adopted["recommendation"]["log_bayes_factor"] == 3.3e5 and "explains 100 %" in adopted["reason"]
    assert t["models"][3]["removed"] == [GLITCH] and t["models"][3]["added"] == []
    assert t["gaps"] == [{"from_index": 8, "to_index": 8, "segments": 1, "t_start": 8 * HOUR, "t_stop": 9 * HOUR}]
    assert t["excluded"] == [
        {
            "kind": "outlier",
            "from_index": 2,
            "to_index": 3,
            "t_start": 2 * HOUR,
            "t_stop": 4 * HOUR,
            "count": 2,
            "z_max": 300.0,
        },
        {
            "kind": "gated",
            "from_index": 9,
            "to_index": 9,
            "t_start": 9 * HOUR,
            "t_stop": 10 * HOUR,
            "count": 1,
            "gate": [9 * HOUR, 9.5 * HOUR],
        },
    ]

    code, out, err = run_ttl(capsys, "inspect", d)
    assert code == 0, err
    lines = [line.strip() for line in out.splitlines()]
    expected = [
        "Timeline: the model from segment to segment (new couplings from segment(s) 4, 11: the monitor's trends "
        "start a new series there)",
        "segments 0-3     linear-ttl  (4 fits)",
        "as configured",
        f"segments 4-6     linear-ttl,{WITNESS}  (3 fits)",
        f"+ {WITNESS} by adopt auto after the diagnosis of segment 3: explains 100 % of the excess, log Bayes "
        "factor 3.3e+05  [new model epoch]",
        f"recommended {WITNESS}, explains 100 % of the excess, log Bayes factor 3.3e+05",
        f"segments 7-9     linear-ttl,{WITNESS},{GLITCH}  (2 fits)",
        f"+ {GLITCH} by adopt auto after the diagnosis of segment 6: explains 80 %",
        f"segment 10       linear-ttl,{WITNESS}  (1 fit)",
        f"- {GLITCH} by window (it left the one-day window)",
        f"segments 11-12   linear-ttl,{WITNESS},drift  (2 fits)",
        "+ drift by control  [new model epoch]",
        "Gaps (no TDI segment: NaN pushed, window kept): segment 8 (0.333-0.375 d)",
        "Left out of the fit: fits 2-3, 2 FFT segment(s) (0.083-0.167 d): outliers, up to 300 sigma above the window",
        "Left out of the fit: fit 9, 1 FFT segment(s) (0.375-0.417 d): gated by the gate 0.375-0.396 d",
    ]
    start = lines.index(expected[0])
    assert lines[start : start + len(expected)] == expected, "\n".join(lines[start : start + len(expected)])
    assert "[step] step of +0.300 mm/rad in 23.phi.tx at 0.500 d (model epoch 2)" in lines


# ---------------------------------------------------------------------------- live or ended: the command printed

#: what the fitter recorded of its diagnosis of segments 0..3 (stages.fitter.live_diagnosis), with
#: the ttl control command of that moment: a router that is gone since
RECORDED_COMMAND = (
    "ttl control --run r1 --connect tls/127.0.0.1:1 --credentials /nowhere/credentials fitter model "
    '\'{"effects": ["linear-ttl", "drift"]}\''
)


def diagnosed_run(tmp_path) -> Path:
    d = tmp_path / "recordings" / RUN
    d.mkdir(parents=True)
    f = StageFile(d, "fitter")
    for i in range(4):
        write_fit(f, i)
    f.rec.write_json(
        "fit/summary",
        {
            "run": RUN,
            "index": 3,
            "names": list(COEFFICIENT_NAMES),
            "coefficients": fit_values(3)[0],
            "sigma": fit_values(3)[1],
            "model": ["linear-ttl", "step:t_step=1h;mosas=12"],
            "fit": {"converged": True},
            "diagnosis": {
                "segments": [0, 3],
                "model": ["linear-ttl", "step:t_step=1h;mosas=12"],
                "chi2_dof": 3.0,
                "fails": True,
                "bands": [{"f_lo": 0.003, "f_hi": 0.01, "chi2_dof": 3.0, "fails": True}],
                "recommendation": {
                    "spec": "drift",
                    "explains": True,
                    "effects": ["linear-ttl", "step:t_step=1h;mosas=12", "drift"],
                    "command": RECORDED_COMMAND,
                },
                "adoption": {"mode": "ask", "adopted": False, "reason": "ask"},
                "removal": [{"spec": "step:t_step=1h;mosas=12", "p": 0.4, "command": RECORDED_COMMAND}],
            },
        },
        schema="ttl.Fit",
    )
    f.close()
    return d


def journal(d: Path, *records) -> None:
    (d / "launcher.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))


def test_inspect_of_an_ended_run_prints_the_offline_refit_not_ttl_control(tmp_path, capsys):
    """Issue 35: the diagnosis' ``ttl control`` names a router that stopped with the run;
    pasted after the run it could only fail.  An ended run (``end`` in the journal, or a
    launcher that is gone) gets the offline ``ttl refit`` of the window diagnosed instead."""
    d = diagnosed_run(tmp_path)
    start = {"time": time.time() - 60, "launcher_pid": os.getpid(), "kind": "start", "router": "tls/127.0.0.1:1"}
    refit = f"ttl refit {d} --effects 'linear-ttl,step:t_step=1h;mosas=12,drift' --baseline 'linear-ttl,step:t_step=1h;mosas=12' --segments 0:3"
    removal = f"ttl refit {d} --effects linear-ttl --baseline 'linear-ttl,step:t_step=1h;mosas=12' --segments 0:3"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    for records, why in (
        ([start, {"time": time.time(), "kind": "end", "status": 0}], "ttl run ended (exit status 0)"),
        ([{**start, "launcher_pid": dead.pid, "time": time.time()}], f"ttl run (pid {dead.pid}) is gone"),
    ):
        journal(d, *records)
        code, out, err = run_ttl(capsys, "inspect", d)
        assert code == 0, err
        assert "ttl control --" not in out, out  # no command to paste (the header may name it)
        assert f"    refit with it offline: {refit}" in out.splitlines(), out
        assert f"refit without it offline: {removal}" in out, out
        assert f"the run is not live here ({why}" in out, out
        r = inspect_run(d)
        assert r["model"]["run_state"]["live"] is False and r["model"]["diagnoses"][0]["advice"] == refit


def test_inspect_of_a_live_run_prints_ttl_control_with_the_live_router(tmp_path, capsys):
    """A live run (its launcher alive, its router answering at the address of the journal's
    last start, which a --resume may have changed) gets ``ttl control`` with that address and
    the run's credentials; credentials missing here: the offline command, and why."""
    import socket as socket_

    d = diagnosed_run(tmp_path)
    creds = tmp_path / "credentials"
    creds.mkdir()
    with socket_.socket() as router:
        router.bind(("127.0.0.1", 0))
        router.listen()
        live = f"tls/127.0.0.1:{router.getsockname()[1]}"
        start = {
            "time": time.time(),
            "launcher_pid": os.getpid(),
            "kind": "start",
            "host": socket_.gethostname(),
            "router": live,
            "credentials": str(creds),
        }
        journal(d, start)
        code, out, err = run_ttl(capsys, "inspect", d)
        assert code == 0 and f"credentials are not here ({creds}/control.pem)" in out, out
        assert "ttl control --" not in out, out
        (creds / "control.pem").write_text("")
        code, out, err = run_ttl(capsys, "inspect", d)
    assert code == 0, err
    command = (
        f"ttl control --run r1 --connect {live} --credentials {creds} fitter model "
        '\'{"effects": ["linear-ttl", "step:t_step=1h;mosas=12", "drift"]}\''
    )
    assert f"    apply it: {command}" in out.splitlines(), out
    assert "remove it: ttl control --run r1 --connect " + live in out and "ttl refit" not in out, out
    assert "tls/127.0.0.1:1 " not in out  # the recorded, dead address
    assert "the run is live (ttl run (pid" in out


def test_inspect_tests_the_last_fits_sigmas_against_the_truth(tmp_path, capsys):
    """``ttl inspect --truth``: the last fit's errors against the truth averaged over its
    window, and whether its sigmas are honest (errors' chi^2 with the fit's covariance,
    pull RMS with its range for that covariance's correlations).  The fits are written with
    errors of known size against a simulated file's truth: 1 sigma each (honest: chi^2 24
    for 24), 4 sigma each (sigmas too small: chi^2 384) and 0.3 sigma (too large: chi^2 2.2)."""
    from ttlcore.estimate.monitoring import FileTruth
    from ttlcore.estimate.pulls import pull_summary

    data = tmp_path / "sim.h5"
    r = subprocess.run(
        [sys.executable, "-m", "ttlcore.cli.main", "simulate", "--duration", "1h", "--telemetry", data, "--quiet"],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert r.returncode == 0, r.stderr
    truth_file = data.with_name("sim.truth.h5")
    t_start, t_stop = 0.0, 3000.0
    true = FileTruth(truth_file).mean(t_start, t_stop)
    sigma = np.full(24, 2e-5)
    cov = np.diag(sigma**2)
    for pulls, verdict in ((1.0, "honest"), (4.0, "too small"), (0.3, "too large")):
        run_dir = tmp_path / f"rec{pulls}" / RUN
        run_dir.mkdir(parents=True)
        c = true + pulls * sigma * np.where(np.arange(24) % 2, 1, -1)
        f = StageFile(run_dir, "fitter")
        f.rec.write_json(
            "fit/summary",
            {
                "run": RUN,
                "index": 0,
                "names": list(COEFFICIENT_NAMES),
                "coefficients": c.tolist(),
                "sigma": sigma.tolist(),
                "covariance": cov.tolist(),
                "t_start": t_start,
                "t_end": t_stop,
                "fit": {"converged": True},
            },
            schema="ttl.Fit",
        )
        f.close()
        code, out, err = run_ttl(capsys, "inspect", run_dir, "--truth", truth_file, "--json", "-")
        assert code == 0, err
        t = json.loads(out)["fits"]["truth_test"]
        expected = pull_summary(c, cov, true).to_json()
        assert t == expected
        assert t["pull_rms"] == pytest.approx(pulls) and t["chi2"] == pytest.approx(24 * pulls**2)
        assert t["verdict"] == verdict
        code, out, err = run_ttl(capsys, "inspect", run_dir, "--truth", truth_file)
        line = next(x for x in out.splitlines() if "last fit against the truth" in x)
        assert f"pull RMS {pulls:.2f}" in line and line.endswith(f"sigmas {verdict}"), line
