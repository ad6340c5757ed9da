"""`ttl analyze`: fit.json, figures, the subtraction, bad input, lisainstrument input.

Short simulations (6 h noise-on, 2 h TTL-only, a 1 h lisainstrument file) keep the module
well under two minutes on two cores.
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from lisainstrument_sim import simulate_lisainstrument
from scipy import signal

from ttlcore.conventions import COEFFICIENT_NAMES, C, ffd_to_displacement_asd
from ttlcore.estimate.noise_psd import requirement_x2
from ttlcore.estimate.spectra import log_average
from ttlcore.estimate.subtraction import (
    analyse_subtraction,
    residual_aet,
    residual_xyz,
    subtract,
    to_aet,
    to_xyz,
    ttl_in_tdi,
)
from ttlcore.io.reader import read_telemetry
from ttlcore.io.truth import read_truth, truth_path
from ttlcore.tdi.data import compute_tdi

REQUIRED_KEYS = {"names", "coefficients", "sigma", "covariance", "chi2_dof", "band", "method"}


def ttl(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "ttlcore.cli.main", *map(str, args)], capture_output=True, text=True, cwd=cwd
    )


def png_size(path: Path) -> tuple[int, int]:
    """Width and height from a PNG's IHDR chunk (asserting the signature)."""
    head = Path(path).read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
    assert head[12:16] == b"IHDR"
    return struct.unpack(">II", head[16:24])


# ---------------------------------------------------------------------------
# fixtures
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def noisy(tmp_path_factory):
    """6 h, unequal arms, all noises, paper coefficients; analysed with its truth."""
    d = tmp_path_factory.mktemp("analyze")
    data = d / "six.h5"
    r = ttl("simulate", "--duration", "6h", "--orbit", "unequal", "--seed", 1, "--out", data, "--quiet")
    assert r.returncode == 0, r.stderr
    out = d / "out"
    r = ttl("analyze", data, "--truth", truth_path(data), "--out", out, "--segment", 3600)
    assert r.returncode == 0, r.stderr
    return {
        "data": data,
        "out": out,
        "stdout": r.stdout,
        "stderr": r.stderr,
        "fit": json.loads((out / "fit.json").read_text()),
    }


@pytest.fixture(scope="module")
def ttl_only(tmp_path_factory):
    """2 h of TTL only (jitter on, no DWS readout noise, no other noise)."""
    data = tmp_path_factory.mktemp("ttl_only") / "ttl.h5"
    r = ttl(
        "simulate",
        "--duration",
        "2h",
        "--orbit",
        "unequal",
        "--seed",
        1,
        "--noises",
        "ttl,sc_jitter,mosa_jitter",
        "--out",
        data,
        "--quiet",
    )
    assert r.returncode == 0, r.stderr
    return data


@pytest.fixture(scope="module")
def li_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("lisainstrument") / "measurements.h5"
    simulate_lisainstrument(path, duration=3600, ttl=True, ttl_coeffs="default", seed=1)
    return path


# ---------------------------------------------------------------------------
# fit.json and figures
# ---------------------------------------------------------------------------


def test_fit_json_content(noisy):
    js = noisy["fit"]
    assert REQUIRED_KEYS | {"truth", "error"} <= set(js)
    assert js["names"] == list(COEFFICIENT_NAMES)
    for key in ("coefficients", "sigma", "truth", "error"):
        assert list(js[key]) == list(COEFFICIENT_NAMES), key
    assert js["method"] == "gls" and js["band"] == [3e-3, 0.9] and js["units"] == "m/rad"
    cov = np.array(js["covariance"])
    assert cov.shape == (24, 24)
    np.testing.assert_allclose(cov, cov.T, rtol=0, atol=1e-12 * np.abs(cov).max())
    np.linalg.cholesky(cov)  # positive definite
    coeffs = np.array([js["coefficients"][n] for n in COEFFICIENT_NAMES])
    sigma = np.array([js["sigma"][n] for n in COEFFICIENT_NAMES])
    truth = np.array([js["truth"][n] for n in COEFFICIENT_NAMES])
    error = np.array([js["error"][n] for n in COEFFICIENT_NAMES])
    np.testing.assert_allclose(sigma, np.sqrt(np.diag(cov)), rtol=1e-12)
    np.testing.assert_allclose(error, coeffs - truth, rtol=0, atol=1e-15)
    # units: m/rad (paper coefficients 2.3 mm/rad; errors and sigmas of tens of um/rad)
    np.testing.assert_allclose(truth, read_truth(truth_path(noisy["data"])).mean_coefficients(), rtol=1e-12)
    np.testing.assert_allclose(truth, 2.3e-3, rtol=1e-12)
    assert np.all((sigma > 1e-6) & (sigma < 1e-4))
    assert np.max(np.abs(error)) < 0.1e-3
    assert 0.7 < js["chi2_dof"] < 1.3
    assert js["truth_source"] == "ttl-truth" and js["ttl_residual_available"] is True
    # the summary line names the largest error and where the files are
    assert "max |error|" in noisy["stdout"] and "fit.json" in noisy["stdout"]
    assert "ttl analyze:" in noisy["stderr"]  # progress on stderr


def test_figures_are_pngs(noisy):
    out = noisy["out"]
    for name in ("asd_X.png", "coefficients.png"):
        path = out / name
        assert path.exists(), name
        w, h = png_size(path)
        assert 800 <= w <= 3000 and 400 <= h <= 2000, (name, w, h)
        assert path.stat().st_size > 20_000
    # atomic writes leave no temporary files behind
    assert sorted(p.name for p in out.iterdir()) == ["asd_X.png", "coefficients.png", "fit.json"]


# ---------------------------------------------------------------------------
# the subtraction, checked independently of the CLI
# ---------------------------------------------------------------------------


def test_true_coefficients_remove_ttl_exactly(ttl_only):
    tm = read_telemetry(ttl_only)
    truth = read_truth(truth_path(ttl_only))
    td = compute_tdi(tm)
    ok = td.valid_slice()
    data = td.data[:, ok]
    res = subtract(td, truth.mean_coefficients())[:, ok]
    assert np.max(np.abs(res)) < 1e-10 * np.max(np.abs(data))
    # the mapping form and the channel helpers agree
    mapping = dict(zip(COEFFICIENT_NAMES, truth.mean_coefficients()))
    np.testing.assert_array_equal(subtract(td, mapping), subtract(td, truth.mean_coefficients()))
    aet = td.to_aet()
    tol = 1e-12 * np.max(np.abs(data))
    np.testing.assert_allclose(residual_aet(td, mapping)[:, ok], subtract(aet, mapping)[:, ok], rtol=0, atol=tol)
    np.testing.assert_allclose(residual_xyz(aet, mapping)[:, ok], subtract(td, mapping)[:, ok], rtol=0, atol=tol)
    np.testing.assert_allclose(to_xyz(to_aet(data, ("X2", "Y2", "Z2")), ("A", "E", "T")), data, rtol=0, atol=tol)
    # TDI of the truth's TTL series is the data here (TTL is all there is)
    ttl_tdi = ttl_in_tdi(truth.ttl, tm.ltt, tm.fs, tm.t0)[:, ok]
    assert np.max(np.abs(ttl_tdi - data)) < 1e-10 * np.max(np.abs(data))
    # all the series of a subtraction with a perturbed "fit"
    fitted = truth.mean_coefficients() + 1e-5
    sub = analyse_subtraction(td, fitted, true_coefficients=truth.mean_coefficients(), ttl_truth=truth.ttl, ltt=tm.ltt)
    assert np.max(np.abs(sub.residual_true[:, ok])) < 1e-10 * np.max(np.abs(data))
    assert np.max(np.abs(sub.noise_without_ttl[:, ok])) < 1e-10 * np.max(np.abs(data))
    np.testing.assert_allclose(sub.ttl_residual[:, ok], sub.residual[:, ok], rtol=0, atol=1e-10 * np.max(np.abs(data)))
    assert np.max(np.abs(sub.residual[:, ok])) > 1e-3 * np.max(np.abs(data))  # 10 um/rad off is visible
    x = sub.channel("X")
    assert set(x) == {"data", "residual", "residual_true", "ttl_tdi", "ttl_residual", "noise_without_ttl"}


def _log_asd(x, fs, nperseg=2**14):
    w = signal.get_window("hann", nperseg)
    w = w / w.sum()
    f, p = signal.welch(x, fs=fs, nperseg=nperseg, detrend=lambda s: s - np.dot(s, w))
    fc, p = log_average(f[1:], p[1:], per_decade=20)
    return fc, ffd_to_displacement_asd(np.sqrt(p), fc), f


def test_residual_below_requirement_in_band(noisy):
    js = noisy["fit"]
    tm = read_telemetry(noisy["data"])
    td = compute_tdi(tm)
    ok = td.valid_slice()
    coeffs = np.array([js["coefficients"][n] for n in COEFFICIENT_NAMES])
    residual = subtract(td, coeffs)[0, ok]
    fc, asd_res, f = _log_asd(residual, tm.fs)
    _, asd_data, _ = _log_asd(td.data[0, ok], tm.fs)
    arm = C * float(np.mean(td.ltt_mean))
    _, req_psd = log_average(f[1:], requirement_x2(f[1:], arm), per_decade=20)
    req = ffd_to_displacement_asd(np.sqrt(req_psd), fc)
    band = (fc >= 3e-3) & (fc <= 0.9)
    assert band.sum() > 30
    ratio = asd_res[band] / req[band]
    assert np.all(ratio < 1.0), f"residual above requirement at {fc[band][ratio >= 1]} Hz"
    assert np.max(asd_data[band] / req[band]) > 1.2  # TTL at 2.3 mm/rad is above it before subtraction
    # analyze's own summary says the same
    assert js["asd_x_vs_requirement"]["residual"]["max"] < 1.0


# ---------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "args, needle",
    [
        (["does-not-exist.h5", "--out", "o"], "does-not-exist.h5"),
        (["DATA", "--band", "1", "0.1", "--out", "o"], "--band"),
        (["DATA", "--band", "0.001", "5", "--out", "o"], "--band"),
        (["DATA", "--method", "bayes", "--out", "o"], "--method"),
        (["DATA", "--segment", "1d", "--out", "o"], "--segment"),
        (["DATA", "--truth", "nothing.truth.h5", "--out", "o"], "nothing.truth.h5"),
    ],
)
def test_bad_input_gives_one_line(noisy, tmp_path, args, needle):
    args = [noisy["data"] if a == "DATA" else a for a in args]
    r = ttl("analyze", *args, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert needle in lines[0] and "Traceback" not in r.stderr
    assert not (tmp_path / "o" / "fit.json").exists()


def test_truth_of_another_simulation_is_refused(noisy, ttl_only, tmp_path):
    r = ttl("analyze", noisy["data"], "--truth", truth_path(ttl_only), "--out", tmp_path / "o", "--quiet")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "truth" in r.stderr


# ---------------------------------------------------------------------------
# lisainstrument input, MCMC, no truth
# ---------------------------------------------------------------------------


def test_lisainstrument_file(li_file, tmp_path):
    from ttlcore.io.lisainstrument import lisainstrument_truth

    out = tmp_path / "li"
    r = ttl("analyze", li_file, "--truth", li_file, "--segment", "1200", "--out", out, "--quiet")
    assert r.returncode == 0, r.stderr
    assert r.stderr.strip() == "" or "lisaconstants" in r.stderr  # quiet: no progress lines
    js = json.loads((out / "fit.json").read_text())
    assert REQUIRED_KEYS | {"truth", "error"} <= set(js)
    assert js["data"]["kind"] == "lisainstrument" and js["truth_source"] == "lisainstrument"
    assert js["ttl_residual_available"] is False
    assert any("no TTL time series" in n for n in js["notes"])
    truth = lisainstrument_truth(li_file)
    assert js["truth"] == pytest.approx(truth, rel=1e-12, abs=0)
    err = np.array([js["error"][n] for n in COEFFICIENT_NAMES])
    assert np.max(np.abs(err)) < 0.5e-3  # one hour only: sigmas of ~50 um/rad
    for name in ("asd_X.png", "coefficients.png"):
        png_size(out / name)


def test_mcmc_without_truth(noisy, tmp_path):
    pytest.importorskip("emcee")
    try:
        import ttlcore.estimate.mcmc  # noqa: F401
    except ImportError:
        pytest.skip("ttlcore.estimate.mcmc not available")
    out = tmp_path / "mcmc"
    r = ttl("analyze", noisy["data"], "--method", "mcmc", "--segment", "3600", "--out", out, "--quiet")
    assert r.returncode == 0, r.stderr
    js = json.loads((out / "fit.json").read_text())
    assert js["method"] == "mcmc" and "error" not in js and "truth" not in js
    assert js["ttl_residual_available"] is False
    gls = noisy["fit"]
    for n in COEFFICIENT_NAMES:  # same likelihood: MCMC mean within a fraction of sigma of GLS
        assert abs(js["coefficients"][n] - gls["coefficients"][n]) < 0.5 * gls["sigma"][n], n
    png_size(out / "coefficients.png")


def test_gapped_file_is_analysed_with_the_loss_reported(noisy, tmp_path):
    """Ten minutes of NaN in eta (a gap): ``ttl analyze`` masks it and reports the loss; the
    coefficients stay within 1 sigma of the gap-free fit of the same file (10 min of 6 h
    lost: the estimate moves by a fraction of its sigma), the residual ASD stays at the
    gap-free level (the ASD uses the longest gap-free stretch, no splicing)."""
    import h5py

    gap = tmp_path / "gap.h5"
    gap.write_bytes(noisy["data"].read_bytes())
    with h5py.File(gap, "r+") as f:
        f["eta"][:, 36000:38400] = np.nan  # 2.5 h .. 2.5 h + 10 min at 4 Hz
    out = tmp_path / "out"
    r = ttl("analyze", gap, "--out", out, "--segment", 3600)
    assert r.returncode == 0, r.stderr
    assert "gaps: 2400 telemetry samples missing (NaN) in 1 stretch(es)" in r.stderr
    js = json.loads((out / "fit.json").read_text())
    loss = js["data_loss"]
    assert loss["stretches"] == [[36000, 38400]] and loss["seconds_missing"] == 600.0
    assert 600 / 21600 < loss["tdi_fraction_lost"] < 0.05  # the gap, spread by the TDI delays (~70 s each side)
    clean = noisy["fit"]
    diff = [abs(js["coefficients"][n] - clean["coefficients"][n]) / clean["sigma"][n] for n in COEFFICIENT_NAMES]
    assert max(diff) < 1.0, diff
    for series, ratio in js["asd_x_vs_requirement"].items():
        assert ratio["median"] < 2 * clean["asd_x_vs_requirement"][series]["median"], series


def test_analysis_equals_a_fit_of_pytdi_outputs(tmp_path):
    # `ttl analyze` computes TDI with the block engine (ttlcore.tdi.engine); the fit must be
    # the one of the same data through pytdi (natural usage: each combination built once,
    # the scalar 0 on links a regressor does not touch, Tx witnesses pre-delayed with its
    # timeshift).  The two agree to ~1e-6 in the fit band (tests/ttlcore/tdi/test_tdi.py),
    # so the coefficients must agree far inside their uncertainty: 1e-3 sigma
    from dataclasses import replace

    from pytdi_reference import pytdi_natural

    from ttlcore.estimate.fit import FitSettings, dws_asd_from_config, fit_tdi

    data = tmp_path / "kepler.h5"
    r = ttl("simulate", "--duration", "2h", "--orbit", "keplerian", "--seed", 7, "--out", data, "--quiet")
    assert r.returncode == 0, r.stderr
    r = ttl("analyze", data, "--out", tmp_path / "out", "--segment", 1800)
    assert r.returncode == 0, r.stderr
    js = json.loads((tmp_path / "out" / "fit.json").read_text())

    tm = read_telemetry(data)
    ref_data, ref_regs = pytdi_natural(tm)
    ours = compute_tdi(tm)
    skip = ours.valid_slice().start  # pytdi pads before the data with zeros where we give NaN
    ref_data[:, :skip] = np.nan
    ref_regs[..., :skip] = np.nan
    ref = replace(ours, data=ref_data, regressors=ref_regs)
    settings = FitSettings(segment_duration=1800.0, dws_asd=dws_asd_from_config(tm.config))
    res, _ = fit_tdi(ref, settings, "gls")
    got = np.array([js["coefficients"][n] for n in COEFFICIENT_NAMES])
    sigma = np.array([js["sigma"][n] for n in COEFFICIENT_NAMES])
    assert np.max(np.abs(got - res.coefficients) / sigma) < 1e-3
    np.testing.assert_allclose(sigma, res.sigma, rtol=1e-3)
    assert js["chi2_dof"] == pytest.approx(res.chi2_dof, rel=1e-4)
