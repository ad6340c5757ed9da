"""Tests of ``ttl reprocess`` (streamer.tools.reprocess, ttlcore.app.reprocessing) on real Dask clusters.

Days are one hour long (14 400 samples at 4 Hz, fits on 15-min segments) so the suite stays
quick; the per-day job is the same code whatever the length.

- the command on a LocalCluster of two worker processes: every day's ``fit.json`` equals
  the one ``ttl analyze`` writes when run alone on that file (coefficients, sigmas, chi^2 to
  1e-12 relative: the same code on the same input; the workers run BLAS single-threaded,
  which may change the last bits of a sum, hence not bit equality), the diagnosis report is
  written in the diagnosis band (the fit's in the fit band), a day whose fit fails (all NaN)
  is reported as failed in one line (never dropped) and not retried, exit status 1;
- the retries: only a transient error (OSError) is run again, an error of the data is not;
- a separately started ``dask scheduler`` with two ``dask worker`` processes: one worker is
  killed with SIGKILL while it processes a day, and every day is still reported (the
  scheduler reschedules the lost task on the surviving worker);
- the days of a recorded run: telemetry segments written to a real MCAP file by the
  recorder, read back and reassembled into day files equal to the source samples.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from ttlcore.conventions import COEFFICIENT_NAMES, LINKS

HOUR = 3600.0
SEGMENT = "15min"
BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def days(tmp_path_factory) -> list[Path]:
    """Three consecutive one-hour days, cut from one 3-h simulation (its noise is made in
    fixed blocks, so 3 h cost what 1 h does).  Laser noise off: TDI removes it anyway."""
    from ttlcore.io.telemetry import write_telemetry
    from ttlcore.sim.simulator import NoiseSwitches, SimulationConfig, simulate

    d = tmp_path_factory.mktemp("days")
    tm, _ = simulate(SimulationConfig(duration=3 * HOUR, seed=10, noises=NoiseSwitches.parse("all,-laser")))
    n = int(HOUR * tm.fs)
    return [write_telemetry(d / f"day{i}.h5", tm.slice(i * n, (i + 1) * n)) for i in range(3)]


def _ttl(*args, timeout=300):
    return subprocess.run([str(BIN / "ttl"), *map(str, args)], capture_output=True, text=True, timeout=timeout)


def test_reprocess_equals_analyze_and_reports_a_failed_day(days, tmp_path, capsys):
    from streamer.tools.cli import main
    from ttlcore.app.analysis import analyze
    from ttlcore.estimate.fit import FitSettings
    from ttlcore.io.telemetry import Telemetry, write_telemetry

    nan = np.full((6, int(4 * HOUR)), np.nan)  # telemetry whose fit fails: no valid segment
    bad = write_telemetry(
        tmp_path / "broken.h5", Telemetry(t0=0.0, fs=4.0, eta=nan, dws_phi=nan, dws_eta=nan, ltt=np.full_like(nan, 8.3))
    )
    out = tmp_path / "out"
    rc = main(
        [
            "reprocess",
            *map(str, days),
            str(bad),
            "--out",
            str(out),
            "--workers",
            "2",
            "--memory-limit",
            "2GiB",
            "--segment",
            SEGMENT,
            "--no-figures",
            "--no-witnesses",
            "--candidates",
            "drift",
            "--retries",
            "1",
        ]
    )
    assert rc == 1  # one day failed
    err = capsys.readouterr().err
    assert "ttl reprocess: 100%" in err and "\r" not in err  # progress as plain lines: not a terminal
    failed_lines = [line for line in err.splitlines() if "broken" in line]
    assert len(failed_lines) == 1 and failed_lines[0].startswith("ttl reprocess: day broken failed: "), err
    assert "Traceback" not in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_days"] == 4 and summary["n_ok"] == 3 and summary["failed"] == ["broken"]
    assert summary["settings"]["bands_hz"] == {"fit": [0.003, 0.9], "diagnosis": [0.003, 0.8]}
    failed = [r for r in summary["days"] if r["status"] == "failed"]
    # an error of the data fails the same way every time: not retried (--retries 1 notwithstanding)
    assert len(failed) == 1 and "broken.h5" in failed[0]["error"] and failed[0]["retries"] == 0
    assert "fit failed" in failed[0]["error"] and "Traceback" in failed[0]["traceback"]
    rows = {r["day"]: r for r in summary["days"] if r["status"] == "ok"}
    assert [r["day"] for r in summary["days"][:3]] == ["day0", "day1", "day2"]  # time order
    md = (out / "summary.md").read_text()
    assert "| broken | FAILED |" in md and "| day1 | ok |" in md
    for p in days:
        alone = analyze(
            p, out_dir=tmp_path / "alone" / p.stem, figures=False, settings=FitSettings(segment_duration=15 * 60.0)
        )["fit_json"]
        mine = json.loads((out / p.stem / "fit.json").read_text())
        for key in ("coefficients", "sigma"):
            a = np.array([alone[key][n] for n in COEFFICIENT_NAMES])
            b = np.array([mine[key][n] for n in COEFFICIENT_NAMES])
            np.testing.assert_allclose(b, a, rtol=1e-12, atol=0)
        assert mine["chi2"] == pytest.approx(alone["chi2"], rel=1e-12)
        assert mine["window"] == alone["window"]
        row = rows[p.stem]
        np.testing.assert_allclose(
            [row["coefficients"][n] for n in COEFFICIENT_NAMES],
            [alone["coefficients"][n] for n in COEFFICIENT_NAMES],
            rtol=1e-12,
            atol=0,
        )
        diag = json.loads((out / p.stem / "diagnosis.json").read_text())
        assert diag["file"] == str(p)
        # each in its own band: the fit in ttl analyze's, the diagnosis in ttl diagnose's
        assert mine["band"] == [0.003, 0.9] and diag["adequacy"]["band"] == [0.003, 0.8]
        assert row["diagnosis"]["chi2_dof"] == diag["adequacy"]["chi2_dof"]
        # one hour of the paper's noise and TTL: the linear model is adequate
        assert 0.8 < row["diagnosis"]["chi2_dof"] < 1.2
    assert not list(out.rglob("*.tmp*"))  # atomic writes leave no temporaries


def test_only_transient_errors_are_retried(monkeypatch, tmp_path):
    """A day failing with an OSError (a shared file system that hiccups) is run again, up to
    ``retries`` times; one failing with an error of the data (TTLError) is run once.  On an
    in-process cluster, whose workers see the patched day job."""
    from distributed import Client

    from ttlcore.app import reprocessing
    from ttlcore.errors import TTLError

    runs: dict[str, int] = {}

    def fake_day(job):
        runs[job.name] = runs.get(job.name, 0) + 1
        if job.name == "flaky" and runs[job.name] == 1:
            raise OSError("stale file handle")
        if job.name == "down":
            raise OSError("no route to the file server")
        if job.name == "bad":
            raise TTLError(f"{job.data}: not a day")
        t0 = {"flaky": 0.0, "bad": HOUR, "down": 2 * HOUR}[job.name]
        return {
            "day": job.name,
            "status": "ok",
            "t_start": t0,
            "t_stop": t0 + HOUR,
            "coefficients": dict.fromkeys(COEFFICIENT_NAMES, 0.0),
            "sigma": dict.fromkeys(COEFFICIENT_NAMES, 1e-4),
            "chi2_dof_fit": 1.0,
        }

    monkeypatch.setattr(reprocessing, "process_day", fake_day)
    jobs = [reprocessing.DayJob(name=n, data=f"{n}.h5", out_dir=str(tmp_path / n)) for n in ("flaky", "bad", "down")]
    with Client(processes=False, n_workers=1, threads_per_worker=1, dashboard_address=None) as client:
        summary = reprocessing.reprocess(jobs, tmp_path, client=client, retries=2)
    assert runs == {"flaky": 2, "bad": 1, "down": 3}
    rows = {r["day"]: r for r in summary["days"]}
    assert rows["flaky"]["status"] == "ok"
    assert rows["bad"]["error"] == "bad.h5: not a day" and rows["bad"]["retries"] == 0
    assert rows["down"]["error"] == "OSError: no route to the file server" and rows["down"]["retries"] == 2
    assert summary["failed"] == ["bad", "down"]


def _start(*cmd, log: Path):
    return subprocess.Popen(
        [str(c) for c in cmd], stdout=open(log, "wb"), stderr=subprocess.STDOUT, start_new_session=True
    )


def test_killed_worker_loses_no_day(days, tmp_path):
    """SIGKILL one of two ``dask worker`` processes while it runs a day: all days reported."""
    from distributed import Client

    sched_file = tmp_path / "scheduler.json"
    procs = [
        _start(
            BIN / "dask",
            "scheduler",
            "--host",
            "127.0.0.1",
            "--port",
            "0",
            "--no-dashboard",
            "--scheduler-file",
            sched_file,
            log=tmp_path / "scheduler.log",
        )
    ]
    try:
        deadline = time.monotonic() + 60
        while not sched_file.exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert sched_file.exists(), (tmp_path / "scheduler.log").read_text()
        for i in range(2):
            procs.append(
                _start(
                    BIN / "dask",
                    "worker",
                    "--scheduler-file",
                    sched_file,
                    "--nthreads",
                    "1",
                    "--no-nanny",
                    "--host",
                    "127.0.0.1",
                    "--memory-limit",
                    "2GiB",
                    "--no-dashboard",
                    log=tmp_path / f"worker{i}.log",
                )
            )
        with Client(scheduler_file=str(sched_file), timeout="30s") as client:
            client.wait_for_workers(2, timeout=90)
            pids = client.run(os.getpid)  # worker address -> pid
            out = tmp_path / "out"
            run = subprocess.Popen(
                [
                    str(BIN / "ttl"),
                    "reprocess",
                    *map(str, days),
                    "--out",
                    str(out),
                    "--scheduler",
                    str(sched_file),
                    "--segment",
                    SEGMENT,
                    "--no-diagnosis",
                    "--no-figures",
                    "--quiet",
                ],
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
            )
            killed = victim_day = None
            deadline = time.monotonic() + 240
            while killed is None and time.monotonic() < deadline and run.poll() is None:
                busy = {a: keys for a, keys in client.processing().items() if keys}
                if busy:
                    addr, keys = next(iter(busy.items()))
                    killed, victim_day = pids[addr], str(keys[0])
                    os.kill(killed, signal.SIGKILL)
                time.sleep(0.05)
            assert killed is not None, "no day was seen running"
            text = run.communicate(timeout=300)[0]
        assert run.returncode == 0, text
        summary = json.loads((out / "summary.json").read_text())
        assert [r["day"] for r in summary["days"]] == ["day0", "day1", "day2"]
        assert all(r["status"] == "ok" for r in summary["days"])
        # the day that was running on the killed worker was done again on the other one
        row = next(r for r in summary["days"] if victim_day.endswith(r["day"]))
        assert row["worker"]["pid"] != killed
        assert all((out / d / "fit.json").is_file() for d in ("day0", "day1", "day2"))
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


# ---------------------------------------------------------------------------- recordings


def test_days_from_recordings_equal_the_source(days, tmp_path):
    """Telemetry segments recorded as the replayer records them (real MCAP file), read back
    and cut into days of 1 h from 30-min segments: the day files hold the source samples."""
    from streamer.bus.codec import encode
    from streamer.recording.recorder import Recorder
    from streamer.tools.reprocess import recorded_days
    from ttlcore.errors import TTLError
    from ttlcore.io.reader import read_telemetry

    run_dir = tmp_path / "recordings" / "r1"
    run_dir.mkdir(parents=True)
    src = [read_telemetry(p) for p in days[:2]]
    n = 1800 * 4
    with Recorder(run_dir / "replayer.mcap", metadata={"run": "r1", "stage": "replayer"}) as rec:
        index = 0
        for tm in src:
            for j in range(0, tm.size, n):
                part = tm.slice(j, j + n)
                payload, att = encode(
                    {k: getattr(part, k) for k in ("eta", "dws_phi", "dws_eta", "ltt")},
                    {
                        "run": "r1",
                        "index": index,
                        "t0": part.t0,
                        "fs": part.fs,
                        "channels": list(LINKS),
                        "producer": "replayer",
                        "meta": {"source": str(days[0]), "dws_asd": 2.1e-10},
                    },
                )
                rec.write_segment("telemetry", json.loads(att), payload)
                index += 1
    paths = recorded_days(run_dir, tmp_path / "days", day_length=HOUR)
    assert [p.name for p in paths] == ["r1-day000.h5", "r1-day001.h5"]
    for p, tm in zip(paths, src):
        got = read_telemetry(p)
        assert got.t0 == tm.t0 and got.size == tm.size
        for k in ("eta", "dws_phi", "dws_eta", "ltt"):
            np.testing.assert_array_equal(getattr(got, k), getattr(tm, k))
        assert got.config["jitter"]["dws"] == 2.1e-10  # the fit's errors-in-variables level
    # a missing segment is named, not skipped
    (run_dir / "replayer.mcap").rename(tmp_path / "full.mcap")
    with Recorder(run_dir / "replayer.mcap", metadata={"run": "r1", "stage": "replayer"}) as rec:
        for index in (0, 2):
            part = src[0].slice(0, n)
            payload, att = encode(
                {k: getattr(part, k) for k in ("eta", "dws_phi", "dws_eta", "ltt")},
                {
                    "run": "r1",
                    "index": index,
                    "t0": index * 1800.0,
                    "fs": 4.0,
                    "channels": list(LINKS),
                    "producer": "replayer",
                    "meta": {},
                },
            )
            rec.write_segment("telemetry", json.loads(att), payload)
    with pytest.raises(TTLError, match=r"segments \[1\] are missing"):
        recorded_days(run_dir, tmp_path / "days2", day_length=HOUR)


def test_local_cluster_listens_on_loopback_ephemeral_ports_only():
    """The LocalCluster of ``ttl reprocess`` (dashboard off): every listening socket of the
    scheduler and of the workers is on 127.0.0.1, none on Dask's fixed 8787 (the scheduler's
    HTTP server used to take it even with the dashboard off, so two runs met on one port),
    and no dashboard is served."""
    import psutil

    from ttlcore.app.reprocessing import dask_client

    with dask_client(workers=1) as client:
        client.wait_for_workers(1, timeout=60)
        pids = {os.getpid(), *client.run(os.getpid).values()}
        listening = [
            c.laddr
            for pid in pids
            for c in psutil.Process(pid).net_connections(kind="inet")
            if c.status == psutil.CONN_LISTEN
        ]
        http = client.cluster.scheduler.http_server.port
        assert urllib.request.urlopen(f"http://127.0.0.1:{http}/health", timeout=10).status == 200
        with pytest.raises(urllib.error.HTTPError, match="404"):  # no dashboard pages
            urllib.request.urlopen(f"http://127.0.0.1:{http}/status", timeout=10)
    assert listening, "no listening socket found: the check would be empty"
    assert all(addr.ip == "127.0.0.1" for addr in listening), listening
    assert all(addr.port != 8787 for addr in listening), listening
