"""Coefficient trends over rolling-window fits: step and drift alerts (ttlcore.diagnose.trends).

The synthetic sequences are built the way the fitter builds its estimates: hourly
segments, each carrying independent information on the 24 coefficients (per-segment
noise ``sigma * sqrt(24)``), and every hour a fit of the last 24 segments, i.e. their
average.  Consecutive fits share 23/24 of their data, so their errors are strongly
correlated, with sigma = 0.01 mm/rad per window, as for a day of real data.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from ttlcore.conventions import COEFFICIENT_NAMES, DAY
from ttlcore.diagnose.trends import (
    Alert,
    TrendMonitor,
    TrendSettings,
    detect_drifts,
    detect_steps,
    trend_estimates,
    window_correlation,
)

HOUR = 3600.0
N = 24  # segments per window
SIGMA = 0.01e-3  # per-window uncertainty [m/rad]
STEP_COEF = "23.phi.tx"
STEP_TIME = 2 * DAY
STEP_SIZE = 0.3e-3  # [m/rad]
DRIFTS = {"31.phi.tx": 0.05e-3, "32.phi.tx": -0.05e-3}  # [m/rad/day]


def rolling_fits(seed, days=4.0, step=(STEP_COEF, STEP_TIME, STEP_SIZE), drifts=DRIFTS, sigma=SIGMA, grow=False):
    """Rolling one-day fits every hour of a truth with a step and drifts.

    Returns ``(t_start, t_stop, coefficients, sigmas, truth_of_each_window)`` in m/rad.
    ``grow``: the run starts with the first segment (windows of 1, 2, ... 24 segments).
    """
    rng = np.random.default_rng(seed)
    lead = 0 if grow else N - 1
    nseg = int(round(days * 24)) + lead
    seg_start = (np.arange(nseg) - lead) * HOUR
    truth = np.tile(rng.normal(0.0, 2e-3, 24), (nseg, 1))
    if step:
        name, t, size = step
        truth[:, COEFFICIENT_NAMES.index(name)] += size * (seg_start >= t)
    for name, rate in drifts.items():  # segment average of a linear drift
        truth[:, COEFFICIENT_NAMES.index(name)] += rate * (seg_start + HOUR / 2) / DAY
    seg = truth + rng.normal(0.0, sigma * math.sqrt(N), truth.shape)
    first = [max(0, k - N + 1) for k in range(lead, nseg)]
    C = np.array([seg[a : k + 1].mean(axis=0) for a, k in zip(first, range(lead, nseg))])
    T = np.array([truth[a : k + 1].mean(axis=0) for a, k in zip(first, range(lead, nseg))])
    n = np.array([k + 1 - a for a, k in zip(first, range(lead, nseg))])
    t_stop = seg_start[lead:] + HOUR
    t_start = t_stop - n * HOUR
    S = sigma * np.sqrt(N / n)[:, None] * np.ones(24)
    return t_start, t_stop, C, S, T


def test_synthetic_sequence_is_realistic():
    t_start, t_stop, C, S, T = rolling_fits(0, step=None, drifts={})
    err = (C - T) * 1e3
    assert 0.007 < err.std() < 0.013  # ~0.01 mm/rad per window
    d = np.diff(err, axis=0)
    assert d.std() < 0.4 * err.std()  # consecutive windows strongly correlated
    rho = window_correlation(t_start, t_stop)
    assert rho[10, 11] == pytest.approx(23 / 24) and rho[10, 10 + N] == 0.0


@pytest.mark.parametrize("seed", range(5))
def test_step_alert_on_the_right_coefficient_within_three_segments(seed):
    t_start, t_stop, C, S, _ = rolling_fits(seed)
    alerts = detect_steps(t_stop, C, S, t_start=t_start)
    steps = [a for a in alerts if a.coefficient == STEP_COEF]
    assert len(steps) == 1, alerts
    a = steps[0]
    assert a.kind == "step"
    assert abs(a.t - STEP_TIME) <= 3 * HOUR  # dated within 3 segments
    assert STEP_TIME < a.t_detected <= STEP_TIME + 4 * HOUR  # raised within 4 refits
    assert a.value == pytest.approx(STEP_SIZE * 1e3, abs=0.15)  # mm/rad
    assert a.significance > 4.5
    assert STEP_COEF in a.message and "mm/rad" in a.message
    assert [x for x in alerts if x.coefficient != STEP_COEF] == []  # nothing else, drifts included


def test_step_alerts_are_causal_and_carry_indices():
    t_start, t_stop, C, S, _ = rolling_fits(1)
    full = detect_steps(t_stop, C, S, t_start=t_start, indices=range(100, 100 + len(t_stop)))
    a = full[0]
    k = a.index - 100
    prefix = detect_steps(
        t_stop[: k + 1], C[: k + 1], S[: k + 1], t_start=t_start[: k + 1], indices=range(100, 101 + k)
    )
    assert prefix == [a]  # same alert from the data up to it
    assert detect_steps(t_stop[:k], C[:k], S[:k], t_start=t_start[:k]) == []


def test_negative_step_and_units_and_covariances():
    t_start, t_stop, C, S, _ = rolling_fits(2, step=("12.eta.rx", STEP_TIME, -STEP_SIZE), drifts={})
    cov = np.einsum("ki,ij->kij", S**2, np.eye(24))
    in_mm = detect_steps(t_stop, C * 1e3, cov * 1e6, t_start=t_start, units="mm/rad")
    in_m = detect_steps(t_stop, C, S, t_start=t_start)
    assert [(a.coefficient, round(a.value, 9)) for a in in_mm] == [(a.coefficient, round(a.value, 9)) for a in in_m]
    assert len(in_m) == 1 and in_m[0].coefficient == "12.eta.rx" and in_m[0].value < -0.15


@pytest.mark.parametrize("seed", range(3))
def test_drift_alerts_for_the_drifting_coefficients_only(seed):
    t_start, t_stop, C, S, _ = rolling_fits(seed)
    steps = detect_steps(t_stop, C, S, t_start=t_start)
    drifts = detect_drifts(t_stop, C, S, t_start=t_start, steps=steps)
    assert sorted(a.coefficient for a in drifts) == sorted(DRIFTS)
    for a in drifts:
        assert a.kind == "drift"
        assert a.value == pytest.approx(DRIFTS[a.coefficient] * 1e3, abs=0.025)  # mm/rad/day
        assert abs(a.significance) >= 5
        assert "mm/rad/day" in a.message
    # the step is modelled, not read as a drift
    est = trend_estimates(t_stop, C, S, t_start=t_start, steps=steps)
    assert est.steps.get(STEP_COEF) and abs(est.significance[COEFFICIENT_NAMES.index(STEP_COEF)]) < 5


def test_false_alarm_control_on_constant_coefficients():
    """No alert on constant coefficients: 10 days x 24 coefficients of rolling fits, with the
    drift test evaluated every three hours as the monitor does (the thresholds give about
    one false step alarm in 600 days and fewer than 3e-4 false drift alarms a day)."""
    false = []
    for seed in (10, 11):
        t_start, t_stop, C, S, _ = rolling_fits(seed, days=5, step=None, drifts={}, grow=True)
        false += detect_steps(t_stop, C, S, t_start=t_start)
        for k in range(12, len(t_stop), 3):
            false += detect_drifts(t_stop[:k], C[:k], S[:k], t_start=t_start[:k])
    assert false == []


def test_without_the_overlap_correlation_the_naive_test_would_fail():
    """Why the windows are needed: treating overlapping windows as independent would report
    the noise of a constant coefficient as a drift."""
    t_start, t_stop, C, S, _ = rolling_fits(3, days=5, step=None, drifts={})
    naive = []
    for k in range(48, len(t_stop), 3):
        naive += detect_drifts(t_stop[:k], C[:k], S[:k], t_start=t_stop[:k] - 1.0)  # 1-s windows: no overlap
    honest = []
    for k in range(48, len(t_stop), 3):
        honest += detect_drifts(t_stop[:k], C[:k], S[:k], t_start=t_start[:k])
    assert naive and not honest


def test_sigmas_that_are_too_small_do_not_raise_alarms():
    """Quoted sigmas three times too small: the differences' own scatter and the GLS chi^2
    take over."""
    t_start, t_stop, C, S, _ = rolling_fits(4, days=5, step=None, drifts={})
    alerts = detect_steps(t_stop, C, S / 3, t_start=t_start)
    alerts += detect_drifts(t_stop, C, S / 3, t_start=t_start)
    assert alerts == []


def test_trend_monitor_reports_each_alert_once():
    t_start, t_stop, C, S, _ = rolling_fits(0)
    mon = TrendMonitor()
    raised = []
    for i in range(len(t_stop)):
        raised += [(i, a) for a in mon.add(i, t_start[i], t_stop[i], C[i], S[i])]
    kinds = sorted((a.kind, a.coefficient) for _, a in raised)
    assert kinds == sorted([("step", STEP_COEF)] + [("drift", c) for c in DRIFTS])
    step_i = next(i for i, a in raised if a.kind == "step")
    assert t_stop[step_i] <= STEP_TIME + 4 * HOUR
    assert mon.drifting == frozenset(DRIFTS)
    assert mon.estimates is not None and mon.estimates.windows >= 40
    # a repeated fit (same index) changes nothing
    assert mon.add(len(t_stop) - 1, t_start[-1], t_stop[-1], C[-1], S[-1]) == []


def test_alert_json_round_trip_and_input_errors():
    a = Alert("step", "12.phi.rx", 10.0, 0.3, 6.0, "m", t_detected=20.0, index=3, details={"se": np.float64(0.05)})
    js = a.to_json()
    assert js["units"] == "mm/rad" and js["details"]["se"] == 0.05
    assert Alert.from_json(js).value == 0.3
    t = np.arange(5.0)
    with pytest.raises(ValueError, match="windows are needed"):
        detect_steps(t, np.zeros((5, 24)), np.ones((5, 24)))
    with pytest.raises(ValueError, match="increase strictly"):
        detect_steps(t[::-1], np.zeros((5, 24)), np.ones((5, 24)), window=10)
    with pytest.raises(ValueError, match="coefficients"):
        detect_drifts(t, np.zeros((4, 24)), np.ones((5, 24)), window=10)
    with pytest.raises(ValueError, match="unknown field"):
        TrendSettings.from_dict({"step_treshold": 5})


def test_monitor_scans_steps_incrementally_with_the_batch_alerts():
    """TrendMonitor scans each new fit from where it stopped (O(baseline) per fit, not
    O(history)): its alerts are those of detect_steps run on the whole history at every fit
    (the scan is causal), and a fit costs the same late in a long run as early."""
    import time as _time

    from ttlcore.diagnose.trends import TrendMonitor, detect_steps

    rng = np.random.default_rng(3)
    hour, k = 3600.0, 120
    te = (np.arange(k) + 1) * hour
    ts = np.maximum(0.0, te - 86400.0)
    C = 2.3e-3 + 1e-6 * rng.standard_normal((k, 24)).cumsum(axis=0) * 0.1
    S = np.full((k, 24), 1e-5)
    frac = np.clip((te - 40 * hour) / (te - ts), 0, 1)  # a 0.2 mm/rad step at 40 h, seen by the windows
    C[:, 5] += 2e-4 * frac
    C[:, 17] -= 3e-4 * np.clip((te - 80 * hour) / (te - ts), 0, 1)
    tm = TrendMonitor()
    online, costs = [], []
    for i in range(k):
        t = _time.perf_counter()
        online += tm.add(i, ts[i], te[i], C[i], S[i])
        costs.append(_time.perf_counter() - t)
    batch = []
    for i in range(2, k + 1):  # what re-running the batch at every fit reports, deduplicated as before
        for a in detect_steps(te[:i], C[:i], S[:i], t_start=ts[:i], indices=list(range(i))):
            if not any(b.coefficient == a.coefficient and abs(b.t - a.t) <= 86400.0 for b in batch):
                batch.append(a)
    steps = [(a.coefficient, a.t, a.value) for a in online if a.kind == "step"]
    assert steps == [(a.coefficient, a.t, a.value) for a in batch] and len(steps) >= 2, (steps, batch)
    assert np.median(costs[-20:]) < 3 * np.median(costs[30:50]) + 0.01, (costs[30:50], costs[-20:])


#: Coefficients the model change moves, by how much [m/rad] (5 and 8 sigma of a window:
#: each difference across the change is ~17 and ~28 of its own standard deviations).
JUMPS = {"12.phi.rx": 5 * SIGMA, "21.eta.tx": -8 * SIGMA, "31.phi.rx": 5 * SIGMA}
LINEAR = ["linear-ttl"]
GHOST = LINEAR + ["witness:source=12.eta,link=23,delay=2"]
GLITCH = LINEAR + ["glitch:t=170000s,tm=12,beta=100s"]


def monitor_with_a_model_change(models, seed=4, change=2 * DAY, step_time=3.2 * DAY):
    """A TrendMonitor fed 4 days of hourly fits whose estimates jump by ``JUMPS`` from the
    first window ending after ``change`` on (as when the fitter rebuilds its window under a
    new model), and with a real 0.3 mm/rad step in ``STEP_COEF`` at ``step_time``; ``models``
    = (model before, model from the jump on).  Returns the monitor, the alerts, the index of
    the first fit after the jump."""
    t_start, t_stop, C, S, _ = rolling_fits(seed, step=(STEP_COEF, step_time, STEP_SIZE), drifts={})
    k_change = int(np.searchsorted(t_stop, change, side="right"))
    for name, jump in JUMPS.items():
        C[k_change:, COEFFICIENT_NAMES.index(name)] += jump
    mon = TrendMonitor()
    alerts = []
    for i in range(len(t_stop)):
        alerts += mon.add(i, t_start[i], t_stop[i], C[i], S[i], model=models[i >= k_change])
    return mon, alerts, k_change


def test_a_jump_at_a_model_change_is_no_step_and_starts_a_new_series():
    """Issue 31: the estimates jump when the fitter's couplings change (a witness adopted):
    no step alert, a new epoch; the same jump under an unchanged model is a step alert; a
    real step later in the new epoch still is."""
    mon, alerts, k = monitor_with_a_model_change((LINEAR, GHOST))
    assert [(a.kind, a.coefficient) for a in alerts] == [("step", STEP_COEF)], [a.message for a in alerts]
    assert alerts[0].t == pytest.approx(3.2 * DAY, abs=3 * HOUR) and alerts[0].details["model_epoch"] == 1
    assert [(e.number, e.index, e.model) for e in mon.epochs] == [(0, 0, LINEAR), (1, k, GHOST)]
    assert mon.epoch is mon.epochs[-1] and mon.epoch.breaks == []
    # the trends restarted: the drift line holds the new epoch's fits only
    assert mon.estimates.t_first >= mon.epoch.t_stop
    mon_same, same, _ = monitor_with_a_model_change((LINEAR, LINEAR))
    jumped = {a.coefficient for a in same if a.kind == "step"}
    assert jumped >= set(JUMPS) | {STEP_COEF}, [a.message for a in same]
    assert min(abs(a.significance) for a in same if a.coefficient in JUMPS) > 5
    assert len(mon_same.epochs) == 1


def test_a_change_of_transients_only_breaks_the_series_without_a_new_epoch():
    """A glitch added to the model moves the estimates by what it pulled them by: the one
    difference across the change is not tested and the drift line gets a level of its own;
    the series goes on (the same epoch), so a real step later is alerted as without it."""
    mon, alerts, k = monitor_with_a_model_change((LINEAR, GLITCH))
    assert [(a.kind, a.coefficient) for a in alerts] == [("step", STEP_COEF)], [a.message for a in alerts]
    assert alerts[0].details["model_epoch"] == 0
    assert len(mon.epochs) == 1 and mon.epoch.breaks == [k]
    assert mon.estimates.t_first < mon.epoch.breaks[0] * HOUR  # the drift line spans the break
    # a real step in the truth exactly at the change, under unchanged couplings, is still a step
    # (its ramp goes on after the one left-out difference)
    mon2, alerts2, _ = monitor_with_a_model_change((LINEAR, GLITCH), step_time=2 * DAY)
    assert STEP_COEF in {a.coefficient for a in alerts2 if a.kind == "step"}, [a.message for a in alerts2]


def test_model_key_separates_couplings_from_transients():
    from ttlcore.diagnose.trends import model_key

    assert model_key(None) is None and model_key("linear-ttl") is None
    assert model_key(GHOST) == (tuple(sorted(GHOST)), ())
    assert model_key(GLITCH + ["gate:start=1s,stop=2s"]) == (("linear-ttl",), ("gate:start=1s,stop=2s", GLITCH[1]))
    assert model_key(list(reversed(GHOST))) == model_key(GHOST)  # the order of the specs is not a change
