"""Tests of the science part of reprocessing (ttlcore.app.reprocessing): trends across days with
the live monitor's step and drift tests (:mod:`ttlcore.diagnose.trends`).  The command itself, on
real Dask clusters, is tested in tests/streamer/tools/test_reprocess_command.py."""

from __future__ import annotations

import numpy as np
import pytest

from ttlcore.app.reprocessing import DAY_TRENDS, day_trends
from ttlcore.conventions import COEFFICIENT_NAMES, DAY


def _rows(n_days: int, rng, step=None, drift=None):
    """Day fits: 2.3 mm/rad +- 0.01 mm/rad noise; step = (name, day, mm), drift = (name, mm/day)."""
    rows = []
    for k in range(n_days):
        c = np.full(24, 2.3e-3) + 1e-5 * rng.standard_normal(24)
        if step and k >= step[1]:
            c[COEFFICIENT_NAMES.index(step[0])] += step[2] * 1e-3
        if drift:
            c[COEFFICIENT_NAMES.index(drift[0])] += drift[1] * 1e-3 * k
        rows.append(
            {
                "day": f"d{k:02d}",
                "t_start": k * DAY,
                "t_stop": (k + 1) * DAY,
                "coefficients": dict(zip(COEFFICIENT_NAMES, c)),
                "sigma": dict.fromkeys(COEFFICIENT_NAMES, 1e-5),
            }
        )
    return rows


def test_trends_across_days_find_a_step_and_a_drift():
    rng = np.random.default_rng(3)
    # 0.3 mm/rad step = 21 sigma of a day-to-day difference (sqrt(2) x 0.01 mm/rad): found on its day
    tr = day_trends(_rows(30, rng, step=("23.phi.tx", 20, 0.3)))
    steps = [a for a in tr["alerts"] if a["kind"] == "step"]
    assert [(a["coefficient"], a["day"]) for a in steps] == [("23.phi.tx", "d20")]
    assert steps[0]["t"] == pytest.approx(20 * DAY, abs=1.0) and steps[0]["value"] == pytest.approx(0.3, abs=0.05)
    # a 0.01 mm/rad/day drift over 10 days of day fits: rate error 0.01 / sqrt(sum (k - mean)^2) = 0.0011
    # mm/rad/day, so 9 sigma, flagged once the line has DAY_TRENDS.drift_min_windows fits and 5 sigma
    tr = day_trends(_rows(10, rng, drift=("12.eta.rx", 0.01)))
    drifts = [a for a in tr["alerts"] if a["kind"] == "drift"]
    assert [a["coefficient"] for a in drifts] == ["12.eta.rx"]
    assert tr["rates_mm_per_rad_per_day"]["12.eta.rx"] == pytest.approx(0.01, abs=0.004)
    # no trend, no alert (the false-alarm rates are those of the live monitor, ttlcore.diagnose.trends)
    assert day_trends(_rows(30, rng))["alerts"] == []
    assert DAY_TRENDS.drift_lookback == 30 * DAY
