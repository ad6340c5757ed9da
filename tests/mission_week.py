"""A blind mission week made by outside code only (issue 31's acceptance), for the week test
(``tests/test_mission_week.py``) and ``bench/mission.py --source lisainstrument``.

lisainstrument simulates the days (Keplerian orbits, its default noises, its own TTL
coefficients: the truth).  Into its measurement file, and with code the pipeline never
runs, go:

- a coupling the pipeline does not name, switched on at a random time of day 3
  (:func:`test_diagnose_blind.blind_case` draws it: a resonance, low-pass or witness of a
  random MOSA's DWS on a random link; :func:`test_diagnose_blind_lisainstrument.injected_eta`
  writes it; scaled to 3-8 times the secondary noise in its strongest band);
- one test-mass glitch a day from lisaglitch (``IntegratedShapeletGlitch``), at a random time
  on a random test mass, its velocity step log-uniform between LISA Pathfinder's 1e-12 m/s and
  a hundred times that, damping log-uniform in 5-300 s;
- a massive-black-hole merger projected by lisagwresponse, at optimal SNR 100-1000, merging
  in days 2-6 (:mod:`blind_signals`);
- a planned gap of 7 h from lisa-gap (``GapMaskGenerator``, NaN: missing data) in every
  beat-note, MPR and DWS series, in the week's second half.

The signals enter the science beat notes as ``gapped_lisainstrument_day_with_a_coupling``
adds them (``eta_ij`` holds ``sci_ij`` undelayed with factor 1: the eta signal times
``central_freq`` [Hz]), so that the pipeline reads lisainstrument's file as a user would.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE / "ttlcore" / "diagnose"))

import blind_signals as bs  # noqa: E402
from lisainstrument_sim import simulate_lisainstrument  # noqa: E402
from test_diagnose_blind import blind_case  # noqa: E402
from test_diagnose_blind_lisainstrument import (  # noqa: E402
    add_to_science_beatnotes,
    gap_every_series,
    injected_eta,
    scaled_to_a_random_level,
)

from ttlcore.conventions import COEFFICIENT_NAMES, DAY, LINKS  # noqa: E402
from ttlcore.io.lisainstrument import lisainstrument_truth  # noqa: E402
from ttlcore.io.reader import read_telemetry  # noqa: E402

HOUR = 3600.0
#: Length of the planned gap [h].
GAP_HOURS = 7.0
#: Glitch velocity steps [m/s]: LISA Pathfinder's catalogue's size up to a hundred times it.
GLITCH_DV = (1e-12, 1e-10)
#: Glitch damping times [s] (the Pathfinder catalogue's range).
GLITCH_BETA = (5.0, 300.0)


def _glitches(rng, t0: float, duration: float) -> list[tuple]:
    """``(mosa, t_inj [s], dv [m/s], beta [s])``: one a day, away from the day's edges."""
    out = []
    for d in range(int(np.ceil(duration / DAY))):
        t = t0 + min(d + rng.uniform(0.1, 0.9), duration / DAY - 0.05) * DAY
        dv = float(np.exp(rng.uniform(*np.log(GLITCH_DV)))) * float(rng.choice([-1.0, 1.0]))
        beta = float(np.exp(rng.uniform(*np.log(GLITCH_BETA))))
        out.append((str(rng.choice(LINKS)), float(t), dv, beta))
    return out


def _planned_gap(t: np.ndarray, rng, seed: int) -> tuple[np.ndarray, tuple[float, float]]:
    """lisa-gap's mask (1, NaN in the gap) with exactly one planned 7-h gap.  lisa-gap places
    planned gaps one period ``1 / rate`` apart, from one period after the start, with a small
    jitter: a period drawn in 0.55-0.8 of the span gives one gap, in its second half (days
    3.9-5.6 of a week; LISA plans one every one to two weeks)."""
    span = float(t[-1] - t[0])
    for k in range(100):
        period = rng.uniform(0.55, 0.8) * span
        mask = bs.gap_mask(t, n_gaps_per_day=DAY / period, duration_hr=GAP_HOURS, seed=seed + k)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], np.isnan(mask).astype(np.int8), [0]])))
        spans = [(float(t[a]), float(t[b - 1])) for a, b in zip(edges[::2], edges[1::2])]
        if len(spans) == 1 and spans[0][1] < t[-1] - HOUR:
            return mask, spans[0]
    raise RuntimeError(f"lisa-gap gave no single gap for seeds {seed}..{seed + 99}")


def blind_week(path, *, days: int = 7, seed: int = 1, clean=None) -> dict:
    """Write the blind week (module docstring) as a lisainstrument file at ``path``.

    ``days`` other than 7 scale the week's times (the coupling's onset in its day 3, the
    merger in days 3-6, the gap in the second half); ``clean``: an existing lisainstrument file to start
    from instead of simulating one (its duration then sets ``days``).

    Returns
    -------
    dict
        ``truth`` (the 24 coefficients [m/rad] in COEFFICIENT_NAMES order), ``coupling``
        (the blind case's spec), ``coupling_on_s`` [s], ``glitches`` (mosa, t [s], dv [m/s],
        beta [s]), ``merger_t_c`` [s] and ``merger_snr``, ``gap_s`` (start, stop [s]),
        ``t0`` and ``duration`` [s], ``lisainstrument_s`` (its wall time).
    """
    import h5py

    path = Path(path)
    rng = np.random.default_rng(seed)
    own = clean is None
    if own:
        clean = path.with_name(path.stem + "-clean.h5")
        info = simulate_lisainstrument(clean, duration=days * DAY, orbits="keplerian", seed=seed)
    truth = lisainstrument_truth(clean)
    tm = read_telemetry(clean)
    n = tm.eta.shape[1]
    t = tm.t0 + np.arange(n) / tm.fs
    duration = n / tm.fs
    week = duration / (7 * DAY)  # the week's days, scaled

    case = blind_case(int(rng.integers(1000)))
    t_on = float(tm.t0 + rng.uniform(2.0, 3.0) * week * DAY)
    extra = scaled_to_a_random_level(tm, injected_eta(tm, case), seed)
    extra[:, t < t_on] = 0.0  # switched on after some event, and stays
    glitches = _glitches(rng, tm.t0, duration)
    extra += bs.glitch_eta(t, np.mean(tm.ltt, axis=1), glitches)
    orbits = path.with_name(path.stem + "-gw-orbits.h5")
    bs.write_orbits(orbits, tm.t0 + duration)
    source = bs.random_merger(rng, duration, t_c=(2.0 / 7, 6.0 / 7))
    source["t_c"] += tm.t0
    gw = bs.gw_link_responses(orbits, duration, tm.fs, t0=tm.t0, **source)
    snr = float(rng.uniform(100, 1000))
    extra += gw * snr / bs.optimal_snr(tm, gw)
    del gw

    shutil.copyfile(clean, path)
    with h5py.File(path, "r+") as f:
        t_file = add_to_science_beatnotes(f, tm, extra)
        mask, gap = _planned_gap(t_file, rng, seed)
        gap_every_series(f, mask)
    if own:
        clean.unlink()
    return {
        "truth": [truth[name] for name in COEFFICIENT_NAMES],
        "coupling": case,
        "coupling_on_s": t_on,
        "glitches": glitches,
        "merger_t_c": float(source["t_c"]),
        "merger_snr": snr,
        "gap_s": list(gap),
        "t0": float(tm.t0),
        "duration": float(duration),
        "lisainstrument_s": round(float(info["wall_time_s"]), 1) if own else None,
    }
