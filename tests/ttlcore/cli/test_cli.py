"""The `ttl` command line: simulate, info, and one-line errors for bad input."""

import subprocess
import sys

import h5py
import numpy as np
import pytest

from ttlcore.io.reader import read_telemetry
from ttlcore.io.truth import read_truth


def ttl(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "ttlcore.cli.main", *map(str, args)], capture_output=True, text=True, cwd=cwd
    )


@pytest.fixture(scope="module")
def hour_file(tmp_path_factory):
    from ttlcore.cli.main import main

    out = tmp_path_factory.mktemp("sim") / "hour.h5"
    # in this process (the command's own entry point): the module's tests share out over the
    # workers, and each worker that takes one makes the file again
    code = main(
        [
            "simulate",
            "--duration",
            "1h",
            "--orbit",
            "keplerian",
            "--coeffs",
            "lisainstrument",
            "--seed",
            "4",
            "--telemetry",
            str(out),
            "--drift",
            "12.phi.rx=0.05",
            "--step",
            "30min:13.eta.tx=0.3",
            "--quiet",
        ]
    )
    assert code == 0
    return out


def test_simulate_writes_telemetry_and_truth(hour_file):
    tm = read_telemetry(hour_file)
    assert tm.size == 14400 and tm.fs == 4.0
    assert np.all(np.isfinite(tm.eta))
    truth = read_truth(hour_file.with_name("hour.truth.h5"))
    from ttlcore.conventions import COEFFICIENT_NAMES

    j = COEFFICIENT_NAMES.index("13.eta.tx")
    assert truth.coefficients[j, 0] == pytest.approx(-0.0 + 1.960050e-03)
    assert truth.coefficients[j, -1] == pytest.approx(1.960050e-03 + 0.3e-3)
    assert tm.config["orbit"] == "keplerian"
    # no leftover temporary files
    assert sorted(p.name for p in hour_file.parent.iterdir()) == ["hour.h5", "hour.truth.h5"]


def test_info_text_and_json(hour_file):
    r = ttl("info", hour_file)
    assert r.returncode == 0 and "14400 samples" in r.stdout and "truth file" in r.stdout
    r = ttl("info", "--json", "-", hour_file)
    assert r.returncode == 0 and '"kind": "ttl"' in r.stdout


@pytest.mark.parametrize(
    "args, needle",
    [
        (["simulate", "--duration", "abc", "--telemetry", "x.h5"], "duration"),
        (["simulate", "--orbit", "moon", "--telemetry", "x.h5"], "moon"),
        (["simulate", "--coeffs", "nope", "--telemetry", "x.h5"], "nope"),
        (["simulate", "--noises", "all,-lazer", "--telemetry", "x.h5"], "lazer"),
        (["simulate", "--drift", "12.phi.xx=1", "--telemetry", "x.h5"], "12.phi.xx"),
        (["info", "does-not-exist.h5"], "does-not-exist.h5"),
    ],
)
def test_bad_arguments_give_one_line(tmp_path, args, needle):
    r = ttl(*args, cwd=tmp_path)
    assert r.returncode == 2
    assert needle in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not any(tmp_path.iterdir())  # nothing half-written


def _copy(src, dst):
    dst.write_bytes(src.read_bytes())
    return dst


def test_truncated_file(hour_file, tmp_path):
    bad = tmp_path / "truncated.h5"
    data = hour_file.read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    r = ttl("info", bad)
    assert r.returncode == 2 and "truncated.h5" in r.stderr and "Traceback" not in r.stderr


def test_missing_dataset(hour_file, tmp_path):
    bad = _copy(hour_file, tmp_path / "missing.h5")
    with h5py.File(bad, "a") as f:
        del f["dws/phi"]
    r = ttl("info", bad)
    assert r.returncode == 2 and "missing.h5" in r.stderr and "dws/phi" in r.stderr


def test_wrong_sampling_attribute(hour_file, tmp_path):
    bad = _copy(hour_file, tmp_path / "fs.h5")
    with h5py.File(bad, "a") as f:
        f.attrs["fs"] = 2.0  # duration and size say 4 Hz
    r = ttl("info", bad)
    assert r.returncode == 2 and "fs.h5" in r.stderr and "@fs" in r.stderr
    with h5py.File(bad, "a") as f:
        f.attrs["fs"] = -4.0
    r = ttl("info", bad)
    assert r.returncode == 2 and "@fs" in r.stderr


def test_info_and_analyze_report_the_gaps_of_a_lisainstrument_file(hour_file, tmp_path):
    """A lisainstrument file with a lisa-gap gap (NaN in every series over 3 min): ``ttl info``
    lists the gap, ours as well; ``ttl analyze`` fits around it and reports the same gap."""
    import json

    import blind_signals as bs
    from lisainstrument_sim import simulate_lisainstrument

    from ttlcore.conventions import MOSAS
    from ttlcore.io.lisainstrument import BEATNOTE_DATASETS, DWS_ETA_DATASET, DWS_PHI_DATASET, MPR_DATASET

    path = tmp_path / "li.h5"
    simulate_lisainstrument(path, duration=1800, orbits="static", seed=7)
    with h5py.File(path, "r+") as f:
        md = json.loads(f.attrs["metadata_json"])
        t = md["t0"] + np.arange(md["size"]) / md["fs"]
        mask = bs.gap_mask(t, n_gaps_per_day=2 * 86400 / 1800, duration_hr=3 / 60, seed=5)  # one, mid-file
        for group in (*BEATNOTE_DATASETS.values(), MPR_DATASET, DWS_PHI_DATASET, DWS_ETA_DATASET):
            for m in MOSAS:
                f[f"{group}/{m}"][...] = f[f"{group}/{m}"][()] * mask
    t_nan = t[np.isnan(mask)]
    assert t_nan.size == 720

    r = ttl("info", path)
    assert r.returncode == 0, r.stderr
    assert "lisainstrument file" in r.stdout and "in 1 span(s)" in r.stdout, r.stdout
    assert "reaches 12.25 s further in eta" in r.stdout and "nan" not in r.stdout.split("ltt [s]")[1].split("gaps")[0]
    r = ttl("info", "--json", "-", path)
    assert r.returncode == 0, r.stderr
    gaps = json.loads(r.stdout)["gaps"]
    # the gap, one MPR sample before it (Doppler factor) and 12.25 s after it (delay + stencil)
    ((a, b),) = gaps["spans_s"]
    assert a == t_nan[0] - 0.25 and b == t_nan[-1] + 0.25 + 12.25
    assert gaps["samples_missing"] == 720 + 1 + 49

    out = tmp_path / "fit"
    r = ttl("analyze", path, "--truth", path, "--segment", 600, "--out", out)
    assert r.returncode == 0, r.stderr
    assert "gaps: 770 telemetry samples missing (NaN) in 1 stretch(es)" in r.stderr, r.stderr
    js = json.loads((out / "fit.json").read_text())
    assert js["data_loss"]["stretches"] == gaps["stretches"]
    assert np.isfinite(js["chi2_dof"]) and all(np.isfinite(v) for v in js["coefficients"].values())

    # our own files: the same report
    ours = _copy(hour_file, tmp_path / "ours.h5")
    with h5py.File(ours, "a") as f:
        f["eta"][:, 4000:4400] = np.nan
    r = ttl("info", "--json", "-", ours)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["gaps"]["stretches"] == [[4000, 4400]]
    assert "gaps: none" in ttl("info", hour_file).stdout


def test_the_same_effect_injected_twice_keeps_both(tmp_path):
    # a glitch a day: ttl simulate refused a second --inject glitch ("injection names must be
    # unique"); the repeats are named glitch-2, ... and each is in the truth and in the data
    # (two glitches of the same size on different test masses: eta moves on both links each
    # one kicks; 2 v / c = 6.7e-20 for 1e-11 m/s, far above nothing - the noises are off)
    out = tmp_path / "two.h5"
    glitches = ["glitch:t=600,tm=12,beta=10,all=1e-11", "glitch:t=1800,tm=23,beta=10,all=1e-11"]
    r = ttl("simulate", "--duration", "1h", "--noises", "none", "--seed", 1, "--telemetry", out,
            *[a for g in glitches for a in ("--inject", g)])  # fmt: skip
    assert r.returncode == 0, r.stderr
    with h5py.File(out.with_name("two.truth.h5")) as f:
        assert sorted(f["injections"]) == ["glitch", "glitch-2"]
    eta = read_telemetry(out).eta
    settled = int(1200 * 4)  # between the two glitches: only the first has moved eta
    assert np.abs(eta[0, settled]) > 5e-20 and eta[1, settled] == 0  # eta_12 moved, eta_23 not yet
    assert np.abs(eta[1, -1]) > 5e-20  # the second one, on tm 23, moved eta_23


def test_an_error_after_ctrl_c_is_the_interrupt(monkeypatch, capsys, tmp_path):
    """Ctrl-C reaches a whole process group at once: a helper that died of it (a ``ttl
    reprocess`` Dask worker) may surface as the command's error (an OSError of its lost
    connection) before the KeyboardInterrupt does.  The exit status is still 130, with the one
    line ``interrupted``; an error with no Ctrl-C before it stays an error (2)."""
    import os
    import signal
    import time

    from ttlcore.cli import main as cli

    def interrupted_then_failed(args):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)  # the handler runs here
        except KeyboardInterrupt:
            pass  # swallowed on the way, as a library's cleanup may
        raise OSError("connection to the worker lost")

    def failed(args):
        raise OSError("connection to the worker lost")

    day = tmp_path / "day.h5"
    day.write_bytes(b"")  # the parser checks that it exists; the handler never opens it
    day = str(day)
    # Python's own SIGINT handler, as in a command started at a terminal (a pytest-xdist
    # worker ignores SIGINT)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        for run, status, line in ((interrupted_then_failed, 130, "interrupted"), (failed, 2, "error: connection")):
            monkeypatch.setattr(cli, "handler", lambda args, run=run: run)
            assert cli.main(["info", day]) == status
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and err[0].startswith(f"ttl info: {line}"), err
            assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
    finally:
        signal.signal(signal.SIGINT, before)
