"""Blind tests of the diagnosis loop on effects it does not name (issue 10).

A generator (:func:`blind_case`) draws an effect outside the named set - a mechanical
resonance of random frequency and quality factor on a random DWS channel coupled into a
random link, a first-order low-pass path of random corner, a plain witness placed on
another link after one or two light travel times - with random link, channel and delay.
It is injected through a plugin the diagnosis never loads (``blind_effects.py``).  The test
then does what a user does: run ``ttl diagnose``, and while it recommends a next step, run
the printed option exactly as printed (at most three steps, no user code).  Acceptance:
every band's chi^2/dof within the tolerance of the noise model (no band fails), max
|C_fit - C_true| < 0.05 mm/rad and the RMS of the coefficient pulls below 1.5.

The levels put the injected signal at 3 to 10 times the secondary noise in ASD in its
strongest band (checked with the independent Welch estimate of ``diagnose_helpers``; a draw
outside is rescaled to a random level of 3 to 8 and simulated again).
"""

import json
import shlex
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from diagnose_helpers import injected_asd_ratio  # noqa: E402

from ttlcore.cli.main import main  # noqa: E402
from ttlcore.conventions import ANGLES, COEFFICIENT_NAMES, LINKS, MOSAS  # noqa: E402
from ttlcore.diagnose.diagnoser import refit  # noqa: E402
from ttlcore.diagnose.whitened import whiten_telemetry  # noqa: E402
from ttlcore.io.reader import read_telemetry  # noqa: E402
from ttlcore.io.truth import read_truth  # noqa: E402

BLIND = str(Path(__file__).parent / "blind_effects.py")
#: the acceptance of issue 10
MAX_ERROR = 5e-5  # m/rad (0.05 mm/rad)
MAX_PULL_RMS = 1.5


def blind_case(seed: int) -> str:
    """A random effect outside the named set, as an ``--inject`` spec of ``blind_effects.py``."""
    rng = np.random.default_rng(seed)
    kind = ("resonance", "lowpass", "witness")[int(rng.integers(3))]
    mosa, angle = str(rng.choice(MOSAS)), str(rng.choice(ANGLES))
    link = str(rng.choice(LINKS))
    if kind == "resonance":
        q = float(10 ** rng.uniform(np.log10(3), np.log10(30)))
        f0 = float(10 ** rng.uniform(np.log10(0.02), np.log10(0.3)))
        extra, gain = f"f0={f0:.4g},q={q:.3g}", 0.05 / q
    elif kind == "lowpass":
        extra, gain = f"fc={10 ** rng.uniform(np.log10(0.01), np.log10(0.2)):.4g}", 8e-3
    else:
        link = str(rng.choice([x for x in LINKS if x != mosa]))
        extra, gain = "", 5e-3
    delay = int(rng.integers(1, 3)) if kind == "witness" else int(rng.integers(0, 2))
    return (
        f"blind-{kind}:source={mosa}.{angle},link={link},delay={delay}"
        + (f",{extra}" if extra else "")
        + f",gain={gain:.3g}"
    )


def simulate_case(tmp_path, spec, duration, seed):
    path = tmp_path / "day.h5"
    args = [
        "simulate",
        "--duration",
        duration,
        "--orbit",
        "keplerian",
        "--seed",
        str(seed),
        "--out",
        str(path),
        "--chunk",
        "7d",
        "--quiet",
    ]
    if spec:
        args += ["--effect-module", BLIND, "--inject", spec]
    assert main(args) == 0
    return path, tmp_path / "day.truth.h5"


def follow_advice(path, truth, tmp_path, max_steps=3, args=()):
    """``ttl diagnose`` (with the user's own ``args``) and its printed next step, at most
    ``max_steps`` times; the reports."""
    reports, option = [], []
    for step in range(max_steps + 1):
        out = tmp_path / f"report{step}.json"
        assert main(["diagnose", str(path), *args, *option, "--truth", str(truth), "--json", str(out), "--quiet"]) == 0
        reports.append(json.loads(out.read_text()))
        rec = reports[-1]["recommendation"]
        if step == max_steps or not rec or not rec.get("option"):
            break
        option = shlex.split(rec["option"])  # exactly as printed
    return reports


def check_accepted(rep, max_error=MAX_ERROR):
    bands = rep["adequacy"]["bands"]
    assert not any(b["fails"] for b in bands), [round(b["chi2_dof"], 3) for b in bands]
    c = rep["model"]["coefficients"]
    err = np.array([c["error"][n] for n in COEFFICIENT_NAMES])
    sig = np.array([c["sigma"][n] for n in COEFFICIENT_NAMES])
    assert np.max(np.abs(err)) < max_error, np.max(np.abs(err))
    assert np.sqrt(np.mean((err / sig) ** 2)) < MAX_PULL_RMS


def with_gain(spec: str, factor: float) -> str:
    """``spec`` with its ``gain`` multiplied by ``factor`` (the injection is linear in it)."""
    name, _, rest = spec.partition(":")
    opts = [kv.split("=") for kv in rest.split(",")]
    return name + ":" + ",".join(f"{k}={float(v) * factor:.4g}" if k == "gain" else f"{k}={v}" for k, v in opts)


def run_blind_day_file(tmp_path, seed, duration="1d"):
    """The blind case of ``seed`` simulated (rescaled into the acceptance's regime when the
    draw is outside it): ``(spec, telemetry path, truth path)``."""
    spec = blind_case(seed)
    path, truth = simulate_case(tmp_path, spec, duration, seed)
    name = spec.split(":")[0]
    ratio = injected_asd_ratio(read_telemetry(path), read_truth(truth).injections[name])
    if not 3.0 <= ratio.max() <= 10.0:
        # the generator's gains suit most draws; one outside the regime the acceptance is
        # for (plainly there, not dominant) is rescaled to a random level of 3 to 8 in its
        # strongest band and simulated again (same seed: the same noise)
        level = 10 ** np.random.default_rng(1000 + seed).uniform(np.log10(3), np.log10(8))
        spec = with_gain(spec, level / ratio.max())
        path, truth = simulate_case(tmp_path, spec, duration, seed)
        ratio = injected_asd_ratio(read_telemetry(path), read_truth(truth).injections[name])
    assert 3.0 <= ratio.max() <= 10.0, (spec, np.round(ratio, 2))
    return spec, path, truth


def run_blind(tmp_path, seed, duration, args=()):
    spec, path, truth = run_blind_day_file(tmp_path, seed, duration)
    reports = follow_advice(path, truth, tmp_path, args=args)
    first = reports[0]
    assert first["adequacy"]["fails"], spec
    assert first["recommendation"]["option"], spec
    # the statistical error of a coefficient scales as 1/sqrt(T): 0.05 mm/rad is the
    # acceptance for a day (sigma ~ 0.01 mm/rad), scaled for shorter data
    hours = float(duration[:-1]) * (24 if duration.endswith("d") else 1)
    check_accepted(reports[-1], MAX_ERROR * np.sqrt(max(24.0 / hours, 1.0)))
    return spec, reports


@pytest.mark.parametrize("seed", [14])
def test_blind_effect_fixed_by_following_the_printed_advice_3h(tmp_path, seed):
    # fast version: the user's first command restricts the named candidates to drift (the
    # witness effects and frequency-dependent couplings are always tried); the day-long
    # science version tries everything
    run_blind(tmp_path, seed, "3h", args=("--candidates", "drift"))


@pytest.mark.science
@pytest.mark.parametrize("seed", [1, 2, 9, 11, 12, 16])
def test_blind_effect_fixed_by_following_the_printed_advice_one_day(tmp_path, seed):
    run_blind(tmp_path, seed, "1d")


@pytest.mark.science
def test_blind_null_day(tmp_path):
    path, truth = simulate_case(tmp_path, None, "1d", 11)
    rep = follow_advice(path, truth, tmp_path, max_steps=0)[0]
    assert not rep["adequacy"]["fails"]
    assert not any(c["significant"] for c in rep["candidates"])
    assert rep["recommendation"] is None


def test_fd_coupling_with_wrong_fixed_poles_fails_the_adequacy_test_and_searched_passes(tmp_path):
    # a resonance of Q = 15 at 80 mHz; fixed at 60 mHz the pole pair cannot absorb it (the
    # coupling's phase turns by pi over f0 / Q = 5 mHz), searched it does
    spec = "blind-resonance:source=23.eta,link=31,f0=0.08,q=15,gain=3e-3"
    path, truth = simulate_case(tmp_path, spec, "3h", 3)
    dg = whiten_telemetry(read_telemetry(path))
    wrong = refit(dg, ["linear-ttl", "fd-coupling:source=23.eta,link=31,f0=0.06,q=15"])
    assert wrong.model.adequacy.fails
    searched = refit(dg, ["linear-ttl", "fd-coupling:source=23.eta,link=31"])
    assert not any(b.fails for b in searched.model.adequacy.bands)
    (found,) = searched.to_json()["model"]["searched"].values()
    lo, hi = found["intervals"]["f0"]
    assert lo < 0.08 < hi or abs(found["estimates"]["f0"] - 0.08) < 0.002
    assert found["estimates"]["q"] == pytest.approx(15, rel=0.3)
