"""Signals and defects of the data are not read as missing effects (issue 24).

Blind days (12 h, our simulator, Keplerian arms, nothing hidden unless said) with, added
by independent code (``blind_signals.py``: lisagwresponse, lisaglitch, lisa-gap, OMS-shaped
noise written there), randomised parameters: a chirp merging inside or just after the
span (SNR 100-3000), one to five test-mass glitches of the LISA Pathfinder size or a
hundred times louder, a gap, a noise level that doubles for a few hours; and a hidden
timing offset on a day that also holds a merger.  For each, the diagnosis is followed as
printed (at most three steps): nothing spurious in the final model, the class stated
right, the advice adding nothing but glitches and gates (item 4), the quiet hours' chi^2/dof
within 2 % of one (their scatter is ~1.5 % an hour, so the mean of the quiet hours is
tested), and the TTL coefficients - those of the fit without
the transient's hours (``transients.robustness.gated``) when it is a signal - within
0.05 mm/rad of the truth with pull RMS < 1.5.

``science``: each case simulates 12 h and runs one to three diagnoses (1-3 min each on
the shared 2-core machine).
"""

import shlex
from dataclasses import replace

import blind_signals as bs
import numpy as np
import pytest
from diagnose_helpers import follow

from ttlcore.conventions import COEFFICIENT_NAMES, LINKS
from ttlcore.diagnose.diagnoser import text_report
from ttlcore.effects import injection_from_spec, split_effects
from ttlcore.sim.simulator import SimulationConfig, simulate

pytestmark = pytest.mark.science

HOURS = 12
DURATION = HOURS * 3600.0
MAX_ERROR = 0.05e-3  # m/rad
MAX_PULL_RMS = 1.5


def day(seed, spec=None):
    inj = (injection_from_spec(spec),) if spec else ()
    tm, truth = simulate(
        SimulationConfig(duration=DURATION, orbit="keplerian", seed=seed, injections=inj), chunk_size=int(DURATION * 4)
    )
    return tm, truth["coefficients"].mean(axis=1)


def quiet_hours(rep):
    """chi2/dof of the hourly slices outside every event (and the hours next to one)."""
    ev = rep["transients"]["events"]
    rows = rep["adequacy"]["time"]["segments"]
    quiet = [
        r["chi2_dof"]
        for r in rows
        if not any(r["t_start"] < e["t_stop"] + 1800 and r["t_stop"] > e["t_start"] - 1800 for e in ev)
    ]
    return np.array(quiet)


def only_transients(rep) -> bool:
    """The advice adds nothing but glitches and gates (item 4: a transient is gated or
    fitted as a glitch, never read as an effect)."""
    opt = (rep["recommendation"] or {}).get("option") or ""
    if not opt:
        return True
    return all(e == "linear-ttl" or e.startswith(("glitch:", "gate:")) for e in split_effects(shlex.split(opt)[1]))


def check_signal(rep, C, expected_class):
    txt = text_report(rep)
    tr = rep["transients"]
    assert tr["classification"]["class"] == expected_class, txt
    assert tr["classification"]["signal"], txt
    assert only_transients(rep), txt  # nothing spurious: no effect added
    q = quiet_hours(rep)
    assert q.size >= 3, txt
    assert abs(q.mean() - 1) < 0.02, (q, txt)
    rb = tr["robustness"]
    idx = [rb["names"].index(n) for n in COEFFICIENT_NAMES]
    err = np.array(rb["gated"])[idx] - C
    pull = err / np.array(rb["sigma_gated"])[idx]
    levels = {k: round(v["psd_scale"], 3) for k, v in rep["adequacy"]["noise_model"]["parameters"].items()}
    print(  # the figures docs/diagnostics.md quotes (pytest -s)
        f"{expected_class}: quiet hours {q.mean():.3f}, quiet tiles {tr['quiet']['chi2_dof']:.3f} "
        f"(gated fit: {bool(tr['quiet'].get('gated'))}), levels {levels}, gated TTL fit "
        f"{1e3 * np.max(np.abs(err)):.3f} mm/rad, pull RMS {np.sqrt(np.mean(pull**2)):.2f}"
    )
    assert np.max(np.abs(err)) < MAX_ERROR, (np.max(np.abs(err)), txt)
    assert np.sqrt(np.mean(pull**2)) < MAX_PULL_RMS, (pull, txt)
    return err, pull


@pytest.fixture(scope="module")
def orbit_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("orbits") / "orbits.h5"
    bs.write_orbits(path, DURATION)
    return path


@pytest.mark.parametrize("seed", [101, 102])
def test_chirp_is_a_gravitational_wave(seed, orbit_file):
    rng = np.random.default_rng(seed)
    tm, C = day(seed)
    # merging inside the span, heavy enough that the chirp is in band for hours at most (a
    # loud inspiral in band over the whole span is a stationary excess: classified
    # gravitational-wave too, but no quiet hours remain to test)
    source = bs.random_merger(rng, DURATION, t_c=(0.3, 0.95), log10_mass=(5.3, 6.3))
    y = bs.gw_link_responses(orbit_file, DURATION, tm.fs, **source)
    snr = rng.uniform(100, 3000)
    y *= snr / bs.optimal_snr(tm, y)
    tm = replace(tm, eta=tm.eta + y)
    reports = follow(tm, C)
    assert all(only_transients(r) for r in reports), text_report(reports[-1])
    check_signal(reports[0], C, "gravitational-wave")


@pytest.mark.parametrize("seed,louder,n", [(201, 100.0, None), (202, 1.0, None), (203, 1.0, 4), (204, 1.0, 4)])
def test_glitches_are_glitches(seed, louder, n):
    """Glitches a hundred times the LISA Pathfinder size are glitches; Pathfinder-sized ones
    (issue 32: four of them on seeds 203, 204) give no advice, or advice that keeps the pull
    RMS below 1.3 and the largest coefficient error within 10 % of the linear fit's (seed
    203: a gate was advised for one read as a gravitational wave, which moved the fit by
    0.49 sigma; followed, the gated fit read chi2/dof 1.058 and failed 0.1-0.8 Hz)."""
    rng = np.random.default_rng(seed)
    tm, C = day(seed)
    n = int(rng.integers(1, 6)) if n is None else n
    t = tm.t0 + np.arange(tm.eta.shape[1]) / tm.fs
    # LISA Pathfinder: velocity steps of 1e-12 to 5e-12 m/s (lisaglitch's level), damping 5-300 s
    glitches = [
        (
            LINKS[int(rng.integers(6))],
            float(rng.uniform(0.5, HOURS - 0.5) * 3600),
            louder * rng.uniform(1e-12, 5e-12),
            float(rng.uniform(5, 300)),
        )
        for _ in range(n)
    ]
    tm = replace(tm, eta=tm.eta + bs.glitch_eta(t, np.mean(tm.ltt, axis=1), glitches))
    reports = follow(tm, C)
    rep = reports[-1]
    if louder > 1:
        assert all(only_transients(r) for r in reports), text_report(rep)
        check_signal(reports[0], C, "glitch")
    else:
        # Pathfinder-sized glitches leave the fit untouched: nothing is added, or what is
        # added keeps the pulls and the error of the linear fit (and nothing but glitches)
        txt = "\n\n".join(text_report(r) for r in reports)
        first, last = reports[0]["model"]["coefficients"], rep["model"]["coefficients"]
        err = np.array([last["error"][k] for k in COEFFICIENT_NAMES])
        pull_rms = float(np.sqrt(np.mean((err / np.array([last["sigma"][k] for k in COEFFICIENT_NAMES])) ** 2)))
        print(
            f"Pathfinder-sized glitches {glitches}: {len(reports)} diagnosis(es), last model "
            f"{rep['model']['cli_effects']}; linear fit {1e3 * first['max_abs_error']:.4f} mm/rad, last "
            f"{1e3 * last['max_abs_error']:.4f} mm/rad, pull RMS {pull_rms:.2f}"
        )
        assert rep["recommendation"] is None or rep["recommendation"]["option"] == "", txt
        assert all(only_transients(r) for r in reports), txt
        if len(reports) > 1:  # advice followed: the fit no worse, and still consistent with the noise
            assert pull_rms < 1.3 and last["max_abs_error"] < 1.1 * first["max_abs_error"], txt
            assert abs(rep["model"]["chi2_dof"] - 1) < 0.02, txt
        assert last["max_abs_error"] < MAX_ERROR, txt


def test_gap_is_gated_before_the_fit_and_nothing_is_advised():
    tm, C = day(301)
    t = tm.t0 + np.arange(tm.eta.shape[1]) / tm.fs
    mask = bs.gap_mask(t, n_gaps_per_day=3.0, duration_hr=0.5, seed=301)  # NaN: missing data
    assert np.isnan(mask).any()
    tm = replace(tm, eta=tm.eta * mask, dws_phi=tm.dws_phi * mask, dws_eta=tm.dws_eta * mask)
    reports = follow(tm, C)
    rep = reports[0]
    txt = text_report(rep)
    gaps = rep["transients"]["gaps"]
    assert gaps, txt
    t_nan = t[np.isnan(mask)]
    # the gap as missing from the decimated TDI: its span and the TDI stencils around it
    assert gaps[0][0] <= t_nan[0] + 60 and gaps[0][1] >= t_nan[-1] - 60, (gaps, t_nan[[0, -1]])
    # the data's gaps are gated (cosine ramps) before anything is fitted: a hole with hard
    # edges pulled the diagnosis' own linear fit by 0.67 mm/rad on this day and read as an
    # excess to gate; gated, the first fit is right and there is nothing to advise
    assert len(reports) == 1 and rep["recommendation"] is None, txt
    assert not rep["adequacy"]["fails"], txt
    assert "gated before the fit" in txt, txt
    c = rep["model"]["coefficients"]
    err = np.array([c["error"][n] for n in COEFFICIENT_NAMES])
    pull = err / np.array([c["sigma"][n] for n in COEFFICIENT_NAMES])
    print(f"gap day: {1e3 * np.max(np.abs(err)):.3f} mm/rad, pull RMS {np.sqrt(np.mean(pull**2)):.2f}")
    assert np.max(np.abs(err)) < MAX_ERROR, (np.max(np.abs(err)), txt)
    assert np.sqrt(np.mean(pull**2)) < MAX_PULL_RMS, (pull, txt)


def test_noise_that_doubles_for_hours_is_a_noise_change():
    rng = np.random.default_rng(401)
    tm, C = day(401)
    n = tm.eta.shape[1]
    a = float(rng.uniform(2, 6)) * 3600
    b = a + float(rng.uniform(2.5, 4)) * 3600
    t = tm.t0 + np.arange(n) / tm.fs
    w = np.clip(np.minimum(t - a, b - t) / 300.0, 0, 1)  # 300-s ramps
    tm = replace(tm, eta=tm.eta + bs.oms_noise_eta(n, tm.fs, 401) * w)
    rep = follow(tm, C)[0]
    check_signal(rep, C, "noise-change")


def test_hidden_timing_offset_on_a_day_with_a_merger_is_found(orbit_file):
    tm, C = day(501, "timing-offset:sc1.d1=0.35")
    source = dict(t_c=0.6 * DURATION, m_total=3e5, q=0.6, distance_mpc=1e4, iota=0.7, beta=0.3, lam=2.0, psi=0.4)
    y = bs.gw_link_responses(orbit_file, DURATION, tm.fs, **source)
    y *= 1000.0 / bs.optimal_snr(tm, y)
    tm = replace(tm, eta=tm.eta + y)
    reports = follow(tm, C)
    # the merger gated first (when short enough to be a transient), then the offset found
    found = [r for r in reports if "timing-offset" in ((r["recommendation"] or {}).get("option") or "")]
    assert found, "\n\n".join(text_report(r) for r in reports)
    assert found[0]["transients"]["classification"]["class"] == "missing-coupling", text_report(found[0])


@pytest.mark.timeout(3600)
@pytest.mark.parametrize("seed", [601])
def test_a_coupling_beside_a_merger_is_advised_without_a_shape_it_does_not_have(seed, orbit_file):
    """Issue 32: a merger in band for hours beside a plain coupling outside the named set (a
    witness of a random MOSA and angle on a random link, zero to two light travel times
    away, injected by the lisainstrument blind tests' own code, 3-8 times the secondary
    noise): following the advice ends with the plain witness - no resonance, pole or
    modulation that the injection does not have (the candidates are ranked again with the
    signal's hours gated, :mod:`ttlcore.diagnose.gated_ranking`) - max |dC| < 0.05 mm/rad,
    pull RMS < 1.5, chi2/dof outside the gated span within 2 % of 1."""
    from test_diagnose_blind_lisainstrument import injected_eta, scaled_to_a_random_level

    from ttlcore.conventions import MOSAS

    rng = np.random.default_rng(seed)
    tm, C = day(seed)
    source = f"{MOSAS[int(rng.integers(6))]}.{('phi', 'eta')[int(rng.integers(2))]}"
    spec = f"blind-witness:source={source},link={LINKS[int(rng.integers(6))]},delay={int(rng.integers(3))},gain=1"
    extra = scaled_to_a_random_level(tm, injected_eta(tm, spec), seed)
    merger = bs.random_merger(rng, DURATION, t_c=(0.4, 0.9), log10_mass=(5.3, 6.0))
    y = bs.gw_link_responses(orbit_file, DURATION, tm.fs, **merger)
    y *= rng.uniform(300, 1500) / bs.optimal_snr(tm, y)
    tm = replace(tm, eta=tm.eta + extra + y)
    reports = follow(tm, C, max_steps=4, witnesses=True)
    txt = "\n\n".join(text_report(r) for r in reports)
    last = reports[-1]
    added = [e for e in last["model"]["effects"] if e != "linear-ttl" and not e.startswith(("glitch:", "gate:"))]
    print(f"{spec} beside a merger: {[r['recommendation'] and r['recommendation']['cli_spec'] for r in reports]}")
    assert len(added) == 1 and added[0].startswith("witness:"), (spec, added, txt)
    assert not any(k in added[0] for k in ("vary=", "f0=", "fc=", "filter=")), (spec, added, txt)
    c = last["model"]["coefficients"]
    err = np.array([c["error"][n] for n in COEFFICIENT_NAMES])
    pull = err / np.array([c["sigma"][n] for n in COEFFICIENT_NAMES])
    print(f"  {1e3 * np.max(np.abs(err)):.3f} mm/rad, pull RMS {np.sqrt(np.mean(pull**2)):.2f}")
    assert np.max(np.abs(err)) < MAX_ERROR, (np.max(np.abs(err)), txt)
    assert np.sqrt(np.mean(pull**2)) < MAX_PULL_RMS, (pull, txt)
    # chi2/dof of the hours outside the gated span (its 900-s ramps included: a chirp's
    # power leaks through them) within 2 % of 1
    spans = [(a - 900.0, b + 900.0) for a, b in last["model"].get("gates") or []]
    rows = last["adequacy"]["time"]["segments"]
    outside = [r["chi2_dof"] for r in rows if not any(r["t_start"] < b and r["t_stop"] > a for a, b in spans)]
    print(f"  the {len(outside)} hours outside the gated span: chi2/dof {np.mean(outside):.4f}")
    assert len(outside) >= 4 and abs(np.mean(outside) - 1) < 0.02, txt
